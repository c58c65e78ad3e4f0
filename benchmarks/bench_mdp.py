"""Speed of the soft Bellman solver, its gradient and the IRL fit on the highway and quadcopter
MDPs, each against a plain vectorised NumPy implementation over the same successor arrays, run
in the same process.

    python benchmarks/bench_mdp.py [--json PATH] [--domains highway quadcopter] [--repeats 15]
                                   [--clock wall|process]

writes the figures, with ``meta`` (the command, the machine and the device), to ``--json PATH``
(default ``benchmarks/results/bench_mdp.json``).

Figures (milliseconds; JAX timings exclude compilation and are the median of ``--repeats``
runs; ``*_ratio`` = NumPy time / JAX time):

- ``cold_solve``: one soft solve from V = 0 (skill A's reward), to relative residual 1e-8
  (``cold_solve_tol1e-10_ms``: the library's default tolerance 1e-10); ``cold_solve_greedy_agreement``
  is the fraction of states whose greedy action equals that of a 1e-13 solve.
- ``warm_solve``: one solve warm-started from the solution for theta, after theta is
  perturbed by a relative 1e-3 (a sampler's or an optimiser's small step).
- ``batch8_solve``: 8 reward tables at once (the three skills and five perturbations), cold.
- ``grad`` / ``grad_cold``: value and gradient of the count log-likelihood of 16 x 200 expert
  steps, warm-started after a 1e-3 step / from V = 0 (solver defaults: tolerance 1e-10,
  adjoint tolerance 1e-11).
- ``batch8_grad``: the same for 8 skills at once, warm-started.
- ``irl_fit``: 30 L-BFGS steps of MAP IRL from theta = 0. The NumPy reference costs its
  per-evaluation time (a warm-started NumPy solve plus a NumPy adjoint solve, measured over
  a few evaluations along the same path) times the number of evaluations the JAX fit made:
  running it in full takes minutes.

NumPy reference: soft value iteration ``Q = r + gamma * (V[succ] * probs).sum(-1)``,
``V = logsumexp(Q)`` to the same relative tolerance, and the adjoint of the gradient by the
fixed-point iteration ``lambda = g + gamma * P_pi^T lambda`` (np.bincount scatter).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from runinfo import run_info  # noqa: E402

TOL = 1e-8  # the solve figures' relative tolerance; gradients and fits use the library default


# --------------------------------------------------------------------------- NumPy reference
class NumpySoftVI:
    """Plain vectorised NumPy soft value iteration and gradient over successor arrays."""

    def __init__(self, mdp):
        self.succ = np.asarray(mdp.successors)
        self.probs = np.asarray(mdp.probs)
        self.features = np.asarray(mdp.features)
        self.gamma = float(mdp.discount)
        self.S, self.A = self.succ.shape[:2]

    def solve(self, r, v0=None, tol=TOL, max_iter=100000):
        V = np.zeros(r.shape[:-1]) if v0 is None else np.array(v0, dtype=np.float64)
        for it in range(max_iter):
            Q = r + self.gamma * (V[..., self.succ] * self.probs).sum(-1)
            m = Q.max(-1)
            V_new = m + np.log(np.exp(Q - m[..., None]).sum(-1))
            res = np.abs(V_new - V).max() / max(1.0, np.abs(V_new).max())
            V = V_new
            if res <= tol:
                break
        Q = r + self.gamma * (V[..., self.succ] * self.probs).sum(-1)
        return V, Q, it + 1

    def _transpose(self, W):
        """sum_{s, a} W[s, a] P(s' | s, a) for W (S, A): a scatter over successors."""
        return np.bincount(self.succ.ravel(), weights=(W[..., None] * self.probs).ravel(), minlength=self.S)

    def ll_and_grad(self, theta, counts, v0=None, tol=TOL, max_iter=100000):
        """Count log-likelihood, its gradient in theta, and V, for one skill."""
        r = self.features @ theta
        V, Q, _ = self.solve(r, v0, tol)
        logpi = Q - V[:, None]
        pi = np.exp(logpi)
        ll = float((counts * logpi).sum())
        g = self.gamma * self._transpose(counts) - counts.sum(-1)
        lam = g.copy()
        for _ in range(max_iter):
            lam_new = g + self.gamma * self._transpose(pi * lam[:, None])
            done = np.abs(lam_new - lam).max() <= tol * max(1.0, np.abs(lam_new).max())
            lam = lam_new
            if done:
                break
        grad_r = counts + pi * lam[:, None]
        return ll, np.einsum("sad,sa->d", self.features, grad_r), V


# --------------------------------------------------------------------------------- timing
CLOCK = time.perf_counter  # --clock process: CPU time of this process (for a shared machine)


def _timed(fn, repeats):
    """Median and minimum time (ms) of fn() over repeats, after one warm-up call."""
    import jax

    jax.block_until_ready(fn())
    times = []
    for _ in range(repeats):
        t0 = CLOCK()
        jax.block_until_ready(fn())
        times.append((CLOCK() - t0) * 1e3)
    return statistics.median(times), min(times)


def _once(fn):
    t0 = CLOCK()
    out = fn()
    return (CLOCK() - t0) * 1e3, out


def _rollout(mdp, policy, rng, N=16, T=200):
    s = rng.choice(mdp.num_states, size=N, p=mdp.initial)
    states = np.zeros((N, T), int)
    actions = np.zeros((N, T), int)
    for t in range(T):
        a = policy[s]
        states[:, t], actions[:, t] = s, a
        s = mdp.sample_next(rng, s, a)
    return states, actions


def bench_domain(name, repeats, numpy_repeats, log=print):
    import jax
    import jax.numpy as jnp

    from npbrs.domains import make_soft_solver
    from npbrs.models.reward.irl import fit_reward
    from npbrs.models.reward.likelihood import count_log_likelihood_and_grad, count_table
    from npbrs.models.reward.prior import PRIOR_SCALE

    if name == "highway":
        from npbrs.domains.highway import highway as make
    elif name == "quadcopter":
        from npbrs.domains.quadcopter import quadcopter as make
    else:
        raise ValueError(f"unknown domain {name!r}")
    dom = make()
    mdp = dom.mdp
    S, A, D = mdp.num_states, mdp.num_actions, mdp.num_features
    rng = np.random.default_rng(0)
    W = np.asarray(dom.skill_weights)
    theta = W[0]
    theta_small = theta * (1 + 1e-3 * rng.normal(size=D))
    thetas8 = np.concatenate([W, W[rng.integers(0, len(W), 8 - len(W))] * (1 + 0.05 * rng.normal(size=(8 - len(W), D)))])
    solver = make_soft_solver(mdp, tol=TOL)
    default = make_soft_solver(mdp)
    ref = NumpySoftVI(mdp)
    out = {}

    def record(key, jax_ms, np_ms, jax_min=None):
        out[f"{name}.{key}_ms"] = jax_ms
        if jax_min is not None:
            out[f"{name}.{key}_min_ms"] = jax_min
        if np_ms is not None:
            out[f"{name}.{key}_numpy_ms"] = np_ms
            out[f"{name}.{key}_ratio"] = np_ms / jax_ms
        ratio = "" if np_ms is None else f"   numpy {np_ms:9.1f} ms   ratio {np_ms / jax_ms:7.1f}x"
        log(f"  {key:14s} {jax_ms:9.2f} ms (min {jax_min:7.2f}){ratio}")

    log(f"{name}: S={S} A={A} B={mdp.num_successors} D={D} gamma={mdp.discount} operator={solver.operator}")
    r = jnp.asarray(mdp.reward(theta))
    r_small = jnp.asarray(mdp.reward(theta_small))
    r8 = jnp.asarray(mdp.reward(thetas8))
    solve_V = jax.jit(lambda r, v: solver(r, v).V)
    V_theta = solve_V(r, jnp.zeros(S))

    # cold and warm solves
    med, mn = _timed(lambda: solve_V(r, jnp.zeros(S)), repeats)
    np_ms = statistics.median(_once(lambda: ref.solve(np.asarray(r)))[0] for _ in range(numpy_repeats))
    record("cold_solve", med, np_ms, mn)
    tight = make_soft_solver(mdp, tol=1e-13)(r)
    from npbrs.domains import greedy_policy

    out[f"{name}.cold_solve_greedy_agreement"] = float(
        (greedy_policy(solver(r).Q) == greedy_policy(tight.Q)).mean())
    solve_default = jax.jit(lambda r, v: default(r, v).V)
    med, mn = _timed(lambda: solve_default(r, jnp.zeros(S)), repeats)
    out[f"{name}.cold_solve_tol1e-10_ms"] = med
    log(f"  {'(tol 1e-10)':14s} {med:9.2f} ms (min {mn:7.2f})")
    med, mn = _timed(lambda: solve_V(r_small, V_theta), repeats)
    np_ms = statistics.median(_once(lambda: ref.solve(np.asarray(r_small), np.asarray(V_theta)))[0]
                              for _ in range(numpy_repeats))
    record("warm_solve", med, np_ms, mn)
    res = solver(r_small, V_theta)
    out[f"{name}.warm_solve_newton_steps"] = int(res.num_iter)
    med, mn = _timed(lambda: solve_V(r8, jnp.zeros((8, S))), max(3, repeats // 3))
    np_ms = _once(lambda: ref.solve(np.asarray(r8)))[0]
    record("batch8_solve", med, np_ms, mn)

    # gradients of the count log-likelihood of expert demonstrations
    ll_grad = jax.jit(lambda t, c, v: count_log_likelihood_and_grad(default, t, c, v)[1])
    policies = dom.expert_policies()
    counts8 = []
    for k in range(8):
        st, ac = _rollout(mdp, policies[k % len(policies)], np.random.default_rng(100 + k))
        counts8.append(np.asarray(count_table(st, ac, None, S, A)))
    counts8 = np.stack(counts8)
    th1 = jnp.asarray(theta_small)[None]
    c1 = jnp.asarray(counts8[:1])
    v1 = V_theta[None]
    med, mn = _timed(lambda: ll_grad(th1, c1, v1), repeats)
    np_ms = _once(lambda: ref.ll_and_grad(theta_small, counts8[0], np.asarray(V_theta)))[0]
    record("grad", med, np_ms, mn)
    med, mn = _timed(lambda: ll_grad(th1, c1, jnp.zeros((1, S))), repeats)
    np_ms = _once(lambda: ref.ll_and_grad(theta_small, counts8[0]))[0]
    record("grad_cold", med, np_ms, mn)
    th8 = jnp.asarray(thetas8)
    V8 = jax.jit(lambda r: solver(r).V)(r8)
    th8_small = th8 * (1 + 1e-3 * jnp.asarray(rng.normal(size=th8.shape)))
    med, mn = _timed(lambda: ll_grad(th8_small, jnp.asarray(counts8), V8), max(3, repeats // 3))
    np_ms = _once(lambda: [ref.ll_and_grad(np.asarray(th8_small[k]), counts8[k], np.asarray(V8[k]))
                           for k in range(8)])[0]
    record("batch8_grad", med, np_ms, mn)

    # one IRL fit (MAP, 30 L-BFGS steps from zero)
    c1 = jnp.asarray(counts8[:1])
    fit_jit = jax.jit(lambda c: fit_reward(default, c, jnp.zeros((1, D)), jnp.zeros((1, S)), PRIOR_SCALE, 30))
    fit = lambda: fit_jit(c1)
    med, mn = _timed(fit, max(3, repeats // 5))
    theta_fit, ll_fit, _, gnorm, evals = fit()
    num_evals = int(evals[0])
    np_eval_ms = _numpy_irl_eval_ms(ref, counts8[0], D, PRIOR_SCALE)
    record("irl_fit", med, np_eval_ms * num_evals, mn)
    out[f"{name}.irl_fit_evaluations"] = num_evals
    out[f"{name}.irl_fit_numpy_ms_per_evaluation"] = np_eval_ms
    out[f"{name}.irl_fit_grad_norm"] = float(gnorm[0])
    return out


def _numpy_irl_eval_ms(ref, counts, D, prior_scale, num_evals=3):
    """Time per value-and-gradient evaluation of a NumPy IRL fit (scipy L-BFGS-B, each solve
    warm-started from the previous one), over its first ``num_evals`` evaluations."""
    from scipy.optimize import minimize

    state = {"V": None, "n": 0}

    def fg(theta):
        ll, g, V = ref.ll_and_grad(theta, counts, state["V"])
        state["V"], state["n"] = V, state["n"] + 1
        return -(ll - 0.5 * theta @ theta / prior_scale ** 2), -(g - theta / prior_scale ** 2)

    t0 = CLOCK()
    minimize(fg, np.zeros(D), jac=True, method="L-BFGS-B", options={"maxfun": num_evals, "maxiter": num_evals})
    return (CLOCK() - t0) * 1e3 / max(state["n"], 1)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--json", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "bench_mdp.json"),
                        help="write the figures to this JSON file (default: benchmarks/results/bench_mdp.json)")
    parser.add_argument("--domains", nargs="+", default=["highway", "quadcopter"])
    parser.add_argument("--repeats", type=int, default=15, help="timed repetitions of each JAX figure")
    parser.add_argument("--numpy-repeats", type=int, default=1, help="timed repetitions of each NumPy figure")
    parser.add_argument("--clock", choices=["wall", "process"], default="wall",
                        help="wall-clock time, or this process's CPU time (steadier on a shared machine; "
                             "pin to one core, e.g. taskset -c 1, so that it is also the wall time of an idle core)")
    args = parser.parse_args(argv)
    global CLOCK
    CLOCK = time.perf_counter if args.clock == "wall" else time.process_time
    import jax

    jax.config.update("jax_enable_x64", True)
    print(f"jax {jax.__version__} on {jax.devices()[0].platform}, {os.cpu_count()} CPU cores, "
          f"{len(os.sched_getaffinity(0))} usable, {args.clock} clock")
    results = {"meta": {**run_info(), "jax": jax.__version__, "device": jax.devices()[0].device_kind,
                        "clock": args.clock, "repeats": args.repeats}}
    for name in args.domains:
        results.update(bench_domain(name, args.repeats, args.numpy_repeats))
    if args.json:
        os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
        tmp = args.json + ".tmp"
        with open(tmp, "w") as f:
            json.dump(results, f, indent=2, sort_keys=True)
        os.replace(tmp, args.json)
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
