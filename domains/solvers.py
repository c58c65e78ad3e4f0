"""Bellman solvers on a :class:`~npbrs.domains.TabularMDP`: soft (maximum causal entropy)
and hard value iteration, in JAX, batched over reward tables, differentiable.

Soft:  Q(s, a) = r(s, a) + gamma * E[V(s') | s, a],  V(s) = logsumexp_a Q(s, a).
Hard:  the same with max in place of logsumexp.

How the soft fixed point is found (``method="newton"``, the default). Value iteration
contracts by gamma per sweep, so a relative tolerance of 1e-10 at gamma = 0.95 takes about 450
sweeps. Newton's method on F(V) = V - logsumexp(r + gamma E[V]) is soft policy iteration: the
Jacobian is I - gamma P_pi with pi = softmax(Q), and a Newton step evaluates the current
Boltzmann policy. It takes 5-7 steps from V = 0 and 2-3 from the previous solution after a
small change of the rewards. Each step's linear system is solved inexactly (Eisenstat-Walker
forcing terms) by restarted GMRES, right-preconditioned with a truncated Neumann series of
gamma P_pi: an iteration costs a couple of expected-next-value applications and no exp/log,
and the clustered spectrum of gamma P_pi (1, a few slow modes, the rest well inside the unit
disc) needs tens of them, not hundreds.

Derivatives are implicit: the fixed point's tangent solves (I - gamma P_pi) dV = sum_a pi dr
with the same GMRES (``jax.lax.custom_linear_solve``, whose transpose is the adjoint solve
(I - gamma P_pi)^T lambda = g for reverse mode), and dQ = dr + gamma E[dV]; no loop is
differentiated. Forward and reverse mode both work (so do Hessians, forward over reverse).

Batches. K reward tables are solved together in lock-step, with one shared loop counter and
each system frozen once it has converged (its result does not depend on the others). Pass a
batch rather than ``vmap`` a solver: under ``vmap`` every loop counter becomes per-system and
every basis update a scatter, about twice as slow.

Layout, for XLA on CPU: inside the loops a Q-table is a tuple of A arrays (K, S), not an
(K, S, A) array (element-wise work over separate columns fuses far better than small
reductions over a minor axis); successor gathers are unrolled over (action, slot), since a
reduction over a gathered axis compiles to code an order of magnitude slower. Where a state's
actions share successors (a gridworld's moves and slips reach the same few cells), a policy
evaluation first folds the policy onto each state's distinct successors (``_Columns.policy``):
on an open gridworld that is 5 gathers per application instead of 15, and a solve at a million
states took 3.1-3.6 s instead of 5.6 s (``benchmarks/bench_scale.py``).

Precision. On large MDPs (``krylov_precision="auto"``: from 50,000 states) the Newton steps'
linear systems are solved in float32: a step only needs its solve to a relative 0.3 to 1e-5,
and the float64 iteration around it (values, backups, the residual that decides convergence)
reaches the same fixed point to the tolerance. Every application and orthogonalisation then
moves half the bytes: 4 tables at a million states took 1.5 s instead of 2.9 s, one table 0.67
s. Derivatives' solves run in float32 too, with one step of iterative refinement (the residual in
float64, its correction solved in float32 again: a relative 1e-5 of 1e-5): a log-likelihood's
gradient sums large terms that cancel near its optimum, and float32's 1e-5 alone left it wrong
by its own size there (an IRL fit's line search then failed step after step).

Transposes. A policy's transpose P_pi^T (the adjoint solve of a gradient) gathers over each
state's predecessors (:func:`predecessors`, precomputed with the fold) rather than scattering
along its successors: XLA's scatter-add on CPU made a transposed solve 3-5 times the forward
one (1.9 s against 0.34 s at 10^5 states, 4 tables, float64); it now costs the same.
"""

from __future__ import annotations

import copy
import weakref
from functools import partial
from typing import Callable, NamedTuple, Optional, Tuple

import jax
import jax.numpy as jnp
import numpy as np

from .util.linalg import solve_upper
from .util.pytree import Pytree
from .util.compiling import jit
from .util.precision import float64_all

__all__ = ["next_value_operator", "soft_value_iteration", "value_iteration", "SolveResult",
           "boltzmann_log_policy", "greedy_policy", "make_soft_solver", "make_hard_solver",
           "SoftSolver", "HardSolver", "check_rewards"]

_METHODS_SOFT = ("newton", "vi")
_METHODS_HARD = ("policy", "vi")
_KINDS = ("auto", "sparse", "dense", "factored")
_MAX_UNROLLED_GATHERS = 32
_MAX_FOLD_TERMS = 256
_MAX_IN_DEGREE = 32  # the folded transpose gathers over predecessors up to this many (else scatters)
_PRECISIONS = ("auto", "float64", "float32")
_FLOAT32_FROM_STATES = 50_000  # krylov_precision="auto": float32 inner solves from this many states
_FLOAT32_RTOL = 1e-5  # the tightest relative residual asked of a float32 inner solve


class SolveResult(NamedTuple):
    """Values of a Bellman solve.

    V: (..., S) state values. Q: (..., S, A) action values, with V = logsumexp_a Q (soft) or
    max_a Q (hard) exactly. num_iter: (...,) Newton / policy-iteration steps or sweeps used.
    residual: (...,) max-norm Bellman residual of the last iterate relative to max(1, max |V|).
    num_matvec: (...,) expected-next-value applications spent inside Krylov solves (0 for
    value iteration).
    """

    V: jax.Array
    Q: jax.Array
    num_iter: jax.Array
    residual: jax.Array
    num_matvec: jax.Array = 0


# ------------------------------------------------------------------ next-value operators
class _Columns(Pytree):
    """E[V(s') | s, a] as A columns, and its transpose, for a batch of value vectors.

    ``apply(V)`` maps V (K, S) to a tuple of A arrays (K, S); ``transpose(cols)`` maps A
    arrays (K, S) to sum_a P_a^T col_a, shape (K, S). Both are linear.
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
    cols = _Columns(mdp, kind)
    if cols.kind == "factored":
        return mdp.next_value_fn

    def op(V):
        V = jnp.asarray(V)
        flat = V.reshape((-1, V.shape[-1]))
        return jnp.stack(cols.apply(flat), -1).reshape(V.shape + (cols.num_actions,))

    return op


# ----------------------------------------------------------------------------- Krylov
def _gmres(matvec, b, rtol, dim: int, max_cycles: int, basis=None):
    """Restarted GMRES(dim) from x = 0 for K systems at once: ||b_k - A_k x_k|| <= rtol ||b_k||.

    ``matvec`` maps (K, n) to (K, n) row by row; b is (K, n), rtol a scalar or (K,). The K
    systems iterate in lock-step with one shared step counter (under ``vmap`` a per-system
    counter would turn every basis update into a scatter), each freezing once converged.

    Givens rotations are accumulated in a small orthogonal matrix Omega per system, so the
    residual norm after Arnoldi step j is |beta * Omega[j, 0]| without a loop over past
    rotations. Orthogonalisation is one pass of classical Gram-Schmidt as two batched
    matrix-vector products: on CPU the basis is read from memory at each step and that, not
    the operator, is the cost of a step. A restart continues from the residual the Arnoldi
    relation gives (no extra matvec).

    The vectors may be float32 (``SoftSolver``'s ``krylov_precision``): the small Hessenberg
    arithmetic stays float64, and a restart normalises the new residual by its own norm rather
    than by the Givens estimate (in float32 the two drift apart at a million states, and
    GMRES(8) stagnated).

    ``basis`` is an optional (K, dim + 1, n) work array with finite entries, returned for
    reuse by the next call (rows not yet written in a cycle are masked out, so it needs no
    zeroing: allocating and clearing it costs as much as a few Arnoldi steps).
    Returns (x (K, n), matvecs (K,), relative residual estimates (K,), basis).
    """
    m = dim
    K, n = b.shape
    dtype = b.dtype  # the vectors' precision
    small = jnp.promote_types(dtype, jnp.float64)  # the Hessenberg's, inner products' and norms'

    def dots(Vb, w):
        return jnp.einsum("kjs,ks->kj", Vb, w).astype(small)

    def norm(w):
        return jnp.linalg.norm(w, axis=-1).astype(small)

    bnorm = norm(b)
    target = rtol * bnorm
    rows = jnp.arange(m + 1)
    ks = jnp.arange(K)
    if basis is None:
        basis = jnp.zeros((K, m + 1, n), dtype)

    def arnoldi(Vb, r, beta, live):
        R = jnp.zeros((K, m + 1, m), small)
        Om = jnp.broadcast_to(jnp.eye(m + 1, dtype=small), (K, m + 1, m + 1))
        v0 = r / jnp.where(beta > 0, beta, 1.0)[:, None].astype(dtype)
        live = live & (beta > target)

        def cond(c):
            return (c[3] < m) & jnp.any(c[6])

        def body(c):
            # each step first stores the vector made by the previous one and only then reads
            # the basis: with the opposite order XLA copies the whole basis every step
            Vb, R, Om, j, v, steps, live = c
            Vb = Vb.at[:, j].set(v)
            w = matvec(v)
            h = jnp.where(rows <= j, dots(Vb, w), 0.0)
            w = w - jnp.einsum("kj,kjs->ks", h.astype(dtype), Vb)
            hn = norm(w)
            col = jnp.einsum("kij,kj->ki", Om, h.at[:, j + 1].set(hn))
            x1, x2 = col[:, j], col[:, j + 1]
            rho = jnp.hypot(x1, x2)
            safe = jnp.where(rho > 0, rho, 1.0)
            cs = jnp.where(rho > 0, x1 / safe, 1.0)[:, None]
            sn = jnp.where(rho > 0, x2 / safe, 0.0)[:, None]
            row_j, row_j1 = Om[:, j], Om[:, j + 1]
            Om_new = Om.at[:, j].set(cs * row_j + sn * row_j1).at[:, j + 1].set(cs * row_j1 - sn * row_j)
            R_new = R.at[:, :, j].set(col.at[:, j].set(rho).at[:, j + 1].set(0.0))
            Om = jnp.where(live[:, None, None], Om_new, Om)
            R = jnp.where(live[:, None, None], R_new, R)
            steps = steps + live
            live = live & (beta * jnp.abs(Om[:, j + 1, 0]) > target)
            return Vb, R, Om, j + 1, w / jnp.where(hn > 0, hn, 1.0)[:, None].astype(dtype), steps, live

        init = (Vb, R, Om, jnp.asarray(0), v0, jnp.zeros(K, jnp.int32), live)
        Vb, R, Om, j, v, steps, _ = jax.lax.while_loop(cond, body, init)
        Vb = Vb.at[:, jnp.minimum(j, m)].set(v)  # row steps_k of a system that stopped last
        used = jnp.arange(m)[None, :] < steps[:, None]  # (K, m)
        Rm = jnp.where(used[:, :, None] & used[:, None, :], R[:, :m], jnp.eye(m, dtype=small))
        g = jnp.where(used, beta[:, None] * Om[:, :m, 0], 0.0)
        y = solve_upper(Rm, g)
        dx = jnp.einsum("kj,kjs->ks", jnp.pad(y, ((0, 0), (0, 1))).astype(dtype), Vb)
        # the residual without another matvec: b - A x = V (beta e1 - H y)
        # = g_j * sum_i Omega[j, i] v_i over the first j + 1 basis vectors, j = steps
        om_j = Om[ks, steps]  # (K, m + 1), zero beyond column j
        g_j = beta * om_j[:, 0]
        r = g_j[:, None].astype(dtype) * jnp.einsum("ki,kis->ks", jnp.where(rows[None, :] <= steps[:, None], om_j,
                                                                             0.0).astype(dtype), Vb)
        return Vb, dx, steps, r, jnp.abs(g_j)

    def cond(c):
        return (c[4] < max_cycles) & jnp.any(c[3] > target)

    def body(c):
        Vb, x, r, rnorm, cyc, nmv = c
        active = rnorm > target
        Vb, dx, steps, r_new, est = arnoldi(Vb, r, rnorm, active)
        if dtype != small:  # float32 vectors: restart from the residual's own norm, not the estimate
            est = norm(r_new)
        return (Vb, x + dx, jnp.where(active[:, None], r_new, r), jnp.where(active, est, rnorm), cyc + 1,
                nmv + steps)

    init = (basis, jnp.zeros_like(b), b, bnorm, jnp.asarray(0), jnp.zeros(K, jnp.int32))
    basis, x, _, rnorm, _, nmv = jax.lax.while_loop(cond, body, init)
    return x, nmv, rnorm / jnp.where(bnorm > 0, bnorm, 1.0), basis


# ----------------------------------------------------------------------- soft backups
def _log_1_to_A(t):
    """log t for t in [1, A] (a sum of exponentials with a largest term of 1), to rounding.

    float32 log (several times faster than float64 on CPU) and one Newton step of
    exp(y) = t in float64, whose error is the square of float32's.
    """
    y = jnp.log(t.astype(jnp.float32)).astype(t.dtype)
    return y + (t * jnp.exp(-y) - 1.0)


def _soft_backup(r_cols, E_cols, gamma):
    """Q columns, V = logsumexp_a Q and the Boltzmann policy columns."""
    Q = tuple(r + gamma * e for r, e in zip(r_cols, E_cols))
    m = Q[0]
    for q in Q[1:]:
        m = jnp.maximum(m, q)
    ex = tuple(jnp.exp(q - m) for q in Q)
    total = sum(ex)
    inv = 1.0 / total
    return Q, m + _log_1_to_A(total), tuple(e * inv for e in ex)


def _relative(diff, V):
    """Max-norm of diff relative to max(1, max |V|), per system: (K, S) -> (K,)."""
    return jnp.max(jnp.abs(diff), axis=-1) / jnp.maximum(1.0, jnp.max(jnp.abs(V), axis=-1))


def _policy_apply(op: _Columns, pi, transpose: bool = False):
    """x -> P_pi x = sum_a pi_a E[x](., a), or x -> P_pi^T x; x (K, S) (``_Columns.policy``)."""
    return op.policy(pi, transpose)


# (``_policy_solve`` and ``_soft_newton`` are jitted so that their traces are kept per argument
# shapes and static options: a fit calls them at dozens of sites, and again inside every vmap
# fold and implicit-derivative rule, and each trace ran the Python of the loops anew (a tiny
# fit traced GMRES 63 times, 34 since). Nested in an enclosing trace their code joins the
# enclosing program as before.)
@partial(jit, static_argnums=(1, 5, 6, 7, 8), static_argnames=("precision",))
def _policy_solve(op: _Columns, gamma, pi, b, rtol, degree: int, dim: int, max_cycles: int,
                  transpose: bool = False, basis=None, precision: str = "float64"):
    """Solve (I - gamma P_pi) x = b (or its transpose) for K systems by GMRES,
    right-preconditioned with the truncated Neumann series M^-1 = sum_{k<degree} (gamma P_pi)^k.

    The preconditioned operator is I - (gamma P_pi)^degree: the bulk of the spectrum shrinks
    to (gamma |lambda|)^degree around 1, so GMRES needs fewer steps (and fewer
    orthogonalisations, which cost about as much as an operator application). The powers
    are taken in a ``fori_loop`` so that XLA materialises each application instead of fusing
    chains of them (which it compiles badly). Returns (x (K, S) in b's dtype, operator
    applications (K,), the GMRES work array for reuse).

    ``precision="float32"`` (``SoftSolver``'s ``krylov_precision``) solves in float32: the
    policy, the right-hand side and the basis (``basis`` must then be float32), to a relative
    residual of at least ``_FLOAT32_RTOL``.
    """
    out_dtype = b.dtype
    if precision == "float32":
        pi = tuple(p.astype(jnp.float32) for p in pi)
        b = b.astype(jnp.float32)
        rtol = jnp.maximum(rtol, _FLOAT32_RTOL)
    P = _policy_apply(op, pi, transpose)

    def power(y):
        return jax.lax.fori_loop(0, degree, lambda _, z: gamma * P(z), y)

    y, k, _, basis = _gmres(lambda y: y - power(y), b, rtol, dim, max_cycles, basis)
    # x = M^-1 y in Horner form, x <- y + gamma P x: one carry, so each application is one fused
    # pass (summing z <- gamma P z into a second carry gave the gathers two consumers, and XLA
    # wrote every gathered column to memory and read it back twice: 5 times the cost)
    x = jax.lax.fori_loop(0, degree - 1, lambda _, x: y + gamma * P(x), y)
    return x.astype(out_dtype), k * degree + degree - 1, basis


@partial(jit, static_argnums=(1, 4, 5, 6, 7, 8, 9, 10))  # (see _policy_solve)
def _soft_newton(op, gamma, r_cols, v0, tol, max_iter, degree, dim, max_cycles, eta, precision="float64"):
    """Inexact Newton (soft policy iteration) for K reward tables in lock-step. Returns the
    last iterates' Q columns, their backups T(V) = logsumexp(Q) (K, S), and per system the
    number of steps, the residual and the operator applications.

    The linear solves' tolerances follow Eisenstat and Walker's second choice,
    eta_k = 0.9 (res_k / res_k-1)^2 (capped at ``eta``, safeguarded against dropping
    abruptly): a loose solve while the policy is still changing (then a Newton step gains
    only a constant factor whatever the solve's accuracy), a tight one once convergence is
    quadratic, and never tighter than reaching ``tol`` needs. The first step has no history:
    its tolerance is min(eta, res_0), so a warm start near the solution gets an accurate first
    solve (one or two steps in all) and a cold one a loose one. A converged system gets a
    zero right-hand side, which GMRES skips.

    ``precision="float32"`` solves the Newton steps' linear systems in float32 (policy weights,
    right-hand side, Krylov basis; ``_policy_solve``), to a relative residual of at least
    ``_FLOAT32_RTOL``: half
    the memory traffic of each operator application and orthogonalisation. The iteration
    itself stays float64 (V, the backups, the residual that decides convergence), and an
    inexact Newton step still converges to the float64 fixed point; only the last steps'
    solves are looser (the floor instead of res^2), which can cost an extra Newton step.
    """
    K = v0.shape[0]
    Q, TV, pi = _soft_backup(r_cols, op.apply(v0), gamma)
    res = _relative(TV - v0, TV)

    def cond(c):
        return (c[10] < max_iter) & jnp.any(c[5] > tol)

    def body(c):
        V, Q, TV, pi, it, res, nmv, res_prev, eta_prev, basis, n = c
        active = res > tol
        ew = 0.9 * (res / res_prev) ** 2
        ew = jnp.where(0.9 * eta_prev ** 2 > 0.1, jnp.maximum(ew, 0.9 * eta_prev ** 2), ew)
        rtol = jnp.where(it == 0, jnp.minimum(eta, res), jnp.minimum(eta, ew))
        rtol = jnp.clip(jnp.maximum(rtol, 0.1 * tol / jnp.maximum(res, 1e-300)), 1e-14, eta)
        rhs = jnp.where(active[:, None], V - TV, 0.0)
        step, k, basis = _policy_solve(op, gamma, pi, rhs, rtol, degree, dim, max_cycles, False, basis,
                                       precision=precision)
        V = V - step
        Q, TV_new, pi = _soft_backup(r_cols, op.apply(V), gamma)
        res_new = jnp.where(active, _relative(TV_new - V, TV_new), res)
        return (V, Q, TV_new, pi, it + active, res_new, nmv + jnp.where(active, k, 0), jnp.where(active, res, res_prev),
                jnp.where(active, rtol, eta_prev), basis, n + 1)

    basis = jnp.zeros((K, dim + 1) + v0.shape[1:], jnp.float32 if precision == "float32" else v0.dtype)
    zeros = jnp.zeros(K, jnp.int32)
    init = (v0, Q, TV, pi, zeros, res, zeros, res, jnp.full(K, eta, res.dtype), basis, jnp.asarray(0))
    _, Q, TV, _, it, res, nmv, *_ = jax.lax.while_loop(cond, body, init)
    return Q, TV, it, res, nmv


def _soft_vi(op, gamma, r_cols, v0, tol, max_iter):
    """Plain soft value iteration for K reward tables (a reference; slow)."""
    K = v0.shape[0]
    Q, TV, _ = _soft_backup(r_cols, op.apply(v0), gamma)

    def cond(c):
        return (c[5] < max_iter) & jnp.any(c[4] > tol)

    def body(c):
        V, Q, TV, it, res, n = c
        active = res > tol
        Q_new, TV_new, _ = _soft_backup(r_cols, op.apply(TV), gamma)
        keep = lambda new, old: jnp.where(active[:, None], new, old)
        return (keep(TV, V), tuple(keep(a, b) for a, b in zip(Q_new, Q)), keep(TV_new, TV), it + active,
                jnp.where(active, _relative(TV_new - TV, TV_new), res), n + 1)

    init = (v0, Q, TV, jnp.zeros(K, jnp.int32), _relative(TV - v0, TV), jnp.asarray(0))
    _, Q, TV, it, res, _ = jax.lax.while_loop(cond, body, init)
    return Q, TV, it, res, jnp.zeros(K, jnp.int32)


# ------------------------------------------------------------------- input checking
def check_rewards(mdp, rewards, name: str = "rewards") -> np.ndarray:
    """Validate a reward table (..., S, A) at the Python boundary: shape and finiteness."""
    r = np.asarray(rewards, dtype=np.float64)
    S, A = mdp.num_states, mdp.num_actions
    if r.ndim < 2 or r.shape[-2:] != (S, A):
        raise ValueError(f"{name} must have shape (..., {S}, {A}) = (..., states, actions), got {r.shape}")
    bad = ~np.isfinite(r)
    if bad.any():
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        lead, (s, a) = idx[:-2], idx[-2:]
        where = f"table {lead[0] if len(lead) == 1 else lead}, " if lead else ""
        raise ValueError(f"{name}: {where}state {s}, action {a} is not finite ({r[idx]})")
    return r


def _check_v0(v0, batch, S):
    v = np.asarray(v0, dtype=np.float64)
    if v.shape != tuple(batch) + (S,):
        raise ValueError(f"v0 must have shape {tuple(batch) + (S,)} to match the rewards, got {v.shape}")
    if not np.all(np.isfinite(v)):
        raise ValueError("v0 (the warm start) has non-finite values")
    return v


def _is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def _check_options(tol, max_iter, krylov_dim, max_restarts, degree):
    if int(degree) < 1:
        raise ValueError(f"precondition_degree must be >= 1, got {degree}")
    if not (np.isfinite(tol) and tol > 0):
        raise ValueError(f"tol must be positive, got {tol}")
    if int(max_iter) < 1:
        raise ValueError(f"max_iter must be >= 1, got {max_iter}")
    if int(krylov_dim) < 1 or int(max_restarts) < 1:
        raise ValueError(f"krylov_dim and max_restarts must be >= 1, got {krylov_dim}, {max_restarts}")


# ------------------------------------------------------------- vmap folded into the batch
def fold_vmap(fn):
    """``fn(op, *arrays)``, every array (leaves of pytrees) and every output with a leading axis of
    K systems solved in lock-step, made to fold a ``vmap``'s mapped axis into that axis: under
    ``vmap`` (n-way) it runs once on n * K systems instead of being batched loop by loop.

    JAX batches a ``while_loop`` whose condition depends on the mapped values by running it until
    every member is done and masking each step's carry with a select; nested in the solver's
    Newton, GMRES and L-BFGS loops that doubles the work of a solve and grows the compiled
    program. The solver already solves its K systems together, so a vmapped call (the sampler's
    chains, a Jacobian's tangents) is simply more systems. The numbers can differ from a
    one-by-one solve in the last bits: a system that converged keeps iterating until the batch
    has (each iterate is a fixed point to the tolerance). An operator ``op`` (a pytree) that is
    itself mapped (dynamics that differ between members) is vmapped as usual."""

    def call(op, *args):
        leaves, treedef = jax.tree.flatten(op)  # (the operator's arrays, passed as leaves)
        unflat = lambda ls, *a: fn(jax.tree.unflatten(treedef, ls), *a)  # noqa: E731
        folded = jax.custom_batching.custom_vmap(unflat)

        @folded.def_vmap
        def rule(axis_size, in_batched, ls, *a):
            if any(in_batched[0]):
                in_axes = tuple(jax.tree.map(lambda b: 0 if b else None, ib) for ib in in_batched)
                out = jax.vmap(unflat, in_axes=in_axes)(ls, *a)
                return out, jax.tree.map(lambda _: True, out)

            def fold(x, batched):
                x = x if batched else jnp.broadcast_to(x, (axis_size,) + jnp.shape(x))
                return x.reshape((axis_size * x.shape[1],) + x.shape[2:])

            # (through ``folded`` again, so that an enclosing vmap folds its axis in too)
            out = folded(ls, *[jax.tree.map(fold, x, b) for x, b in zip(a, in_batched[1:])])
            out = jax.tree.map(lambda x: x.reshape((axis_size, x.shape[0] // axis_size) + x.shape[1:]), out)
            return out, jax.tree.map(lambda _: True, out)

        return folded(leaves, *args)

    return call


# ------------------------------------------------------------------------ soft solver
@jit
def _solve_batch(solver, r, v0):
    """A solver's ``_solve_batch``, compiled per solver kind, options and shapes (the solver's
    arrays are arguments: another MDP of the same shapes reuses the program)."""
    return solver._solve_batch(r, v0)


def _call_flat(solver, r, v0, S, A):
    """Call the solver's compiled solve on K = prod(batch) systems and restore the batch shape,
    so that every batch shape with the same number of systems shares one compiled program."""
    batch = r.shape[:-2]
    K = int(np.prod(batch, dtype=int))
    res = _solve_batch(solver, r.reshape(K, S, A), None if v0 is None else v0.reshape(K, S))
    return SolveResult(res.V.reshape(batch + (S,)), res.Q.reshape(batch + (S, A)), res.num_iter.reshape(batch),
                       res.residual.reshape(batch), res.num_matvec.reshape(batch))


def _flattened(core, r, v0, S, A):
    """Run a batched core on r (..., S, A) and v0 (..., S) or None, flattened to K systems."""
    batch = r.shape[:-2]
    K = int(np.prod(batch, dtype=int))
    v = jnp.zeros((K, S), r.dtype) if v0 is None else v0.reshape(K, S)
    V, Q, it, res, nmv = core(r.reshape(K, S, A), v)
    return SolveResult(V.reshape(batch + (S,)), Q.reshape(batch + (S, A)), it.reshape(batch), res.reshape(batch),
                       nmv.reshape(batch))


class SoftSolver(Pytree):
    """Soft value iteration for one MDP as a pure, jit-able, differentiable function.

    ``solver(rewards, v0)`` maps reward tables (..., S, A) and a warm start (..., S) (or None:
    zeros) to a :class:`SolveResult`. Leading axes are solved together, in lock-step; under
    ``vmap`` the mapped axis joins them (:func:`fold_vmap`: one solve of all the systems, not a
    loop batched step by step). It can be called inside ``jax.jit``, ``vmap`` and ``lax``
    loops, and differentiated (forward or reverse) with respect to the rewards by implicit
    differentiation at the fixed point. Outside a trace the inputs are checked (shape,
    finiteness) and a ValueError names what is wrong.

    Build one with :func:`make_soft_solver`; its attributes ``mdp``, ``discount``,
    ``features`` (S, A, D) and ``num_states``/``num_actions``/``num_features`` describe the
    problem, and ``rewards(theta)`` maps weights (..., D) to reward tables (..., S, A).
    """

    def __init__(self, mdp, *, tol: float = 1e-10, max_iter: Optional[int] = None, method: str = "newton",
                 operator: str = "auto", krylov_dim: int = 5, max_restarts: int = 40, precondition_degree: int = 4,
                 forcing: float = 0.3, grad_tol: float = 1e-11, krylov_precision: str = "auto"):
        if method not in _METHODS_SOFT:
            raise ValueError(f"unknown soft solver method {method!r}; expected one of {_METHODS_SOFT}")
        if max_iter is None:
            max_iter = 100 if method == "newton" else 10000
        _check_options(tol, max_iter, krylov_dim, max_restarts, precondition_degree)
        if not (0 < forcing < 1):
            raise ValueError(f"forcing must lie in (0, 1), got {forcing}")
        if not (np.isfinite(grad_tol) and grad_tol > 0):
            raise ValueError(f"grad_tol must be positive, got {grad_tol}")
        if krylov_precision not in _PRECISIONS:
            raise ValueError(f"unknown krylov_precision {krylov_precision!r}; expected one of {_PRECISIONS}")
        if krylov_precision == "auto":
            krylov_precision = "float32" if mdp.num_states >= _FLOAT32_FROM_STATES else "float64"
        self.mdp = mdp
        self.discount = float(mdp.discount)
        self.method = method
        self.tol = float(tol)
        self.max_iter = int(max_iter)
        self.krylov_dim = int(krylov_dim)
        self.max_restarts = int(max_restarts)
        self.precondition_degree = int(precondition_degree)
        self.forcing = float(forcing)
        self.grad_tol = float(grad_tol)
        self.krylov_precision = krylov_precision
        self.num_states, self.num_actions, self.num_features = mdp.num_states, mdp.num_actions, mdp.num_features
        self._op = _Columns(mdp, operator)
        self.operator = self._op.kind
        self.features = jnp.asarray(mdp.features)
        self._fixed_point, self._at_values = self._make_fixed_point()

    # (closures over the operator's arrays: rebuilt when the solver is unflattened under jit)
    _pytree_derived = ("_fixed_point", "_at_values")

    def _pytree_rebuild(self):
        self._fixed_point, self._at_values = self._make_fixed_point()

    def __repr__(self):
        return (f"SoftSolver(mdp={self.mdp.name!r}, method={self.method!r}, operator={self.operator!r}, "
                f"tol={self.tol:g}, max_iter={self.max_iter}, krylov_precision={self.krylov_precision!r})")

    # -- the fixed points of K reward tables (K, S, A), with their implicit derivative
    def _core(self, op, r, v0):
        r_cols = tuple(r[..., a] for a in range(self.num_actions))
        if self.method == "newton":
            return _soft_newton(op, self.discount, r_cols, v0, self.tol, self.max_iter,
                                self.precondition_degree, self.krylov_dim, self.max_restarts, self.forcing,
                                self.krylov_precision)
        return _soft_vi(op, self.discount, r_cols, v0, self.tol, self.max_iter)

    def _make_fixed_point(self):
        # the operator's arrays are an argument (not closed over): under jit they are traced,
        # and a custom derivative may not close over traced values; only the static options are
        # taken from self. Derivatives are with respect to the rewards (the operator's tangent
        # is ignored: the dynamics are data, not parameters). Two functions share the derivative
        # rule: the fixed point from a warm start (a solve), and the fixed point at values
        # already solved for (one backup: :meth:`at_values`).
        gamma, A = self.discount, self.num_actions
        dim, cycles, gtol, degree = self.krylov_dim, self.max_restarts, self.grad_tol, self.precondition_degree
        precision, core = self.krylov_precision, fold_vmap(self._core)

        def tangent(op, V, Q, dr):
            """(dV, dQ) of the fixed point (V, Q) along reward tangents dr: (I - gamma P_pi) dV
            = sum_a pi_a dr_a, by the linear solves (or their transposes, reverse mode)."""
            pi = tuple(jnp.exp(Q[..., a] - V) for a in range(A))
            rhs = sum(p * dr[..., a] for a, p in enumerate(pi))

            def operator(x, transpose=False):  # (I - gamma P_pi) x, or its transpose, in float64
                return x - gamma * _policy_apply(op, pi, transpose)(x)

            def solve(b, transpose):
                one = fold_vmap(lambda o, p, c: _policy_solve(o, gamma, p, c, gtol, degree, dim, cycles, transpose,
                                                              precision=precision)[0])
                x = one(op, pi, b)
                if precision == "float32":
                    # one step of iterative refinement: the float64 residual's correction solved in
                    # float32 again (relative 1e-5 of 1e-5). A gradient of a log-likelihood sums
                    # large terms that cancel near its optimum: at float32's 1e-5 alone it was wrong
                    # by its own size there, and IRL fits' line searches failed (56 evaluations
                    # for a 20-step fit at 10^5 states, against 13 in float64)
                    x = x + one(op, pi, b - operator(x, transpose))
                return x

            dV = jax.lax.custom_linear_solve(
                operator, rhs,
                solve=lambda _, b: solve(b, False), transpose_solve=lambda _, b: solve(b, True))
            return dV, dr + gamma * jnp.stack(op.apply(dV), -1)

        def with_tangent(fn):
            def jvp(primals, tangents):
                op, r, v = primals
                V, Q, it, res, nmv = out = fn(op, r, v)
                dV, dQ = tangent(op, V, Q, tangents[1])
                zero_int = np.zeros(it.shape, dtype=jax.dtypes.float0)
                return out, (dV, dQ, zero_int, jnp.zeros_like(res), zero_int)

            fn.defjvp(jvp)
            return fn

        @with_tangent
        @jax.custom_jvp
        def fixed_point(op, r, v0):
            Q, V, it, res, nmv = core(op, r, v0)
            # V = logsumexp(Q) exactly (same Q columns), so Q - V is a normalised log-policy
            return V, jnp.stack(Q, -1), it, res, nmv

        @with_tangent
        @jax.custom_jvp
        def at_values(op, r, V):
            r_cols = tuple(r[..., a] for a in range(A))
            Q, TV, _ = _soft_backup(r_cols, op.apply(V), gamma)
            zeros = jnp.zeros(V.shape[:1], jnp.int32)
            return TV, jnp.stack(Q, -1), zeros, _relative(TV - V, TV), zeros

        return fixed_point, at_values

    def with_tolerance(self, tol: float, grad_tol: Optional[float] = None) -> "SoftSolver":
        """This solver with another relative tolerance (and that of its derivative's linear
        solves, ``grad_tol``; default a tenth of ``tol``), sharing the MDP's arrays: usable
        inside a trace, where it copies the traced solver. Nothing is tightened: each tolerance
        is the looser of this solver's and the one asked for."""
        tol = float(tol)
        grad_tol = tol / 10.0 if grad_tol is None else float(grad_tol)
        _check_options(tol, self.max_iter, self.krylov_dim, self.max_restarts, self.precondition_degree)
        if not (np.isfinite(grad_tol) and grad_tol > 0):
            raise ValueError(f"grad_tol must be positive, got {grad_tol}")
        new = copy.copy(self)
        new.tol, new.grad_tol = max(self.tol, tol), max(self.grad_tol, grad_tol)
        new._fixed_point, new._at_values = new._make_fixed_point()
        return new

    def _solve_batch(self, r, v0):
        return _flattened(partial(self._fixed_point, self._op), r, v0, self.num_states, self.num_actions)

    def __call__(self, rewards, v0=None) -> SolveResult:
        """Solve for reward tables (..., S, A), warm-started from v0 (..., S) or zeros."""
        S, A = self.num_states, self.num_actions
        shape = jnp.shape(rewards)
        if len(shape) < 2 or tuple(shape[-2:]) != (S, A):
            raise ValueError(f"rewards must have shape (..., {S}, {A}) = (..., states, actions), got {shape}")
        if v0 is not None and tuple(jnp.shape(v0)) != tuple(shape[:-2]) + (S,):
            raise ValueError(f"v0 must have shape {tuple(shape[:-2]) + (S,)} to match the rewards, "
                             f"got {jnp.shape(v0)}")
        if _is_concrete(rewards):
            check_rewards(self.mdp, rewards)
        if v0 is not None and _is_concrete(v0):
            _check_v0(v0, shape[:-2], S)
        rewards = jnp.asarray(rewards, jnp.float64)
        v0 = None if v0 is None else jnp.asarray(v0, jnp.float64)
        return _call_flat(self, rewards, v0, S, A)

    def at_values(self, rewards, V) -> SolveResult:
        """The :class:`SolveResult` of reward tables (..., S, A) whose soft values V (..., S)
        are already known (a solve's or an IRL fit's, e.g. :func:`npbrs.models.fit_reward`'s):
        one soft backup from V, no solve (``num_iter`` 0; ``residual`` says how far V is from
        the fixed point). Differentiable like a call, by the same implicit derivative (only the
        tangent or adjoint linear solves), which is the fixed point's to the accuracy of V: a
        program that needs a policy or a Fisher information where the values are at hand holds
        no copy of the nonlinear solve."""
        S, A = self.num_states, self.num_actions
        shape = jnp.shape(rewards)
        if len(shape) < 2 or tuple(shape[-2:]) != (S, A):
            raise ValueError(f"rewards must have shape (..., {S}, {A}) = (..., states, actions), got {shape}")
        if tuple(jnp.shape(V)) != tuple(shape[:-2]) + (S,):
            raise ValueError(f"V must have shape {tuple(shape[:-2]) + (S,)} to match the rewards, got {jnp.shape(V)}")
        if _is_concrete(rewards):
            check_rewards(self.mdp, rewards)
        if _is_concrete(V) and not np.all(np.isfinite(np.asarray(V))):
            raise ValueError("V (the known soft values) has non-finite values")
        return _flattened(partial(self._at_values, self._op), jnp.asarray(rewards, jnp.float64),
                          jnp.asarray(V, jnp.float64), S, A)

    def rewards(self, theta) -> jax.Array:
        """Reward tables r = phi . theta, (..., S, A) for theta (..., D)."""
        theta = jnp.asarray(theta, jnp.float64)
        if theta.shape[-1:] != (self.num_features,):
            raise ValueError(f"theta must have shape (..., {self.num_features}) for features "
                             f"{list(self.mdp.feature_names)}, got {theta.shape}")
        return jnp.einsum("sad,...d->...sa", self.features, theta)

    def expected_next_value(self, V) -> jax.Array:
        """E[V(s') | s, a], (..., S, A) for V (..., S)."""
        V = jnp.asarray(V)
        flat = V.reshape((-1, V.shape[-1]))
        return jnp.stack(self._op.apply(flat), -1).reshape(V.shape + (self.num_actions,))


def make_soft_solver(mdp, *, tol: float = 1e-10, max_iter: Optional[int] = None, method: str = "newton",
                     operator: str = "auto", krylov_dim: int = 5, max_restarts: int = 40,
                     precondition_degree: int = 4, forcing: float = 0.3, grad_tol: float = 1e-11,
                     krylov_precision: str = "auto") -> SoftSolver:
    """A pure, jit-able soft value iteration for ``mdp``: ``solve(rewards, v0) -> SolveResult``.

    Args:
        mdp: the TabularMDP (its discount, dynamics and features are closed over).
        tol: relative max-norm Bellman residual at which to stop.
        max_iter: cap on Newton steps ("newton", default 100) or sweeps ("vi", default 10000).
        method: "newton" (soft policy iteration with GMRES policy evaluation) or "vi" (plain
            value iteration; slow, kept as a reference).
        operator: next-value operator kind (see :func:`next_value_operator`).
        krylov_dim: GMRES restart length; max_restarts: GMRES cycles per linear solve.
        precondition_degree: degree of the truncated Neumann-series preconditioner of each
            policy evaluation (1: none; see the module docstring).
        forcing: the largest relative residual a Newton step's linear solve may stop at (the
            Eisenstat-Walker forcing terms are capped by it; see ``_soft_newton``).
        grad_tol: relative tolerance of the linear solves of derivatives.
        krylov_precision: "float64", "float32" or "auto" (float32 from 50,000 states): the
            precision of the Newton steps' linear solves. The solution is float64 either way
            (the Newton iteration and its convergence test are); float32 halves the memory
            traffic of the solves, which is their cost on large MDPs (a million-state gridworld,
            4 tables: 1.5 s against 2.9 s), and can cost an extra Newton step. Derivatives'
            solves follow it, refined once in float64 (see the module docstring): near an IRL
            fit's optimum a relative 1e-5 alone left its gradient wrong by its own size.
    Returns:
        A :class:`SoftSolver`; ``solver(rewards (..., S, A), v0 (..., S) or None)``.

    Example::

        solver = make_soft_solver(mdp)
        res = solver(rewards)                          # rewards (K, S, A): res.V (K, S), res.Q (K, S, A)
        res = jax.jit(solver)(rewards * 1.01, res.V)   # warm start, inside jit
        g = jax.grad(lambda r: solver(r).V.sum())(rewards)  # implicit gradient
    """
    return SoftSolver(mdp, tol=tol, max_iter=max_iter, method=method, operator=operator, krylov_dim=krylov_dim,
                      max_restarts=max_restarts, precondition_degree=precondition_degree, forcing=forcing,
                      grad_tol=grad_tol, krylov_precision=krylov_precision)


# ------------------------------------------------------------------------ hard solver
def _hard_policy_iteration(op, gamma, r_cols, v0, tol, max_iter, degree, dim, max_cycles):
    """Howard's policy iteration for K reward tables in lock-step; evaluation by GMRES to
    rounding, improvement keeps the current action unless another is better by more than
    rounding (so ties cannot make it cycle). ``tol`` is unused: it stops when no policy
    changes."""
    A = len(r_cols)
    K = v0.shape[0]

    def greedy(Q, current, V):
        Qs = jnp.stack(Q, 0)  # (A, K, S)
        best = jnp.argmax(Qs, axis=0)
        q_best = jnp.max(Qs, 0)
        q_cur = jnp.take_along_axis(Qs, current[None], 0)[0]
        margin = 1e-12 * jnp.maximum(1.0, jnp.max(jnp.abs(V), axis=-1, keepdims=True))
        return jnp.where(q_best > q_cur + margin, best, current)

    def qcols(V):
        return tuple(r + gamma * e for r, e in zip(r_cols, op.apply(V)))

    def cond(c):
        return (c[6] < max_iter) & jnp.any(c[4])

    def body(c):
        policy, V, _, it, changed, nmv, n = c
        onehot = tuple((policy == a).astype(V.dtype) for a in range(A))
        r_pi = sum(o * r for o, r in zip(onehot, r_cols))
        residual = jnp.where(changed[:, None], r_pi - V + gamma * _policy_apply(op, onehot)(V), 0.0)
        step, k, _ = _policy_solve(op, gamma, onehot, residual, 1e-14, degree, dim, max_cycles)
        V = V + step
        Q = qcols(V)
        new = greedy(Q, policy, V)
        return new, V, Q, it + changed, jnp.any(new != policy, axis=-1), nmv + jnp.where(changed, k + 1, 0), n + 1

    Q0 = qcols(v0)
    pol0 = jnp.argmax(jnp.stack(Q0, 0), axis=0)
    zeros = jnp.zeros(K, jnp.int32)
    init = (pol0, v0, Q0, zeros, jnp.ones(K, bool), zeros, jnp.asarray(0))
    _, V, Q, it, _, nmv, _ = jax.lax.while_loop(cond, body, init)
    Vmax = jnp.max(jnp.stack(Q, 0), 0)
    return Q, Vmax, it, _relative(Vmax - V, Vmax), nmv


def _hard_vi(op, gamma, r_cols, v0, tol, max_iter):
    K = v0.shape[0]

    def backup(V):
        Q = tuple(r + gamma * e for r, e in zip(r_cols, op.apply(V)))
        return Q, jnp.max(jnp.stack(Q, 0), 0)

    def cond(c):
        return (c[5] < max_iter) & jnp.any(c[4] > tol)

    def body(c):
        V, Q, TV, it, res, n = c
        active = res > tol
        Q_new, TV_new = backup(TV)
        keep = lambda new, old: jnp.where(active[:, None], new, old)
        return (keep(TV, V), tuple(keep(a, b) for a, b in zip(Q_new, Q)), keep(TV_new, TV), it + active,
                jnp.where(active, _relative(TV_new - TV, TV_new), res), n + 1)

    Q, TV = backup(v0)
    init = (v0, Q, TV, jnp.zeros(K, jnp.int32), _relative(TV - v0, TV), jnp.asarray(0))
    _, Q, TV, it, res, _ = jax.lax.while_loop(cond, body, init)
    return Q, TV, it, res, jnp.zeros(K, jnp.int32)


class HardSolver(Pytree):
    """Hard (max) Bellman solver for one MDP: ``solver(rewards (..., S, A), v0) -> SolveResult``.

    ``method="policy"`` (default): Howard's policy iteration with GMRES policy evaluation; it
    stops when the greedy policy no longer changes, so the greedy policy of the result is
    exactly optimal (up to ties within 1e-12 relative). ``method="vi"``: value iteration to
    the relative tolerance ``tol``. Pure and jit-able; not differentiable.
    """

    def __init__(self, mdp, *, tol: float = 1e-12, max_iter: Optional[int] = None, method: str = "policy",
                 operator: str = "auto", krylov_dim: int = 12, max_restarts: int = 100, precondition_degree: int = 4):
        if method not in _METHODS_HARD:
            raise ValueError(f"unknown hard solver method {method!r}; expected one of {_METHODS_HARD}")
        if max_iter is None:
            max_iter = 200 if method == "policy" else 20000
        _check_options(tol, max_iter, krylov_dim, max_restarts, precondition_degree)
        self.mdp = mdp
        self.discount = float(mdp.discount)
        self.precondition_degree = int(precondition_degree)
        self.method, self.tol, self.max_iter = method, float(tol), int(max_iter)
        self.krylov_dim, self.max_restarts = int(krylov_dim), int(max_restarts)
        self.num_states, self.num_actions = mdp.num_states, mdp.num_actions
        self._op = _Columns(mdp, operator)
        self.operator = self._op.kind

    def _core(self, r, v0):
        r_cols = tuple(r[..., a] for a in range(self.num_actions))
        if self.method == "policy":
            Q, V, it, res, nmv = _hard_policy_iteration(self._op, self.discount, r_cols, v0, self.tol,
                                                        self.max_iter, self.precondition_degree, self.krylov_dim,
                                                        self.max_restarts)
        else:
            Q, V, it, res, nmv = _hard_vi(self._op, self.discount, r_cols, v0, self.tol, self.max_iter)
        return V, jnp.stack(Q, -1), it, res, nmv

    def _solve_batch(self, r, v0):
        return _flattened(self._core, r, v0, self.num_states, self.num_actions)

    def __call__(self, rewards, v0=None) -> SolveResult:
        shape = jnp.shape(rewards)
        S, A = self.num_states, self.num_actions
        if len(shape) < 2 or tuple(shape[-2:]) != (S, A):
            raise ValueError(f"rewards must have shape (..., {S}, {A}) = (..., states, actions), got {shape}")
        if _is_concrete(rewards):
            check_rewards(self.mdp, rewards)
        if v0 is not None:
            if tuple(jnp.shape(v0)) != tuple(shape[:-2]) + (S,):
                raise ValueError(f"v0 must have shape {tuple(shape[:-2]) + (S,)} to match the rewards, "
                                 f"got {jnp.shape(v0)}")
            if _is_concrete(v0):
                _check_v0(v0, shape[:-2], S)
            v0 = jnp.asarray(v0, jnp.float64)
        return _call_flat(self, jnp.asarray(rewards, jnp.float64), v0, S, A)


def make_hard_solver(mdp, *, tol: float = 1e-12, max_iter: Optional[int] = None, method: str = "policy",
                     operator: str = "auto", krylov_dim: int = 12, max_restarts: int = 100,
                     precondition_degree: int = 4) -> HardSolver:
    """A pure, jit-able hard (max) Bellman solver for ``mdp`` (see :class:`HardSolver`)."""
    return HardSolver(mdp, tol=tol, max_iter=max_iter, method=method, operator=operator, krylov_dim=krylov_dim,
                      max_restarts=max_restarts, precondition_degree=precondition_degree)


# --------------------------------------------------------------- convenience functions
_CACHE: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def _cached(mdp, cls, **options):
    """One solver per (mdp, options), so repeated calls reuse the compiled function."""
    per_mdp = _CACHE.setdefault(mdp, {})
    key = (cls.__name__,) + tuple(sorted(options.items()))
    if key not in per_mdp:
        per_mdp[key] = cls(mdp, **options)
    return per_mdp[key]


def soft_value_iteration(mdp, rewards, *, v0=None, tol: float = 1e-10, max_iter: Optional[int] = None,
                         operator: str = "auto", method: str = "newton") -> SolveResult:
    """Soft value iteration for reward tables ``rewards`` (..., S, A).

    Args:
        mdp: the TabularMDP.
        rewards: (S, A) or (K, S, A) reward tables.
        v0: optional warm start (..., S).
        tol: relative max-norm Bellman residual at which to stop.
        max_iter: iteration cap (Newton steps, or sweeps for method "vi").
        operator: next-value operator kind (see :func:`next_value_operator`).
        method: "newton" (default) or "vi" (see :func:`make_soft_solver`).
    Returns:
        SolveResult with V (..., S) and Q (..., S, A).
    """
    solver = _cached(mdp, SoftSolver, tol=float(tol), max_iter=max_iter, operator=operator, method=method)
    return solver(rewards, v0)


def value_iteration(mdp, rewards, *, v0=None, tol: float = 1e-12, max_iter: Optional[int] = None,
                    operator: str = "auto", method: str = "policy") -> SolveResult:
    """Hard (max) Bellman solve for reward tables (..., S, A): the optimal Q of each.

    method: "policy" (policy iteration, exact greedy policy; default) or "vi" (value iteration).
    """
    solver = _cached(mdp, HardSolver, tol=float(tol), max_iter=max_iter, operator=operator, method=method)
    return solver(rewards, v0)


def boltzmann_log_policy(Q) -> jax.Array:
    """log softmax_a Q(s, a): the Boltzmann (soft-optimal) policy, (..., S, A)."""
    return jax.nn.log_softmax(Q, axis=-1)


def greedy_policy(Q, atol: float = 1e-9) -> np.ndarray:
    """Deterministic optimal policy: the lowest-index action within ``atol`` of the max. (..., S)."""
    Q = np.asarray(Q)
    best = Q.max(-1, keepdims=True)
    return np.argmax(Q >= best - atol * np.maximum(1.0, np.abs(best)), axis=-1)


float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
