"""The reward (Boltzmann / maximum-entropy IRL) emission's numerics.

A skill is a reward r_k(s, a) = phi(s, a) . theta_k; its demonstrator acts with the Boltzmann
policy pi_k(a | s) = exp(Q_k(s, a) - V_k(s)) of the soft Bellman equation of the rewards
tau * r_k (tau: the demonstrator's inverse temperature, 1 by default), mixed with uniform actions
at rate epsilon for a noisy expert. ``log_policy`` is the one place tau and epsilon enter, and
``log_posterior`` the one density of a skill's weights (the MALA move of
:mod:`npbrs.models.reward_mala`, the IRL fits and the MAP update all use it). Because

    sum_t w_t log pi(a_t | s_t) = sum_{s, a} C[s, a] log pi(a | s),

with C the weighted count table of the steps, every quantity a sampler needs of a skill's
steps (log-likelihood, its gradient, an IRL fit, a MALA move) depends on the data only through
an (S, A) table; ``count_table`` builds it with one scatter-add.

Gradients are implicit (see :mod:`npbrs.domains.solvers`): the soft fixed point is never
unrolled, and the gradient of a log-likelihood costs one adjoint linear solve, batched over
skills.

Prior scale. Rewards are in nats per step (the Boltzmann temperature is folded into theta), so
the prior's sigma says how deterministic a skill may be. The likelihood of an optimal (hence
near-deterministic) demonstrator keeps growing along the direction of its reward: the data fix
the direction and the prior fixes the scale. With 16 x 200 expert steps the MAP weights come out
at 3-12 sigma on the highway and quadcopter domains (quadcopter skill A: sigma = 1 gives
theta = (12.9, 0.15, -0.23), sigma = 10 gives (97, 0.5, -0.3), sigma = 100 gives (481, 1.0,
-0.4)), with the same optimal policies and held-out log-likelihoods of -0.35, -0.26 and -0.24
nats per step (uniform: -1.39). The default sigma = 10 (``PRIOR_SCALE``) puts a decisive
step (a one-sigma weight on a feature that differs by one between two actions) at e^10, about
20000 : 1, which is as deterministic as demonstrations of an optimal agent look, while keeping
Q-gaps at tens rather than hundreds of nats: a much wider prior gains almost no likelihood but
makes every misassigned step cost hundreds of nats (extreme acceptance ratios for birth, death
and split-merge moves) and MALA's steps (which scale with the smallest posterior standard
deviation) relatively smaller.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..domains.solvers import SoftSolver, make_soft_solver
from npbrs.domains.util.compiling import jit
from npbrs.domains.util.precision import float64_all

__all__ = ["PRIOR_SCALE", "count_table", "log_policy", "step_log_likelihoods", "count_log_likelihood",
           "count_log_likelihood_and_values",
           "count_log_likelihood_and_grad", "fisher_information", "log_prior", "prior_grad", "prior_curvature", "check_prior_df",
           "log_posterior", "Posterior", "irl_fit",
           "fit_reward", "IRLFit", "as_solver"]

PRIOR_SCALE = 10.0


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
               solved: bool = False):
    """Boltzmann log-policies of reward weights.

    Args:
        solver: a SoftSolver (:func:`npbrs.domains.make_soft_solver`), or a TabularMDP.
        theta: (D,) or (K, D) reward weights.
        v0: optional warm start (K, S) (or (S,)), e.g. the V of a previous call.
        temperature: inverse temperature tau: the policy of the rewards tau * phi . theta.
        epsilon: the noisy expert's random-action probability (:func:`noisy_log_policy`).
        solved: v0 holds these weights' soft values already (e.g. :func:`fit_reward`'s V, to
            the solver's tolerance): the policies by one backup from them, no solve.
    Returns:
        (log_pi, V): log pi(a | s), (K, S, A) (or (S, A)), and the soft values (K, S) (or (S,)).
    """
    solver = as_solver(solver)
    if _is_concrete(theta):
        _check_theta(theta, solver.num_features)
    if solved and v0 is None:
        raise ValueError("log_policy: solved=True needs the soft values v0 of theta")
    log_pi, V, _ = _solve_policy(solver, theta, v0, temperature, epsilon, solved)
    return log_pi, V


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


def log_prior(theta, prior_scale=PRIOR_SCALE, prior_df=None) -> jax.Array:
    """log Normal(theta; 0, prior_scale^2 I) summed over features, () or (K,); with ``prior_df``
    nu (a Python float), each weight's prior is instead a Student t of nu degrees of freedom and
    scale ``prior_scale`` (the Gaussian's scale mixture over sigma^2 ~ InvGamma(nu/2, nu s^2/2)):
    a heavy-tailed, sparsity-favouring prior, for one weight per state."""
    import numpyro.distributions as dist

    theta = jnp.asarray(theta, jnp.float64)
    if prior_df is None:
        return jnp.sum(dist.Normal(0.0, prior_scale).log_prob(theta), axis=-1)
    return jnp.sum(dist.StudentT(float(prior_df), 0.0, prior_scale).log_prob(theta), axis=-1)


def check_prior_df(prior_df):
    """``prior_df`` as :func:`log_prior` takes it: None (the Gaussian) or a positive float; a
    ValueError naming it otherwise."""
    if prior_df is None:
        return None
    if isinstance(prior_df, (bool, str)) or not (np.ndim(prior_df) == 0 and np.isfinite(prior_df) and prior_df > 0):
        raise ValueError(f"prior_df must be None (a Gaussian prior) or a positive number, got {prior_df!r}")
    return float(prior_df)


def prior_grad(theta, prior_scale=PRIOR_SCALE, prior_df=None) -> jax.Array:
    """The gradient of :func:`log_prior` in theta (the shape of theta; ``prior_scale`` broadcast
    against it)."""
    if prior_df is None:
        return -theta / prior_scale ** 2
    nu = float(prior_df)
    return -(nu + 1.0) * theta / (nu * prior_scale ** 2 + theta ** 2)


def prior_curvature(theta, prior_scale=PRIOR_SCALE, prior_df=None) -> jax.Array:
    """Minus the second derivative of :func:`log_prior` per weight (the shape of theta), the
    prior's part of a Laplace precision and of the MALA preconditioner: 1 / sigma^2 for the
    Gaussian; for the Student t, (nu + 1)(nu s^2 - theta^2) / (nu s^2 + theta^2)^2, negative in
    its tails, floored at a hundredth of its value at 0 (a stand-in that keeps the precision
    positive; the moves themselves stay exact)."""
    theta = jnp.asarray(theta, jnp.float64)
    if prior_df is None:
        return jnp.broadcast_to(1.0 / jnp.asarray(prior_scale, jnp.float64) ** 2, theta.shape)
    nu, s2 = float(prior_df), jnp.asarray(prior_scale, jnp.float64) ** 2
    peak = (nu + 1.0) / (nu * s2)
    return jnp.maximum((nu + 1.0) * (nu * s2 - theta ** 2) / (nu * s2 + theta ** 2) ** 2, 0.01 * peak)


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


# ----------------------------------------------------------------------------- IRL fit
class IRLFit(NamedTuple):
    """Result of :func:`irl_fit`.

    theta: (D,) or (K, D) maximum a posteriori reward weights.
    log_lik: () or (K,) count log-likelihood at theta (without the prior).
    """

    theta: jax.Array
    log_lik: jax.Array


def _two_loop(g, S_hist, Y_hist, rho, count, newest, history):
    """L-BFGS directions -H g of K problems from circular histories (K, history, D), masked to
    their first ``count`` (K,) entries, newest at ``newest`` (K,)."""
    ks = jnp.arange(g.shape[0])
    q = g
    alphas = jnp.zeros(rho.shape, g.dtype)

    def first(i, c):
        q, alphas = c
        j = (newest - i) % history
        a = jnp.where(i < count, rho[ks, j] * jnp.sum(S_hist[ks, j] * q, -1), 0.0)
        return q - a[:, None] * Y_hist[ks, j], alphas.at[ks, j].set(a)

    q, alphas = jax.lax.fori_loop(0, history, first, (q, alphas))
    y_new = Y_hist[ks, newest]
    yy = jnp.sum(y_new * y_new, -1)
    scale = jnp.where(count > 0, 1.0 / (rho[ks, newest] * jnp.where(yy > 0, yy, 1.0)), 1.0)
    z = scale[:, None] * q

    def second(i, z):
        age = history - 1 - i
        j = (newest - age) % history
        b = rho[ks, j] * jnp.sum(Y_hist[ks, j] * z, -1)
        return z + jnp.where(age < count, alphas[ks, j] - b, 0.0)[:, None] * S_hist[ks, j]

    return -jax.lax.fori_loop(0, history, second, z)


def fit_reward(solver: SoftSolver, counts, theta0, v0, prior_scale=PRIOR_SCALE, num_steps: int = 30,
               history: int = 10, max_backtracks: int = 10, epsilon: float = 0.0, temperature: float = 1.0,
               prior_df=None):
    """The jit-able core of :func:`irl_fit` for K skills: static shapes, no input checks.

    L-BFGS with a backtracking (Armijo) line search on the negative :func:`log_posterior` of
    every skill, all skills in lock-step: each iteration evaluates the objective once per skill
    (its start, a trial step or a backtrack) by one batched solve and one batched adjoint solve,
    every solve warm-started from the skill's last accepted values. So the program holds a
    single copy of the solver and no loop counter is per-skill. A skill stops after
    ``num_steps`` steps, or earlier once the predicted decrease is below the objective's
    accuracy (ten times the solver's relative tolerance), or after two failed line searches in
    a row (the first one resets its history and tries the scaled gradient).

    Args:
        solver: a SoftSolver.
        counts: (K, S, A); theta0: (K, D); v0: (K, S); prior_scale: scalar or (K,).
        num_steps: L-BFGS steps; history: L-BFGS memory; max_backtracks: halvings per line search.
        epsilon: the noisy expert's random-action probability (:func:`noisy_log_policy`).
        temperature: the demonstrator's inverse temperature tau (:func:`log_policy`).
        prior_df: None, or the Student t prior's degrees of freedom (:func:`log_prior`).
    Returns:
        (theta (K, D), log_lik (K,), V (K, S), norm of the log-posterior's gradient (K,),
        number of value-and-gradient evaluations (K,)).
    """
    K, D = theta0.shape
    scale = jnp.broadcast_to(jnp.asarray(prior_scale, jnp.float64), (K,))
    noise = max(10.0 * solver.tol, 1e-13)  # relative accuracy of the objective
    # (a Student t's: one over the square root of its curvature at 0)
    step_scale = scale if prior_df is None else 1.0 / jnp.sqrt(prior_curvature(jnp.zeros(K), scale, prior_df))

    def objective(theta, v):
        post = log_posterior(solver, theta, counts, v, scale, temperature, epsilon, prior_df)
        return -post.log_density, -post.grad, post.log_lik, post.V

    def direction(g, Sh, Yh, rho, count, newest):
        d = _two_loop(g, Sh, Yh, rho, count, newest, history)
        gnorm = jnp.linalg.norm(g, axis=-1, keepdims=True)
        # before any curvature pair, or if the quasi-Newton direction is not a descent
        # direction: the Newton step of the prior alone (sigma^2 g; the likelihood only adds
        # curvature), at most one prior scale long (a Student t's: its curvature's at 0)
        fallback = -g * jnp.minimum(step_scale[:, None] ** 2, step_scale[:, None] / jnp.where(gnorm > 0, gnorm, 1.0))
        ok = (count > 0) & (jnp.sum(g * d, -1) < 0)
        return jnp.where(ok[:, None], d, fallback)

    def shrink(alpha, f_new, f, slope):
        """The next trial step of a backtracking line search after ``alpha`` failed: the
        minimiser of the quadratic through f, the slope and f_new, safeguarded to [0.1, 0.5]
        alpha (Nocedal and Wright, section 3.5). A first step of the prior's scale from near
        an optimum (a warm-started refit) overshoots by orders of magnitude: halving alone
        spent all of its backtracks there and failed."""
        curvature = f_new - f - slope * alpha
        quad = -slope * alpha ** 2 / (2.0 * jnp.where(curvature > 0, curvature, 1.0))
        quad = jnp.where(jnp.isfinite(f_new) & (curvature > 0), quad, 0.1 * alpha)
        return jnp.clip(quad, 0.1 * alpha, 0.5 * alpha)

    def cond(c):
        return jnp.any(~c["done"])

    def body(c):
        live = ~c["done"]
        first = c["evals"] == 0
        trial = jnp.where(live[:, None], c["theta"] + c["alpha"][:, None] * c["d"], c["theta"])
        f_new, g_new, ll_new, V_new = objective(trial, c["V"])
        slope = jnp.sum(c["g"] * c["d"], -1)
        armijo = jnp.isfinite(f_new) & (f_new <= c["f"] + 1e-4 * c["alpha"] * slope)
        exhausted = c["backtracks"] >= max_backtracks
        accept = live & (first | armijo)
        done_step = live & (first | armijo | exhausted)  # move on to a new direction
        failed = live & exhausted & ~accept
        # curvature pair of an accepted step
        s_vec = c["alpha"][:, None] * c["d"]
        y_vec = g_new - c["g"]
        sy = jnp.sum(s_vec * y_vec, -1)
        store = accept & ~first & (sy > 1e-10 * jnp.linalg.norm(s_vec, axis=-1) * jnp.linalg.norm(y_vec, axis=-1))
        slot = jnp.where(store, (c["newest"] + 1) % history, c["newest"])
        ks = jnp.arange(K)
        Sh = jnp.where(store[:, None, None], c["S"].at[ks, slot].set(s_vec), c["S"])
        Yh = jnp.where(store[:, None, None], c["Y"].at[ks, slot].set(y_vec), c["Y"])
        rho = jnp.where(store[:, None], c["rho"].at[ks, slot].set(1.0 / jnp.where(sy != 0, sy, 1.0)), c["rho"])
        count = jnp.where(store, jnp.minimum(c["count"] + 1, history), c["count"])
        count = jnp.where(failed, 0, count)  # a failed line search forgets the history
        pick = lambda new, old: jnp.where(accept.reshape(accept.shape + (1,) * (new.ndim - 1)), new, old)
        theta, f, g, ll, V = (pick(trial, c["theta"]), pick(f_new, c["f"]), pick(g_new, c["g"]),
                              pick(ll_new, c["ll"]), pick(V_new, c["V"]))
        d = jnp.where(done_step[:, None], direction(g, Sh, Yh, rho, count, slot), c["d"])
        steps = c["steps"] + (done_step & ~first)
        failures = jnp.where(failed, c["failures"] + 1, jnp.where(accept, 0, c["failures"]))
        # nothing left to gain that the solver's tolerance would not hide
        converged = done_step & (jnp.abs(jnp.sum(g * d, -1)) <= noise * (1.0 + jnp.abs(f)))
        done = c["done"] | (steps >= num_steps) | (failures >= 2) | converged
        return dict(theta=theta, f=f, g=g, ll=ll, V=V, S=Sh, Y=Yh, rho=rho, count=count, newest=slot, d=d,
                    alpha=jnp.where(done_step, 1.0, shrink(c["alpha"], f_new, c["f"], slope)),
                    backtracks=jnp.where(done_step, 0, c["backtracks"] + live), steps=steps,
                    evals=c["evals"] + live, failures=failures, done=done)

    zeros_i = jnp.zeros(K, jnp.int32)
    init = dict(theta=theta0, f=jnp.full(K, jnp.inf), g=jnp.zeros((K, D)), ll=jnp.zeros(K), V=v0,
                S=jnp.zeros((K, history, D)), Y=jnp.zeros((K, history, D)), rho=jnp.zeros((K, history)),
                count=zeros_i, newest=jnp.full(K, history - 1, jnp.int32), d=jnp.zeros((K, D)), alpha=jnp.zeros(K),
                backtracks=zeros_i, steps=zeros_i, evals=zeros_i, failures=zeros_i,
                done=jnp.full(K, num_steps <= 0))
    if num_steps <= 0:
        f, g, ll, V = objective(theta0, v0)
        return theta0, ll, V, jnp.linalg.norm(g, axis=-1), jnp.ones(K, jnp.int32)
    c = jax.lax.while_loop(cond, body, init)
    return c["theta"], c["ll"], c["V"], jnp.linalg.norm(c["g"], axis=-1), c["evals"]


def irl_fit(solver, counts, theta0=None, *, prior_scale=PRIOR_SCALE, num_steps: int = 30, v0=None,
            history: int = 10, temperature: float = 1.0, epsilon: float = 0.0, prior_df=None) -> IRLFit:
    """Maximum a posteriori maximum-entropy IRL: argmax_theta sum C log pi_theta + log N(theta; 0, sigma^2 I)
    (or a Student t prior per weight, ``prior_df``).

    A fixed number of L-BFGS steps with a backtracking line search, every soft solve
    warm-started from the previous one; pure and jit-able with static shapes (``fit_reward``
    is the same without input checks), batched over skills.

    Args:
        solver: a SoftSolver or a TabularMDP.
        counts: (S, A) or (K, S, A) weighted counts of the skill's steps (:func:`count_table`).
        theta0: optional starting weights (D,) or (K, D) (zeros by default): warm-start from a
            previous fit.
        prior_scale: sigma of the Gaussian prior (see the module docstring for the default).
        num_steps: L-BFGS steps.
        v0: optional warm start of the soft values (K, S) (or (S,)).
        history: L-BFGS memory.
        temperature: the demonstrator's inverse temperature tau (policies of tau * phi . theta).
        epsilon: the noisy expert's random-action probability (:func:`noisy_log_policy`).
        prior_df: None (the Gaussian prior), or the degrees of freedom of a Student t prior of
            scale ``prior_scale`` on each weight (:func:`log_prior`).
    Returns:
        IRLFit(theta (D,) or (K, D), log_lik () or (K,)).
    """
    solver = as_solver(solver)
    S, D = solver.num_states, solver.num_features
    if _is_concrete(counts):
        _check_counts(counts, S, solver.num_actions)
    _check_prior_scale(prior_scale)
    if int(num_steps) < 0 or int(history) < 1:
        raise ValueError(f"num_steps must be >= 0 and history >= 1, got {num_steps}, {history}")
    counts = jnp.asarray(counts, jnp.float64)
    single = counts.ndim == 2
    C = counts[None] if single else counts
    K = C.shape[0]
    if theta0 is None:
        theta0 = jnp.zeros((K, D))
    else:
        if _is_concrete(theta0):
            _check_theta(theta0, D)
        theta0 = jnp.broadcast_to(jnp.asarray(theta0, jnp.float64), (K, D))
    if v0 is None:
        v0 = jnp.zeros((K, S))
    else:
        v0 = jnp.broadcast_to(jnp.asarray(v0, jnp.float64), (K, S))
    for name, value in [("temperature", temperature), ("epsilon", epsilon)]:
        if not np.isfinite(value) or value < 0 or (name == "temperature" and value == 0) or \
                (name == "epsilon" and value >= 1):
            raise ValueError(f"{name} must be {'positive' if name == 'temperature' else 'in [0, 1)'}, got {value!r}")
    theta, ll, *_ = _fit_jit(solver, C, theta0, v0, prior_scale, int(num_steps), int(history), float(epsilon),
                             float(temperature), check_prior_df(prior_df))
    return IRLFit(theta[0], ll[0]) if single else IRLFit(theta, ll)


def _fit_jit(solver, counts, theta0, v0, prior_scale, num_steps, history, epsilon=0.0, temperature=1.0, prior_df=None):
    return _FIT_JIT(solver, counts, theta0, v0, jnp.asarray(prior_scale, jnp.float64), num_steps, history, 10,
                    epsilon, temperature, prior_df)


_FIT_JIT = jit(fit_reward, static_argnums=(5, 6, 7, 8, 10))  # temperature is traced


float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
