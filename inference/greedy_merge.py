"""Greedy merges of the BP-HMM sampler's warmup: an optimisation move that removes copies.

Started from random windows, the Gibbs sweeps on the paper's domains often settle with one or
two extra skills that are copies of a true skill (the same reward direction, a few hundred
steps that the main skill explains about as well). Started from the true segmentation, the
same sampler keeps the true skills at a *higher* log joint (``benchmarks/bench_oversplit.py``),
so the copies are a mixing failure, and the exact split-merge move rarely removes them: its
reverse split must re-create the copy by a deterministic allocation, which it does not.

This move is not a Metropolis-Hastings step. It runs only during warmup, whose draws are
discarded, so the chain's stationary distribution (the sampling sweeps) is unchanged; what it
changes is where the sampling sweeps start. A trial:

1. picks a used skill j uniformly, and the used skill k != j under whose current parameters
   j's steps have the highest likelihood;
2. proposes z' = z with j -> k, features f_k | f_j on k and j off;
3. keeps the merge when it raises the log joint *given the skill sequences*, with everything
   else integrated out: the transition weights and popularities exactly
   (``collapsed_sequence_log_prob``, ``collapsed_feature_log_prob``) and each skill's
   parameters by the emission's ``fit_evidence`` (exact for conjugate emissions, a Laplace
   approximation at an IRL fit for rewards):

       gain = log ev(steps of j and k) - log ev(steps of j) - log ev(steps of k)
              + log p(z' | F') - log p(z | F) + log p(F') - log p(F).

   Integrating the parameters out is what makes states with different numbers of skills
   comparable (a point density such as p0(theta_j) depends on the parametrisation); the
   evidence carries the Occam factor of the extra skill.

A kept merge gives k the fit to the union and slot j a prior draw (an unused slot's
conditional). The sweep redraws eta and omega given (z', F') right after, then the emission's
parameters.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from npbrs.models.bphmm import collapsed_feature_log_prob, collapsed_sequence_log_prob

__all__ = ["GreedyMergeInfo", "greedy_merge", "greedy_merge_at", "merge_score"]


class GreedyMergeInfo(NamedTuple):
    """Diagnostics of one greedy merge trial: the skills (j merged into k), whether it was
    possible and kept, and the change of the score."""

    j: jax.Array
    k: jax.Array
    possible: jax.Array
    accepted: jax.Array
    gain: jax.Array


def merge_score(emission, data, hyper, features, z, init=None):
    """log p(x, z, F) up to a constant: the log joint given the skill sequences with eta,
    omega and each used skill's parameters integrated out (the parameters by
    ``emission.fit_evidence``, fits started at ``init`` (K, ...) when given). Returns
    (score, fits (K, ...), log evidence per skill (K,), 0 for unused skills)."""
    K = features.shape[1]
    mask = data.mask
    onehot = jax.nn.one_hot(z, K, dtype=jnp.float64) * mask[..., None]
    used = jnp.sum(onehot, axis=(0, 1)) > 0
    fits, log_ev = emission.fit_evidence(data, onehot, init)
    log_ev = jnp.where(used, log_ev, 0.0)
    seq = jnp.sum(collapsed_sequence_log_prob(z, mask, features, hyper.kappa, hyper.gamma))
    return jnp.sum(log_ev) + seq + collapsed_feature_log_prob(features, hyper.alpha), fits, log_ev


def greedy_merge(key, emission, data, hyper, features, z, params, log_lik):
    """One greedy merge trial of a used skill chosen uniformly: returns (features, z, params,
    log_lik, info) (see :func:`greedy_merge_at`)."""
    K = features.shape[1]
    k_pick, k_move = jax.random.split(key)
    used = jnp.any(jax.nn.one_hot(z, K, dtype=bool) & data.mask[..., None], axis=(0, 1))
    j = jax.random.categorical(k_pick, jnp.where(used, 0.0, -jnp.inf))
    return greedy_merge_at(k_move, j, emission, data, hyper, features, z, params, log_lik)


def greedy_merge_at(key, j, emission, data, hyper, features, z, params, log_lik):
    """Merge skill j into the used skill that explains its steps best, if that raises
    :func:`merge_score`: returns (features, z, params, log_lik, info). ``log_lik`` (N, T, K)
    must hold the likelihoods of ``params``; the returned one holds those of the returned
    parameters. ``key`` draws slot j's new parameters from the prior. The emission needs
    ``fit_evidence``."""
    K = features.shape[1]
    mask = data.mask
    onehot = jax.nn.one_hot(z, K, dtype=jnp.float64) * mask[..., None]
    used = jnp.sum(onehot, axis=(0, 1)) > 0
    steps_j = onehot[..., j]
    absorb = jnp.sum(log_lik * steps_j[..., None], axis=(0, 1))  # (K,) likelihood of j's steps
    k = jnp.argmax(jnp.where(used & (jnp.arange(K) != j), absorb, -jnp.inf))
    possible = used[j] & (jnp.sum(used) >= 2)

    z_new = jnp.where(z == j, k, z).astype(z.dtype)
    f_new = features.at[:, k].set(jnp.maximum(features[:, k], features[:, j])).at[:, j].set(0.0)
    # the evidence of j's steps, k's steps and their union, fits started at the current parameters
    w = jnp.stack([steps_j, onehot[..., k], steps_j + onehot[..., k]], -1)
    init = jax.tree.map(lambda p: jnp.stack([p[j], p[k], p[k]]), params)
    fits, log_ev = emission.fit_evidence(data, w, init)
    seq = lambda zz, ff: jnp.sum(collapsed_sequence_log_prob(zz, mask, ff, hyper.kappa, hyper.gamma))  # noqa: E731
    gain = (log_ev[2] - log_ev[0] - log_ev[1] + seq(z_new, f_new) - seq(z, features)
            + collapsed_feature_log_prob(f_new, hyper.alpha) - collapsed_feature_log_prob(features, hyper.alpha))
    prior_j = emission.sample_prior_one(key)
    two = jax.tree.map(lambda a, b: jnp.stack([a[2], b]), fits, prior_j)  # new k, new j
    new_params = jax.tree.map(lambda p, t: p.at[k].set(t[0]).at[j].set(t[1]), params, two)
    cols, _ = emission.log_likelihoods(two, data, emission.init_cache(2))  # (N, T, 2)
    new_log_lik = log_lik.at[..., k].set(cols[..., 0]).at[..., j].set(cols[..., 1])
    accept = possible & jnp.isfinite(gain) & (gain > 0)
    pick = lambda a, b: jax.tree.map(lambda x, y: jnp.where(accept, x, y), a, b)  # noqa: E731
    info = GreedyMergeInfo(j, k, possible, accept, jnp.where(possible, gain, -jnp.inf))
    return pick(f_new, features), pick(z_new, z), pick(new_params, params), pick(new_log_lik, log_lik), info
