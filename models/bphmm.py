"""The Beta-Process HMM as a NumPyro model: the single statement of the joint density.

Weak-limit truncation at K = ``max_skills`` slots (all shapes static):

    omega_k ~ Beta(alpha / K, 1)                      skill popularity
    f_ik | omega_k ~ Bernoulli(omega_k)                trajectory i may use skill k
    eta_ijk ~ Gamma(gamma + kappa [j == k], 1)         unnormalised transition weights
    pi_ij = eta_ij * f_i / sum(eta_ij * f_i)           transitions among i's active skills
    z_i1 ~ uniform over i's active skills;  z_it ~ pi_i,z_i(t-1)
    params_k ~ emission prior                          e.g. reward weights theta_k
    step t of trajectory i ~ emission(params_{z_it})

With state-dependent switching (a :class:`Termination`; ``fit(..., switching="state")``) the
skills are options with a termination function: skill k *ends* on entering state s with
probability beta_k(s), and then the next skill is drawn from row k of pi_i without k itself;
otherwise it continues:

    mu_k ~ Beta(a, b)                                  skill k's typical end probability
    beta_k(s) | mu_k ~ Beta(c mu_k, c (1 - mu_k))      its end probability in state s
    z_it | z_i(t-1) = k ~ (1 - beta_k(s_it)) [z = k] + beta_k(s_it) pi~_ik    (pi~: pi_ik without k)

(a trajectory with one skill keeps it). c large makes the ends nearly the same in every state
(a per-skill sticky HMM); c small lets them follow the states, as when a skill ends once its
goal is reached. The diagonal of eta then plays no part, so kappa has none either.

The skill sequences z are summed out by the forward filter, which enters the model as one
``numpyro.factor``. The MCMC kernel evaluates every acceptance ratio and Gibbs conditional
with the functions below (``prior_distributions``, ``hmm_parameters``,
``log_marginal_likelihoods``), which this model also uses: the density is written once.
"""

from __future__ import annotations

from functools import partial
from typing import Dict, NamedTuple, Optional, Tuple

import jax
import jax.numpy as jnp
import numpy as np
import numpyro
import numpyro.distributions as dist
from jax.scipy.special import betaln

from .hmm import NEG_LOG, batch_forward_filter, batch_viterbi, transition_counts
from npbrs.domains.util.compiling import jit
from npbrs.domains.options import arrival_counts
from npbrs.domains.util.precision import float64_all

__all__ = ["Hyper", "Termination", "prior_distributions", "sample_prior_eta", "hmm_parameters", "eta_gamma_shapes", "eta_from_gammas",
           "end_gate", "end_counts", "end_log_prior", "sample_end_means", "sample_ends",
           "log_marginal_likelihoods", "feature_predictive", "predictive_log_likelihoods",
           "bphmm_model", "log_joint_terms",
           "collapsed_feature_log_prob", "collapsed_sequence_log_prob", "eta_counts", "sequence_counts",
           "collapsed_transition_log_prob", "collapsed_end_log_prob", "switching_log_evidence"]

class Hyper(NamedTuple):
    """BP-HMM hyperparameters: IBP mass alpha, stickiness kappa, transition concentration gamma."""

    alpha: jax.Array
    kappa: jax.Array
    gamma: jax.Array


class Termination(NamedTuple):
    """The prior of state-dependent skill ends (see the module docstring): beta_k(s) ~
    Beta(c mu_k, c (1 - mu_k)), mu_k ~ Beta(*mean_prior). Plain numbers (a static part of a
    compiled program).

    num_states: S, the MDP's states (the ``states`` of the data index them).
    concentration: c > 0.
    mean_prior: (a, b) > 0, the Beta prior of each skill's mean end probability mu_k.
    """

    num_states: int
    concentration: float = 8.0
    mean_prior: Tuple[float, float] = (1.0, 9.0)


def end_gate(ends, states, mask):
    """(N, T, K) each step's end probabilities beta_k(s_it) for the filters' ``gate`` from
    ``ends`` (K, S) and the data's states (N, T); 1 at padding (not read)."""
    S = ends.shape[1]
    gate = jnp.take(ends.T, jnp.clip(states, 0, S - 1), axis=0)  # (N, T, K)
    return jnp.where(mask[..., None], gate, 1.0)


def end_counts(z, mask, states, features, num_states: int):
    """(ends, stays), each (K, S): how often a step of skill k was followed by another skill
    (an end) or by k again, counted in the state entered, over the trajectories with at least
    two skills in their set (a trajectory with one skill cannot end it: its steps say nothing
    of beta). The counting is the options' (:func:`npbrs.domains.options.arrival_counts`)."""
    two_or_more = jnp.sum(features > 0, -1) >= 2
    return arrival_counts(z, states, mask & two_or_more[:, None], num_states, features.shape[1])


def end_log_prior(ends, mean, term: Termination):
    """(log p(mu), log p(beta | mu)) of the end probabilities ends (K, S) and means mean (K,)."""
    a, b = term.mean_prior
    c = term.concentration
    lp_mean = jnp.sum(dist.Beta(a, b).log_prob(mean))
    lp_ends = jnp.sum(dist.Beta(c * mean[:, None], c * (1.0 - mean[:, None])).log_prob(ends))
    return lp_mean, lp_ends


_END_CLIP = 1e-12


def sample_ends(key, mean, counts, term: Termination):
    """beta | mu, counts: Beta(c mu_k + ends_ks, c (1 - mu_k) + stays_ks), (K, S), kept within
    [1e-12, 1 - 1e-12]; counts: :func:`end_counts`."""
    ended, stayed = counts
    c = term.concentration
    k1, k2 = jax.random.split(key)
    ga = jax.random.gamma(k1, c * mean[:, None] + ended)
    gb = jax.random.gamma(k2, c * (1.0 - mean[:, None]) + stayed)
    return jnp.clip(ga / jnp.maximum(ga + gb, 1e-300), _END_CLIP, 1.0 - _END_CLIP)


def _ends_beta_binomial(mean, counts, concentration):
    """log p(counts_k | mu_k) with the ends beta integrated out, per skill (K,): a Beta-binomial
    of each state's (ends, stays) under Beta(c mu_k, c (1 - mu_k)); counts: :func:`end_counts`."""
    ended, stayed = counts
    x, y = concentration * mean[:, None], concentration * (1.0 - mean[:, None])
    seen = (ended + stayed) > 0
    return jnp.sum(jnp.where(seen, betaln(x + ended, y + stayed) - betaln(x, y), 0.0), -1)


def _mean_log_target(mean, counts, term: Termination):
    """log p(mu_k) + log p(counts_k | mu_k) with beta integrated out (a Beta-binomial per
    state), per skill (K,)."""
    a, b = term.mean_prior
    return _ends_beta_binomial(mean, counts, term.concentration) + dist.Beta(a, b).log_prob(mean)


def collapsed_end_log_prob(z, mask, states, features, mean, concentration, num_states: int):
    """log p(z's ends and stays | mu) with the ends beta integrated out, per skill (K,): a
    Beta-binomial of each (skill, state entered)'s :func:`end_counts` under Beta(c mu_k,
    c (1 - mu_k)). What the greedy moves score skill sequences by under state-dependent ends,
    so that a proposed skill is not judged by ends drawn for another's steps."""
    return _ends_beta_binomial(mean, end_counts(z, mask, states, features, num_states), concentration)


#: quadrature nodes of :func:`switching_log_evidence`'s integrals over kappa and each mu_k
EVIDENCE_NODES = 64


def switching_log_evidence(z, mask, states, num_states: int, termination: Termination, gamma: float = 1.0,
                           kappa_prior: Tuple[float, float] = (1.0, 0.02), features=None,
                           num_skills: Optional[int] = None) -> Tuple[float, float]:
    """(sticky, state): log p(z) of skill sequences under the sticky BP-HMM and under
    state-dependent ends, each trajectory's skills being those it uses, with everything else
    integrated out: eta exactly (:func:`collapsed_sequence_log_prob`'s Dirichlet-multinomials),
    the ends given their means exactly (:func:`collapsed_end_log_prob`), the sticky model's
    kappa under Gamma(``kappa_prior``) (shape, rate) and each skill's mean end probability mu_k
    under Beta(``termination.mean_prior``) by quadrature at :data:`EVIDENCE_NODES` quantiles of
    the prior. Their difference is the Bayes factor of the two switching models given z (the
    emission's terms are the same in both). Host arrays in, floats out: one compiled program
    per shape (N, T), ``num_skills`` and ``num_states``; the quadrature's nodes are its
    arguments, so other priors or data of the same shapes reuse it.

    Args:
        z: (N, T) skill indices (anything at masked steps); mask: (N, T) bool (trajectories
            without steps, padding, are left out); states: (N, T).
        num_states: S; termination: the state model's prior (its concentration and mean prior).
        gamma: the transition concentration; kappa_prior: (shape, rate) of kappa's Gamma.
        features: (N, K) 0/1, each trajectory's skills; None: those it uses.
        num_skills: K, the skill slots (at least the largest index in z plus one; default that).
    """
    from scipy.special import betaincinv, gammaincinv, logsumexp  # (not scipy.stats: 0.4 s to import)

    mask = np.asarray(mask, bool)
    z = np.where(mask, np.asarray(z), -1).astype(np.int32)
    K = int(num_skills) if num_skills is not None else max(int(z.max()) + 1, 1)
    if int(z.max()) >= K:
        raise ValueError(f"z holds skill {int(z.max())}, past num_skills={K}")
    if features is None:
        features = np.stack([np.any((z == k) & mask, axis=1) for k in range(K)], 1)
    q = (np.arange(EVIDENCE_NODES) + 0.5) / EVIDENCE_NODES
    kappas = gammaincinv(kappa_prior[0], q) / kappa_prior[1]  # the priors' quantiles
    means = betaincinv(termination.mean_prior[0], termination.mean_prior[1], q)
    per_kappa, per_mean, sticky_rest, state_rest = (np.asarray(x) for x in _switching_terms(
        jnp.asarray(z), jnp.asarray(mask), jnp.asarray(np.asarray(states), jnp.int32),
        jnp.asarray(np.asarray(features, np.float64)), jnp.asarray(kappas), jnp.asarray(means),
        jnp.float64(termination.concentration), jnp.float64(gamma), int(num_states)))
    log_g = np.log(EVIDENCE_NODES)
    sticky = float(logsumexp(per_kappa) - log_g + sticky_rest)
    state = float(state_rest + np.sum(logsumexp(per_mean, axis=0) - log_g))
    return sticky, state


@partial(jit, static_argnums=(8,))
def _switching_terms(z, mask, states, features, kappas, means, concentration, gamma, num_states):
    """:func:`switching_log_evidence`'s terms at its quadrature nodes: the sticky transitions'
    log-probability per kappa (G,), the ends' per mean and skill (G, K), and the parts that
    depend on neither (the first skills', and the state model's switches)."""
    K = features.shape[1]
    valid = jnp.any(mask, axis=1)
    counts, rest = sequence_counts(z, mask, features)
    rest = jnp.sum(jnp.where(valid, rest, 0.0))
    per_kappa = jax.vmap(lambda k: jnp.sum(jnp.where(valid, collapsed_transition_log_prob(
        counts, features, k, gamma), 0.0)))(kappas)
    state = jnp.sum(jnp.where(valid, collapsed_sequence_log_prob(z, mask, features, 0.0, gamma, None, True), 0.0))
    per_mean = jax.vmap(lambda m: collapsed_end_log_prob(z, mask, states, features, jnp.full((K,), m),
                                                         concentration, num_states))(means)  # (G, K)
    return per_kappa, per_mean, rest, state


def sample_end_means(key, mean, counts, term: Termination, steps: int = 5, scale: float = 0.5):
    """mu | counts with beta integrated out: ``steps`` random-walk Metropolis steps on logit mu_k,
    every skill at once (independent given the counts). Followed by :func:`sample_ends`, it
    is a draw of (mu, beta) given the skill sequences."""
    def one(mu, k):
        k1, k2 = jax.random.split(k)
        logit = jnp.log(mu) - jnp.log1p(-mu)
        prop_logit = logit + scale * jax.random.normal(k1, mu.shape)
        prop = jnp.clip(jax.nn.sigmoid(prop_logit), _END_CLIP, 1.0 - _END_CLIP)
        # the logit's Jacobian: log mu (1 - mu)
        log_ratio = (_mean_log_target(prop, counts, term) + jnp.log(prop) + jnp.log1p(-prop)
                     - _mean_log_target(mu, counts, term) - jnp.log(mu) - jnp.log1p(-mu))
        accept = jnp.log(jax.random.uniform(k2, mu.shape)) < log_ratio
        return jnp.where(accept, prop, mu), None

    mean, _ = jax.lax.scan(one, mean, jax.random.split(key, steps))
    return mean


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


def sample_prior_eta(key, hyper: Hyper, shape):
    """Draws of the transition weights from their prior (``prior_distributions``' "eta"), of
    ``shape`` (..., K, K): Gamma(gamma + kappa, 1) on the diagonal, Gamma(gamma, 1) off it.

    Exact, and cheap where it matters: at gamma = 1 (the default) the off-diagonal draws are
    Exponential(1) draws, which cost about a sixtieth of ``jax.random.gamma``'s rejection
    sampler (K - 1 of every K draws; the predictive draws millions of them for hundreds of short
    trajectories). Other gammas take the Gamma sampler."""
    K = shape[-1]
    k_diag, k_off = jax.random.split(key)
    dtype = jnp.result_type(float)
    gamma = jnp.asarray(hyper.gamma, dtype)
    diag = jax.random.gamma(k_diag, jnp.broadcast_to(gamma + hyper.kappa, shape[:-1]), dtype=dtype)
    off = jax.lax.cond(gamma == 1.0, lambda k: jax.random.exponential(k, shape, dtype),
                       lambda k: jax.random.gamma(k, jnp.broadcast_to(gamma, shape), dtype=dtype), k_off)
    return jnp.where(jnp.eye(K, dtype=bool), diag[..., :, None], off)


def hmm_parameters(features, eta, gated: bool = False):
    """Per-trajectory HMM parameters in the form the array filters take.

    Args:
        features: (N, K) 0/1 skills each trajectory may use.
        eta: (N, K, K) positive transition weights.
        gated: the switch matrix of state-dependent ends (the filters' ``gate``): the diagonal
            left out, except in a trajectory with a single skill (which can only continue). A
            bool, or a traced one (the kernel's sticky phase).
    Returns:
        log_init (N, K) (zeros: uniform over the active skills), log_trans (N, K, K)
        (log eta, normalised over the active skills by the filters), active (N, K) bool.
    """
    log_trans = jnp.log(eta)
    if gated is not False:
        K = features.shape[1]
        alone = jnp.sum(features > 0, -1) < 2
        diag = jnp.eye(K, dtype=bool) & jnp.asarray(gated, bool)
        log_trans = jnp.where(diag, jnp.where(alone, 0.0, NEG_LOG)[:, None, None], log_trans)
    return jnp.zeros(features.shape, eta.dtype), log_trans, features > 0


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


def log_marginal_likelihoods(features, eta, log_lik, mask, gate=None, gated=None):
    """log p(data_i | f_i, eta_i, params) with the skill sequence summed out, per trajectory (N,);
    ``gate``: (N, T, K) :func:`end_gate` with state-dependent ends, else None; ``gated``: as
    :func:`hmm_parameters`' (default: whether a gate is given)."""
    log_init, log_trans, active = hmm_parameters(features, eta, gate is not None if gated is None else gated)
    log_marg, _ = batch_forward_filter(log_init, log_trans, log_lik, mask, active, gate)
    return log_marg


def feature_predictive(counts, num_trajectories, alpha):
    """P(f_k = 1) of a new trajectory given the other trajectories' features, omega integrated
    out: (m_k + alpha/K) / (N + 1 + alpha/K), the weak-limit beta-Bernoulli predictive.

    Args:
        counts: (..., K) m_k, the trajectories using each skill; num_trajectories: N.
    """
    a = alpha / jnp.shape(counts)[-1]
    return (counts + a) / (num_trajectories + 1.0 + a)


def _guided_eta(key, hyper: Hyper, features, eta, log_lik, mask):
    """Importance sampling of the transition weights around each trajectory's own stays:
    (eta, log importance weight (M, n)).

    Drawn from their prior alone, the weights rarely fit a long trajectory (a skill's hundreds of
    stays each contribute log pi_kk: a 500-step trajectory's log-likelihood varies with an sd of
    about 30 nats over prior draws), and the log of the Monte Carlo mean falls below its stated
    error. The likelihood sees only each row's proportions over the active skills (the row
    totals are not identified; their posterior is their prior). A row's Dirichlet(c_j)
    proportions split into the self share pi_jj ~ Beta(c_jj, sum of the others' c) and the
    others' shares among themselves, independent of it. So each (sample, trajectory) keeps, with
    probability 1/2, its prior draw; else every active row's self share is redrawn from
    Beta(c_jj + n_jj, sum over the other active skills of c_jl + n_jl), with n the transitions
    along the Viterbi path under the prior mean transitions and the sample's skill set
    (deterministic given the data), keeping the prior draw's total and other shares. The weight
    is the self shares' prior Beta density over the mixture's (at most 2). Unbiased at every
    length; its draws are 2 x (M, n, K) Gammas, not (M, n, K, K)."""
    M, n, K = features.shape
    dtype = eta.dtype
    eye = jnp.eye(K, dtype=bool)
    conc = hyper.gamma + hyper.kappa * jnp.eye(K, dtype=dtype)

    def counts_of(f):
        log_init, log_trans, active = hmm_parameters(f, jnp.broadcast_to(conc, (n, K, K)))
        z, _ = batch_viterbi(log_init, log_trans, log_lik, mask, active)
        return transition_counts(z, mask, K).astype(dtype)

    counts = jax.vmap(counts_of)(features)  # (M, n, K, K)
    on_row = features > 0  # (M, n, K)
    on = on_row[..., None, :] & ~eye  # the other active skills of each row
    rows = on_row & jnp.any(on, -1)  # active rows with somewhere to switch to
    a0 = hyper.gamma + hyper.kappa
    b0 = jnp.sum(jnp.where(on, hyper.gamma, 0.0), -1)
    prior = dist.Beta(a0, jnp.where(rows, b0, 1.0))
    guide = dist.Beta(a0 + jnp.diagonal(counts, axis1=-2, axis2=-1),
                      jnp.where(rows, b0 + jnp.sum(jnp.where(on, counts, 0.0), -1), 1.0))
    k_use, k_draw = jax.random.split(key)
    redraw = jax.random.bernoulli(k_use, 0.5, (M, n))[..., None] & rows
    diag = jnp.diagonal(eta, axis1=-2, axis2=-1)
    rest = jnp.sum(jnp.where(on, eta, 0.0), -1)
    total = diag + rest
    share = jnp.clip(jnp.where(redraw, guide.sample(k_draw), diag / total), 1e-300, 1.0 - 1e-16)
    scale = jnp.where(rows, (1.0 - share) * total / jnp.where(rest > 0, rest, 1.0), 1.0)
    out = jnp.where(eye, (share * total)[..., :, None], jnp.where(on, eta * scale[..., None], eta))
    log_p, log_q = (jnp.sum(jnp.where(rows, d.log_prob(share), 0.0), -1) for d in (prior, guide))
    return out, log_p - jnp.logaddexp(log_p, log_q) + jnp.log(2.0)


def predictive_log_likelihoods(key, log_lik, mask, p_on, hyper: Hyper, num_samples: int, marginals: bool = False,
                               gate=None, guided: bool = False):
    """log p(x_i | f, eta, params) of trajectories for ``num_samples`` draws of their skill sets
    and transition weights: f_k ~ Bernoulli(p_on[k]) independently (``feature_predictive`` for a
    new trajectory; 0/1 for a known skill set), eta from its prior (``sample_prior_eta``);
    the skill sequence summed out by the forward filter. A skill set with no skill cannot emit
    (-inf).

    Args:
        key: PRNG key. log_lik: (n, T, K) per-step log-likelihoods under a draw's skills;
            mask: (n, T) bool.
        p_on: (K,) or (n, K) probabilities that each skill is in a trajectory's set.
        hyper: the draw's hyperparameters.
        marginals: also return the posterior marginals of the skill sequence.
        gate: (n, T, K) :func:`end_gate` of the draw's end probabilities at the trajectories'
            states, with state-dependent ends; else None.
        guided: importance-sample eta's self shares around each trajectory's own stays
            (:func:`_guided_eta`; the values then include the importance weights) instead of
            drawing it from its prior alone; without ``gate`` only.
    Returns:
        (num_samples, n) log-likelihoods, one per (f, eta) sample; with ``marginals``, also
        (num_samples, n, T, K) log p(z_t | x, f, eta, params) (``NEG_LOG`` at padding).
    """
    from .hmm import batch_smooth

    n, _, K = log_lik.shape
    k_f, k_eta = jax.random.split(key)
    features = jax.random.bernoulli(k_f, p_on, (num_samples, n, K)).astype(log_lik.dtype)
    eta = jnp.maximum(sample_prior_eta(k_eta, hyper, (num_samples, n, K, K)), 1e-300)
    log_w = 0.0
    if guided and gate is None:  # (the same prior draws as without: f and eta's other entries)
        eta, log_w = _guided_eta(jax.random.fold_in(k_eta, 1), hyper, features, eta, log_lik, mask)

    def one(f, e):
        log_init, log_trans, active = hmm_parameters(f, e, gate is not None)
        log_marg, log_alpha = batch_forward_filter(log_init, log_trans, log_lik, mask, active, gate)
        return log_marg, (batch_smooth(log_trans, log_alpha, mask, active, gate) if marginals else None)

    log_marg, post = jax.vmap(one)(features, eta)
    log_marg = jnp.where(jnp.sum(features, -1) > 0, log_marg + log_w, -jnp.inf)
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


def collapsed_sequence_log_prob(z, mask, features, kappa, gamma, gate=None, gated=None):
    """log p(z_i | f_i) with the transition weights eta_i integrated out, per trajectory (N,).

    Given f_i, row j of pi_i is Dirichlet(gamma + kappa [j == k], k active) (normalised
    Gamma weights), so each row contributes a Dirichlet-multinomial term of its transition
    counts; the first skill is uniform over the active ones. A sequence that uses an
    inactive skill has probability 0 (-inf).

    With state-dependent ends, ``gate`` (N, T, K) (:func:`end_gate` of the ends, held fixed):
    log p(z_i | f_i, ends), each step of a trajectory with two skills or more contributing
    log (1 - beta) when its skill continues and log beta when it ends, and the switches'
    Dirichlet-multinomial over the other active skills (Dirichlet(gamma), the diagonal left
    out).

    The work splits into what depends on z (:func:`sequence_counts`) and what depends on kappa
    and gamma (:func:`collapsed_transition_log_prob`), so that the hyperparameters' moves count
    once.

    Args:
        z: (N, T) skills (-1 or anything at masked steps); mask: (N, T) bool;
        features: (N, K) 0/1; kappa, gamma: the hyperparameters.
        gated: as :func:`sequence_counts`' (a traced bool, false in the kernel's sticky phase:
            then the sticky BP-HMM's probability, the gate's part off; true without a gate:
            the switches' probability, the ends left out).
    """
    counts, rest = sequence_counts(z, mask, features, gate, gated)
    on = (gate is not None) if gated is None else gated
    return collapsed_transition_log_prob(counts, features, kappa, gamma, on) + rest


def eta_counts(z, mask, num_skills: int, gated=False):
    """The transition counts (N, K, K) that inform eta, float64: with state-dependent ends
    (``gated``: a bool, or a traced one, false in the kernel's sticky phase) the diagonal left
    out, since only the switches inform eta there (a skill that continues says nothing of it).
    The kernel's conditional, the collapsed sequence probability and split-merge count here."""
    from .hmm import transition_counts

    counts = transition_counts(jnp.where(mask, z, -1), mask, num_skills).astype(jnp.float64)
    if gated is False:
        return counts
    return jnp.where(jnp.eye(num_skills, dtype=bool) & jnp.asarray(gated, bool), 0.0, counts)


def sequence_counts(z, mask, features, gate=None, gated=None):
    """What :func:`collapsed_sequence_log_prob` needs of z: (transition counts (N, K, K), the
    terms that do not depend on kappa and gamma (N,)): the first skill's uniform probability,
    with ``gate`` the ends' and continuations' log-probabilities, and -inf where a sequence uses
    an inactive skill or a trajectory with steps has none. With state-dependent ends (``gated``:
    a bool or a traced one, false in the kernel's sticky phase; default: whether ``gate`` is
    given) the diagonal counts are left out (only switches inform eta); the ends' terms need
    ``gate`` (without it, gated: the ends are left to the caller, e.g. integrated out by
    :func:`collapsed_end_log_prob`)."""
    N, K = features.shape
    active = features > 0
    z = jnp.where(mask, z, -1)
    on = (gate is not None) if gated is None else gated
    counts = eta_counts(z, mask, K, on)  # (N, K, K)
    ends = 0.0
    if gate is not None:
        prev, nxt = jnp.clip(z[:, :-1], 0, K - 1), z[:, 1:]
        g = jnp.clip(jnp.take_along_axis(gate[:, 1:], prev[..., None], axis=-1)[..., 0], 1e-300, 1.0)
        step = jnp.where(nxt == prev, jnp.log1p(-jnp.minimum(g, 1.0 - 1e-16)), jnp.log(g))
        several = jnp.sum(active, -1) >= 2
        ends = jnp.where(several & on, jnp.sum(jnp.where(mask[:, 1:] & mask[:, :-1], step, 0.0), -1), 0.0)
    has_steps = jnp.any(mask, -1)
    n_active = jnp.sum(active, -1)
    init = jnp.where(has_steps, -jnp.log(jnp.maximum(n_active, 1)), 0.0)
    used = jnp.any(jax.nn.one_hot(z, K, dtype=bool) & mask[..., None], axis=1)
    ok = ~jnp.any(used & ~active, -1) & (n_active > 0)
    return counts, jnp.where(ok, ends + init, -jnp.inf)


def collapsed_transition_log_prob(counts, features, kappa, gamma, gated: bool = False):
    """The rows' Dirichlet-multinomial terms of :func:`collapsed_sequence_log_prob` from
    :func:`sequence_counts`' counts (N, K, K), per trajectory (N,); ``gated``: state-dependent
    ends (the diagonal left out, so kappa plays no part; a bool or a traced one)."""
    from jax.scipy.special import gammaln

    K = features.shape[1]
    active = features > 0
    conc = gamma + kappa * jnp.eye(K)
    pair = active[:, :, None] & active[:, None, :]
    if gated is not False:
        pair = pair & ~(jnp.eye(K, dtype=bool) & jnp.asarray(gated, bool))
    c = jnp.where(pair, conc, 0.0)
    c_row = jnp.sum(c, -1)
    row = (gammaln(jnp.maximum(c_row, 1e-300)) - gammaln(jnp.maximum(c_row + jnp.sum(counts, -1), 1e-300))
           + jnp.sum(jnp.where(pair, gammaln(c + counts) - gammaln(jnp.where(pair, c, 1.0)), 0.0), -1))
    row = jnp.where(c_row > 0, row, 0.0)  # (gated: a single skill's row has no switch to make)
    return jnp.sum(jnp.where(active, row, 0.0), -1)


def _hyper_value(name, value, hyperpriors):
    if hyperpriors is not None and name in hyperpriors:
        shape, rate = hyperpriors[name]
        return numpyro.sample(name, dist.Gamma(shape, rate))
    return jnp.asarray(value, dtype=jnp.float64)


def bphmm_model(data, emission, max_skills: int, alpha=1.0, kappa=10.0, gamma=1.0,
                hyperpriors: Optional[Dict] = None, termination: Optional[Termination] = None):
    """The BP-HMM joint density as a NumPyro model.

    Args:
        data: an :class:`~npbrs.models.emissions.HMMData` (N padded trajectories).
        emission: an :class:`~npbrs.models.emissions.Emission`.
        max_skills: truncation K.
        alpha, kappa, gamma: hyperparameter values (used when not sampled).
        hyperpriors: optional {"alpha" | "kappa" | "gamma": (shape, rate)} Gamma hyperpriors;
            a named hyperparameter becomes a sample site.
        termination: a :class:`Termination` for state-dependent ends (sites ``end_mean`` (K,)
            and ``ends`` (K, S)); None: the sticky BP-HMM.
    """
    N = data.states.shape[0]
    K = max_skills
    hyper = Hyper(_hyper_value("alpha", alpha, hyperpriors), _hyper_value("kappa", kappa, hyperpriors),
                  _hyper_value("gamma", gamma, hyperpriors))
    priors = prior_distributions(N, K, hyper)
    omega = numpyro.sample("omega", priors["omega"])
    features = numpyro.sample("features", priors["features"](omega))
    eta = numpyro.sample("eta", priors["eta"])
    gate = None
    if termination is not None:
        a, b = termination.mean_prior
        c, S = termination.concentration, termination.num_states
        mean = numpyro.sample("end_mean", dist.Beta(jnp.full((K,), a), b).to_event(1))
        shape = jnp.ones((1, S))
        ends = numpyro.sample("ends", dist.Beta(c * mean[:, None] * shape, c * (1.0 - mean[:, None]) * shape).to_event(2))
        gate = end_gate(ends, data.states, data.mask)
    params = emission.sample_params(K)
    log_lik, _ = emission.log_likelihoods(params, data, emission.init_cache(K))
    numpyro.factor("log_likelihood", jnp.sum(log_marginal_likelihoods(features, eta, log_lik, data.mask, gate)))


def log_joint_terms(omega, features, eta, params, log_marginals, hyper: Hyper, emission,
                    hyperpriors: Optional[Dict] = None, valid=None, ends=None, end_mean=None,
                    termination: Optional[Termination] = None):
    """The model's log density split into its terms, from already computed marginals.

    The kernel uses this to avoid recomputing emission log-likelihoods; a test checks that the
    sum equals ``numpyro.infer.util.log_density(bphmm_model, ...)``. ``valid`` (N,) bool: the
    trajectories that are data; the others (padding to a shape bucket, no steps) are left out
    of the feature and transition-weight terms, so the sum is the density of the real ones.
    With a ``termination``, ``ends`` (K, S) and ``end_mean`` (K,) add the terms "end_mean" and
    "ends" (``log_marginals`` must then come from the gated filter).
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
    if termination is not None:
        terms["end_mean"], terms["ends"] = end_log_prior(ends, end_mean, termination)
    if hyperpriors:
        for name, (shape, rate) in hyperpriors.items():
            terms[name] = dist.Gamma(shape, rate).log_prob(getattr(hyper, name))
    return terms


float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
