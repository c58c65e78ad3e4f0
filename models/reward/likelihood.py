"""The reward emission's likelihood: Boltzmann policies of linear rewards, count tables, the
log-likelihoods of steps and their gradients, the Fisher information, and the one density of a
skill's weights (:func:`log_posterior`).

A skill is a reward r_k(s, a) = phi(s, a) . theta_k; its demonstrator acts with the Boltzmann
policy pi_k(a | s) = exp(Q_k(s, a) - V_k(s)) of the soft Bellman equation of the rewards
tau * r_k (tau: the demonstrator's inverse temperature, 1 by default), mixed with uniform actions
at rate epsilon for a noisy expert. ``log_policy`` is the one place tau and epsilon enter, and
``log_posterior`` the one density of a skill's weights (the MALA move of
:mod:`npbrs.models.reward.mala`, the IRL fits and the MAP update all use it). Because

    sum_t w_t log pi(a_t | s_t) = sum_{s, a} C[s, a] log pi(a | s),

with C the weighted count table of the steps, every quantity a sampler needs of a skill's
steps (log-likelihood, its gradient, an IRL fit, a MALA move) depends on the data only through
an (S, A) table; ``count_table`` builds it with one scatter-add.

Gradients are implicit (see :mod:`npbrs.domains.solvers`): the soft fixed point is never
unrolled, and the gradient of a log-likelihood costs one adjoint linear solve, batched over
skills.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from npbrs.domains.solvers import SoftSolver, make_soft_solver
from npbrs.domains.util.compiling import jit
from npbrs.domains.util.precision import float64_all
from .prior import PRIOR_SCALE, log_prior, prior_grad

__all__ = ["count_table", "log_policy", "step_log_likelihoods", "count_log_likelihood",
           "count_log_likelihood_and_values", "count_log_likelihood_and_grad", "fisher_information",
           "log_posterior", "Posterior", "as_solver"]


# --------------------------------------------------------------------------- checking
def _is_concrete(*xs) -> bool:
    return not any(isinstance(x, jax.core.Tracer) for x in xs)


def _check_steps(states, actions, S, A, mask=None):
    """States/actions (N, T) inside 0..S-1 / 0..A-1 on real steps: ValueError naming the step."""
    s = np.asarray(states)
    a = np.asarray(actions)
    if s.shape != a.shape or s.ndim != 2:
        raise ValueError(f"states and actions must both have shape (N, T), got {s.shape} and {a.shape}")
    real = np.ones(s.shape, bool) if mask is None else np.asarray(mask, bool)
    if real.shape != s.shape:
        raise ValueError(f"mask must have shape {s.shape} like the states, got {real.shape}")
    for name, x, n in (("state", s, S), ("action", a, A)):
        if not np.issubdtype(x.dtype, np.integer):
            raise ValueError(f"{name}s must be integers, got dtype {x.dtype}")
        bad = real & ((x < 0) | (x >= n))
        if bad.any():
            i, t = (int(v) for v in np.argwhere(bad)[0])
            raise ValueError(f"trajectory {i}, step {t}: {name} {x[i, t]} is outside 0..{n - 1}")


def _check_theta(theta, D):
    t = np.asarray(theta, dtype=np.float64)
    if t.ndim not in (1, 2) or t.shape[-1] != D:
        raise ValueError(f"theta must have shape (D,) or (K, D) with D = {D} features, got {t.shape}")
    if not np.all(np.isfinite(t)):
        idx = tuple(int(i) for i in np.argwhere(~np.isfinite(t))[0])
        raise ValueError(f"theta{list(idx)} is not finite ({t[idx]})")


def _check_counts(counts, S, A):
    c = np.asarray(counts, dtype=np.float64)
    if c.ndim not in (2, 3) or c.shape[-2:] != (S, A):
        raise ValueError(f"counts must have shape (S, A) or (K, S, A) with (S, A) = ({S}, {A}), got {c.shape}")
    bad = ~np.isfinite(c) | (c < 0)
    if bad.any():
        idx = tuple(int(i) for i in np.argwhere(bad)[0])
        raise ValueError(f"counts{list(idx)} = {c[idx]} is negative or not finite")


def _check_prior_scale(prior_scale):
    if _is_concrete(prior_scale) and not np.all(np.asarray(prior_scale) > 0):
        raise ValueError(f"prior_scale must be positive, got {prior_scale}")


def as_solver(mdp_or_solver, **options) -> SoftSolver:
    """A SoftSolver: the argument itself, or ``make_soft_solver(mdp, **options)`` for an MDP."""
    if isinstance(mdp_or_solver, SoftSolver):
        return mdp_or_solver
    return make_soft_solver(mdp_or_solver, **options)


# ----------------------------------------------------------------------------- counts
def count_table(states, actions, weights, num_states: int, num_actions: int, mask=None) -> jax.Array:
    """Weighted (state, action) counts of demonstration steps, by one scatter-add.

    Args:
        states, actions: int arrays (N, T).
        weights: (N, T) or (N, T, K) weights of the steps (e.g. one-hot skill assignments),
            or None for ones.
        num_states, num_actions: S and A.
        mask: optional bool (N, T), False on padded steps (they count 0).
    Returns:
        (S, A) for weights (N, T) or None, (K, S, A) for weights (N, T, K).
    """
    S, A = int(num_states), int(num_actions)
    if _is_concrete(states, actions, mask):
        _check_steps(states, actions, S, A, mask)
    states = jnp.asarray(states)
    actions = jnp.asarray(actions)
    w = jnp.ones(states.shape) if weights is None else jnp.asarray(weights, jnp.float64)
    if w.shape[:2] != states.shape or w.ndim not in (2, 3):
        raise ValueError(f"weights must have shape (N, T) or (N, T, K) with (N, T) = {states.shape}, got {w.shape}")
    if mask is not None:
        w = w * jnp.asarray(mask, bool).reshape(states.shape + (1,) * (w.ndim - 2))
    flat = (states * A + actions).reshape(-1)
    c = jax.ops.segment_sum(w.reshape(flat.shape[0], -1), flat, num_segments=S * A)  # (S*A, K')
    if w.ndim == 2:
        return c[:, 0].reshape(S, A)
    return jnp.moveaxis(c, -1, 0).reshape(w.shape[2], S, A)


# --------------------------------------------------------------------------- policies
def _solve_policy(solver, theta, v0=None, temperature=1.0, epsilon=0.0, solved=False):
    """The one place the demonstrator's policy is made from reward weights: the soft solve of
    the rewards tau * phi . theta (tau: the inverse temperature), its Boltzmann log-policy mixed
    with uniform actions at rate epsilon. Returns (log_pi, V, the solver's residual).
    ``solved``: v0 are these rewards' soft values already (an IRL fit's), and the policy is one
    backup from them (:meth:`SoftSolver.at_values`: no solve, the same derivative)."""
    rewards = solver.rewards(theta * temperature)
    res = solver.at_values(rewards, v0) if solved else solver(rewards, v0)
    return noisy_log_policy(res.Q - res.V[..., None], epsilon), res.V, res.residual


def log_policy(solver: SoftSolver, theta, v0=None, temperature: float = 1.0, epsilon: float = 0.0,
               solved: bool = False, with_residual: bool = False):
    """Boltzmann log-policies of reward weights.

    Args:
        solver: a SoftSolver (:func:`npbrs.domains.make_soft_solver`), or a TabularMDP.
        theta: (D,) or (K, D) reward weights.
        v0: optional warm start (K, S) (or (S,)), e.g. the V of a previous call.
        temperature: inverse temperature tau: the policy of the rewards tau * phi . theta.
        epsilon: the noisy expert's random-action probability (:func:`noisy_log_policy`).
        solved: v0 holds these weights' soft values already (e.g. :func:`fit_reward`'s V, to
            the solver's tolerance): the policies by one backup from them, no solve.
        with_residual: also return the solver's relative Bellman residual (K,) (or ()), which
            is at most ``solver.tol`` where the solve converged.
    Returns:
        (log_pi, V): log pi(a | s), (K, S, A) (or (S, A)), and the soft values (K, S) (or (S,));
        with ``with_residual`` (log_pi, V, residual).
    """
    solver = as_solver(solver)
    if _is_concrete(theta):
        _check_theta(theta, solver.num_features)
    if solved and v0 is None:
        raise ValueError("log_policy: solved=True needs the soft values v0 of theta")
    log_pi, V, residual = _solve_policy(solver, theta, v0, temperature, epsilon, solved)
    return (log_pi, V, residual) if with_residual else (log_pi, V)


def step_log_likelihoods(log_pi, states, actions, mask=None) -> jax.Array:
    """Per-step log-likelihoods log pi_k(a_t | s_t), the array the HMM consumes.

    Args:
        log_pi: (K, S, A) (or (S, A)) log-policies.
        states, actions: int arrays (N, T).
        mask: optional bool (N, T); padded steps get 0.
    Returns:
        (N, T, K) (or (N, T) for a single (S, A) log-policy).
    """
    log_pi = jnp.asarray(log_pi)
    single = log_pi.ndim == 2
    if log_pi.ndim not in (2, 3):
        raise ValueError(f"log_pi must have shape (S, A) or (K, S, A), got {log_pi.shape}")
    S, A = log_pi.shape[-2:]
    if _is_concrete(states, actions, mask):
        _check_steps(states, actions, S, A, mask)
    lp = log_pi[None] if single else log_pi
    ll = jnp.moveaxis(lp[:, jnp.asarray(states), jnp.asarray(actions)], 0, -1)  # (N, T, K)
    if mask is not None:
        ll = jnp.where(jnp.asarray(mask, bool)[..., None], ll, 0.0)
    return ll[..., 0] if single else ll


def count_log_likelihood(solver: SoftSolver, theta, counts, v0=None) -> jax.Array:
    """sum_{s,a} C[s, a] log pi_theta(a | s), differentiable in theta (implicitly).

    Args:
        solver: a SoftSolver or a TabularMDP.
        theta: (D,) or (K, D).
        counts: (S, A) or (K, S, A) count tables (one per skill).
        v0: optional warm start (K, S) (or (S,)).
    Returns:
        () for theta (D,) with counts (S, A); (K,) otherwise (broadcast over skills).
    """
    solver = as_solver(solver)
    if _is_concrete(counts):
        _check_counts(counts, solver.num_states, solver.num_actions)
    log_pi, _ = log_policy(solver, theta, v0)
    return jnp.sum(jnp.asarray(counts, jnp.float64) * log_pi, axis=(-2, -1))


def noisy_log_policy(log_pi, epsilon: float = 0.0):
    """log((1 - epsilon) pi(a | s) + epsilon / A): a Boltzmann policy that acts uniformly at
    random with probability epsilon (a noisy expert). epsilon = 0 returns ``log_pi``."""
    if not epsilon:
        return log_pi
    A = log_pi.shape[-1]
    return jnp.logaddexp(jnp.log1p(-epsilon) + log_pi, jnp.log(epsilon / A))


def count_log_likelihood_and_grad(solver: SoftSolver, theta, counts, v0=None, epsilon: float = 0.0):
    """Value and gradient of :func:`count_log_likelihood` per skill, and the new soft values.

    Args:
        solver: a SoftSolver or a TabularMDP.
        theta: (K, D) (or (D,)) reward weights; counts: (K, S, A) (or (S, A)).
        v0: optional warm start (K, S) (or (S,)).
        epsilon: the noisy expert's random-action probability (:func:`noisy_log_policy`).
    Returns:
        (log_lik (K,), grad (K, D), V (K, S)), without the K axis for theta (D,).
    """
    solver = as_solver(solver)
    if _is_concrete(theta, counts):
        _check_theta(theta, solver.num_features)
        _check_counts(counts, solver.num_states, solver.num_actions)
    theta = jnp.asarray(theta, jnp.float64)
    counts = jnp.asarray(counts, jnp.float64)
    if theta.ndim == 1:
        if counts.ndim != 2:
            raise ValueError(f"theta (D,) needs counts (S, A), got {counts.shape}")
        ll, g, V = count_log_likelihood_and_grad(solver, theta[None], counts[None],
                                                 None if v0 is None else jnp.asarray(v0)[None], epsilon)
        return ll[0], g[0], V[0]
    K = theta.shape[0]
    counts = jnp.broadcast_to(counts, (K,) + counts.shape[-2:])
    if v0 is None:
        v0 = jnp.zeros((K, solver.num_states))
    return _LL_AND_GRAD(solver, theta, counts, v0, float(epsilon))


def _ll_grad_residual(solver, theta, counts, v0, epsilon=0.0, temperature=1.0):
    """(K,) log-likelihoods, (K, D) gradients and (K, S) values of K skills, and whether each
    solve converged with a finite log-likelihood (K,) (:func:`count_log_likelihood_and_values`,
    differentiated), by one batched solve and one batched adjoint solve (skill k's
    log-likelihood depends on theta_k only, so the gradient of their sum holds every skill's
    gradient)."""

    def total(t):
        ll, V, ok = count_log_likelihood_and_values(solver, t, counts, v0, temperature, epsilon)
        return jnp.sum(ll), (ll, V, ok)

    (_, (ll, V, ok)), g = jax.value_and_grad(total, has_aux=True)(theta)
    return ll, g, V, ok


class Posterior(NamedTuple):
    """:func:`log_posterior` of K skills: log_density (K,) up to a constant, its gradient
    (K, D), the soft values V (K, S) (the next solve's warm start), ok (K,) (the solve
    converged and both are finite) and the log-likelihood alone, log_lik (K,)."""

    log_density: jax.Array
    grad: jax.Array
    V: jax.Array
    ok: jax.Array
    log_lik: jax.Array


def log_posterior(solver, theta, counts, v0, prior_scale=PRIOR_SCALE, temperature=1.0, epsilon=0.0,
                  prior_df=None) -> Posterior:
    """The conditional log-posterior of K skills' reward weights given their steps' count
    tables, up to a constant: sum_{s,a} C_k[s, a] log pi_k(a | s) + log N(theta_k; 0, sigma_k^2 I),
    with pi_k the policy of the rewards tau * phi . theta_k (:func:`log_policy`). The one
    density of the reward moves, the IRL fits and the MAP update.

    Args:
        solver: a SoftSolver; theta: (K, D); counts: (K, S, A); v0: (K, S) warm start.
        prior_scale: sigma, scalar or (K,); temperature: tau; epsilon: the noisy expert's rate.
        prior_df: None (a Gaussian prior) or a Student t's degrees of freedom (:func:`log_prior`).
    Returns:
        A :class:`Posterior`.
    """
    scale = jnp.broadcast_to(jnp.asarray(prior_scale, jnp.float64), theta.shape[:1])[:, None]
    ll, g, V, converged = _ll_grad_residual(solver, theta, counts, v0, epsilon, temperature)
    lp = ll + log_prior(theta, scale, prior_df)
    grad = g + prior_grad(theta, scale, prior_df)
    ok = converged & jnp.isfinite(lp) & jnp.all(jnp.isfinite(grad), axis=-1)
    return Posterior(lp, grad, V, ok, ll)


def count_log_likelihood_and_values(solver, theta, counts, v0, temperature=1.0, epsilon=0.0):
    """The log-likelihood part of :func:`log_posterior` without its gradient (no adjoint solve):
    (log_lik (K,), soft values V (K, S), ok (K,): the solve converged and log_lik is finite),
    for moves that need the density's value only (e.g. the reward scale's magnitude move)."""
    log_pi, V, residual = _solve_policy(solver, theta, v0, temperature, epsilon)
    ll = jnp.sum(counts * log_pi, axis=(-2, -1))
    return ll, V, (residual <= solver.tol) & jnp.isfinite(ll)


def _ll_and_grad(solver, theta, counts, v0, epsilon=0.0):
    """(K,) log-likelihoods, (K, D) gradients and (K, S) values (:func:`_ll_grad_residual`)."""
    return _ll_grad_residual(solver, theta, counts, v0, epsilon)[:3]


_LL_AND_GRAD = jit(_ll_and_grad, static_argnums=4)


def fisher_information(solver: SoftSolver, theta, counts, v0=None, temperature: float = 1.0,
                       solved: bool = False) -> jax.Array:
    """Fisher information of each skill's weights given its steps' count table,
    sum_s n_s Cov_{a ~ pi(.|s)}[d log pi(a | s) / d theta].

    One batched solve and D batched forward-mode (implicit tangent) solves, all skills at once;
    with ``solved`` (v0 holds theta's soft values already, e.g. :func:`fit_reward`'s V) the
    tangent solves only.

    Args:
        solver: a SoftSolver or a TabularMDP.
        theta: (K, D) (or (D,)); counts: (K, S, A) (or (S, A)); v0: optional (K, S) warm start.
        temperature: tau, as in :func:`log_policy` (the information of theta, not of tau theta).
        solved: v0 are the soft values at theta (to the solver's tolerance): no solve.
    Returns:
        (K, D, D) (or (D, D)).
    """
    solver = as_solver(solver)
    theta = jnp.asarray(theta, jnp.float64)
    counts = jnp.asarray(counts, jnp.float64)
    if theta.ndim == 1:
        return fisher_information(solver, theta[None], counts[None], None if v0 is None else jnp.asarray(v0)[None],
                                  temperature, solved)[0]
    K, D = theta.shape
    if solved and v0 is None:
        raise ValueError("fisher_information: solved=True needs the soft values v0 at theta")

    def log_pi(t):
        return _solve_policy(solver, t, v0, temperature, solved=solved)[0]

    # the D tangent solves batched (vmap), not unrolled: a program of one solve's size for any D;
    # the policy is the jvp's primal, which does not depend on the direction (one solve, not two)
    basis = jnp.broadcast_to(jnp.eye(D, dtype=theta.dtype)[:, None, :], (D, K, D))
    log_p, J = jax.vmap(lambda e: jax.jvp(log_pi, (theta,), (e,)), out_axes=(None, -1))(basis)  # J (K, S, A, D)
    pi = jnp.exp(log_p)
    n = jnp.sum(counts, axis=-1)
    mean = jnp.einsum("ksa,ksad->ksd", pi, J)
    return jnp.einsum("ks,ksa,ksad,ksae->kde", n, pi, J, J) - jnp.einsum("ks,ksd,kse->kde", n, mean, mean)


float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
