"""The exact Gibbs conditionals of the sweep, as functions of arrays.

:meth:`~npbrs.inference.sampler.kernel.BPHMMKernel.sweep` draws, in turn, the features with the
skill sequences summed out (:func:`sample_features`), the skill sequences (forward filtering,
backward sampling, ``npbrs.models.hmm``), the hyperparameters with a prior
(:func:`sample_hyperparameters`), eta and omega (:func:`sample_eta_omega`) and with
state-dependent ends their means and the ends (:func:`sample_end_model`). Every density is one
of the model's own (``npbrs.models.bphmm``).

Trajectories without steps (padding to a shape bucket or to the devices, after the real ones)
are left out of the model: their features and transition weights are drawn (from the prior
given omega) but nothing reads them: omega's conditional, the moves' counts of skill users and
the log joint count the real trajectories only, and every random draw is numbered per
trajectory, so a padded run's draws of the real trajectories are the unpadded run's.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpyro.distributions as dist

from npbrs.models.bphmm import (Hyper, Termination, collapsed_feature_log_prob, collapsed_transition_log_prob,
                                end_counts, eta_counts, eta_from_gammas, eta_gamma_shapes, log_marginal_likelihoods,
                                sample_end_means, sample_ends, sequence_counts)
from npbrs.models.mcmc import metropolis_accept

from npbrs.domains.util.precision import float64_all

__all__ = ["HYPER_STEPS", "feature_conditional", "sample_features", "sample_eta_omega", "sample_end_model",
           "sample_hyperparameters"]

#: random-walk Metropolis steps per sweep on each sampled hyperparameter's log (cheap: the
#: counts are made once, each step is O(N K^2))
HYPER_STEPS = 10


def feature_conditional(features, k, eta, log_lik, omega, mask, gate=None, gated=None, current=None):
    """The conditional of f_ik for every trajectory i, with the skill sequences summed out.

    Args:
        features: (N, K) 0/1, the features it is conditioned on (f_ik's own value aside).
        k: the skill.
        eta: (N, K, K) transition weights. log_lik: (N, T, K) per-step log-likelihoods.
        omega: (K,) skill popularities. mask: (N, T) the real steps.
        gate: the ends' (N, T, K) gate with state-dependent ends, else None; gated: as
            ``log_marginal_likelihoods``' (a traced bool, false in the sticky phase).
        current: (N,) the trajectories' log marginals under ``features`` when known (the sweep
            carries them); None: filtered here.

    Returns:
        (logits log p(f_ik = 1 | rest) - log p(f_ik = 0 | rest) (N,), log marginals with
        f_ik = 1 (N,), with f_ik = 0 (N,)).
    """
    off = features.at[:, k].set(0.0)
    if current is None:
        current = log_marginal_likelihoods(features, eta, log_lik, mask, gate, gated)
    is_on = features[:, k] > 0
    flipped = features.at[:, k].set(jnp.where(is_on, 0.0, 1.0))
    lm_flip = log_marginal_likelihoods(flipped, eta, log_lik, mask, gate, gated)
    lm_on, lm_off = jnp.where(is_on, current, lm_flip), jnp.where(is_on, lm_flip, current)
    # a trajectory must keep at least one skill (to emit its steps: one without steps, padding
    # to a shape bucket, may have none, or its features would weigh on omega)
    lm_off = jnp.where((jnp.sum(off, -1) > 0) | ~jnp.any(mask, axis=1), lm_off, -jnp.inf)
    prior = dist.Bernoulli(probs=omega[k])
    return (lm_on + prior.log_prob(1.0)) - (lm_off + prior.log_prob(0.0)), lm_on, lm_off


def sample_features(key, features, eta, log_lik, omega, mask, current, gate=None, gated=None):
    """Gibbs on every f_ik with z summed out; skills in turn, trajectories at once (given omega,
    the trajectories' features are conditionally independent). The log marginals of the current
    features are carried from skill to skill, so each skill filters every trajectory once, with
    its feature flipped.

    Args:
        key: a PRNG key.
        features: (N, K) 0/1, the current features.
        eta, log_lik, omega, mask, gate, gated: as :func:`feature_conditional`'s.
        current: (N,) the log marginals of ``features`` under ``gate`` and ``gated`` (the
            state's, which the kernel's ``_finish`` computed, or the sticky phase's).

    Returns:
        (N, K) the new features.
    """
    K = features.shape[1]

    def one_skill(carry, k_key):
        features, current = carry
        k, key = k_key
        logit, lm_on, lm_off = feature_conditional(features, k, eta, log_lik, omega, mask, gate, gated, current)
        new = jax.random.bernoulli(key, jax.nn.sigmoid(logit))
        return (features.at[:, k].set(new.astype(features.dtype)), jnp.where(new, lm_on, lm_off)), None

    (features, _), _ = jax.lax.scan(one_skill, (features, current), (jnp.arange(K), jax.random.split(key, K)))
    return features


def sample_eta_omega(key, z, features, hyper: Hyper, mask, switches_only):
    """eta | z, F and omega | F, from a single batch of Gamma draws (one Gamma sampler in the
    compiled sweep instead of five).

    eta: Dirichlet(conc + counts) proportions over the active skills times a Gamma(sum conc)
    total (the Gamma-Dirichlet decomposition); inactive entries keep their Gamma prior.
    omega_k ~ Beta(alpha/K + m_k, 1 + N - m_k) as a ratio of Gammas, N and m_k counting the
    trajectories with steps.

    The draws are laid out omega's first, then trajectory by trajectory (K^2 + K each): JAX's
    partitionable threefry numbers each draw by its position, so a trajectory's draws do not
    depend on how many trajectories follow it (padding the data with empty trajectories, for
    shape buckets or devices, leaves the real ones' draws alone). (Under a mesh that shards the
    trajectories the batch is gathered: JAX's Gamma sampler flattens it; it is small next to
    the filtering.)

    Args:
        key: a PRNG key.
        z: (N, T) skill sequences (-1 on padding). features: (N, K) 0/1.
        hyper: :class:`~npbrs.models.bphmm.Hyper`. mask: (N, T) the real steps.
        switches_only: whether only the switches inform eta (state-dependent ends; a traced
            bool, false in the sticky phase, where the stays inform eta's diagonal as in the
            sticky BP-HMM).

    Returns:
        (eta (N, K, K), omega (K,)).
    """
    N, K = features.shape
    counts = eta_counts(z, mask, K, switches_only)
    shape_g, shape_total, active = eta_gamma_shapes(counts, features, hyper)
    valid = jnp.any(mask, axis=1)
    m = jnp.sum(jnp.where(valid[:, None], features, 0.0), axis=0)
    n = jnp.sum(valid).astype(m.dtype)
    shape_omega = jnp.concatenate([hyper.alpha / K + m, 1.0 + n - m])  # (2K,)
    per_trajectory = jnp.concatenate([shape_g.reshape(N, K * K), shape_total], axis=1)  # (N, K^2 + K)
    shapes = jnp.concatenate([shape_omega, per_trajectory.ravel()])
    draws = jnp.maximum(jax.random.gamma(key, jnp.maximum(shapes, 1e-300)), 1e-300)
    a, b = draws[:2 * K].reshape(2, K)
    rows = draws[2 * K:].reshape(N, K * K + K)
    g = rows[:, :K * K].reshape(N, K, K)
    total = rows[:, K * K:].reshape(N, K, 1)
    eta = eta_from_gammas(g, total, active)
    omega = jnp.clip(a / (a + b), 1e-300, 1.0 - 1e-16)
    return eta, omega


def sample_end_model(key, z, features, end_mean, data, termination: Termination):
    """(mu, beta) | z: the skills' mean end probabilities by Metropolis with the ends integrated
    out, then the ends from their Beta conditional.

    Args:
        key: a PRNG key.
        z: (N, T) skill sequences. features: (N, K) 0/1. end_mean: (K,) the current means.
        data: HMMData (its states and mask). termination: the ends' prior.

    Returns:
        (end_mean (K,), ends (K, S)).
    """
    counts = end_counts(z, data.mask, data.states, features, termination.num_states)
    k1, k2 = jax.random.split(key)
    end_mean = sample_end_means(k1, end_mean, counts, termination)
    return end_mean, sample_ends(k2, end_mean, counts, termination)


def sample_hyperparameters(key, z, features, hyper: Hyper, hyperpriors, mask, gate=None, gated=None,
                           steps: int = HYPER_STEPS) -> Hyper:
    """The hyperparameters with a prior given the skill sequences and the features, with omega
    and eta integrated out: alpha's target is log p(F | alpha)
    (:func:`~npbrs.models.bphmm.collapsed_feature_log_prob`), kappa's and gamma's
    log p(z | F, kappa, gamma) (the rows' Dirichlet-multinomials,
    :func:`~npbrs.models.bphmm.collapsed_transition_log_prob`), each times its Gamma
    hyperprior; ``steps`` random-walk Metropolis steps each on the log scale (in turn). The sweep
    then draws eta and omega given the new values: together a blocked Gibbs step of
    (hyperparameters, eta, omega) | z, F. Conditioned on eta instead, kappa barely moves (eta's
    row totals, which the data do not inform, are drawn with the current kappa; see
    ``benchmarks/NOTES.md``).

    Args:
        key: a PRNG key.
        z: (N, T) skill sequences. features: (N, K) 0/1. hyper: the current values.
        hyperpriors: {"alpha" | "kappa" | "gamma": (shape, rate)}: those sampled, in this order.
        mask: (N, T) the real steps.
        gate: the ends' (N, T, K) gate with state-dependent ends (then kappa plays no part),
            else None; gated: a traced bool, false in the sticky phase (None: whether a gate is given).
        steps: Metropolis steps per hyperparameter.

    Returns:
        Hyper, the others as they are.
    """
    valid = jnp.any(mask, axis=1)
    counts, _ = sequence_counts(z, mask, features, gate, gated)
    gated = (gate is not None) if gated is None else gated

    def log_target(name, h):
        shape, rate = hyperpriors[name]
        prior = dist.Gamma(shape, rate).log_prob(getattr(h, name))
        if name == "alpha":
            return prior + collapsed_feature_log_prob(features, h.alpha, valid)
        seq = collapsed_transition_log_prob(counts, features, h.kappa, h.gamma, gated)
        return prior + jnp.sum(jnp.where(valid, seq, 0.0))

    for name, k in zip(hyperpriors, jax.random.split(key, len(hyperpriors))):
        def step(h, k, name=name):
            k1, k2 = jax.random.split(k)
            old = getattr(h, name)
            prop = old * jnp.exp(0.3 * jax.random.normal(k1))
            cand = h._replace(**{name: prop})
            # log-scale proposal: Jacobian log(prop / old)
            log_ratio = log_target(name, cand) - log_target(name, h) + jnp.log(prop) - jnp.log(old)
            accept, _ = metropolis_accept(k2, log_ratio)
            return h._replace(**{name: jnp.where(accept, prop, old)}), None

        hyper, _ = jax.lax.scan(step, hyper, jax.random.split(k, steps))
    return hyper


float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
