"""How npbrs scales: the soft Bellman solve in the number of states S (``--part states``), and
the sampler in the number of trajectories N (``--part trajectories``).

    python benchmarks/bench_scale.py [--json PATH] [--part states|trajectories|devices|memory|all]
                                     [--sizes 1e4 1e5 1e6] [--skills 4] [--repeats 3] [--note TEXT]
                                     [--ns 16 128 1024] [--lengths 500 20] [--chains 2] [--sweeps 3]
                                     [--device-length 500] [--device-sweeps 4]

``--part all`` runs states, trajectories and devices and writes every key of the issue in one
JSON (``exponent_n``, ``exponent_s``, ``solve_1e6_cold_s``, ``fit_n1024_peak_mb``,
``devices4_ratio``); ``--part memory`` runs a whole default fit alone (below). The JSON, with
the command and the machine, goes to ``--json PATH``; by default
``benchmarks/results/bench_scale.json`` for ``--part all``, ``bench_scale_PART.json`` beside it
for the other parts.

Devices. One chain's 1024 highway trajectories of ``--device-length`` steps, its trajectories
sharded over 4 CPU host devices against 1 device, each in a process of its own
(``benchmarks/bench_devices.py``'s measurement): ``devices4_ratio``, and whether both drew the
same segmentation. On a 2-core machine the 4 "devices" share the two cores: no speed-up expected.

Sweep (``--part sweep``). A whole sampler sweep of ``fit``'s defaults on the open gridworld of
each ``--sizes`` (1 chain, 16 demonstrations of 100 steps by two experts): ``sweep_1e6_s``,
``sweep_1e6_peak_mb``, ``exponent_s_sweep``.

Memory. ``fit_n1024_default_peak_mb``: the peak resident memory of a whole default fit (every
default, 2 chains) of 1024 highway trajectories x 500 steps, in a process of its own.

Trajectories. Highway demonstrations of N trajectories x T steps, ``fit``'s defaults (the reward
emission, every move, 8 slots; the greedy moves run in the last quarter of warmup) with 2
chains, each (N, T) in a fresh process: ``first_fit_s`` a fit of 1 + 1 sweeps (compiling, no
persistent cache), ``sweep_s`` a second fit's time over its 2 x ``--sweeps`` sweeps,
``peak_rss_mb``; ``exponent_n`` the slope of log(sweep_s) in log(N) at the longest T, and
``fit_n1024_peak_mb`` the N = 1024 run's peak memory there (a short fit: a default fit's 400
sweeps add only their recorded draws).

States. The world is :func:`npbrs.domains.gridworld.open_gridworld` with side L = round(sqrt(S))
(S = 10^4, 99856, 10^6), 5 actions, 3 successor slots, 4 goal-nearness features, discount 0.95.
The rewards are K = ``--skills`` tables solved together in one call, skill k seeking goal k
(theta = 5 e_k; with K > 4, the weights cycle). The solver is ``make_soft_solver(mdp)`` with its
defaults (Newton-GMRES, relative tolerance 1e-10, float64 values; the Newton steps' linear
solves in float32 from 50,000 states, ``krylov_precision="auto"``, recorded per row). Each size
runs in a fresh process of its own (so that its peak memory is its own), and reports

- ``build_s``: building the world; ``first_call_s``: the first solve from V = 0, compilation
  included (no persistent compilation cache: what a new process pays;
  ``solve_1e6_first_call_s``). ``--skills 1`` measures one reward table alone;
- ``solve_s``: the same solve again, compiled (the median of ``--repeats``; ``solve_runs_s``
  all of them). This is the cold solve, ``solve_1e6_cold_s``: from V = 0, as in "a cold soft
  solve takes 7 ms, a warm one 1.9 ms";
- ``warm_start_s``: a solve after the rewards change by a relative 1e-3, started from the
  previous values (a sampler's or an optimiser's step; the median of ``--repeats``);
- ``*_cpu_s``: the same figures in CPU time of the process (all its threads): on a shared machine
  the wall times grow with the other jobs' load, the CPU times much less (they still grow with
  the memory bandwidth those jobs take);
- ``newton_steps``, ``matvecs``: per reward table, of the solve from V = 0 and the warm start;
- ``peak_rss_mb``: the process's peak resident memory (``ru_maxrss``), ``build_rss_mb`` its
  peak after building the world (before JAX touched it).

The growth exponent ``exponent_s`` is the least-squares slope of log(solve_s) against log(S)
over the sizes (``exponent_s_warm_start`` the same for warm_start_s). The machine's load
(``os.getloadavg()``) and the other busy processes are recorded before and after each size:
on a shared 2-core machine another job's processes halve what a run gets.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
from runinfo import processor  # noqa: E402

DEFAULT_SIZES = (10 ** 4, 10 ** 5, 10 ** 6)


# ------------------------------------------------------------------------------- machine
def machine_state() -> dict:
    """The load averages and the processes (other than this one and its children) using CPU."""
    others = []
    try:
        out = subprocess.run(["ps", "-eo", "pid,ppid,pcpu,rss,etime,args", "--sort=-pcpu"], capture_output=True,
                             text=True, timeout=10).stdout.splitlines()[1:]
        mine = {os.getpid()}
        for line in out:
            pid, ppid, pcpu, rss, etime, args = line.split(None, 5)
            if int(pid) in mine or int(ppid) in mine or "ps -eo" in args or float(pcpu) < 5.0:
                continue
            others.append({"pid": int(pid), "cpu_percent": float(pcpu), "rss_mb": round(int(rss) / 1024),
                           "elapsed": etime, "command": args[:120]})
    except (OSError, subprocess.SubprocessError, ValueError):
        pass
    return {"loadavg": [round(x, 2) for x in os.getloadavg()], "busy_processes": others[:8]}


def fit_exponent(sizes, times) -> float:
    """Least-squares slope of log(time) against log(size)."""
    x, y = np.log(np.asarray(sizes, float)), np.log(np.asarray(times, float))
    return float(np.polyfit(x, y, 1)[0])


def run_child(flags, what: str) -> dict:
    """This script again in a fresh process with ``flags``; its last line's JSON, with the
    machine's load before and after."""
    before = machine_state()
    out = subprocess.run([sys.executable, os.path.abspath(__file__)] + [str(f) for f in flags],
                         capture_output=True, text=True)
    if out.returncode:
        raise RuntimeError(f"{what} failed:\n{out.stderr[-3000:]}")
    row = json.loads(out.stdout.strip().splitlines()[-1])
    row.update(load_before=before["loadavg"], load_after=machine_state()["loadavg"])
    return row


# ---------------------------------------------------------------------------- states part
def measure_states(S: int, skills: int, repeats: int) -> dict:
    """One size, in this process: build, first call, compiled and warm-started solves."""
    import jax

    from npbrs.domains import make_soft_solver
    from npbrs.domains.gridworld import open_gridworld

    L = int(round(math.sqrt(S)))
    t = time.perf_counter()
    mdp = open_gridworld(L)
    build_s = time.perf_counter() - t
    build_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    solver = make_soft_solver(mdp)
    theta = np.zeros((skills, mdp.num_features))
    theta[np.arange(skills), np.arange(skills) % mdp.num_features] = 5.0
    rewards = np.asarray(solver.rewards(theta))
    stepped = rewards * (1.0 + 1e-3)
    v0 = np.zeros((skills, mdp.num_states))  # an explicit zero start: one program for every solve

    def timed(r, v):
        t, c = time.perf_counter(), time.process_time()
        res = solver(r, v)
        jax.block_until_ready(res.V)
        return time.perf_counter() - t, time.process_time() - c, res

    first, first_cpu, res = timed(rewards, v0)
    runs = [timed(rewards, v0)[:2] for _ in range(repeats)]
    warm = [timed(stepped, res.V) for _ in range(repeats)]
    ws = warm[-1][2]
    return {
        "S": mdp.num_states, "L": L, "A": mdp.num_actions, "B": mdp.num_successors, "K": skills,
        "krylov_precision": solver.krylov_precision,
        "build_s": build_s, "first_call_s": first, "first_call_cpu_s": first_cpu,
        "solve_s": statistics.median(r[0] for r in runs), "solve_runs_s": [r[0] for r in runs],
        "solve_cpu_s": statistics.median(r[1] for r in runs),
        "warm_start_s": statistics.median(w[0] for w in warm), "warm_start_runs_s": [w[0] for w in warm],
        "warm_start_cpu_s": statistics.median(w[1] for w in warm),
        "newton_steps": np.asarray(res.num_iter).tolist(), "matvecs": np.asarray(res.num_matvec).tolist(),
        "residual_max": float(np.max(res.residual)),
        "warm_start_newton_steps": np.asarray(ws.num_iter).tolist(),
        "warm_start_matvecs": np.asarray(ws.num_matvec).tolist(),
        "build_rss_mb": build_rss, "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }


def part_states(sizes, skills: int, repeats: int) -> dict:
    """Every size in a fresh process; the table, the exponents and the 10^6 figures."""
    rows = []
    for S in sizes:
        row = run_child(["--_states-child", S, "--skills", skills, "--repeats", repeats], f"the S = {S} run")
        print(f"  S = {row['S']:>8}: first call {row['first_call_s']:7.2f} s, solve {row['solve_s']:7.2f} s, "
              f"warm start {row['warm_start_s']:7.2f} s, peak {row['peak_rss_mb']:6.0f} MB "
              f"(load {row['load_before'][0]:.1f})", flush=True)
        rows.append(row)
    result = {"rows": rows}
    if len(rows) >= 2:
        result["exponent_s"] = fit_exponent([r["S"] for r in rows], [r["solve_s"] for r in rows])
        result["exponent_s_warm_start"] = fit_exponent([r["S"] for r in rows], [r["warm_start_s"] for r in rows])
        result["exponent_s_cpu"] = fit_exponent([r["S"] for r in rows], [r["solve_cpu_s"] for r in rows])
    big = [r for r in rows if r["S"] == 10 ** 6]
    if big:
        result["solve_1e6_cold_s"] = big[0]["solve_s"]
        result["solve_1e6_cold_cpu_s"] = big[0]["solve_cpu_s"]
        result["solve_1e6_first_call_s"] = big[0]["first_call_s"]
        result["solve_1e6_first_call_cpu_s"] = big[0]["first_call_cpu_s"]
        result["solve_1e6_warm_start_s"] = big[0]["warm_start_s"]
        result["peak_rss_1e6_mb"] = big[0]["peak_rss_mb"]
    return result


def print_states(result: dict) -> None:
    print("seconds, wall (CPU)")
    print(f"{'S':>9} {'build':>6} {'first call':>15} {'solve':>15} {'warm start':>15} {'Newton':>7} {'matvecs':>8} "
          f"{'peak MB':>8} {'load':>5}")
    for r in result["rows"]:
        print(f"{r['S']:>9} {r['build_s']:>6.2f} {r['first_call_s']:>7.2f} ({r['first_call_cpu_s']:>5.2f}) "
              f"{r['solve_s']:>7.2f} ({r['solve_cpu_s']:>5.2f}) {r['warm_start_s']:>7.2f} ({r['warm_start_cpu_s']:>5.2f}) "
              f"{max(r['newton_steps']):>7} {max(r['matvecs']):>8} {r['peak_rss_mb']:>8.0f} "
              f"{r['load_before'][0]:>5.1f}")
    if "exponent_s" in result:
        print(f"growth exponent in S: {result['exponent_s']:.3f} (solve), "
              f"{result['exponent_s_warm_start']:.3f} (warm start), {result['exponent_s_cpu']:.3f} (solve, CPU time)")


# ------------------------------------------------------------------------ trajectories part
DEFAULT_NS = (16, 128, 1024)
DEFAULT_LENGTHS = (500, 20)


def measure_trajectories(N: int, T: int, chains: int, sweeps: int) -> dict:
    """One fresh process: highway demonstrations N x T, ``fit``'s defaults (reward emission,
    every move, 8 slots) with ``chains`` chains: a first fit of 1 + 1 sweeps (compiling), then
    the same shapes again with ``sweeps`` warmup and ``sweeps`` sampling sweeps (compiled)."""
    os.environ.setdefault("NPBRS_CACHE_DIR", "off")  # what a new machine pays
    from npbrs.domains import generate_demonstrations, get_domain
    from npbrs.inference import fit

    dom = get_domain("highway")
    demos = generate_demonstrations(dom, num_trajectories=N, length=T, seed=0)
    kw = dict(num_chains=chains, progress_bar=False, seed=0)
    start = time.perf_counter()
    fit(dom.mdp, demos, num_warmup=1, num_samples=1, **kw)
    first = time.perf_counter() - start
    start = time.perf_counter()
    result = fit(dom.mdp, demos, num_warmup=sweeps, num_samples=sweeps, **kw)
    timed = time.perf_counter() - start
    return {"N": N, "T": T, "chains": chains, "first_fit_s": round(first, 2), "timed_fit_s": round(timed, 2),
            "sweep_s": round(timed / (2 * sweeps), 4), "skills": int(result.num_skills),
            "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)}


def part_trajectories(args) -> dict:
    """The sampler's cost in the number of trajectories N: for each length T and N, one fresh
    process (:func:`measure_trajectories`); ``exponent_n`` is the least-squares slope of
    log(sweep_s) against log(N) over the N at the longest T (``exponent_n_by_length`` per T);
    ``fit_n1024_peak_mb`` the peak memory of the N = 1024 run at the longest T. A sweep's time
    includes the sweep's share of fit's per-sweep host work (recording draws)."""
    rows = []
    for T in args.lengths:
        for N in args.ns:
            row = run_child(["--_trajectories-child", f"{N},{T}", "--chains", args.chains, "--sweeps", args.sweeps],
                            f"N = {N}, T = {T}")
            print(f"  N {N:5d} T {T:4d}: first fit {row['first_fit_s']:7.1f} s, sweep {row['sweep_s']:.3f} s, "
                  f"peak {row['peak_rss_mb']} MB, {row['skills']} skills", flush=True)
            rows.append(row)

    def slope(rs):
        x = np.log([r["N"] for r in rs])
        y = np.log([r["sweep_s"] for r in rs])
        return round(float(np.polyfit(x, y, 1)[0]), 3) if len(rs) > 1 else None

    longest = max(args.lengths)
    by_length = {str(T): slope([r for r in rows if r["T"] == T]) for T in args.lengths}
    big = [r for r in rows if r["T"] == longest and r["N"] == max(args.ns)]
    return {"rows": rows, "exponent_n": by_length[str(longest)], "exponent_n_by_length": by_length,
            "fit_n1024_peak_mb": big[0]["peak_rss_mb"] if big and max(args.ns) == 1024 else None,
            "chains": args.chains, "sweeps": args.sweeps}


# ------------------------------------------------------------------------------- sweep part
@contextlib.contextmanager
def timed_sweeps():
    """Within the block, every sweep of a ``fit`` is timed on its own (the driver's
    ``_Chains.advance`` wrapped, the chains' state waited for) and so is the chains' start
    (``_Compiled.init``): yields (sweep times, start times), lists of seconds that fill as fits
    run; the driver is restored on exit."""
    import jax

    from npbrs.inference.driver import fit as driver

    times, starts, advance, init = [], [], driver._Chains.advance, driver._Compiled.init

    def timed_advance(self):
        t = time.perf_counter()
        records = advance(self)
        jax.block_until_ready(self.states)
        times.append(time.perf_counter() - t)
        return records

    def timed_init(self, *args, **kwargs):
        t = time.perf_counter()
        state = jax.block_until_ready(init(self, *args, **kwargs))
        starts.append(time.perf_counter() - t)
        return state

    driver._Chains.advance, driver._Compiled.init = timed_advance, timed_init
    try:
        yield times, starts
    finally:
        driver._Chains.advance, driver._Compiled.init = advance, init


def measure_sweep(S: int, chains: int, sweeps: int) -> dict:
    """One fresh process: ``fit``'s defaults on the open gridworld of S states (the reward
    emission, 8 slots, every move): 16 demonstrations of 100 steps by two Boltzmann experts (theta
    = 1000 e_k: walk to goal k), switching with probability 0.02 a step.

    One fit of ``sweeps`` + ``sweeps`` sweeps, each sweep timed on its own (the driver's
    ``_Chains.advance`` wrapped, the chains' state waited for): the first sweep compiles and is
    left out; the warmup's last quarter runs the greedy moves, as in every default fit. Reports
    the start (``init_s``: the initial IRL fits of the skills, compilation included), the median
    plain warmup, greedy and sampling sweep, and ``sweep_s``: the mean sweep of a default fit
    (200 + 200 sweeps; greedy from ``MOVE_DEFAULTS["greedy_from"]`` of warmup: 150 plain, 50
    greedy, 200 sampling) from those medians."""
    import types

    os.environ.setdefault("NPBRS_CACHE_DIR", "off")

    from npbrs.domains import generate_demonstrations, make_soft_solver
    from npbrs.domains.gridworld import open_gridworld
    from npbrs.inference import fit
    from npbrs.inference.sampler.options import MOVE_DEFAULTS

    mdp = open_gridworld(int(round(math.sqrt(S))))
    solver = make_soft_solver(mdp)
    theta = np.zeros((2, mdp.num_features))
    theta[[0, 1], [0, 1]] = 1000.0
    res = solver(np.asarray(solver.rewards(theta)))
    policies = np.exp(np.asarray(res.Q) - np.asarray(res.V)[..., None])
    policies /= policies.sum(-1, keepdims=True)
    demos = generate_demonstrations(types.SimpleNamespace(mdp=mdp), num_trajectories=16, length=100, seed=0,
                                    policies=policies)
    del res, policies
    with timed_sweeps() as (times, starts):
        start = time.perf_counter()
        result = fit(mdp, demos, num_warmup=sweeps, num_samples=sweeps, num_chains=chains, progress_bar=False, seed=0)
        wall = time.perf_counter() - start
    init_s, per_sweep = starts[0], np.asarray(times)
    greedy_share = MOVE_DEFAULTS["greedy_from"]  # the warmup's greedy sweeps start at this fraction
    greedy_from = int(np.floor(greedy_share * sweeps))
    plain = np.median(per_sweep[1:greedy_from]) if greedy_from > 1 else float("nan")
    greedy = np.median(per_sweep[greedy_from:sweeps])
    sample = np.median(per_sweep[sweeps:])
    mean = (greedy_share * plain + (1 - greedy_share) * greedy + sample) / 2  # 200 + 200 sweeps
    return {"S": mdp.num_states, "chains": chains, "sweeps": 2 * sweeps, "fit_s": round(wall, 2),
            "init_s": round(init_s, 2), "first_sweep_s": round(float(per_sweep[0]), 2),
            "warmup_sweep_s": round(float(plain), 3), "greedy_sweep_s": round(float(greedy), 3),
            "sample_sweep_s": round(float(sample), 3), "sweep_s": round(float(mean), 3),
            "sweep_times": [round(float(t), 3) for t in per_sweep], "skills": int(result.num_skills),
            "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)}


def part_sweep(args) -> dict:
    """A whole sampler sweep on the open gridworld for each of ``--sizes`` (fresh processes):
    ``sweep_1e6_s`` and ``sweep_1e6_peak_mb`` at a million states, ``exponent_s_sweep``."""
    rows = []
    for S in args.sizes:
        row = run_child(["--_sweep-child", int(S), "--chains", args.sweep_chains, "--sweeps", args.sweeps],
                        f"S = {int(S)}")
        print(f"  S {row['S']:8d}: start {row['init_s']:7.1f} s; sweeps: warmup {row['warmup_sweep_s']:.2f} s, "
              f"greedy {row['greedy_sweep_s']:.2f} s, sampling {row['sample_sweep_s']:.2f} s, a default fit's mean "
              f"{row['sweep_s']:.3f} s; peak {row['peak_rss_mb']} MB, {row['skills']} skills", flush=True)
        rows.append(row)
    out = {"rows": rows}
    if len(rows) > 1:
        sizes = [r["S"] for r in rows]
        out["exponent_s_sweep"] = round(fit_exponent(sizes, [r["sweep_s"] for r in rows]), 3)
        for key in ("init", "warmup_sweep", "greedy_sweep", "sample_sweep"):
            out[f"exponent_s_{key}"] = round(fit_exponent(sizes, [r[f"{key}_s"] for r in rows]), 3)
    big = [r for r in rows if r["S"] == 10 ** 6]
    if big:
        out["sweep_1e6_s"], out["sweep_1e6_peak_mb"] = big[0]["sweep_s"], big[0]["peak_rss_mb"]
    return out


# ------------------------------------------------------------------------------ devices part
def part_devices(args) -> dict:
    """A sweep's time with one chain's N = 1024 highway trajectories sharded over 4 CPU host
    devices against 1 device (``benchmarks/bench_devices.py``'s measurement, at
    ``--device-length`` steps): ``devices4_ratio`` (below 1: faster), and whether the two runs
    drew the same segmentation."""
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    import bench_devices

    out = {"trajectories": 1024, "length": args.device_length, "sweeps": args.device_sweeps}
    base = os.path.join(tempfile.mkdtemp(prefix="npbrs-devices-"), "run")
    res = bench_devices.compare(args.device_length, args.device_sweeps, base, lambda m: print("  " + m, flush=True))
    out.update(res, devices4_same_segmentation=res.pop("same_segmentation"),
               devices4_log_joint_max_rel_diff=res.pop("log_joint_max_rel_diff"))
    return out


# ------------------------------------------------------------------------------- memory part
def measure_default_fit(N: int, T: int, chains: int) -> dict:
    """One fresh process: a default ``fit`` (every default: 200 + 200 sweeps, 8 slots, every
    move) of N highway trajectories x T steps with ``chains`` chains; its wall time and the
    process's peak resident memory."""
    os.environ.setdefault("NPBRS_CACHE_DIR", "off")
    from npbrs.domains import generate_demonstrations, get_domain
    from npbrs.inference import fit

    dom = get_domain("highway")
    demos = generate_demonstrations(dom, num_trajectories=N, length=T, seed=0)
    start = time.perf_counter()
    result = fit(dom.mdp, demos, num_chains=chains, seed=0, progress_bar=False)
    return {"N": N, "T": T, "chains": chains, "fit_s": round(time.perf_counter() - start, 1),
            "skills": int(result.num_skills),
            "peak_rss_mb": round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)}


def part_memory(args) -> dict:
    """``fit_n1024_default_peak_mb``: the peak memory of a whole default 2-chain fit of 1024
    highway trajectories x 500 steps (about a quarter of an hour on 2 cores; the trajectories
    part's ``fit_n1024_peak_mb`` is a short fit's)."""
    row = run_child(["--_memory-child", "1024,500", "--chains", args.chains], "the default fit")
    print(f"  default fit N 1024 T 500, {args.chains} chains: {row['fit_s']} s, peak {row['peak_rss_mb']} MB, "
          f"{row['skills']} skills", flush=True)
    return {"default_fit": row, "fit_n1024_default_peak_mb": row["peak_rss_mb"]}


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--json", help="write the results here (default: benchmarks/results/bench_scale.json for "
                                       "--part all, bench_scale_PART.json for another part)")
    parser.add_argument("--part", choices=("states", "trajectories", "devices", "sweep", "memory", "all"),
                        default="states",
                        help="all: states, trajectories and devices (sweep and memory run alone)")
    parser.add_argument("--sizes", nargs="+", type=float, default=DEFAULT_SIZES, help="numbers of states")
    parser.add_argument("--skills", type=int, default=4, help="reward tables solved together")
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--note", default="", help="free text saved in the JSON (what else the machine was doing)")
    parser.add_argument("--ns", nargs="+", type=int, default=DEFAULT_NS, help="numbers of trajectories")
    parser.add_argument("--lengths", nargs="+", type=int, default=DEFAULT_LENGTHS, help="trajectory lengths")
    parser.add_argument("--chains", type=int, default=2, help="chains of the trajectories part's fits")
    parser.add_argument("--sweeps", type=int, default=3, help="timed warmup (and sampling) sweeps")
    parser.add_argument("--device-length", type=int, default=500, help="trajectory length of the devices part")
    parser.add_argument("--device-sweeps", type=int, default=4, help="timed sweeps of the devices part")
    parser.add_argument("--_states-child", type=float, help=argparse.SUPPRESS)
    parser.add_argument("--_memory-child", help=argparse.SUPPRESS)
    parser.add_argument("--sweep-chains", type=int, default=1, help="chains of the sweep part's fits")
    parser.add_argument("--_sweep-child", type=int, help=argparse.SUPPRESS)
    parser.add_argument("--_trajectories-child", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args._sweep_child:
        print(json.dumps(measure_sweep(args._sweep_child, args.chains, args.sweeps)))
        return 0
    if args._memory_child:
        N, T = (int(v) for v in args._memory_child.split(","))
        print(json.dumps(measure_default_fit(N, T, args.chains)))
        return 0
    if args._trajectories_child:
        N, T = (int(v) for v in args._trajectories_child.split(","))
        print(json.dumps(measure_trajectories(N, T, args.chains, args.sweeps)))
        return 0
    if args._states_child:
        print(json.dumps(measure_states(int(args._states_child), args.skills, args.repeats)))
        return 0

    if args.json is None:
        name = "bench_scale.json" if args.part == "all" else f"bench_scale_{args.part}.json"
        args.json = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", name)
    import jax

    report = {"benchmark": "bench_scale", "command": " ".join([os.path.basename(sys.executable)] + sys.argv),
              "machine": {"cpus": os.cpu_count(), "platform": platform.platform(), "processor": processor(),
                          "python": platform.python_version(),
                          "jax": jax.__version__, "xla_flags": os.environ.get("XLA_FLAGS", "")},
              "started": time.strftime("%Y-%m-%d %H:%M:%S"), "note": args.note, "machine_at_start": machine_state()}
    if args.part in ("states", "all"):
        print(f"states: sizes {[int(s) for s in args.sizes]}, K = {args.skills}", flush=True)
        report["states"] = part_states([int(s) for s in args.sizes], args.skills, args.repeats)
        report.update({k: v for k, v in report["states"].items() if k != "rows"})
        print_states(report["states"])
    if args.part in ("trajectories", "all"):
        print(f"trajectories: N {list(args.ns)}, T {list(args.lengths)}, {args.chains} chains", flush=True)
        report["trajectories"] = part_trajectories(args)
        report.update({k: v for k, v in report["trajectories"].items() if k != "rows"})
    if args.part in ("devices", "all"):
        print(f"devices: N 1024, T {args.device_length}, 1 chain, 1 and 4 host devices", flush=True)
        report["devices"] = part_devices(args)
        report["devices4_ratio"] = report["devices"]["devices4_ratio"]
    if args.part == "sweep":
        print(f"sweep: open gridworld, sizes {[int(s) for s in args.sizes]}, {args.sweep_chains} chain(s)", flush=True)
        report["sweep"] = part_sweep(args)
        report.update({k: v for k, v in report["sweep"].items() if k != "rows"})
    if args.part == "memory":
        print(f"memory: a default fit, N 1024, T 500, {args.chains} chains", flush=True)
        report["memory"] = part_memory(args)
        report["fit_n1024_default_peak_mb"] = report["memory"]["fit_n1024_default_peak_mb"]
    report["machine_at_end"] = machine_state()
    if args.json:
        os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
        tmp = args.json + ".tmp"
        with open(tmp, "w") as f:
            json.dump(report, f, indent=1)
        os.replace(tmp, args.json)
        print(f"wrote {args.json}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
