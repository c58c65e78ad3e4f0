"""Hidden Markov model inference on arrays: forward filter, backward sampler, smoother, Viterbi.

Pure JAX functions, one ``lax.scan`` over time each, jit- and vmap-friendly: the forward filter
runs in probability space (see :func:`forward_filter`), the others in log space.
They know nothing about emission models: an emission supplies the ``(T, K)`` array of
per-step log-likelihoods ``log_lik[t, k] = log p(x_t | z_t = k)``.

Conventions shared by every function here:

- ``mask`` (T,) bool marks real steps; False marks padding. A masked step is skipped: it
  neither emits nor advances the chain, so padding at the end of a ragged trajectory changes
  nothing, and whatever ``log_lik`` holds there is ignored.
- ``active`` (K,) bool (optional; all True when omitted) marks the skills a trajectory may
  use (its features f_i). ``log_init`` and the rows of ``log_trans`` are restricted to the
  active skills and renormalised over them, so they may be given unnormalised: passing
  ``log eta_i`` with ``active = f_i`` gives ``pi_i = eta_i f_i / sum``, and ``log_init = 0``
  gives a uniform start over the active skills. Inactive skills get the finite log weight
  ``NEG_LOG`` internally, never -inf (a row of -inf makes NaN in values and gradients), so an
  inactive skill has probability exactly 0 after exponentiation, one active skill is enough,
  and -inf entries in the inputs are safe. At least one skill must be active.
- Skill sequences use ``-1`` at padded steps.
- ``gate`` (T, K) (optional) makes the transitions depend on the step: ``gate[t, k]`` is the
  probability that skill k *ends* on entering step t (e.g. its termination in the state
  reached at t), and the transition into step t is
  ``A_t[k, j] = (1 - gate[t, k]) [j == k] + gate[t, k] pi[k, j]``: the skill continues, or it
  ends and the next one is drawn from row k of ``log_trans`` (which then usually puts no
  weight on k itself). ``gate[0]`` is not used. Without a gate, ``A_t = pi`` at every step.
  Padding must come at the end of a trajectory when a gate is given (the gate of the step
  after a real step is read from the next row).
"""

from __future__ import annotations

from typing import Tuple

import jax
import jax.numpy as jnp
from npbrs.domains.util.precision import float64_all

__all__ = ["NEG_LOG", "forward_filter", "backward_sample", "smooth", "path_log_prob", "viterbi", "batch_forward_filter",
           "batch_backward_sample", "batch_smooth", "batch_viterbi", "transition_counts", "initial_counts",
           "inverse_transform"]

# Stands in for log 0. exp(NEG_LOG) is exactly 0 in float32 and float64, and sums of a few of
# them stay far from overflow; any real log-likelihood is far above it.
NEG_LOG = -1e10

# The forward filter's floor on an active skill's prediction, exp(-700): no normaliser can
# underflow (see :func:`forward_filter`).
_FLOOR = 9.85967654375977e-305


def _prepare(log_init, log_trans, active):
    """Restrict to the active skills, renormalise, and replace log 0 by NEG_LOG."""
    K = log_trans.shape[-1]
    if active is None:
        active = jnp.ones(K, dtype=bool)
    active = jnp.asarray(active, dtype=bool)
    pair = active[:, None] & active[None, :]
    log_trans = jnp.where(pair, jnp.maximum(log_trans, NEG_LOG), NEG_LOG)
    log_trans = log_trans - jax.nn.logsumexp(log_trans, axis=-1, keepdims=True)
    log_trans = jnp.where(pair, log_trans, NEG_LOG)
    out = (active, log_trans)
    if log_init is not None:
        log_init = jnp.where(active, jnp.maximum(log_init, NEG_LOG), NEG_LOG)
        log_init = log_init - jax.nn.logsumexp(log_init)
        log_init = jnp.where(active, log_init, NEG_LOG)
        out = out + (log_init,)
    return out


def _next_gate(gate, T, K, dtype):
    """The gate of the *next* step at each step, (T, K): a gate's rows shifted up by one (the
    last row, which nothing reads, is 1: the skill ends), kept within [tiny, 1]."""
    gate = jnp.clip(jnp.asarray(gate, dtype), jnp.finfo(dtype).tiny, 1.0)
    return jnp.concatenate([gate[1:], jnp.ones((1, K), dtype)], axis=0)


def _gate_logs(gate, T, K, dtype):
    """(log gate, log (1 - gate)) of the next step at each step, (T, K) each (:func:`_next_gate`)."""
    nxt = _next_gate(gate, T, K, dtype)
    return jnp.log(nxt), jnp.log1p(-nxt)


def _gated_column(log_trans, log_end, log_stay, j):
    """Column j (K,) of the step's gated log transition matrix, log[g_i pi_ij + (1 - g_i) [i == j]],
    from log pi (K, K) and the gate's log g, log (1 - g) (K,). Only i == j sums two terms: the
    rest is log g_i + log pi_ij, as a logaddexp with -inf gives, to the bit (one logaddexp, not K)."""
    col = log_end + log_trans[:, j]
    return col.at[j].set(jnp.logaddexp(col[j], log_stay[j]))


def _gated_trans(log_trans, log_end, log_stay):
    """The step's (K, K) gated log transition matrix log[(1 - g) I + g pi]: every column of
    :func:`_gated_column` at once, the same values to the bit. (Its rule written for the whole
    matrix, the diagonal selected by a mask: the columns mapped one by one, or the diagonal set by
    one scatter, made the gated Viterbi 12-20% slower.)"""
    K = log_trans.shape[-1]
    ended = log_end[:, None] + log_trans
    diagonal = jnp.logaddexp(jnp.diagonal(ended), log_stay)
    return jnp.where(jnp.eye(K, dtype=bool), diagonal[:, None], ended)


def _prepare_lik(log_lik, active):
    # NaN or -inf in an inactive skill's column must not leak into the sums (or their gradients)
    return jnp.where(active, jnp.maximum(log_lik, NEG_LOG), 0.0)


def _scaled_transitions(log_trans, active):
    """The probability-space recursions' transition matrix: (shift (K,), each column's largest
    log weight (NEG_LOG: an inactive skill); trans (K, K), the matrix in units of it, 0 for
    inactive skills; unshift (K,), exp(-shift) for an active skill (at most exp(700)), else 0)."""
    shift = jnp.max(log_trans, axis=0)
    trans = jnp.exp(log_trans - shift)  # P = trans * exp(shift) column by column
    unshift = jnp.where(active, jnp.exp(-jnp.maximum(shift, -700.0)), 0.0)
    return shift, trans, unshift


def _predict(p, trans, unshift, active, gate_t=()):
    """A step's prediction from the previous step's filtered probabilities p (K,), in units of
    each column's largest transition weight, floored at ``_FLOOR`` for an active skill; gate_t:
    (end, stay) (K,) of leaving the previous step, with state-dependent ends: p(z_t+1 = j) =
    sum_k p_k g_k pi_kj + p_j (1 - g_j), those that end through the matrix, those that continue
    divided by their column's exp(shift)."""
    if gate_t:
        end, stay = gate_t
        pred = (p * end) @ trans + p * stay * unshift
    else:
        pred = p @ trans
    return jnp.where(active, jnp.maximum(pred, _FLOOR), 0.0)


def forward_filter(log_init, log_trans, log_lik, mask=None, active=None, gate=None) -> Tuple[jax.Array, jax.Array]:
    """Forward filter: the marginal likelihood with the skill sequence summed out.

    Args:
        log_init: (K,) log initial weights.
        log_trans: (K, K) log transition weights, ``log_trans[j, k]`` from j to k.
        log_lik: (T, K) per-step log-likelihoods.
        mask: (T,) bool, real steps (default all).
        active: (K,) bool, usable skills (default all).
        gate: (T, K) end probabilities (see the module docstring), or None.
    Returns:
        log_marginal: scalar, log p(x_{1:T}).
        log_alpha: (T, K) normalised filtered log-probabilities log p(z_t | x_{1:t}); at a
            masked step, a copy of the last real step's (the normalised ``log_init`` before
            the first real step). A probability below the smallest normal float (about
            exp(-708)) is given as that float's log.

    The first real step is taken in log space; from there the recursion runs in probability
    space with no exponential or logarithm inside the loop but the one of each step's
    normaliser: the likelihoods are exponentiated for all steps at once beforehand, each
    step's shifted by its largest entry, and the columns of the transition matrix by theirs
    (``shift``; a column's scale moves from the matrix to the step's likelihoods, so a skill
    entered only rarely stays representable). A step's prediction, in units of each column's
    largest transition weight, is floored at ``_FLOOR`` = exp(-700) for an active skill: the
    step's likelihoods have largest entry 1, so no normaliser falls below the smallest normal
    float (about exp(-708)). Only a transition that much less likely than its column's
    likeliest one is treated as that likely (the log-space recursion this replaced floored
    predictions at exp(-708) in absolute terms). Otherwise the recursion agrees with the
    log-space one to rounding (about 1e-13 in the log marginal over 500 steps), at less than
    half its cost: a 500-step marginal of 400 trajectories and 8 skills takes 11 ms where the
    log-space one took 24-28 ms.
    """
    log_lik = jnp.asarray(log_lik)
    T, K = log_lik.shape
    dtype = log_lik.dtype
    mask = jnp.ones(T, dtype=bool) if mask is None else jnp.asarray(mask, dtype=bool)
    active, log_trans, log_init = _prepare(jnp.asarray(log_init), jnp.asarray(log_trans), active)
    log_lik = _prepare_lik(log_lik, active)
    shift, trans, unshift = _scaled_transitions(log_trans, active)
    # every step's likelihoods times exp(shift), over the step's largest (the shift's other half)
    shifted = jnp.where(active, log_lik + shift, -jnp.inf)
    top = jnp.max(shifted, axis=1)  # (T,)
    lik = jnp.exp(shifted - top[:, None])  # (T, K) in [0, 1]
    if gate is not None:
        # the gate of entering each step, from the previous step's skill
        end_next = _next_gate(gate, T, K, dtype)
        ends = (jnp.concatenate([jnp.zeros((1, K), dtype), end_next[:-1]]),
                jnp.concatenate([jnp.zeros((1, K), dtype), 1.0 - end_next[:-1]]))
    else:
        ends = ()
    # the first real step (its prediction is log_init, not a transition) in log space, before
    # the loop; the loop starts from its filter
    first = jnp.argmax(mask)
    joint = log_init + log_lik[first]
    log_c0 = jax.nn.logsumexp(joint)
    p_init = jnp.where(active, jnp.exp(log_init), 0.0)  # the filter before the first real step
    p_first = jnp.where(active, jnp.exp(joint - log_c0), 0.0)
    later = mask & (jnp.arange(T) > first)
    before = (jnp.arange(T) < first) | ~jnp.any(mask)

    def step(carry, inputs):
        p, total = carry
        lik_t, top_t, real, before, *gate_t = inputs
        joint = _predict(p, trans, unshift, active, tuple(gate_t)) * lik_t
        # (1 at a step not taken: before and at the first real step the gate's prediction is 0,
        # floored at exp(-700), and dividing by that sum would overflow the gradient's zeros)
        c = jnp.where(real, jnp.sum(joint), 1.0)
        p = jnp.where(real, joint / c, p)
        return (p, total + jnp.where(real, jnp.log(c) + top_t, 0.0)), jnp.where(before, p_init, p)

    init = (p_first, jnp.where(jnp.any(mask), log_c0, 0.0))
    (_, log_marginal), probs = jax.lax.scan(step, init, (lik, top, later, before) + tuple(ends))
    tiny = jnp.finfo(dtype).tiny
    log_alpha = jnp.where(active, jnp.log(jnp.maximum(probs, tiny)), NEG_LOG)
    return log_marginal, log_alpha


def backward_sample(key, log_trans, log_alpha, mask=None, active=None, gate=None) -> jax.Array:
    """Draw a skill sequence from p(z_{1:T} | x_{1:T}) given the filter's output.

    Step t draws its skill by inverse transform from one uniform of the key
    ``jax.random.fold_in(key, t)``, so a padded trajectory draws the same sequence as the
    unpadded one from the same key.

    Args:
        key: a PRNG key.
        log_trans: (K, K) log transition weights, as given to :func:`forward_filter`.
        log_alpha: (T, K) filtered log-probabilities from :func:`forward_filter`.
        mask: (T,) bool, real steps (default all).
        active: (K,) bool, as given to :func:`forward_filter`.
        gate: (T, K) or None, as given to :func:`forward_filter`.
    Returns:
        z: (T,) int32 skills, -1 at masked steps.
    """
    log_alpha = jnp.asarray(log_alpha)
    T, K = log_alpha.shape
    mask = jnp.ones(T, dtype=bool) if mask is None else jnp.asarray(mask, dtype=bool)
    _, log_trans = _prepare(None, jnp.asarray(log_trans), active)

    # every step's uniform at once, outside the scan: one per step, by inverse transform (the
    # Gumbel-max trick needs K random numbers a step, and generating them was two thirds of the
    # pass)
    uniforms = jax.vmap(lambda t: jax.random.uniform(jax.random.fold_in(key, t), (), log_alpha.dtype))(jnp.arange(T))

    ends = _gate_logs(gate, T, K, log_alpha.dtype) if gate is not None else ()

    def step(z_next, inputs):
        u, filt, real, *gate_t = inputs
        # z_next == -1 until the last real step has been drawn
        zn = jnp.maximum(z_next, 0)
        # the column z_next of the next step's (gated) transition matrix
        into = log_trans[:, zn] if gate is None else _gated_column(log_trans, *gate_t, zn)
        to_next = jnp.where(z_next >= 0, into, 0.0)
        z = inverse_transform(filt + to_next, u)
        z = jnp.where(real, z, jnp.int32(-1))
        return jnp.where(real, z, z_next), z

    _, z = jax.lax.scan(step, jnp.int32(-1), (uniforms, log_alpha, mask) + tuple(ends), reverse=True)
    return z


def inverse_transform(logits, u) -> jax.Array:
    """A categorical draw by inverse transform from one uniform: the first index whose cumulative
    weight exceeds u times the total (an index of zero weight never does). Where rounding leaves
    none above (u within 2^-52 of 1), the heaviest index. The backward sampler's draw of each step.

    Args:
        logits: (K,) unnormalised log-probabilities (NEG_LOG or -inf for weight 0).
        u: a uniform in [0, 1), scalar.
    Returns:
        () int32, the index drawn with probability proportional to exp(logits).
    """
    w = jnp.exp(logits - jnp.max(logits))
    c = jnp.cumsum(w)
    above = c > u * c[-1]
    return jnp.where(jnp.any(above), jnp.argmax(above), jnp.argmax(w)).astype(jnp.int32)


def smooth(log_trans, log_alpha, mask=None, active=None, gate=None) -> jax.Array:
    """Posterior marginals log p(z_t | x_{1:T}) from the filter's output (a backward pass over
    the filtered probabilities: p(z_t | x) = p(z_t | x_{1:t}) sum_k pi(z_t, k) p(z_{t+1} = k | x)
    / p(z_{t+1} = k | x_{1:t})).

    Args:
        log_trans: (K, K) log transition weights, as given to :func:`forward_filter`.
        log_alpha: (T, K) filtered log-probabilities from :func:`forward_filter`.
        mask: (T,) bool, real steps (default all).
        active: (K,) bool, as given to :func:`forward_filter`.
        gate: (T, K) or None, as given to :func:`forward_filter`.
    Returns:
        (T, K) normalised log-probabilities (below the smallest normal float: that float's log;
        an inactive skill's: ``NEG_LOG``); ``NEG_LOG`` everywhere at masked steps.

    In probability space, as the filter: each column of the transition matrix in units of its
    largest entry (the scale cancels between a step's prediction and its ratio), the
    prediction floored at ``_FLOOR`` for an active skill as the filter floors it, and no
    exponential or logarithm inside the loop (a third of the log-space recursion's cost).
    """
    log_alpha = jnp.asarray(log_alpha)
    T, K = log_alpha.shape
    dtype = log_alpha.dtype
    mask = jnp.ones(T, dtype=bool) if mask is None else jnp.asarray(mask, dtype=bool)
    active, log_trans = _prepare(None, jnp.asarray(log_trans), active)
    _, trans, unshift = _scaled_transitions(log_trans, active)
    alpha = jnp.where(active, jnp.exp(log_alpha), 0.0)
    if gate is not None:
        end_next = _next_gate(gate, T, K, dtype)  # at step t, the gate of leaving it
        ends = (end_next, 1.0 - end_next)
    else:
        ends = ()

    def step(carry, inputs):
        after, seen = carry  # the next real step's marginals, and whether there is one
        filt, real, *gate_t = inputs
        pred = _predict(filt, trans, unshift, active, tuple(gate_t))
        ratio = jnp.where(active, after / jnp.where(active, pred, 1.0), 0.0)
        if gate is None:
            back = trans @ ratio
        else:
            end, stay = gate_t
            back = end * (trans @ ratio) + stay * unshift * ratio
        post = jnp.where(seen, filt * back, filt)
        post = post / jnp.sum(post)
        return (jnp.where(real, post, after), seen | real), post

    init = (jnp.zeros(K, dtype), jnp.bool_(False))
    _, probs = jax.lax.scan(step, init, (alpha, mask) + tuple(ends), reverse=True)
    log_post = jnp.where(active, jnp.log(jnp.maximum(probs, jnp.finfo(dtype).tiny)), NEG_LOG)
    return jnp.where(mask[:, None], log_post, NEG_LOG)


def path_log_prob(log_init, log_trans, log_lik, z, mask=None, active=None, gate=None) -> jax.Array:
    """log p(z_{1:T}, x_{1:T}) of one skill sequence under the model of :func:`forward_filter`.

    Minus the filter's ``log_marginal`` it is the log-probability with which
    :func:`backward_sample` draws ``z``. A sequence that uses an inactive skill gets a value
    near ``NEG_LOG`` (far below any real log-probability), never NaN.

    Args:
        log_init, log_trans, log_lik, mask, active, gate: as for :func:`forward_filter`.
        z: (T,) int skills (ignored at masked steps).
    Returns:
        scalar log-probability.
    """
    log_lik = jnp.asarray(log_lik)
    T, K = log_lik.shape
    mask = jnp.ones(T, dtype=bool) if mask is None else jnp.asarray(mask, dtype=bool)
    active, log_trans, log_init = _prepare(jnp.asarray(log_init), jnp.asarray(log_trans), active)
    log_lik = _prepare_lik(log_lik, active)
    z = jnp.clip(jnp.asarray(z), 0, K - 1)
    emit = jnp.where(active[z], jnp.take_along_axis(log_lik, z[:, None], axis=1)[:, 0], NEG_LOG)

    # the gate of step t is row t (the filters read it one step ahead)
    ends = (tuple(jnp.concatenate([x[-1:], x[:-1]]) for x in _gate_logs(gate, T, K, log_lik.dtype))
            if gate is not None else ())

    def step(prev, inputs):
        zt, e, real, *gate_t = inputs
        first = prev < 0
        pv = jnp.maximum(prev, 0)
        move = log_trans[pv, zt] if gate is None else _gated_column(log_trans, *gate_t, zt)[pv]
        lp = jnp.where(first, log_init[zt], move) + e
        return jnp.where(real, zt, prev), jnp.where(real, lp, 0.0)

    _, terms = jax.lax.scan(step, jnp.int32(-1), (z.astype(jnp.int32), emit, mask) + tuple(ends))
    return jnp.sum(terms)


def viterbi(log_init, log_trans, log_lik, mask=None, active=None, gate=None) -> Tuple[jax.Array, jax.Array]:
    """The most probable skill sequence, argmax_z p(z_{1:T}, x_{1:T}).

    Args:
        log_init, log_trans, log_lik, mask, active, gate: as for :func:`forward_filter`.
    Returns:
        z: (T,) int32, the path, -1 at masked steps (ties go to the lowest skill index).
        log_prob: scalar, its joint log-probability log p(z, x) (0 when no step is real).
    """
    log_lik = jnp.asarray(log_lik)
    T, K = log_lik.shape
    mask = jnp.ones(T, dtype=bool) if mask is None else jnp.asarray(mask, dtype=bool)
    active, log_trans, log_init = _prepare(jnp.asarray(log_init), jnp.asarray(log_trans), active)
    log_lik = _prepare_lik(log_lik, active)
    identity = jnp.arange(K, dtype=jnp.int32)
    ends = _gate_logs(gate, T, K, log_lik.dtype) if gate is not None else ()

    def forward(carry, inputs):
        # best: max over paths into each skill at the next real step; pointer: where they came from
        best, pointer, last_delta = carry
        ll, real, *gate_t = inputs
        delta = best + ll
        scores = delta[:, None] + (log_trans if gate is None else _gated_trans(log_trans, *gate_t))
        new = (jnp.max(scores, axis=0), jnp.argmax(scores, axis=0).astype(jnp.int32), delta)
        carry = jax.tree.map(lambda a, b: jnp.where(real, a, b), new, carry)
        return carry, jnp.where(real, pointer, identity)

    init = (log_init, identity, jnp.zeros(K, log_lik.dtype))
    (_, _, last_delta), pointers = jax.lax.scan(forward, init, (log_lik, mask) + tuple(ends))

    def backward(z, pointer):
        return pointer[z], z

    _, z = jax.lax.scan(backward, jnp.argmax(last_delta).astype(jnp.int32), pointers, reverse=True)
    return jnp.where(mask, z, -1), jnp.max(last_delta)


def _axis(x, batched_ndim):
    return None if x is None or jnp.ndim(x) < batched_ndim else 0


def batch_forward_filter(log_init, log_trans, log_lik, mask=None, active=None, gate=None):
    """:func:`forward_filter` over N trajectories.

    Args:
        log_init: (K,) shared or (N, K) per trajectory.
        log_trans: (K, K) shared or (N, K, K) per trajectory.
        log_lik: (N, T, K).
        mask: (N, T) bool (default all real).
        active: None, (K,) shared or (N, K) per trajectory.
        gate: None or (N, T, K).
    Returns:
        log_marginal: (N,); log_alpha: (N, T, K).
    """
    axes = (_axis(log_init, 2), _axis(log_trans, 3), 0, _axis(mask, 2), _axis(active, 2), _axis(gate, 3))
    return jax.vmap(forward_filter, in_axes=axes)(log_init, log_trans, log_lik, mask, active, gate)


def batch_backward_sample(key, log_trans, log_alpha, mask=None, active=None, gate=None) -> jax.Array:
    """:func:`backward_sample` over N trajectories, with independent keys split from ``key``.

    Args:
        key: a PRNG key.
        log_trans: (K, K) or (N, K, K).
        log_alpha: (N, T, K) from :func:`batch_forward_filter`.
        mask: (N, T) bool (default all real).
        active: None, (K,) or (N, K).
        gate: None or (N, T, K).
    Returns:
        z: (N, T) int32, -1 at masked steps.
    """
    keys = jax.random.split(key, jnp.shape(log_alpha)[0])
    axes = (0, _axis(log_trans, 3), 0, _axis(mask, 2), _axis(active, 2), _axis(gate, 3))
    return jax.vmap(backward_sample, in_axes=axes)(keys, log_trans, log_alpha, mask, active, gate)


def batch_smooth(log_trans, log_alpha, mask=None, active=None, gate=None) -> jax.Array:
    """:func:`smooth` over N trajectories: log_trans (K, K) or (N, K, K), log_alpha (N, T, K),
    mask (N, T), active None, (K,) or (N, K), gate None or (N, T, K). Returns (N, T, K)."""
    axes = (_axis(log_trans, 3), 0, _axis(mask, 2), _axis(active, 2), _axis(gate, 3))
    return jax.vmap(smooth, in_axes=axes)(log_trans, log_alpha, mask, active, gate)


def batch_viterbi(log_init, log_trans, log_lik, mask=None, active=None, gate=None):
    """:func:`viterbi` over N trajectories (arguments as for :func:`batch_forward_filter`).

    Returns:
        z: (N, T) int32, -1 at masked steps; log_prob: (N,).
    """
    axes = (_axis(log_init, 2), _axis(log_trans, 3), 0, _axis(mask, 2), _axis(active, 2), _axis(gate, 3))
    return jax.vmap(viterbi, in_axes=axes)(log_init, log_trans, log_lik, mask, active, gate)


def _one_hot(z, mask, num_states):
    z = jnp.asarray(z)
    mask = jnp.ones(z.shape, dtype=bool) if mask is None else jnp.asarray(mask, dtype=bool)
    return jax.nn.one_hot(z, num_states, dtype=jnp.int32) * (mask & (z >= 0))[..., None]


def transition_counts(z, mask, num_states: int) -> jax.Array:
    """Counts of transitions j -> k between consecutive real steps.

    Args:
        z: (N, T) int skill sequences (or (T,)).
        mask: (N, T) bool real steps, padding at the end (None: all real).
        num_states: K (static).
    Returns:
        (N, K, K) int32 counts ``n[i, j, k]`` (or (K, K)).
    """
    hot = _one_hot(z, mask, num_states)
    return jnp.einsum("...tj,...tk->...jk", hot[..., :-1, :], hot[..., 1:, :])


def initial_counts(z, mask, num_states: int) -> jax.Array:
    """One-hot first skill of each trajectory: (N, K) int32 (or (K,)); zeros if it is empty."""
    return _one_hot(z, mask, num_states)[..., 0, :]


float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
