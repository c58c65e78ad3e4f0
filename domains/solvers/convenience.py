"""Convenience functions: a Bellman solve of one MDP without building a solver first (one solver
kept per MDP and options), and the policies of a Q-table."""

from __future__ import annotations

import weakref
from typing import Optional

import jax
import numpy as np

from ..util.precision import float64_all
from .common import SolveResult
from .hard import HardSolver
from .soft import SoftSolver

__all__ = ["soft_value_iteration", "value_iteration", "boltzmann_log_policy", "greedy_policy"]

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
