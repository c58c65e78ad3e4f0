"""The soft (maximum causal entropy) Bellman solver: inexact Newton (soft policy iteration) with
GMRES policy evaluations, plain soft value iteration as a reference, and :class:`SoftSolver`
with its implicit derivatives (see :mod:`npbrs.domains.solvers`)."""

from __future__ import annotations

import copy
from functools import partial
from typing import Optional

import jax
import jax.numpy as jnp
import numpy as np

from ..util.pytree import Pytree
from ..util.compiling import jit
from ..util.precision import float64_all
from .common import (SolveResult, _call_flat, _check_options, _check_v0, _flattened, _is_concrete, _relative,
                     check_rewards, fold_vmap)
from .krylov import _policy_apply, _policy_solve
from .operators import Columns

__all__ = ["make_soft_solver", "SoftSolver"]

_METHODS_SOFT = ("newton", "vi")
_PRECISIONS = ("auto", "float64", "float32")
#: ``krylov_precision="auto"``: the Newton steps' linear systems are solved in float32 from this
#: many states on (where their memory traffic is their cost), in float64 below
FLOAT32_FROM_STATES = 50_000


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


# ------------------------------------------------------------------------ soft solver
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
            krylov_precision = "float32" if mdp.num_states >= FLOAT32_FROM_STATES else "float64"
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
        self._op = Columns(mdp, operator)
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
            policy evaluation (1: none; see :mod:`npbrs.domains.solvers`).
        forcing: the largest relative residual a Newton step's linear solve may stop at (the
            Eisenstat-Walker forcing terms are capped by it; see ``_soft_newton``).
        grad_tol: relative tolerance of the linear solves of derivatives.
        krylov_precision: "float64", "float32" or "auto" (float32 from 50,000 states): the
            precision of the Newton steps' linear solves. The solution is float64 either way
            (the Newton iteration and its convergence test are); float32 halves the memory
            traffic of the solves, which is their cost on large MDPs (a million-state gridworld,
            4 tables: 1.5 s against 2.9 s), and can cost an extra Newton step. Derivatives'
            solves follow it, refined once in float64 (see :mod:`npbrs.domains.solvers`): near an IRL
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


float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
