"""MALA update of reward weights theta_k given the (state, action) counts of skill k's steps.

The target is the conditional posterior of each skill's weights,

    p(theta_k | counts_k) ∝ exp(sum_{s,a} C_k[s, a] log pi_theta_k(a | s)) N(theta_k; 0, sigma^2 I),

with the Boltzmann policy of the soft Bellman equation (:mod:`npbrs.models.reward`). One step is
a Metropolis-adjusted Langevin move per skill, for all skills at once: propose
theta' = theta + (eps^2 / 2) M^-1 grad log p(theta) + eps M^-1/2 xi and accept with the
Metropolis-Hastings ratio including both proposal densities, so the conditional is left
invariant exactly (up to the solver's tolerance). All skills' proposals are solved together
(one batched solve and one batched adjoint solve per step), every solve warm-started from the
values of the current state.

Blackjax-style: ``init`` makes the state, ``build_kernel`` returns
``kernel(rng_key, state, counts, step_size, inverse_mass=None) -> (state, info)``; both are pure
and jit-able with static shapes.

A proposal whose solve did not reach the solver's tolerance (a far-out theta, or the iteration
cap) is rejected; this keeps a failed solve from being accepted on a wrong density, and happens
with negligible probability at sensible step sizes (``info.solver_failed`` counts it).
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp

from ..models.reward import PRIOR_SCALE, _check_prior_scale, _ll_grad_residual, as_solver, log_prior
from npbrs.domains.precision import float64_all

__all__ = ["RewardMALAState", "RewardMALAInfo", "init", "build_kernel"]


class RewardMALAState(NamedTuple):
    """State of the reward-weight MALA chain of K skills.

    theta: (K, D) reward weights. log_density: (K,) log-likelihood of the counts plus log-prior.
    grad: (K, D) its gradient. V: (K, S) soft values at theta (the next solve's warm start).
    """

    theta: jax.Array
    log_density: jax.Array
    grad: jax.Array
    V: jax.Array


class RewardMALAInfo(NamedTuple):
    """Diagnostics of one MALA step, per skill (K,).

    acceptance_rate: min(1, Metropolis-Hastings ratio). is_accepted: whether the proposal was
    taken. proposal_log_density: log density at the proposal. solver_failed: the proposal's
    solve missed the tolerance (the proposal was rejected).
    """

    acceptance_rate: jax.Array
    is_accepted: jax.Array
    proposal_log_density: jax.Array
    solver_failed: jax.Array


def _log_density_and_grad(solver, theta, counts, v0, prior_scale):
    """log p(theta_k | counts_k) up to a constant for K skills (one batched solve), its
    gradient, V, and whether each solve converged."""

    ll, g, V, residual = _ll_grad_residual(solver, theta, counts, v0)
    lp = ll + log_prior(theta, prior_scale[:, None])
    g = g - theta / prior_scale[:, None] ** 2
    ok = (residual <= solver.tol) & jnp.isfinite(lp)
    return lp, g, V, ok & jnp.all(jnp.isfinite(g), axis=-1)


_LOG_DENSITY_AND_GRAD = jax.jit(_log_density_and_grad)


def init(solver, theta, counts, prior_scale=PRIOR_SCALE, v0=None) -> RewardMALAState:
    """The chain's state at theta (K, D) for counts (K, S, A).

    Args:
        solver: a SoftSolver (:func:`npbrs.domains.make_soft_solver`) or a TabularMDP.
        theta: (K, D) starting weights; counts: (K, S, A) count tables.
        prior_scale: sigma of the Gaussian prior, scalar or (K,).
        v0: optional (K, S) warm start of the first solve.
    """
    solver = as_solver(solver)
    _check_prior_scale(prior_scale)
    theta = jnp.asarray(theta, jnp.float64)
    counts = jnp.asarray(counts, jnp.float64)
    if theta.ndim != 2 or theta.shape[1] != solver.num_features:
        raise ValueError(f"theta must have shape (K, {solver.num_features}), got {theta.shape}")
    K = theta.shape[0]
    if counts.shape != (K, solver.num_states, solver.num_actions):
        raise ValueError(f"counts must have shape ({K}, {solver.num_states}, {solver.num_actions}), got {counts.shape}")
    v0 = jnp.zeros((K, solver.num_states)) if v0 is None else jnp.asarray(v0, jnp.float64)
    scale = jnp.broadcast_to(jnp.asarray(prior_scale, jnp.float64), (K,))
    lp, g, V, _ = _LOG_DENSITY_AND_GRAD(solver, theta, counts, v0, scale)
    return RewardMALAState(theta, lp, g, V)


def build_kernel(solver, prior_scale=PRIOR_SCALE) -> Callable:
    """A MALA kernel for K skills' reward weights.

    Args:
        solver: a SoftSolver or a TabularMDP (its tolerance sets the density's accuracy).
        prior_scale: sigma of the Gaussian prior, scalar or (K,).
    Returns:
        ``kernel(rng_key, state, counts, step_size, inverse_mass=None) -> (state, info)`` with
        counts (K, S, A), step_size scalar or (K,), inverse_mass (the diagonal preconditioner
        M^-1) None, (D,) or (K, D).
    """
    solver = as_solver(solver)
    _check_prior_scale(prior_scale)

    def kernel(rng_key, state: RewardMALAState, counts, step_size, inverse_mass=None):
        K, D = state.theta.shape
        counts = jnp.asarray(counts, jnp.float64)
        if counts.shape != (K, solver.num_states, solver.num_actions):
            raise ValueError(f"counts must have shape ({K}, {solver.num_states}, {solver.num_actions}), "
                             f"got {counts.shape}")
        eps = jnp.broadcast_to(jnp.asarray(step_size, jnp.float64), (K,))[:, None]
        minv = jnp.ones((K, D)) if inverse_mass is None else \
            jnp.broadcast_to(jnp.asarray(inverse_mass, jnp.float64), (K, D))
        scale = jnp.broadcast_to(jnp.asarray(prior_scale, jnp.float64), (K,))
        k_prop, k_acc = jax.random.split(rng_key)
        theta, lp, grad, V = state
        mean_fwd = theta + 0.5 * eps ** 2 * minv * grad
        prop = mean_fwd + eps * jnp.sqrt(minv) * jax.random.normal(k_prop, theta.shape)
        # all skills' proposals in one batched solve, warm-started from the current values
        lp_new, grad_new, V_new, ok = _LOG_DENSITY_AND_GRAD(solver, prop, counts, V, scale)
        mean_bwd = prop + 0.5 * eps ** 2 * minv * grad_new
        log_q_fwd = -0.5 * jnp.sum((prop - mean_fwd) ** 2 / minv / eps ** 2, -1)
        log_q_bwd = -0.5 * jnp.sum((theta - mean_bwd) ** 2 / minv / eps ** 2, -1)
        log_ratio = lp_new - lp + log_q_bwd - log_q_fwd
        log_ratio = jnp.where(ok & jnp.isfinite(log_ratio), log_ratio, -jnp.inf)
        accept = jnp.log(jax.random.uniform(k_acc, (K,))) < log_ratio
        rate = jnp.exp(jnp.minimum(log_ratio, 0.0))
        pick = lambda new, old: jnp.where(accept.reshape((K,) + (1,) * (new.ndim - 1)), new, old)
        new_state = RewardMALAState(pick(prop, theta), pick(lp_new, lp), pick(grad_new, grad), pick(V_new, V))
        return new_state, RewardMALAInfo(rate, accept, lp_new, ~ok)

    return kernel


float64_all(globals())  # npbrs.domains.precision: float64 inside, the user's setting outside
