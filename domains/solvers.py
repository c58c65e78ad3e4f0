"""Bellman solvers on a :class:`~npbrs.domains.TabularMDP`: soft (maximum causal entropy)
and hard value iteration, in JAX, batched over reward tables.

Soft:  Q(s, a) = r(s, a) + gamma * E[V(s') | s, a],  V(s) = logsumexp_a Q(s, a).
Hard:  the same with max in place of logsumexp.
"""

from __future__ import annotations

from typing import Callable, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

__all__ = ["next_value_operator", "soft_value_iteration", "value_iteration", "SolveResult",
           "boltzmann_log_policy", "greedy_policy"]


class SolveResult(NamedTuple):
    """Values of a Bellman solve.

    V: (..., S) state values. Q: (..., S, A) action values. num_iter: iterations used.
    residual: final max-norm Bellman residual relative to max |V|.
    """

    V: jax.Array
    Q: jax.Array
    num_iter: jax.Array
    residual: jax.Array


def next_value_operator(mdp, kind: str = "auto") -> Callable:
    """E[V(s') | s, a] as a function of V (..., S) -> (..., S, A).

    kind: "auto" (the domain's factored operator if it has one, else "sparse"),
    "sparse" (gather over successor arrays), "dense" (matrix product with P[s, a, s']),
    "factored" (the domain's own operator; error if it has none).
    """
    if kind == "auto":
        kind = "factored" if mdp.next_value_fn is not None else "sparse"
    if kind == "sparse":
        succ = jnp.asarray(mdp.successors)
        probs = jnp.asarray(mdp.probs)

        def op(V):
            return jnp.sum(V[..., succ] * probs, axis=-1)

        return op
    if kind == "dense":
        P = jnp.asarray(mdp.dense_transitions())

        def op(V):
            return jnp.einsum("sat,...t->...sa", P, V)

        return op
    if kind == "factored":
        if mdp.next_value_fn is None:
            raise ValueError(f"MDP {mdp.name!r} supplies no factored next-value operator")
        return mdp.next_value_fn
    raise ValueError(f"unknown next-value operator kind {kind!r}; expected 'auto', 'sparse', 'dense' or 'factored'")


def _check_rewards(mdp, rewards):
    r = jnp.asarray(rewards, dtype=jnp.float64)
    if r.shape[-2:] != (mdp.num_states, mdp.num_actions):
        raise ValueError(f"rewards must have shape (..., {mdp.num_states}, {mdp.num_actions}), got {r.shape}")
    return r


def _fixed_point(backup, r, gamma, next_value, v0, tol, max_iter):
    def body(carry):
        V, _, it, _ = carry
        Q = r + gamma * next_value(V)
        V_new = backup(Q)
        res = jnp.max(jnp.abs(V_new - V)) / jnp.maximum(1.0, jnp.max(jnp.abs(V_new)))
        return V_new, Q, it + 1, res

    def cond(carry):
        _, _, it, res = carry
        return (it < max_iter) & (res > tol)

    Q0 = r + gamma * next_value(v0)
    init = (backup(Q0), Q0, jnp.asarray(1), jnp.asarray(jnp.inf))
    V, Q, it, res = jax.lax.while_loop(cond, body, init)
    return SolveResult(V, Q, it, res)


def soft_value_iteration(mdp, rewards, *, v0=None, tol: float = 1e-10, max_iter: int = 5000,
                         operator: str = "auto") -> SolveResult:
    """Soft value iteration for reward tables ``rewards`` (..., S, A).

    Args:
        mdp: the TabularMDP.
        rewards: (S, A) or (K, S, A) reward tables.
        v0: optional warm start (..., S).
        tol: relative max-norm tolerance on successive values.
        max_iter: iteration cap.
        operator: next-value operator kind (see :func:`next_value_operator`).
    Returns:
        SolveResult with V (..., S) and Q (..., S, A).
    """
    r = _check_rewards(mdp, rewards)
    gamma = float(mdp.discount)
    op = next_value_operator(mdp, operator)
    if v0 is None:
        v0 = jnp.zeros(r.shape[:-1])
    return _fixed_point(lambda Q: jax.nn.logsumexp(Q, axis=-1), r, gamma, op, jnp.asarray(v0, jnp.float64),
                        tol, max_iter)


def value_iteration(mdp, rewards, *, v0=None, tol: float = 1e-12, max_iter: int = 10000,
                    operator: str = "auto") -> SolveResult:
    """Hard (max) value iteration for reward tables (..., S, A); the optimal Q of each."""
    r = _check_rewards(mdp, rewards)
    gamma = float(mdp.discount)
    op = next_value_operator(mdp, operator)
    if v0 is None:
        v0 = jnp.zeros(r.shape[:-1])
    return _fixed_point(lambda Q: jnp.max(Q, axis=-1), r, gamma, op, jnp.asarray(v0, jnp.float64), tol, max_iter)


def boltzmann_log_policy(Q) -> jax.Array:
    """log softmax_a Q(s, a): the Boltzmann (soft-optimal) policy, (..., S, A)."""
    return jax.nn.log_softmax(Q, axis=-1)


def greedy_policy(Q, atol: float = 1e-9) -> np.ndarray:
    """Deterministic optimal policy: the lowest-index action within ``atol`` of the max. (..., S)."""
    Q = np.asarray(Q)
    best = Q.max(-1, keepdims=True)
    return np.argmax(Q >= best - atol * np.maximum(1.0, np.abs(best)), axis=-1)
