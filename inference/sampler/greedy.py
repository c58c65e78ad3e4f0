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
move's deterministic sequential allocation (:func:`npbrs.inference.sampler.split_merge.allocation`,
the two parts' fits refitted as the allocation grows, by the same ``fit_evidence`` call that
then scores the final allocation: :func:`_run_trial`), gives k2 the features of the
trajectories that use it, and keeps the split when the same score rises:

    gain = log ev(steps of k1') + log ev(steps of k2) - log ev(steps of k1)
           + log p(z' | F') - log p(z | F) + log p(F') - log p(F).

With state-dependent ends the structure term integrates the ends out too, given the skills'
mean end probabilities (each (skill, state) a Beta-binomial, ``collapsed_end_log_prob``; a
split's new skill starts with its parent's mean): scored given the chain's current ends, a
proposed skill would pay for ends drawn for other steps (a split's new slot holds a prior draw),
and on the highway under ``switching="state"`` the moves then kept extra skills (one-to-one
accuracy 0.915 against 0.983 with the ends integrated out, ``benchmarks/NOTES.md``).

The sweep redraws eta and omega given (z', F') right after either move, then the emission's
parameters (and with state-dependent ends the ends' means and the ends). Since every kept move raises the score, a merge never undoes a split at once.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from npbrs.models.mcmc import select
from npbrs.models.bphmm import collapsed_end_log_prob, collapsed_feature_log_prob, collapsed_sequence_log_prob

from npbrs.domains.util.precision import float64_all

from .split_merge import Allocation, allocate_block, allocated_steps, allocation, skill_counts, visiting_order
from .state import MoveState

__all__ = ["GreedyInfo", "greedy_merge", "greedy_merge_at", "greedy_split", "greedy_split_at", "greedy_trials",
           "merge_score", "structure_log_prob"]


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
    return jnp.sum(jnp.where(used, log_ev, 0.0)) + structure_log_prob(hyper, data.mask, z, features, gate)


def structure_log_prob(hyper, mask, z, features, gate=None, gated=None, end_model=None, states=None):
    """log p(z | F) + log p(F) with eta and omega integrated out: the part of the greedy moves'
    score (:func:`merge_score`) that the skill sequences and features make, trajectories
    without steps (padding) left out.

    Args:
        hyper: :class:`~npbrs.models.bphmm.Hyper` (alpha, kappa, gamma).
        mask: (N, T) bool, the real steps.
        z: (N, T) int skill sequences (-1 on padding).
        features: (N, K) 0/1.
        gate: with state-dependent ends, their (N, T, K) gate (the switches given the ends);
            None: the sticky BP-HMM.
        gated: with a gate, a traced bool, false in the kernel's sticky phase; None: True.
        end_model: with state-dependent ends, (ends (K, S), their means (K,), concentration):
            the ends integrated out given their means (each (skill, state) a Beta-binomial),
            instead of the ``gate``'s.
        states: (N, T) int, the data's states (needed with ``end_model``).

    Returns:
        () float, the log probability.
    """
    valid = jnp.any(mask, axis=1)
    ends = 0.0
    if end_model is not None:  # (the switches' probability without a gate; the ends integrated out)
        ends_ks, mean, conc = end_model
        gate, gated = None, (True if gated is None else gated)
        ends = jnp.where(gated, jnp.sum(collapsed_end_log_prob(z, mask, states, features, mean, conc,
                                                               ends_ks.shape[1])), 0.0)
    seq = collapsed_sequence_log_prob(z, mask, features, hyper.kappa, hyper.gamma, gate, gated)
    return jnp.sum(jnp.where(valid, seq, 0.0)) + ends + collapsed_feature_log_prob(features, hyper.alpha, valid)


class _Trial(NamedTuple):
    """A greedy trial before its fits (:func:`_run_trial`): ``merging`` (a merge or a split);
    the three fits' starts ``init`` (3, ...) and their first step weights: ``parts`` (N, T, 2)
    and ``whole`` (N, T), a merge's parts being j and k (the whole their union), a split's its
    two new skills, whose steps the allocation ``plan`` makes (the whole: k1's steps);
    ``z``, ``features``: a merge's proposed (z, F), a split's current ones; ``slots`` (2,),
    the skills that get new parameters; ``prior_key`` (a merge's second slot gets a prior
    draw); ``possible`` (for the info); ``j``, ``k``: the skills the info reports."""

    merging: jax.Array
    init: dict
    parts: jax.Array
    whole: jax.Array
    z: jax.Array
    features: jax.Array
    slots: jax.Array
    prior_key: jax.Array
    possible: jax.Array
    j: jax.Array
    k: jax.Array
    plan: Allocation


def _merge_trial(key, state: MoveState, data, j, num_blocks) -> _Trial:
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
    init = jax.tree.map(lambda p: jnp.stack([p[j], p[k], p[k]]), params)
    possible = used[j] & (jnp.sum(used) >= 2)
    slots = jnp.stack([k, j]).astype(jnp.int32)
    # (no allocation: a plan of empty blocks, its anchors anywhere)
    zero = jnp.int32(0)
    plan = allocation(data, z, features, k, j, (zero, zero, zero, zero), jnp.arange(z.shape[0]), num_blocks)
    plan = plan._replace(rows=jnp.full_like(plan.rows, -1))
    return _Trial(jnp.bool_(True), init, jnp.stack([steps_j, onehot[..., k]], -1), steps_j + onehot[..., k], z_new,
                  f_new, slots, key, possible, jnp.int32(j), jnp.int32(k), plan)


def _split_trial(key, state: MoveState, data, anchors, num_blocks) -> _Trial:
    """Split the skill of anchor a between it and a free slot, anchor b going to the slot, by
    the split-merge move's sequential allocation (its steps run in :func:`_run_trial`)."""
    features, z, params = state.features, state.z, state.params
    mask = data.mask
    ia, ta, ib, tb = anchors
    k1 = z[ia, ta]
    real = jnp.any(mask, axis=1)  # (trajectories without steps, padding, count for no skill)
    free = jnp.sum(jnp.where(real[:, None], features, 0.0), axis=0) == 0  # no trajectory may use the slot
    k2 = jnp.argmax(free)
    possible = jnp.any(free) & (z[ib, tb] == k1) & ~((ia == ib) & (ta == tb)) & mask[ia, ta] & mask[ib, tb]
    plan = allocation(data, z, features, k1, k2, anchors, visiting_order(key, mask, ia, ib), num_blocks)
    # the parts' fits start at k1's current parameters, and so does the whole's
    init = jax.tree.map(lambda p: jnp.stack([p[k1], p[k1], p[k1]]), params)
    slots = jnp.stack([k1, k2]).astype(jnp.int32)
    whole = ((z == k1) & mask).astype(jnp.float64)
    return _Trial(jnp.bool_(False), init, plan.start, whole, z, features, slots, key, possible, jnp.int32(k1),
                  jnp.int32(k2), plan)


def _run_trial(trial: _Trial, state: MoveState, emission, data, hyper):
    """Fit and score a trial by the change of :func:`merge_score`, give its two slots their new
    parameters, and keep it when the score rises: (state, :class:`GreedyInfo`).

    One loop of the allocation's ``num_blocks + 1`` steps, each one ``fit_evidence`` of three
    columns (the two parts, the whole) with the fits' likelihoods, so that the program holds
    one compiled copy of it (for the reward emission, an IRL fit with its solves and their
    adjoints; the likelihoods come from the fits' own soft values, no solve). A split's step
    fits the parts to the allocation so far (the whole again from its start, the same fit each
    time), then allocates the step's block; its last step (no block) fits the final allocation
    and computes the evidences. A merge runs the last step only. The kept likelihood columns
    are the last step's: a split's parts', a merge's whole's for skill k; a merge's slot j, its
    parameters a prior draw, keeps its column (see :func:`greedy_merge_at`)."""
    plan, merging = trial.plan, trial.merging
    N = data.mask.shape[0]
    last_step = plan.rows.shape[0] - 1
    prior = emission.sample_prior_one(trial.prior_key)
    nan3 = jnp.full((3,), jnp.nan)
    old_j = state.log_lik[..., trial.slots[1]]  # (a merge's slot j: its column, kept)

    def pair(fits, final):
        """The two slots' parameters at the end: a merge's whole and a prior draw, a split's parts."""
        return jax.tree.map(lambda f, p: jnp.where(merging & final, jnp.stack([f[2], p]), f[:2]), fits, prior)

    def pair_lik(lik3, final):
        """The two columns of likelihoods a step needs, of the fits' three (N, T, 3): the
        allocation's parts, or at a merge's end the whole's and slot j's own."""
        return jnp.where(merging & final, jnp.stack([lik3[..., 2], old_j], -1), lik3[..., :2])

    def fit_step(carry, x):
        z, done, parts, fits, log_ev, lik = carry
        rows, fit_on, step = x
        last = step == last_step

        def fit(operand):
            fits, _, _ = operand
            # the parts from the last fits, the whole from its start
            init = jax.tree.map(lambda f, i: i.at[:2].set(f[:2]), fits, trial.init)
            w = jnp.concatenate([parts, trial.whole[..., None]], -1)
            new, log_ev, lik3 = _fit_evidence(emission, data, w, init, last)
            return new, log_ev, pair_lik(lik3, last)

        run = jnp.where(merging, last, fit_on | last)
        fits, log_ev, lik = jax.lax.cond(run, fit, lambda operand: operand, (fits, log_ev, lik))
        z, done = jax.lax.cond(jnp.any(rows >= 0), lambda zd: allocate_block(plan, data, *zd, lik, rows),
                               lambda zd: zd, (z, done))
        parts = jnp.where(merging, parts, allocated_steps(plan, data, z, done))
        return (z, done, parts, fits, log_ev, lik), None

    steps = jnp.arange(last_step + 1)
    start = (trial.z, jnp.zeros(N, bool), trial.parts, trial.init, nan3, jnp.zeros(data.mask.shape + (2,)))
    (z_alloc, _, parts, fits, log_ev, lik), _ = jax.lax.scan(fit_step, start, (plan.rows, plan.fit_on, steps))
    # a split's proposed state: k2 gets the features of the trajectories that use it, and k1
    # loses those of the involved trajectories that use only k2 now
    mask, k1, k2 = data.mask, plan.k1, plan.k2
    used_a = jnp.any((z_alloc == k1) & mask, axis=1)
    used_b = jnp.any((z_alloc == k2) & mask, axis=1)
    f = trial.features
    involved = f[:, k1] > 0
    f_split = f.at[:, k1].set(jnp.where(involved & ~used_a & used_b, 0.0, f[:, k1])).at[:, k2].set(
        used_b.astype(f.dtype))
    z_new = jnp.where(merging, trial.z, z_alloc.astype(trial.z.dtype))
    f_new = jnp.where(merging, trial.features, f_split)
    valid = merging | (jnp.any(used_a) & jnp.any(used_b))

    features, z, params, log_lik = state.features, state.z, state.params, state.log_lik
    parts_minus_whole = log_ev[0] + log_ev[1] - log_ev[2]
    end_model, end_new = state.end_model, state.end_model
    if end_model is not None:  # a split's new skill starts with its parent's mean end probability
        mean = end_model[1]
        end_new = (end_model[0], jnp.where(merging, mean, mean.at[trial.k].set(mean[trial.j])), end_model[2])
    structure = (structure_log_prob(hyper, data.mask, z_new, f_new, state.gate, state.gated, end_new, data.states)
                 - structure_log_prob(hyper, data.mask, z, features, state.gate, state.gated, end_model,
                                      data.states))
    gain = jnp.where(merging, -parts_minus_whole, parts_minus_whole) + structure
    two = pair(fits, True)  # (the last step's: ``lik`` holds their likelihoods)
    a, b = trial.slots[0], trial.slots[1]
    new_params = jax.tree.map(lambda p, t: p.at[a].set(t[0]).at[b].set(t[1]), params, two)
    new_log_lik = log_lik.at[..., a].set(lik[..., 0]).at[..., b].set(lik[..., 1])
    accept = trial.possible & valid & jnp.isfinite(gain) & (gain > 0)
    info = GreedyInfo(trial.j, trial.k, trial.possible, accept, jnp.where(trial.possible, gain, -jnp.inf))
    new = state._replace(features=f_new, z=z_new, params=new_params, log_lik=new_log_lik, end_model=end_new)
    return select(accept, new, state), info


def _fit_evidence(emission, data, weights, init, with_evidence):
    """``emission.fit_evidence`` and the fits' likelihoods (N, T, M): (fits, log evidences,
    likelihoods). It is told when only the fits are needed if it declares ``fits_without_evidence``
    (an emission without it computes its evidences always), and asked for the likelihoods if it
    declares ``fits_with_likelihoods`` (the reward emission's come from its fits' soft values);
    otherwise they are the fits' ``log_likelihoods``."""
    kwargs = {"with_evidence": with_evidence} if emission.fits_without_evidence else {}
    if emission.fits_with_likelihoods:
        return emission.fit_evidence(data, weights, init, with_likelihoods=True, **kwargs)
    fits, log_ev = emission.fit_evidence(data, weights, init, **kwargs)
    lik, _ = emission.log_likelihoods(fits, data, emission.init_cache(weights.shape[-1]))
    return fits, log_ev, lik


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
    the likelihoods of its ``params`` before; after a kept merge, those of every skill with
    steps, while slot j (no steps now) keeps its column. ``key`` draws slot j's new parameters
    from the prior: an unused slot's likelihoods are read by no greedy trial (they pick among
    skills with steps) and the sweep computes every slot's anew after the emission's update, so
    the draw's are not solved for here. The emission needs ``fit_evidence``."""
    return _run_trial(_merge_trial(key, state, data, j, 1), state, emission, data, hyper)


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
    return _run_trial(_split_trial(key, state, data, anchors, num_blocks), state, emission, data, hyper)


def greedy_trials(key_merge, key_split, state: MoveState, emission, data, hyper, num_merges: int,
                  num_splits: int, num_blocks: int = 2):
    """``num_merges`` greedy merge trials (keys from ``key_merge``), then ``num_splits`` split
    trials (keys from ``key_split``), each as :func:`greedy_merge` and :func:`greedy_split`
    with the same random numbers: returns (state, kept merges, kept splits).

    The trials run in one loop whose body holds one ``fit_evidence`` and one
    ``log_likelihoods`` (:func:`_run_trial`: a split's allocation fits by them too); only the
    setup differs between a merge and a split. For the reward emission, an evidence is an IRL
    fit and a Fisher information: one compiled copy instead of three is a large part of a
    fit's compile time."""
    if num_merges + num_splits == 0:
        return state, jnp.int32(0), jnp.int32(0)
    keys = jnp.concatenate([jax.random.split(key_merge, num_merges), jax.random.split(key_split, num_splits)]
                           if num_merges and num_splits else
                           [jax.random.split(key_merge if num_merges else key_split, num_merges + num_splits)])
    is_split = jnp.arange(num_merges + num_splits) >= num_merges

    def merge(key, carry):
        j, k_move = _pick_merge(key, carry, data)
        return _merge_trial(k_move, carry, data, j, num_blocks)

    def split(key, carry):
        anchors, k_move = _pick_split(key, carry, data)
        return _split_trial(k_move, carry, data, anchors, num_blocks)

    def one(carry, x):
        key, splitting = x
        if num_merges and num_splits:
            trial = jax.lax.cond(splitting, split, merge, key, carry)
        else:
            trial = (merge if num_merges else split)(key, carry)
        carry, info = _run_trial(trial, carry, emission, data, hyper)
        return carry, info.accepted

    state, accepted = jax.lax.scan(one, state, (keys, is_split))
    return (state, jnp.sum(accepted & ~is_split, dtype=jnp.int32), jnp.sum(accepted & is_split, dtype=jnp.int32))


float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
