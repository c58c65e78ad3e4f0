"""The hard (max) Bellman solver: Howard's policy iteration with GMRES policy evaluations, or
value iteration, and :class:`HardSolver` (see :mod:`npbrs.domains.solvers`)."""

from __future__ import annotations

from typing import Optional

import jax
import jax.numpy as jnp

from ..util.pytree import Pytree
from ..util.precision import float64_all
from .common import (SolveResult, _call_flat, _check_options, _check_v0, _flattened, _is_concrete, _relative,
                     check_rewards)
from .krylov import _policy_apply, _policy_solve
from .operators import Columns

__all__ = ["make_hard_solver", "HardSolver"]

_METHODS_HARD = ("policy", "vi")


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
        self._op = Columns(mdp, operator)
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


float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
