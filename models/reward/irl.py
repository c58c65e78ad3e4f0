"""Maximum a posteriori maximum-entropy IRL: L-BFGS on :func:`npbrs.models.reward.likelihood.log_posterior`,
batched over skills (the data-driven proposals' and the evidences' fits, and the ``"map"`` update)."""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from npbrs.domains.solvers import SoftSolver
from npbrs.domains.util.compiling import jit
from npbrs.domains.util.precision import float64_all
from .likelihood import _check_counts, _check_prior_scale, _check_theta, _is_concrete, as_solver, log_posterior
from .prior import PRIOR_SCALE, check_prior_df, prior_curvature

__all__ = ["irl_fit", "fit_reward", "IRLFit"]


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
