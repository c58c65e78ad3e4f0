"""Greedy merges and splits of the BP-HMM sampler's warmup: optimisation moves that remove
copies of a skill and separate skills that share one slot.

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
conditional).

A greedy split is the converse, for a start that lumps two true skills into one slot (seen on
the highway: ``benchmarks/NOTES.md``). It picks a used skill k1 and two of its steps (see
:func:`greedy_split`), allocates k1's steps between k1 and a free slot k2 by the split-merge
move's deterministic sequential allocation (:func:`npbrs.inference.sampler.split_merge.allocate`,
point fits refitted as the allocation grows), gives k2 the features of the trajectories that
use it, and keeps the split when the same score rises:

    gain = log ev(steps of k1') + log ev(steps of k2) - log ev(steps of k1)
           + log p(z' | F') - log p(z | F) + log p(F') - log p(F).

The sweep redraws eta and omega given (z', F') right after either move, then the emission's
parameters. Since every kept move raises the score, a merge never undoes a split at once.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from npbrs.models.mcmc import select
from npbrs.models.bphmm import collapsed_feature_log_prob, collapsed_sequence_log_prob

from npbrs.domains.precision import float64_all

from .split_merge import allocate, skill_counts, visiting_order
from .state import MoveState

__all__ = ["GreedyInfo", "greedy_merge", "greedy_merge_at", "greedy_split", "greedy_split_at", "greedy_trials",
           "merge_score"]


class GreedyInfo(NamedTuple):
    """Diagnostics of one greedy trial: the skills (j merged into k, or j split into j and k),
    whether it was possible and kept, and the change of the score (:func:`merge_score`; -inf
    when impossible)."""

    j: jax.Array
    k: jax.Array
    possible: jax.Array
    accepted: jax.Array
    gain: jax.Array


def merge_score(emission, data, hyper, features, z, init=None, gate=None):
    """log p(x, z, F) up to a constant: the log joint given the skill sequences with eta,
    omega and each used skill's parameters integrated out (the parameters by
    ``emission.fit_evidence``, fits started at ``init`` (K, ...) when given); ``gate``: the
    ends' (N, T, K) with state-dependent ends (then given the ends). The moves keep a change
    when it raises this score; they compute only the terms that change."""
    K = features.shape[1]
    onehot = jax.nn.one_hot(z, K, dtype=jnp.float64) * data.mask[..., None]
    _, log_ev = emission.fit_evidence(data, onehot, init)
    used = jnp.sum(onehot, axis=(0, 1)) > 0
    return jnp.sum(jnp.where(used, log_ev, 0.0)) + _structure_log_prob(hyper, data.mask, z, features, gate)


def _structure_log_prob(hyper, mask, z, features, gate=None):
    """log p(z | F) + log p(F), eta and omega integrated out (trajectories without steps,
    padding, left out); with state-dependent ends, given the ends' ``gate`` (the moves hold
    the ends fixed)."""
    valid = jnp.any(mask, axis=1)
    seq = collapsed_sequence_log_prob(z, mask, features, hyper.kappa, hyper.gamma, gate)
    return jnp.sum(jnp.where(valid, seq, 0.0)) + collapsed_feature_log_prob(features, hyper.alpha, valid)


class _Proposal(NamedTuple):
    """A greedy trial's proposed change, before the one evidence computation that scores it:
    the proposed (z, F); three step-weight columns ``w`` (N, T, 3) and the fits' starts
    ``init`` (3, ...) for ``fit_evidence``: (part, part, whole), a merge's parts being j and k,
    a split's its two new skills; ``merging``, which of the two it is (a merge's gain is
    whole - parts, and its second slot gets a prior draw from ``prior_key``; a split's gain is
    parts - whole, its slots the parts' fits); ``slots`` (2,), the skills that get new
    parameters; ``possible`` (for the info) and ``valid`` (further conditions of keeping it);
    ``j``, ``k``: the skills the info reports."""

    z: jax.Array
    features: jax.Array
    w: jax.Array
    init: dict
    merging: jax.Array
    slots: jax.Array
    prior_key: jax.Array
    possible: jax.Array
    valid: jax.Array
    j: jax.Array
    k: jax.Array


def _merge_proposal(key, state: MoveState, data, j) -> _Proposal:
    """Merge skill j into the used skill under whose parameters its steps are likeliest."""
    features, z, params, log_lik = state.features, state.z, state.params, state.log_lik
    K = features.shape[1]
    onehot = jax.nn.one_hot(z, K, dtype=jnp.float64) * data.mask[..., None]
    used = jnp.sum(onehot, axis=(0, 1)) > 0
    steps_j = onehot[..., j]
    absorb = jnp.sum(log_lik * steps_j[..., None], axis=(0, 1))  # (K,) likelihood of j's steps
    k = jnp.argmax(jnp.where(used & (jnp.arange(K) != j), absorb, -jnp.inf))
    z_new = jnp.where(z == j, k, z).astype(z.dtype)
    f_new = features.at[:, k].set(jnp.maximum(features[:, k], features[:, j])).at[:, j].set(0.0)
    # the evidence of j's steps, k's steps and their union, fits started at the current parameters
    w = jnp.stack([steps_j, onehot[..., k], steps_j + onehot[..., k]], -1)
    init = jax.tree.map(lambda p: jnp.stack([p[j], p[k], p[k]]), params)
    possible = used[j] & (jnp.sum(used) >= 2)
    slots = jnp.stack([k, j]).astype(jnp.int32)
    return _Proposal(z_new, f_new, w, init, jnp.bool_(True), slots, key, possible, jnp.bool_(True), jnp.int32(j),
                     jnp.int32(k))


def _split_proposal(key, state: MoveState, emission, data, anchors, num_blocks) -> _Proposal:
    """Split the skill of anchor a between it and a free slot, anchor b going to the slot, by
    the split-merge move's sequential allocation."""
    features, z, params = state.features, state.z, state.params
    mask = data.mask
    ia, ta, ib, tb = anchors
    k1 = z[ia, ta]
    real = jnp.any(mask, axis=1)  # (trajectories without steps, padding, count for no skill)
    free = jnp.sum(jnp.where(real[:, None], features, 0.0), axis=0) == 0  # no trajectory may use the slot
    k2 = jnp.argmax(free)
    possible = jnp.any(free) & (z[ib, tb] == k1) & ~((ia == ib) & (ta == tb)) & mask[ia, ta] & mask[ib, tb]
    order = visiting_order(key, mask, ia, ib)
    theta_k1 = jax.tree.map(lambda p: p[k1], params)
    z_new, alloc_fits = allocate(emission, data, z, features, k1, k2, anchors, order, theta_k1, num_blocks)
    z_new = z_new.astype(z.dtype)
    used_a = jnp.any((z_new == k1) & mask, axis=1)
    used_b = jnp.any((z_new == k2) & mask, axis=1)
    involved = features[:, k1] > 0
    f_new = features.at[:, k1].set(jnp.where(involved & ~used_a & used_b, 0.0, features[:, k1]))
    f_new = f_new.at[:, k2].set(used_b.astype(features.dtype))
    steps_a = ((z_new == k1) & mask).astype(jnp.float64)
    steps_b = ((z_new == k2) & mask).astype(jnp.float64)
    w = jnp.stack([steps_a, steps_b, steps_a + steps_b], -1)
    # the two parts' fits start at the allocation's, the whole's at k1's current parameters
    init = jax.tree.map(lambda a, p: jnp.stack([a[0], a[1], p]), alloc_fits, theta_k1)
    slots = jnp.stack([k1, k2]).astype(jnp.int32)
    return _Proposal(z_new, f_new, w, init, jnp.bool_(False), slots, key, possible, jnp.any(used_a) & jnp.any(used_b),
                     jnp.int32(k1), jnp.int32(k2))


def _keep_if_better(prop: _Proposal, state: MoveState, emission, data, hyper):
    """Score a proposal by the change of :func:`merge_score` (the three log evidences by one
    ``fit_evidence`` call), give its two slots their new parameters, and keep it when the score
    rises: (state, :class:`GreedyInfo`)."""
    features, z, params, log_lik = state.features, state.z, state.params, state.log_lik
    fits, log_ev = emission.fit_evidence(data, prop.w, prop.init)
    parts_minus_whole = log_ev[0] + log_ev[1] - log_ev[2]
    structure = (_structure_log_prob(hyper, data.mask, prop.z, prop.features, state.gate)
                 - _structure_log_prob(hyper, data.mask, z, features, state.gate))
    gain = jnp.where(prop.merging, -parts_minus_whole, parts_minus_whole) + structure
    prior = emission.sample_prior_one(prop.prior_key)
    # a merge: the whole's fit, then a prior draw; a split: the two parts' fits
    two = jax.tree.map(lambda f, p: jnp.where(prop.merging, jnp.stack([f[2], p]), f[:2]), fits, prior)
    a, b = prop.slots[0], prop.slots[1]
    new_params = jax.tree.map(lambda p, t: p.at[a].set(t[0]).at[b].set(t[1]), params, two)
    cols, _ = emission.log_likelihoods(two, data, emission.init_cache(2))  # (N, T, 2)
    new_log_lik = log_lik.at[..., a].set(cols[..., 0]).at[..., b].set(cols[..., 1])
    accept = prop.possible & prop.valid & jnp.isfinite(gain) & (gain > 0)
    info = GreedyInfo(prop.j, prop.k, prop.possible, accept, jnp.where(prop.possible, gain, -jnp.inf))
    new = state._replace(features=prop.features, z=prop.z, params=new_params, log_lik=new_log_lik)
    return select(accept, new, state), info


def _pick_merge(key, state: MoveState, data):
    """A used skill chosen uniformly, and the key of the rest of the trial."""
    K = state.features.shape[1]
    k_pick, k_move = jax.random.split(key)
    used = skill_counts(state.z, data.mask, K) > 0
    return jax.random.categorical(k_pick, jnp.where(used, 0.0, -jnp.inf)), k_move


def _pick_split(key, state: MoveState, data):
    """The skill (in proportion to its steps) and the two anchor steps of a split (see
    :func:`greedy_split`), and the key of the rest of the trial."""
    N, T = data.mask.shape
    features, z, log_lik = state.features, state.z, state.log_lik
    K = features.shape[1]
    k_pick, k_a, k_b, k_move = jax.random.split(key, 4)
    flat = (jax.nn.one_hot(z, K, dtype=bool) & data.mask[..., None]).reshape(N * T, K)
    counts = jnp.sum(flat, axis=0)
    k1 = jax.random.categorical(k_pick, jnp.where(counts > 0, jnp.log(jnp.maximum(counts, 1)), -jnp.inf))
    a = jax.random.categorical(k_a, jnp.where(flat[:, k1], 0.0, -jnp.inf))
    badness = -log_lik.reshape(N * T, K)[:, k1]
    b = jax.random.categorical(k_b, jnp.where(flat[:, k1] & (jnp.arange(N * T) != a), badness, -jnp.inf))
    return (a // T, a % T, b // T, b % T), k_move


def greedy_merge(key, state: MoveState, emission, data, hyper):
    """One greedy merge trial of a used skill chosen uniformly: returns (state,
    :class:`GreedyInfo`) (see :func:`greedy_merge_at`)."""
    j, k_move = _pick_merge(key, state, data)
    return greedy_merge_at(k_move, state, emission, data, hyper, j)


def greedy_merge_at(key, state: MoveState, emission, data, hyper, j):
    """Merge skill j into the used skill that explains its steps best, if that raises
    :func:`merge_score`: returns (state, :class:`GreedyInfo`). The state's ``log_lik`` holds
    the likelihoods of its ``params``, before and after. ``key`` draws slot j's new parameters
    from the prior. The emission needs ``fit_evidence``."""
    return _keep_if_better(_merge_proposal(key, state, data, j), state, emission, data, hyper)


def greedy_split(key, state: MoveState, emission, data, hyper, num_blocks: int = 2):
    """One greedy split trial: returns (state, :class:`GreedyInfo`) (see :func:`greedy_split_at`).
    The skill is drawn in proportion to its steps (a lumped pair is large), the first anchor
    uniformly among its steps, the second among its other steps in proportion to
    exp(-log-likelihood) under the skill (steps it explains badly are likely the other skill's).
    No reverse move is needed, so the choice may look at the state."""
    anchors, k_move = _pick_split(key, state, data)
    return greedy_split_at(k_move, state, emission, data, hyper, anchors, num_blocks)


def greedy_split_at(key, state: MoveState, emission, data, hyper, anchors, num_blocks: int = 2):
    """Split the skill of anchor step (i_a, t_a) between it and a free slot, the step
    (i_b, t_b) of the same skill going to the new slot, if that raises :func:`merge_score`
    (see the module notes): returns (state, :class:`GreedyInfo`). ``key`` orders the
    allocation's trajectories after the anchors'."""
    prop = _split_proposal(key, state, emission, data, anchors, num_blocks)
    return _keep_if_better(prop, state, emission, data, hyper)


def greedy_trials(key_merge, key_split, state: MoveState, emission, data, hyper, num_merges: int,
                  num_splits: int, num_blocks: int = 2):
    """``num_merges`` greedy merge trials (keys from ``key_merge``), then ``num_splits`` split
    trials (keys from ``key_split``), each as :func:`greedy_merge` and :func:`greedy_split`
    with the same random numbers: returns (state, kept merges, kept splits).

    The trials run in one loop whose body holds one ``fit_evidence`` and one
    ``log_likelihoods``; only the proposal differs between a merge and a split. For the reward
    emission, an evidence is an IRL fit and a Fisher information: one compiled copy instead of
    two is a large part of a fit's compile time."""
    if num_merges + num_splits == 0:
        return state, jnp.int32(0), jnp.int32(0)
    keys = jnp.concatenate([jax.random.split(key_merge, num_merges), jax.random.split(key_split, num_splits)]
                           if num_merges and num_splits else
                           [jax.random.split(key_merge if num_merges else key_split, num_merges + num_splits)])
    is_split = jnp.arange(num_merges + num_splits) >= num_merges

    def merge(key, carry):
        j, k_move = _pick_merge(key, carry, data)
        return _merge_proposal(k_move, carry, data, j)

    def split(key, carry):
        anchors, k_move = _pick_split(key, carry, data)
        return _split_proposal(k_move, carry, emission, data, anchors, num_blocks)

    def one(carry, x):
        key, splitting = x
        if num_merges and num_splits:
            prop = jax.lax.cond(splitting, split, merge, key, carry)
        else:
            prop = (merge if num_merges else split)(key, carry)
        carry, info = _keep_if_better(prop, carry, emission, data, hyper)
        return carry, info.accepted

    state, accepted = jax.lax.scan(one, state, (keys, is_split))
    return (state, jnp.sum(accepted & ~is_split, dtype=jnp.int32), jnp.sum(accepted & is_split, dtype=jnp.int32))


float64_all(globals())  # npbrs.domains.precision: float64 inside, the user's setting outside
