"""Next-value operators: E[V(s') | s, a] of a :class:`~npbrs.domains.TabularMDP` as A columns
(:class:`Columns`), the policy-weighted operator P_pi and its transpose, and the tables they are
built from (:func:`successor_union`, :func:`predecessors`). See :mod:`npbrs.domains.solvers`
for why the columns are laid out as they are."""

from __future__ import annotations

from typing import Callable, Tuple

import jax
import jax.numpy as jnp
import numpy as np

from ..util.pytree import Pytree
from ..util.precision import float64_all

__all__ = ["next_value_operator"]

_KINDS = ("auto", "sparse", "dense", "factored")
_MAX_UNROLLED_GATHERS = 32
_MAX_FOLD_TERMS = 256
_MAX_IN_DEGREE = 32  # the folded transpose gathers over predecessors up to this many (else scatters)


# ------------------------------------------------------------------ next-value operators
class Columns(Pytree):
    """E[V(s') | s, a] as A columns, and its transpose, for a batch of value vectors: the
    next-value operator every solver applies, and the policy-weighted P_pi of its policy
    evaluations (:meth:`policy`).

    ``apply(V)`` maps V (K, S) to a tuple of A arrays (K, S); ``transpose(cols)`` maps A
    arrays (K, S) to sum_a P_a^T col_a, shape (K, S). Both are linear.

    Args:
        mdp: the TabularMDP.
        kind: "auto", "sparse", "dense" or "factored" (see :func:`next_value_operator`).
    """

    def __init__(self, mdp, kind: str):
        if kind not in _KINDS:
            raise ValueError(f"unknown next-value operator kind {kind!r}; expected one of {_KINDS}")
        if kind == "auto":
            kind = "factored" if mdp.next_value_fn is not None else "sparse"
        self.kind = kind
        S, A, B = mdp.successors.shape
        self.num_states, self.num_actions = S, A
        self._union = self._fold = self._pred = None
        if kind == "sparse":
            # (A, B, S): one contiguous index row per (action, slot); slots never used by any
            # state are dropped
            used = np.any(mdp.probs > 0, axis=(0, 1))
            self._succ = jnp.asarray(np.transpose(mdp.successors[:, :, used], (1, 2, 0)))
            self._prob = jnp.asarray(np.transpose(mdp.probs[:, :, used], (1, 2, 0)))
            union, slot = successor_union(mdp.successors[:, :, used], mdp.probs[:, :, used])
            slots = A * int(np.sum(used))
            # folded where that saves gathers, and while the fold's terms (one per distinct
            # successor and (action, slot)) keep the program small
            if union.shape[0] < slots and union.shape[0] * slots <= _MAX_FOLD_TERMS:
                # the probability of reaching distinct successor u by action a, summed over slots
                prob = np.transpose(mdp.probs[:, :, used], (1, 2, 0))
                fold = np.stack([np.sum(np.where(slot == u, prob, 0.0), axis=1) for u in range(union.shape[0])])
                self._union, self._fold = jnp.asarray(union), jnp.asarray(fold)  # (U, S), (U, A, S)
                self._pred = predecessors(union, _MAX_IN_DEGREE)
        elif kind == "dense":
            self._P = jnp.asarray(np.transpose(mdp.dense_transitions(), (1, 0, 2)))  # (A, S, S')
        else:
            if mdp.next_value_fn is None:
                raise ValueError(f"MDP {mdp.name!r} supplies no factored next-value operator")
            self._fn = mdp.next_value_fn

    def apply(self, V) -> Tuple[jax.Array, ...]:
        A = self.num_actions
        if self.kind == "sparse":
            nb = self._succ.shape[1]
            if A * nb <= _MAX_UNROLLED_GATHERS:
                # one gather per (action, slot), unrolled: XLA fuses them into one pass; a
                # reduction over a gathered axis compiles to code an order of magnitude slower
                return tuple(sum(V[..., self._succ[a, b]] * self._prob[a, b].astype(V.dtype) for b in range(nb))
                             for a in range(A))

            def slot(b, acc):  # many successors: a loop keeps the program small
                idx = jax.lax.dynamic_index_in_dim(self._succ, b, 1, keepdims=False)
                p = jax.lax.dynamic_index_in_dim(self._prob, b, 1, keepdims=False)
                return acc + jnp.moveaxis(V[..., idx], -2, 0) * p[(slice(None),) + (None,) * (V.ndim - 1)]

            E = jax.lax.fori_loop(0, nb, slot, jnp.zeros((A,) + V.shape, V.dtype))
            return tuple(E[a] for a in range(A))
        if self.kind == "dense":
            return tuple(V @ self._P[a].T for a in range(A))
        E = self._fn(V)
        return tuple(E[..., a] for a in range(A))

    def transpose(self, cols) -> jax.Array:
        A = self.num_actions
        if self.kind == "sparse":
            out = jnp.zeros(cols[0].shape, cols[0].dtype)
            for a in range(A):
                for b in range(self._succ.shape[1]):
                    out = out.at[..., self._succ[a, b]].add(self._prob[a, b].astype(out.dtype) * cols[a])
            return out
        if self.kind == "dense":
            return sum(cols[a] @ self._P[a] for a in range(A))
        transposed = jax.linear_transpose(self._fn, jnp.zeros(cols[0].shape, cols[0].dtype))
        return transposed(jnp.stack(cols, -1))[0]

    def policy(self, pi, transpose: bool = False) -> Callable:
        """x -> P_pi x = sum_a pi_a E[x](., a) (or x -> P_pi^T x) for x (K, S), with pi a tuple
        of A arrays (K, S).

        Where the actions of a state share successors (a gridworld's moves and slips reach the
        same few neighbours), the policy is folded into one weight per distinct successor first,
        W_u(s) = sum_a pi_a(s) F_ua(s), with F_ua(s) the probability that action a reaches
        union[u, s] (precomputed): an application is then U gathers instead of A B, and reads U
        weight rows instead of A policy rows and A B probability and index rows (on CPU an
        application's cost is that memory traffic). The weights are computed once per policy, in
        pi's dtype, behind an optimisation barrier: without it XLA fused the fold into every
        application of the loops that use it (at a million states a fold reads about 25 rows,
        an application 5).

        x's dtype should be pi's (the inner solves may run in float32, ``SoftSolver``'s
        ``krylov_precision``)."""
        if self._union is None:
            if transpose:
                return lambda x: self.transpose(tuple(p * x for p in pi)).astype(x.dtype)
            return lambda x: sum(p * e for p, e in zip(pi, self.apply(x))).astype(x.dtype)
        dtype = pi[0].dtype
        W = jax.lax.optimization_barrier([sum(self._fold[u, a].astype(dtype) * p for a, p in enumerate(pi))
                                          for u in range(self._union.shape[0])])
        if transpose and self._pred is not None:
            # P_pi^T as gathers over each state's predecessors: the weight of each (predecessor,
            # distinct successor) pair gathered once per policy, then R gathers an application
            # like the forward one (a scatter-add per row instead made a transposed solve 3-5
            # times the forward one on CPU: 1.9 s against 0.4 s at 10^5 states, 4 tables)
            source, flat = self._pred
            rows = jnp.stack(W, -2).reshape(W[0].shape[:-1] + (-1,))  # (..., U S)
            rows = jnp.concatenate([rows, jnp.zeros(rows.shape[:-1] + (1,), dtype)], -1)  # U S: no pair
            WT = jax.lax.optimization_barrier([rows[..., flat[r]] for r in range(flat.shape[0])])
            return lambda x: sum(w * x[..., source[r]] for r, w in enumerate(WT))
        if transpose:
            def apply_transpose(x):
                out = jnp.zeros(x.shape, x.dtype)
                for u, w in enumerate(W):
                    out = out.at[..., self._union[u]].add(w * x)
                return out

            return apply_transpose
        return lambda x: sum(w * x[..., self._union[u]] for u, w in enumerate(W))


def successor_union(successors, probs) -> Tuple[np.ndarray, np.ndarray]:
    """The distinct successors of each state over all its actions, and where each (action, slot)
    goes among them.

    successors, probs: (S, A, B). Returns union (U, S) int32, with U the largest number of
    distinct successors (with probability > 0) of any state (a state with fewer repeats its
    first), and slot (A, B, S) int8, the row of union that successors[s, a, b] is in (0 where
    the probability is 0).
    """
    S, A, B = successors.shape
    key = np.where(probs > 0, successors, -1).reshape(S, A * B).astype(np.int32)  # -1: unused
    ordered = np.sort(key, axis=1)
    first = np.ones(ordered.shape, bool)
    first[:, 1:] = ordered[:, 1:] != ordered[:, :-1]
    first &= ordered >= 0
    rank = np.cumsum(first, axis=1, dtype=np.int32) - 1  # each distinct successor's row
    U = int(rank[:, -1].max()) + 1
    union = np.empty((U, S), np.int32)
    union[:] = ordered[np.arange(S), np.argmax(first, axis=1)]  # a state with fewer repeats its first
    for c in range(A * B):  # (column by column: no temporaries of S x A x B indices)
        rows = np.flatnonzero(first[:, c])
        union[rank[rows, c], rows] = ordered[rows, c]
    slot = np.zeros((A * B, S), np.int8 if U < 128 else np.int32)
    for u in range(U - 1, -1, -1):  # (a state's repeated first successor maps to row 0)
        slot[(key.T == union[u]) & (key.T >= 0)] = u
    return union, slot.reshape(A, B, S)


def predecessors(union, max_in_degree: int):
    """Each state's predecessors through the distinct-successor table ``union`` (U, S) of
    :func:`successor_union`: (source (R, S) int32, flat (R, S) int32), with R the largest number
    of (state, row) pairs whose distinct successor is one state, such that row r of state t
    is the pair (source[r, t], u) with union[u, source[r, t]] = t, and flat[r, t] = u S +
    source[r, t] (U S where a state has fewer than R pairs: a weight of 0). A row of ``union``
    that repeats a state's first successor (padding) is no pair. None if R > ``max_in_degree``
    (a hub reached from everywhere: its gathers would be mostly padding)."""
    U, S = union.shape
    real = np.ones((U, S), bool)
    real[1:] = union[1:] != union[:1]
    u, src = np.nonzero(real)
    dst = union[u, src]
    order = np.argsort(dst, kind="stable")
    u, src, dst = u[order], src[order], dst[order]
    counts = np.bincount(dst, minlength=S)
    R = int(counts.max()) if counts.size else 0
    if R > max_in_degree:
        return None
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    rank = np.arange(dst.size) - start[dst]
    source = np.tile(np.arange(S, dtype=np.int32), (R, 1))
    flat = np.full((R, S), U * S, np.int64 if U * S + 1 > np.iinfo(np.int32).max else np.int32)
    source[rank, dst] = src
    flat[rank, dst] = u * S + src
    return jnp.asarray(source), jnp.asarray(flat)


def next_value_operator(mdp, kind: str = "auto") -> Callable:
    """E[V(s') | s, a] as a function of V (..., S) -> (..., S, A).

    kind: "auto" (the domain's factored operator if it has one, else "sparse"),
    "sparse" (gather over successor arrays), "dense" (matrix product with P[s, a, s']),
    "factored" (the domain's own operator; error if it has none).
    """
    cols = Columns(mdp, kind)
    if cols.kind == "factored":
        return mdp.next_value_fn

    def op(V):
        V = jnp.asarray(V)
        flat = V.reshape((-1, V.shape[-1]))
        return jnp.stack(cols.apply(flat), -1).reshape(V.shape + (cols.num_actions,))

    return op


float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
