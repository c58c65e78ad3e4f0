"""Trans-dimensional moves of the BP-HMM sampler: data-driven birth and death of unique skills.

A skill is *unique* to trajectory i when i is the only trajectory that may use it
(f_ik = 1, m_k = 1); a slot is *unused* when no trajectory may use it (m_k = 0). Under the
weak-limit truncation every slot always has parameters; those of an unused slot do not touch
the data and follow the prior.

Birth (trajectory i, an unused slot k): switch f_ik on and propose the slot's parameters
from the emission's data-driven proposal fitted to a random window of trajectory i.
Death (trajectory i, one of its unique skills k): switch f_ik off and draw the slot's
parameters from the prior. The window is an auxiliary choice drawn independently of the
state, the same way in both directions, so each choice is a valid Metropolis-Hastings
kernel (DESIGN.md, "Sampler notes"). Both directions integrate out omega (the
beta-Bernoulli marginal of the features, :func:`npbrs.models.bphmm.collapsed_feature_log_prob`);
the sweep redraws omega from its conditional right after. The skill sequences are summed
out by the forward filter; only trajectory i's marginal likelihood changes.

With prior p0, proposal q(. | window), n_free unused slots before a birth and n_unique
unique skills of i after it, the birth's log acceptance ratio is

    [log p(x_i | f_i', params') - log p(x_i | f_i, params)] + log p0(params_k')
    + [log p(F') - log p(F)] - log q(params_k' | window) + log n_free - log n_unique'

and the death's is exactly its negative at the reversed states (:func:`birth_death_log_ratio`
of the current and the proposed state).
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from npbrs.models.mcmc import metropolis_accept, select
from npbrs.models.bphmm import collapsed_feature_log_prob, hmm_parameters
from npbrs.models.emissions import log_likelihoods_and_ok
from npbrs.models.hmm import forward_filter
from npbrs.domains.util.precision import float64_all

from .state import MoveState

__all__ = ["BirthDeathInfo", "birth_death", "birth_death_proposal", "birth_death_log_ratio", "window_weights"]


class BirthDeathInfo(NamedTuple):
    """Diagnostics of one birth/death trial: which move, whether it was possible and accepted,
    its log acceptance ratio (-inf when impossible), the trajectory i and the skill slot k."""

    is_birth: jax.Array
    possible: jax.Array
    accepted: jax.Array
    log_ratio: jax.Array
    i: jax.Array
    k: jax.Array


def window_weights(key, mask, i, min_len: int, max_len: int):
    """Weights (N, T) that are 1 on a random window of trajectory i and 0 elsewhere.

    The window's length is uniform on [min_len, max_len] (clipped to the trajectory) and its
    start uniform over the positions where it fits.
    """
    N, T = mask.shape
    length_i = jnp.sum(mask[i])
    k1, k2 = jax.random.split(key)
    hi = jnp.minimum(max_len, length_i)
    lo = jnp.minimum(min_len, hi)
    length = jax.random.randint(k1, (), lo, hi + 1)
    start = jax.random.randint(k2, (), 0, length_i - length + 1)
    t = jnp.arange(T)
    row = ((t >= start) & (t < start + length) & mask[i]).astype(jnp.float64)
    return jnp.zeros((N, T)).at[i].set(row)


def _skill_users(features, real):
    """m_k: the trajectories with steps that have skill k, (K,)."""
    return jnp.sum(jnp.where(real[:, None], features, 0.0), axis=0)


def _set_slot(params, k, one):
    return jax.tree.map(lambda p, o: p.at[k].set(o), params, one)


def _get_slot(params, k):
    return jax.tree.map(lambda p: p[k], params)


def _trajectory_log_marginal(features_i, eta_i, log_lik_i, mask_i, gate_i=None, gated=False):
    log_init, log_trans, active = hmm_parameters(features_i[None], eta_i[None], gated)
    lm, _ = forward_filter(log_init[0], log_trans[0], log_lik_i, mask_i, active[0], gate_i)
    return lm


def _one_log_lik(emission, data, one):
    """Per-step log-likelihoods (N, T) of a single skill's parameters and whether they are to be
    trusted, () bool (:func:`npbrs.models.emissions.log_likelihoods_and_ok`)."""
    params = jax.tree.map(lambda x: x[None], one)
    ll, _, ok = log_likelihoods_and_ok(emission, params, data, emission.init_cache(1))
    return ll[..., 0], ok[0]


def _birth_death_proposal(state: MoveState, emission, data, i, k, one, is_birth):
    """:func:`birth_death_proposal` and whether slot k's new likelihoods are ok."""
    features = state.features.at[i, k].set(jnp.where(is_birth, 1.0, 0.0))
    ll, ok = _one_log_lik(emission, data, one)
    log_lik = state.log_lik.at[:, :, k].set(ll)
    return state._replace(features=features, params=_set_slot(state.params, k, one), log_lik=log_lik), ok


def birth_death_proposal(state: MoveState, emission, data, i, k, one, is_birth) -> MoveState:
    """The state a birth (``is_birth``) or death of slot k in trajectory i proposes: f_ik on (or
    off), slot k's parameters replaced by ``one`` (the born skill's, or the prior draw that
    replaces a dying skill's) and their per-step log-likelihoods with them."""
    return _birth_death_proposal(state, emission, data, i, k, one, is_birth)[0]


def birth_death_log_ratio(current: MoveState, proposed: MoveState, emission, data, hyper, i, k, window, log_q=None):
    """log acceptance ratio of the move from ``current`` to ``proposed`` that switches f_ik on (a
    birth: ``proposed.features[i, k]`` is 1) or off (a death), slot k's parameters replaced
    (:func:`birth_death_proposal`); the death from ``proposed`` back to ``current`` has its
    negative. ``window`` (N, T): the proposal's weights; ``log_q``: the proposal's density of the
    born (or dying) skill's parameters, if already known."""
    features, new_features = current.features, proposed.features
    is_birth = new_features[i, k] > 0
    gate_i = None if current.gate is None else current.gate[i]  # the moves hold the ends' gate fixed
    gated = current.is_gated
    lm_old = _trajectory_log_marginal(features[i], current.eta[i], current.log_lik[i], data.mask[i], gate_i, gated)
    lm_new = _trajectory_log_marginal(new_features[i], proposed.eta[i], proposed.log_lik[i], data.mask[i], gate_i,
                                      gated)
    # the skill that is (or becomes) used: its parameters, prior and proposal density
    used = jax.tree.map(lambda n, o: jnp.where(is_birth, n, o), _get_slot(proposed.params, k),
                        _get_slot(current.params, k))
    log_p0 = emission.log_prior(jax.tree.map(lambda x: x[None], used))[0]
    if log_q is None:
        log_q = emission.log_proposal(used, data, window)
    real = jnp.any(data.mask, axis=1)  # trajectories without steps (padding) are left out
    m = _skill_users(features, real)
    m_new = _skill_users(new_features, real)
    n_free_before_birth = jnp.where(is_birth, jnp.sum(m == 0), jnp.sum(m_new == 0))
    unique_i = lambda f, m: jnp.sum((f[i] > 0) & (m == 1))  # noqa: E731
    n_unique_after_birth = jnp.where(is_birth, unique_i(new_features, m_new), unique_i(features, m))
    birth = (log_p0 - log_q + jnp.log(n_free_before_birth) - jnp.log(n_unique_after_birth))
    sign = jnp.where(is_birth, 1.0, -1.0)
    return (lm_new - lm_old) + (collapsed_feature_log_prob(new_features, hyper.alpha, real)
                                - collapsed_feature_log_prob(features, hyper.alpha, real)) + sign * birth


def birth_death(key, state: MoveState, emission, data, hyper, min_len: int = 10, max_len: int = 50):
    """One birth-or-death trial (each with probability 1/2) on a random trajectory: returns
    (state, :class:`BirthDeathInfo`). Impossible moves (no unused slot for a birth, or a born
    skill whose likelihoods the emission does not report ok, e.g. an unconverged solve; no unique
    skill, or only one skill, for a death) leave the state unchanged.
    """
    features = state.features
    N, K = features.shape
    k_type, k_i, k_win, k_slot, k_prop, k_prior, k_acc = jax.random.split(key, 7)
    is_birth = jax.random.bernoulli(k_type)
    # the trajectory among those with steps: trajectories that pad the data (shape buckets,
    # sharding) come last and are left out of the move and of the skills' counts, so that
    # padding does not change the draws
    real = jnp.any(data.mask, axis=1)
    i = jax.random.randint(k_i, (), 0, jnp.maximum(jnp.sum(real), 1))
    window = window_weights(k_win, data.mask, i, min_len, max_len)
    m = _skill_users(features, real)
    free = m == 0
    unique = (features[i] > 0) & (m == 1)
    candidates = jnp.where(is_birth, free, unique)
    # a death may not take a trajectory's last skill
    possible = jnp.any(candidates) & (is_birth | (features[i].sum() >= 2)) & real[i]
    k = jax.random.categorical(k_slot, jnp.where(candidates, 0.0, -jnp.inf))
    k = jnp.where(possible, k, 0)
    old_one = _get_slot(state.params, k)
    proposed, log_q_new, log_q_old = emission.propose_and_score(k_prop, data, window, old_one)
    with_prior = emission.sample_prior_one(k_prior)
    new_one = jax.tree.map(lambda b, d: jnp.where(is_birth, b, d), proposed, with_prior)
    new, new_ok = _birth_death_proposal(state, emission, data, i, k, new_one, is_birth)
    # a birth needs the born skill's likelihoods to be trusted (its solve converged); a death's
    # ratio holds the dying skill's, already in the state, and none of the prior draw's
    possible = possible & (new_ok | ~is_birth)
    log_ratio = birth_death_log_ratio(state, new, emission, data, hyper, i, k, window,
                                      log_q=jnp.where(is_birth, log_q_new, log_q_old))
    accept, _ = metropolis_accept(k_acc, log_ratio, possible)
    info = BirthDeathInfo(is_birth, possible, accept, jnp.where(possible, log_ratio, -jnp.inf), i, k)
    return select(accept, new, state), info


float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
