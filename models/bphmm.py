"""The Beta-Process HMM as a NumPyro model: the single statement of the joint density.

Weak-limit truncation at K = ``max_skills`` slots (all shapes static):

    omega_k ~ Beta(alpha / K, 1)                      skill popularity
    f_ik | omega_k ~ Bernoulli(omega_k)                trajectory i may use skill k
    eta_ijk ~ Gamma(gamma + kappa [j == k], 1)         unnormalised transition weights
    pi_ij = eta_ij * f_i / sum(eta_ij * f_i)           transitions among i's active skills
    z_i1 ~ uniform over i's active skills;  z_it ~ pi_i,z_i(t-1)
    params_k ~ emission prior                          e.g. reward weights theta_k
    step t of trajectory i ~ emission(params_{z_it})

The skill sequences z are summed out by the forward filter, which enters the model as one
``numpyro.factor``. The MCMC kernel evaluates every acceptance ratio and Gibbs conditional
with the functions below (``prior_distributions``, ``hmm_parameters``,
``log_marginal_likelihoods``), which this model also uses: the density is written once.
"""

from __future__ import annotations

from typing import Dict, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpyro
import numpyro.distributions as dist
from jax.scipy.special import betaln

from .hmm import batch_forward_filter
from npbrs.domains.precision import float64_all

__all__ = ["Hyper", "prior_distributions", "hmm_parameters", "eta_gamma_shapes", "eta_from_gammas",
           "log_marginal_likelihoods", "feature_predictive", "predictive_log_likelihoods",
           "bphmm_model", "log_joint_terms",
           "collapsed_feature_log_prob", "collapsed_sequence_log_prob"]

class Hyper(NamedTuple):
    """BP-HMM hyperparameters: IBP mass alpha, stickiness kappa, transition concentration gamma."""

    alpha: jax.Array
    kappa: jax.Array
    gamma: jax.Array


def prior_distributions(num_trajectories: int, max_skills: int, hyper: Hyper) -> Dict:
    """The BP-HMM's prior distributions (omega, features given omega, eta).

    Returns a dict with ``"omega"`` (a Distribution over (K,)), ``"features"`` (a function
    omega -> Distribution over (N, K)) and ``"eta"`` (a Distribution over (N, K, K)).
    """
    N, K = num_trajectories, max_skills
    alpha, kappa, gamma = hyper
    omega = dist.Beta(jnp.full((K,), alpha / K), jnp.ones((K,))).to_event(1)

    def features(om):
        return dist.Bernoulli(probs=jnp.broadcast_to(om, (N, K))).to_event(2)

    conc = gamma + kappa * jnp.eye(K)
    eta = dist.Gamma(jnp.broadcast_to(conc, (N, K, K)), 1.0).to_event(3)
    return {"omega": omega, "features": features, "eta": eta}


def hmm_parameters(features, eta):
    """Per-trajectory HMM parameters in the form the array filters take.

    Args:
        features: (N, K) 0/1 skills each trajectory may use.
        eta: (N, K, K) positive transition weights.
    Returns:
        log_init (N, K) (zeros: uniform over the active skills), log_trans (N, K, K)
        (log eta, normalised over the active skills by the filters), active (N, K) bool.
    """
    return jnp.zeros(features.shape, eta.dtype), jnp.log(eta), features > 0


def eta_gamma_shapes(counts, features, hyper):
    """Gamma shapes of eta's conditional given transition counts (N, K, K) and F.

    Per row, the entries in active columns are Dirichlet(conc + counts) proportions times a
    Gamma(sum conc) total (the Gamma-Dirichlet decomposition); inactive entries keep their
    Gamma(conc) prior; conc = gamma + kappa * I. Returns (shapes of the entries (N, K, K),
    shapes of the totals (N, K), active columns (N, 1, K) bool). With zero counts this is
    the prior."""
    K = features.shape[1]
    conc = hyper.gamma + hyper.kappa * jnp.eye(K)
    active = (features > 0)[:, None, :]
    return jnp.where(active, conc + counts, conc), jnp.sum(jnp.where(active, conc, 0.0), -1), active


def eta_from_gammas(g, total, active):
    """eta from Gamma draws of :func:`eta_gamma_shapes`' shapes: g (N, K, K), total (N, K, 1)."""
    g_active_sum = jnp.sum(jnp.where(active, g, 0.0), -1, keepdims=True)
    scaled = g / jnp.maximum(g_active_sum, 1e-300) * total
    return jnp.maximum(jnp.where(active, scaled, g), 1e-300)


def log_marginal_likelihoods(features, eta, log_lik, mask):
    """log p(data_i | f_i, eta_i, params) with the skill sequence summed out, per trajectory (N,)."""
    log_init, log_trans, active = hmm_parameters(features, eta)
    log_marg, _ = batch_forward_filter(log_init, log_trans, log_lik, mask, active)
    return log_marg


def feature_predictive(counts, num_trajectories, alpha):
    """P(f_k = 1) of a new trajectory given the other trajectories' features, omega integrated
    out: (m_k + alpha/K) / (N + 1 + alpha/K), the weak-limit beta-Bernoulli predictive.

    Args:
        counts: (..., K) m_k, the trajectories using each skill; num_trajectories: N.
    """
    a = alpha / jnp.shape(counts)[-1]
    return (counts + a) / (num_trajectories + 1.0 + a)


def predictive_log_likelihoods(key, log_lik, mask, p_on, hyper: Hyper, num_samples: int, marginals: bool = False):
    """log p(x_i | f, eta, params) of trajectories for ``num_samples`` draws of their skill sets
    and transition weights: f_k ~ Bernoulli(p_on[k]) independently (``feature_predictive`` for a
    new trajectory; 0/1 for a known skill set), eta from its prior (``prior_distributions``);
    the skill sequence summed out by the forward filter. A skill set with no skill cannot emit
    (-inf).

    Args:
        key: PRNG key. log_lik: (n, T, K) per-step log-likelihoods under a draw's skills;
            mask: (n, T) bool.
        p_on: (K,) or (n, K) probabilities that each skill is in a trajectory's set.
        hyper: the draw's hyperparameters.
        marginals: also return the posterior marginals of the skill sequence.
    Returns:
        (num_samples, n) log-likelihoods, one per (f, eta) sample; with ``marginals``, also
        (num_samples, n, T, K) log p(z_t | x, f, eta, params) (``NEG_LOG`` at padding).
    """
    from .hmm import batch_smooth

    n, _, K = log_lik.shape
    k_f, k_eta = jax.random.split(key)
    features = jax.random.bernoulli(k_f, p_on, (num_samples, n, K)).astype(log_lik.dtype)
    eta = jnp.maximum(prior_distributions(n, K, hyper)["eta"].sample(k_eta, (num_samples,)), 1e-300)

    def one(f, e):
        log_init, log_trans, active = hmm_parameters(f, e)
        log_marg, log_alpha = batch_forward_filter(log_init, log_trans, log_lik, mask, active)
        return log_marg, (batch_smooth(log_trans, log_alpha, mask, active) if marginals else None)

    log_marg, post = jax.vmap(one)(features, eta)
    log_marg = jnp.where(jnp.sum(features, -1) > 0, log_marg, -jnp.inf)
    return (log_marg, post) if marginals else log_marg


def collapsed_feature_log_prob(features, alpha, valid=None):
    """log p(F) with the skill popularities omega integrated out of the model's
    omega_k ~ Beta(alpha/K, 1), f_ik ~ Bernoulli(omega_k):
    sum_k [log B(m_k + alpha/K, N - m_k + 1) - log B(alpha/K, 1)], m_k = sum_i f_ik.
    ``valid`` (N,) bool: the trajectories that are data; the others (padding, no steps) are
    left out (N and m_k count the valid ones), so padding does not change the value."""
    N, K = features.shape
    a = alpha / K
    if valid is None:
        m = jnp.sum(features, axis=0)
    else:
        m = jnp.sum(jnp.where(valid[:, None], features, 0.0), axis=0)
        N = jnp.sum(valid).astype(features.dtype)
    return jnp.sum(betaln(m + a, N - m + 1.0) - betaln(a, 1.0))


def collapsed_sequence_log_prob(z, mask, features, kappa, gamma):
    """log p(z_i | f_i) with the transition weights eta_i integrated out, per trajectory (N,).

    Given f_i, row j of pi_i is Dirichlet(gamma + kappa [j == k], k active) (normalised
    Gamma weights), so each row contributes a Dirichlet-multinomial term of its transition
    counts; the first skill is uniform over the active ones. A sequence that uses an
    inactive skill has probability 0 (-inf).

    Args:
        z: (N, T) skills (-1 or anything at masked steps); mask: (N, T) bool;
        features: (N, K) 0/1; kappa, gamma: the hyperparameters.
    """
    from jax.scipy.special import gammaln

    from .hmm import transition_counts

    N, K = features.shape
    active = features > 0
    z = jnp.where(mask, z, -1)
    counts = transition_counts(z, mask, K).astype(jnp.float64)  # (N, K, K)
    conc = gamma + kappa * jnp.eye(K)
    pair = active[:, :, None] & active[:, None, :]
    c = jnp.where(pair, conc, 0.0)
    row = (gammaln(jnp.maximum(jnp.sum(c, -1), 1e-300)) - gammaln(jnp.sum(c, -1) + jnp.sum(counts, -1))
           + jnp.sum(jnp.where(pair, gammaln(c + counts) - gammaln(jnp.where(pair, c, 1.0)), 0.0), -1))
    trans = jnp.sum(jnp.where(active, row, 0.0), -1)
    has_steps = jnp.any(mask, -1)
    n_active = jnp.sum(active, -1)
    init = jnp.where(has_steps, -jnp.log(jnp.maximum(n_active, 1)), 0.0)
    used = jnp.any(jax.nn.one_hot(z, K, dtype=bool) & mask[..., None], axis=1)
    ok = ~jnp.any(used & ~active, -1) & (n_active > 0)
    return jnp.where(ok, trans + init, -jnp.inf)


def _hyper_value(name, value, hyperpriors):
    if hyperpriors is not None and name in hyperpriors:
        shape, rate = hyperpriors[name]
        return numpyro.sample(name, dist.Gamma(shape, rate))
    return jnp.asarray(value, dtype=jnp.float64)


def bphmm_model(data, emission, max_skills: int, alpha=1.0, kappa=10.0, gamma=1.0,
                hyperpriors: Optional[Dict] = None):
    """The BP-HMM joint density as a NumPyro model.

    Args:
        data: an :class:`~npbrs.models.emissions.HMMData` (N padded trajectories).
        emission: an :class:`~npbrs.models.emissions.Emission`.
        max_skills: truncation K.
        alpha, kappa, gamma: hyperparameter values (used when not sampled).
        hyperpriors: optional {"alpha" | "kappa" | "gamma": (shape, rate)} Gamma hyperpriors;
            a named hyperparameter becomes a sample site.
    """
    N = data.states.shape[0]
    K = max_skills
    hyper = Hyper(_hyper_value("alpha", alpha, hyperpriors), _hyper_value("kappa", kappa, hyperpriors),
                  _hyper_value("gamma", gamma, hyperpriors))
    priors = prior_distributions(N, K, hyper)
    omega = numpyro.sample("omega", priors["omega"])
    features = numpyro.sample("features", priors["features"](omega))
    eta = numpyro.sample("eta", priors["eta"])
    params = emission.sample_params(K)
    log_lik, _ = emission.log_likelihoods(params, data, emission.init_cache(K))
    numpyro.factor("log_likelihood", jnp.sum(log_marginal_likelihoods(features, eta, log_lik, data.mask)))


def log_joint_terms(omega, features, eta, params, log_marginals, hyper: Hyper, emission,
                    hyperpriors: Optional[Dict] = None, valid=None):
    """The model's log density split into its terms, from already computed marginals.

    The kernel uses this to avoid recomputing emission log-likelihoods; a test checks that the
    sum equals ``numpyro.infer.util.log_density(bphmm_model, ...)``. ``valid`` (N,) bool: the
    trajectories that are data; the others (padding to a shape bucket, no steps) are left out
    of the feature and transition-weight terms, so the sum is the density of the real ones.
    """
    N, K = features.shape
    priors = prior_distributions(N, K, hyper)
    row = (lambda x: jnp.sum(x)) if valid is None else (lambda x: jnp.sum(jnp.where(valid, x, 0.0)))
    terms = {
        "omega": priors["omega"].log_prob(omega),
        "features": row(priors["features"](omega).base_dist.log_prob(features).sum(-1)),
        "eta": row(priors["eta"].base_dist.log_prob(eta).sum((-2, -1))),
        "params": jnp.sum(emission.log_prior(params)),
        "log_likelihood": jnp.sum(log_marginals),
    }
    if hyperpriors:
        for name, (shape, rate) in hyperpriors.items():
            terms[name] = dist.Gamma(shape, rate).log_prob(getattr(hyper, name))
    return terms


float64_all(globals())  # npbrs.domains.precision: float64 inside, the user's setting outside
