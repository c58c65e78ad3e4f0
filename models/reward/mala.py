"""The reward move: Metropolis-adjusted Langevin (MALA) steps on K skills' reward weights.

The target is each skill's conditional posterior given its steps' count table,

    p(theta_k | C_k) ∝ exp(sum_{s,a} C_k[s, a] log pi_k(a | s)) N(theta_k; 0, sigma_k^2 I),

the one density :func:`npbrs.models.reward.likelihood.log_posterior` (temperature and epsilon enter there).
One step proposes, for all skills at once,

    theta' = theta + (eps^2 / 2) M^-1 grad log p(theta) + eps M^-1/2 xi,

and accepts with the Metropolis-Hastings ratio including both proposal densities, so the
conditional is left invariant exactly (up to the solver's tolerance). All skills' proposals are
solved together (one batched solve and one batched adjoint solve per step), warm-started from
the current values. A proposal whose solve did not reach the solver's tolerance (a far-out
theta, or the iteration cap) is rejected, so no proposal is accepted on a wrong density
(``info.solver_failed`` says when that happened).

Blackjax-style: ``init`` makes the state, ``build_kernel`` returns
``kernel(rng_key, state, counts, step_size, inverse_mass=None) -> (state, info)``; both are pure
and jit-able with static shapes. The reward emission (:mod:`npbrs.models.reward.emission`) runs
this kernel and adds only the warmup tuning (the step size per skill and the preconditioner
M^-1 from the Fisher information).
"""

from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ..mcmc import metropolis_accept, select
from .likelihood import Posterior, as_solver, log_posterior
from .prior import PRIOR_SCALE, check_prior_df
from npbrs.domains.util.compiling import jit
from npbrs.domains.util.precision import float64_all

__all__ = ["RewardMALAState", "RewardMALAInfo", "init", "build_kernel", "unevaluated"]


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

    acceptance_rate: min(1, Metropolis-Hastings ratio) (0 for a failed solve). is_accepted:
    whether the proposal was taken. proposal_log_density: log density at the proposal.
    solver_failed: the proposal's solve missed the tolerance (the proposal was rejected).
    """

    acceptance_rate: jax.Array
    is_accepted: jax.Array
    proposal_log_density: jax.Array
    solver_failed: jax.Array


_POSTERIOR = jit(log_posterior, static_argnums=(6, 7))  # epsilon (0 skips the mixture) and prior_df static

# Skills solved together when only some are active: a batched solve costs about its batch size
# times one skill's once a skill's policy has this many (state, action) entries (measured on the
# highway, 1080 x 3: 3.6 ms for one skill, 10 ms for 3, 36 ms for 8), while small MDPs cost the
# same for 1 skill as for 8 (the labyrinth, 127 x 4: about 1.2 ms either way).
BATCH_ENTRIES = 4096


def chunk_size(solver, K: int) -> int:
    """How many active skills one solve takes (a power of two, static): K (all at once, the
    inactive ones too) for MDPs of at most ``BATCH_ENTRIES / K`` (state, action) entries, down
    to 1 for large ones."""
    entries = max(1, solver.num_states * solver.num_actions)
    c = max(1, BATCH_ENTRIES // entries)
    return K if c >= K else 1 << (c.bit_length() - 1)


def _posterior(solver, theta, counts, v0, prior_scale, temperature, epsilon, active, fallback, prior_df=None):
    """:func:`log_posterior` of the ``active`` skills (K,) bool, solved ``chunk_size`` at a time
    in a loop that runs as many times as the active skills need (under ``vmap`` over chains: as
    the chain with the most needs); an inactive skill is not solved and gets ``fallback``'s
    (log_density, grad, V) with ok False. ``active=None``, or an MDP small enough to batch all K
    skills, solves all K at once."""
    K = theta.shape[0]
    c = chunk_size(solver, K)
    if active is None or c >= K:
        return _POSTERIOR(solver, theta, counts, v0, prior_scale, temperature, epsilon, prior_df)
    scale = jnp.broadcast_to(jnp.asarray(prior_scale, jnp.float64), (K,))
    order = jnp.argsort(~active, stable=True)  # the active skills first, in slot order
    order = jnp.concatenate([order, jnp.full((-K) % c, K, order.dtype)])  # pad to whole chunks
    num_chunks = (jnp.sum(active) + c - 1) // c
    lp0, grad0, V0 = fallback
    init = Posterior(lp0, grad0, V0, jnp.zeros(K, bool), jnp.zeros(K))

    def body(j, out):
        idx = jax.lax.dynamic_slice(order, (j * c,), (c,))
        take = lambda x: jnp.take(x, idx, axis=0, mode="clip")  # noqa: E731  (index K: slot K - 1 again)
        new = _POSTERIOR(solver, take(theta), take(counts), take(v0), take(scale), temperature, epsilon, prior_df)
        # a chunk's tail may hold inactive skills or index K: solved, and not written back
        keep = take(active) & (idx < K)
        return jax.tree.map(lambda o, n: o.at[jnp.where(keep, idx, K)].set(n, mode="drop"), out, new)

    return jax.lax.fori_loop(0, num_chunks, body, init)


def _check_options(prior_scale, temperature, epsilon, prior_df=None):
    if not isinstance(prior_scale, jax.core.Tracer) and not np.all(np.isfinite(prior_scale) & (np.asarray(prior_scale) > 0)):
        raise ValueError(f"prior_scale must be positive and finite, got {prior_scale!r}")
    if not (np.isfinite(temperature) and temperature > 0):
        raise ValueError(f"temperature must be a positive number, got {temperature!r}")
    if not (np.isfinite(epsilon) and 0 <= epsilon < 1):
        raise ValueError(f"epsilon must lie in [0, 1), got {epsilon!r}")
    return float(temperature), float(epsilon), check_prior_df(prior_df)


def _check_counts(solver, counts, K):
    if counts.shape != (K, solver.num_states, solver.num_actions):
        raise ValueError(f"counts must have shape ({K}, {solver.num_states}, {solver.num_actions}), got {counts.shape}")


def init(solver, theta, counts, prior_scale=PRIOR_SCALE, v0=None, *, temperature: float = 1.0,
         epsilon: float = 0.0, active=None, prior_df=None) -> RewardMALAState:
    """The chain's state at theta (K, D) for counts (K, S, A).

    Args:
        solver: a SoftSolver (:func:`npbrs.domains.make_soft_solver`) or a TabularMDP.
        theta: (K, D) starting weights; counts: (K, S, A) count tables.
        prior_scale: sigma of the Gaussian prior, scalar or (K,).
        v0: optional (K, S) warm start of the first solve.
        prior_df: None, or the degrees of freedom of a Student t prior of scale ``prior_scale``
            on each weight (:func:`npbrs.models.reward.prior.log_prior`).
        temperature, epsilon: the demonstrator's inverse temperature and random-action rate.
        active: optional (K,) bool, the skills to solve (see :func:`build_kernel`); the others
            get log_density 0 and gradient 0, and keep v0.
    """
    solver = as_solver(solver)
    temperature, epsilon, prior_df = _check_options(prior_scale, temperature, epsilon, prior_df)
    theta = jnp.asarray(theta, jnp.float64)
    counts = jnp.asarray(counts, jnp.float64)
    if theta.ndim != 2 or theta.shape[1] != solver.num_features:
        raise ValueError(f"theta must have shape (K, {solver.num_features}), got {theta.shape}")
    K = theta.shape[0]
    _check_counts(solver, counts, K)
    v0 = jnp.zeros((K, solver.num_states)) if v0 is None else jnp.asarray(v0, jnp.float64)
    kernel = build_kernel(solver, prior_scale, temperature=temperature, epsilon=epsilon, prior_df=prior_df)
    return kernel(jax.random.PRNGKey(0), unevaluated(theta, v0), counts, 1.0, active=active, evaluate=True)[0]


def unevaluated(theta, v0) -> RewardMALAState:
    """A state at theta (K, D) whose density is not computed yet (zeros), values v0 (K, S): the
    start of a chain whose first kernel step has ``evaluate=True`` (:func:`init` in the same
    compiled code as the steps)."""
    return RewardMALAState(theta, jnp.zeros(theta.shape[0]), jnp.zeros_like(theta), v0)


def build_kernel(solver, prior_scale=PRIOR_SCALE, *, temperature: float = 1.0, epsilon: float = 0.0,
                 prior_df=None) -> Callable:
    """A MALA kernel for K skills' reward weights.

    Args:
        solver: a SoftSolver or a TabularMDP (its tolerance sets the density's accuracy).
        prior_scale: sigma of the Gaussian prior, scalar or (K,) (an array may be traced).
        temperature, epsilon: the demonstrator's inverse temperature and random-action rate.
        prior_df: None, or a Student t prior's degrees of freedom (see :func:`init`).
    Returns:
        ``kernel(rng_key, state, counts, step_size, inverse_mass=None, active=None,
        evaluate=False) -> (state, info)`` with counts (K, S, A), step_size scalar or (K,),
        inverse_mass (the diagonal preconditioner M^-1) None, (D,) or (K, D), and active None
        (every skill moves) or (K,) bool: only the active skills' proposals are solved
        (:func:`chunk_size` at a time) and can be accepted; the others keep their state
        (acceptance rate 0, not a failed solve). The random numbers are drawn for all K skills
        either way, so an active skill's step is the same as in a step of all K (up to the
        solver's tolerance). ``evaluate`` (a bool, traced or not): instead of a step, the
        density, gradient and values at the state's own theta, solved from its values (what
        :func:`init` does), so that a chain's start and its steps can share one compiled
        solve in a loop (inactive skills keep the state's; the info's rate is 0).
    """
    solver = as_solver(solver)
    temperature, epsilon, prior_df = _check_options(prior_scale, temperature, epsilon, prior_df)

    def kernel(rng_key, state: RewardMALAState, counts, step_size, inverse_mass=None, active=None, evaluate=False):
        K, D = state.theta.shape
        counts = jnp.asarray(counts, jnp.float64)
        _check_counts(solver, counts, K)
        eps = jnp.broadcast_to(jnp.asarray(step_size, jnp.float64), (K,))[:, None]
        minv = jnp.ones((K, D)) if inverse_mass is None else \
            jnp.broadcast_to(jnp.asarray(inverse_mass, jnp.float64), (K, D))
        k_prop, k_acc = jax.random.split(rng_key)
        theta, lp, grad, V = state
        mean_fwd = theta + 0.5 * eps ** 2 * minv * grad
        prop = mean_fwd + eps * jnp.sqrt(minv) * jax.random.normal(k_prop, theta.shape)
        prop = jnp.where(evaluate, theta, prop)
        # the (active) skills' proposals solved together, warm-started from the current values
        new = _posterior(solver, prop, counts, V, prior_scale, temperature, epsilon, active, (lp, grad, V), prior_df)
        mean_bwd = prop + 0.5 * eps ** 2 * minv * new.grad
        log_q_fwd = -0.5 * jnp.sum((prop - mean_fwd) ** 2 / minv / eps ** 2, -1)
        log_q_bwd = -0.5 * jnp.sum((theta - mean_bwd) ** 2 / minv / eps ** 2, -1)
        log_ratio = new.log_density - lp + log_q_bwd - log_q_fwd
        # (an inactive skill is never moved, whether its proposal was solved or not)
        accept, rate = metropolis_accept(k_acc, log_ratio, possible=new.ok if active is None else new.ok & active)
        accept, rate = accept | evaluate, jnp.where(evaluate, 0.0, rate)
        state = select(accept, RewardMALAState(prop, new.log_density, new.grad, new.V), state)
        failed = (~new.ok if active is None else active & ~new.ok) & ~evaluate
        return state, RewardMALAInfo(rate, accept, new.log_density, failed)

    return kernel


float64_all(globals())  # npbrs.domains.util.precision: float64 inside, the user's setting outside
