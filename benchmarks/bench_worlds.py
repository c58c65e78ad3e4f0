"""npbrs with ``fit``'s defaults on worlds that look like what researchers bring.

For each world of :mod:`npbrs.domains.worlds` (``tabular_grid``, ``labyrinth``, ``rooms``; seed
``--seed``, full sizes, one-hot state features) it fits the training demonstrations with
``fit(mdp, demos)`` (every default: the reward emission, chains, sweeps, truncation, prior) and
with one unsegmented reward (``emission="single"``, ``max_skills=1``, the other defaults), and
reports per world:

- ``skills`` (``FitResult.num_skills``: in the best draw's segmentation) and ``true_skills``;
- ``hungarian`` (one-to-one matching) and ``many_to_one`` (the paper's labelling: an inferred
  skill takes the true label holding more than half of its steps, else its steps count as
  wrong) accuracy of each step's most probable skill under the run's posterior
  (``FitResult.segment(mdp).labels``, as the paper's tables and ``npbrs demo`` score a run:
  the labels that are right at the most steps in expectation), against ``oracle_hungarian``,
  the true model's Viterbi segmentation's; the same for the best draw's segmentation
  (``FitResult.segmentation``, one posterior sample) in ``hungarian_best_draw`` and
  ``many_to_one_best_draw``, and for the same labels counted over the sampler's own draws
  (``FitResult.skill_probabilities``, free where ``segment`` recomputes) in
  ``hungarian_sampler``, ``switch_ratio_sampler``;
- ``switch_ratio``: switches per trajectory of those per-step labels over the truth's
  (``switch_ratio_best_draw``: the best draw's; a draw's boundaries jitter and it keeps short
  excursions that the average over draws does not);
- ``heldout_ll``: ``FitResult.log_predictive(mdp, heldout).per_step`` (nats per step), against
  ``oracle_heldout_ll`` (the generating model's), ``sticky_heldout_ll`` (the true policies
  under switching that does not depend on the state, as the BP-HMM's never does: about the best
  a fit can reach; ``Oracle.sticky_heldout_ll``) and ``single_heldout_ll`` (one reward's);
- ``rhat_max``: the largest R-hat of the label-invariant scalars (``result.rhat``), with every
  R-hat and ESS alongside; ``switching``: ``FitResult.switching`` (the switching model ``fit``
  chose and the log Bayes factor it chose by); ``restart``: ``FitResult.restart`` (each chain's score at warmup's
  end and the chain whose state it continued from);
- ``wall_s``: the default fit's wall time, compilation included; ``peak_mb``: the peak resident
  memory of the process that generated the world and ran that fit (each world runs in a process
  of its own), measured right after the fit.

    python benchmarks/bench_worlds.py [--json benchmarks/results/bench_worlds.json]
        [--worlds tabular_grid,labyrinth] [--quick] [--seed 0] [--note "what ran, how"]
        [--fit-options '{"switching": "state"}'] [--cache]

JAX's persistent compilation cache is off unless ``--cache``: ``fit`` would otherwise reuse the
programs an earlier run left in npbrs's folder, and the wall time and peak memory would say
whether one had (the labyrinth's default fit: 66 s and 1.0 GB with a warm cache, 84-90 s and
1.9-2.2 GB cold).

``--fit-options`` (JSON) gives the fitted model's options (for a model variant measured the same
way: the single-reward comparison keeps the defaults): ``fit``'s own keyword arguments
(``num_chains``, ``seed``, ...) go to the call, every other name to its config (``switching``,
``moves``, ...); the JSON records them.

It prints a markdown table and writes the JSON at PATH (top-level keys: ``meta`` and one per
world) and the markdown next to it (PATH with the suffix ``.md``). Rows of worlds already in
PATH and not run again are kept, so worlds can be run one at a time into one file. ``--quick``
runs tiny worlds and short fits (a smoke test of the script, not a measurement).

Times are absolute wall-clock seconds on whatever machine runs this; what else was running on
it is unknown (the output says so and records the load average before and after each world).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import subprocess
import sys
import tempfile
import time
from datetime import datetime, timezone

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from runinfo import processor  # noqa: E402

WORLD_NAMES = ("tabular_grid", "labyrinth", "rooms")
DEFAULT_JSON = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "bench_worlds.json")

QUICK_SIZES = {
    "tabular_grid": dict(num_trajectories=8, length=60, num_heldout=4),
    "labyrinth": dict(num_trajectories=20, num_heldout=10),
    "rooms": dict(num_trajectories=8, min_length=30, max_length=50, num_heldout=4),
}
QUICK_FIT = dict(num_chains=2, num_warmup=6, num_samples=6)
# fit's own keyword arguments; every other option is its config's
FIT_KEYWORDS = ("num_chains", "num_samples", "num_warmup", "seed", "init_segmentation", "progress_bar",
                "checkpoint_path", "resume", "devices")
QUICK_PREDICTIVE = dict(num_draws=4, num_samples=8)

UNKNOWN_LOAD = ("What else was running on the machine during the run is unknown (another engineer may have been "
                "timing things on it); wall times are absolute seconds under that unknown load, with the 1-minute "
                "load average recorded before and after each world.")


def _now() -> str:
    return datetime.now(timezone.utc).astimezone().isoformat(timespec="seconds")


def _peak_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux reports KiB


def _finite(x):
    x = float(x)
    return x if np.isfinite(x) else None


def run_world(name: str, seed: int, quick: bool, options: dict = None) -> dict:
    """Generate one world, fit it with the defaults and with one reward, and measure."""
    from npbrs.domains.worlds import WORLDS
    from npbrs.inference import fit
    from npbrs.inference.analysis.metrics import hungarian_accuracy, num_switches, paper_accuracy

    row = {"started": _now(), "load_before": os.getloadavg()[0]}
    world = WORLDS[name](seed=seed, **(QUICK_SIZES[name] if quick else {}))
    mdp, demos, heldout = world.mdp, world.demos, world.heldout
    fit_options = QUICK_FIT if quick else {}
    predictive = QUICK_PREDICTIVE if quick else {}
    print(f"[{_now()}] {name}: {world!r}", flush=True)
    oracle = world.oracle()

    start = time.perf_counter()
    given = {**fit_options, **(options or {})}
    call = {k: v for k, v in given.items() if k in FIT_KEYWORDS}
    config = {k: v for k, v in given.items() if k not in FIT_KEYWORDS}
    result = fit(mdp, demos, config or None, progress_bar=False, **call)
    wall = time.perf_counter() - start
    peak = _peak_mb()
    print(f"[{_now()}] {name}: default fit {wall:.0f} s, {result.num_skills} skills", flush=True)

    start = time.perf_counter()
    held = result.log_predictive(mdp, heldout, **predictive)
    predictive_s = time.perf_counter() - start

    start = time.perf_counter()
    labels = result.segment(mdp, **predictive).labels  # each step's most probable skill, over the draws
    segment_s = time.perf_counter() - start
    counted = result.skill_probabilities().labels  # the same, counted over the sampler's draws

    start = time.perf_counter()
    single = fit(mdp, demos, {"emission": "single", "max_skills": 1}, progress_bar=False, **fit_options)
    single_s = time.perf_counter() - start
    single_held = single.log_predictive(mdp, heldout, **predictive)
    print(f"[{_now()}] {name}: single-reward fit {single_s:.0f} s", flush=True)

    true_switches = num_switches(demos.skills)
    found_switches = num_switches(labels)
    best_switches = num_switches(result.segmentation)
    rhat, ess = result.rhat, result.ess
    finite_rhat = [v for v in rhat.values() if np.isfinite(v)]
    row.update({
        "skills": int(result.num_skills),
        "true_skills": int(world.model.num_skills),
        "hungarian": hungarian_accuracy(demos.skills, labels),
        "many_to_one": paper_accuracy(demos.skills, labels),
        "hungarian_best_draw": hungarian_accuracy(demos.skills, result.segmentation),
        "many_to_one_best_draw": paper_accuracy(demos.skills, result.segmentation),
        "labelled_skills": int(len(np.unique(np.concatenate(labels)))),
        "hungarian_sampler": hungarian_accuracy(demos.skills, counted),
        "switch_ratio_sampler": num_switches(counted) / true_switches,
        "oracle_hungarian": hungarian_accuracy(demos.skills, oracle.viterbi),
        "oracle_viterbi_accuracy": oracle.viterbi_accuracy,
        "switch_ratio": found_switches / true_switches,
        "switches": found_switches,
        "switch_ratio_best_draw": best_switches / true_switches,
        "true_switches": true_switches,
        "heldout_ll": float(held.per_step),
        "heldout_ll_se": float(held.per_step_se),
        "oracle_heldout_ll": oracle.heldout_ll,
        "sticky_heldout_ll": oracle.sticky_heldout_ll,
        "sticky_viterbi_accuracy": oracle.sticky_viterbi_accuracy,
        "single_heldout_ll": float(single_held.per_step),
        "single_heldout_ll_se": float(single_held.per_step_se),
        "uniform_ll": -float(np.log(mdp.num_actions)),
        "rhat_max": max(finite_rhat) if finite_rhat else None,
        "rhat": {k: _finite(v) for k, v in rhat.items()},
        "ess": {k: _finite(v) for k, v in ess.items()},
        "restart": result.restart,
        "switching": result.switching,
        "wall_s": wall,
        "peak_mb": peak,
        "predictive_s": predictive_s,
        "segment_s": segment_s,
        "single_wall_s": single_s,
        "num_states": mdp.num_states,
        "num_trajectories": demos.num_trajectories,
        "num_steps": demos.num_steps,
        "heldout_trajectories": heldout.num_trajectories,
        "heldout_steps": heldout.num_steps,
        "world_params": {k: (list(v) if isinstance(v, tuple) else v) for k, v in world.params.items()},
        "fit_config": result.config,
        "fit_options": options or {},
        "finished": _now(),
        "load_after": os.getloadavg()[0],
        "quick": quick,
    })
    return row


# --------------------------------------------------------------------------------- output
def _fmt(x, spec):
    return "—" if x is None else format(x, spec)


def markdown(rows: dict, meta: dict) -> str:
    options = sorted({json.dumps(r.get("fit_options") or {}, sort_keys=True) for r in rows.values()})
    variant = "" if options == ["{}"] else f" and `{'; '.join(options)}`"
    lines = [f"# npbrs with `fit`'s defaults{variant} on the benchmark worlds", "",
             f"Run {meta.get('started', '?')} to {meta.get('finished', '?')} on {meta.get('machine', '?')}. "
             + UNKNOWN_LOAD, ""] + ([meta["run_note"], ""] if meta.get("run_note") else []) + [
             f"World seed {meta.get('seed', '?')}; JAX {meta.get('jax', '?')}, NumPyro {meta.get('numpyro', '?')}.", "",
             "| world | skills (true) | one-to-one acc. (oracle) | many-to-one acc. | switches found / true | "
             "best draw: one-to-one acc., switches / true | "
             "held-out LL per step: npbrs (oracle; sticky oracle; one reward; uniform) | R-hat max | wall s | peak MB |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for name in WORLD_NAMES:
        r = rows.get(name)
        if r is None:
            continue
        lines.append(
            f"| {name} | {r['skills']} ({r['true_skills']}) | {r['hungarian']:.3f} ({r['oracle_hungarian']:.3f}) "
            f"| {r['many_to_one']:.3f} | {r['switch_ratio']:.2f} ({r['switches']:.1f} / {r['true_switches']:.1f}) "
            f"| {_fmt(r.get('hungarian_best_draw'), '.3f')}, {_fmt(r.get('switch_ratio_best_draw'), '.2f')} "
            f"| {r['heldout_ll']:.3f} ({r['oracle_heldout_ll']:.3f}; {_fmt(r.get('sticky_heldout_ll'), '.3f')}; "
            f"{r['single_heldout_ll']:.3f}; "
            f"{r['uniform_ll']:.3f}) | {_fmt(r['rhat_max'], '.3f')} | {r['wall_s']:.0f} | {r['peak_mb']:.0f} |")
    lines += ["", "Per world: when it ran, the load around it, the data and the other timings:", ""]
    def _switching_text(switching):
        if not switching:
            return ""
        return (f"switching chosen: {switching['chosen']} (log Bayes factor of state ends "
                f"{switching['log_bayes_factor']:+.1f} nats); ")

    def _restart_text(restart):
        if not restart:
            return ""
        moved = [f"{c} <- {f}" for c, f in enumerate(restart["from"]) if c != f]
        return f"restarted at warmup's end: {', '.join(moved) or 'none'} (margin {restart['margin']:g}); "

    for name in WORLD_NAMES:
        r = rows.get(name)
        if r is None:
            continue
        rhat = ", ".join(f"{k} {_fmt(v, '.3f')}" for k, v in r["rhat"].items())
        ess = ", ".join(f"{k} {_fmt(v, '.0f')}" for k, v in r["ess"].items())
        lines.append(f"- {name}: {r['started']} to {r['finished']} (load average {r['load_before']:.2f} before, "
                     f"{r['load_after']:.2f} after); {r['num_trajectories']} trajectories, {r['num_steps']} steps, "
                     f"{r['num_states']} states; held out {r['heldout_trajectories']} trajectories, "
                     f"{r['heldout_steps']} steps; held-out LL standard errors {r['heldout_ll_se']:.4f} (npbrs), "
                     f"{r['single_heldout_ll_se']:.4f} (one reward); R-hat {rhat}; ESS {ess}; "
                     f"{_restart_text(r.get('restart'))}{_switching_text(r.get('switching'))}scoring the "
                     f"held-out set {r['predictive_s']:.0f} s; labelling the steps "
                     f"{_fmt(r.get('segment_s'), '.0f')} s; the one-reward fit {r['single_wall_s']:.0f} s"
                     + ("; QUICK (tiny sizes, short fits)" if r.get("quick") else "") + ".")
    lines += ["", "Accuracy and switches are of each step's most probable skill under the run's posterior "
              "(`FitResult.segment`, as the paper's tables score a run; the same labels counted over the sampler's "
              "draws, `FitResult.skill_probabilities`, are in the JSON as `hungarian_sampler`); "
              "the best draw's segmentation (`FitResult.segmentation`, one posterior sample) is beside them. "
              "One-to-one is Hungarian matching; many-to-one is the paper's labelling (an inferred "
              "skill takes the true skill holding more than half of its steps, else its steps count as wrong); the "
              "oracle is the generating model's Viterbi segmentation; the sticky oracle is the true policies under "
              "switching that does not depend on the state (fitted to the true skills), the BP-HMM's kind of switching. "
              "Held-out log-likelihoods are of the actions "
              "given the states, nats per step (the sum over held-out trajectories over their steps). R-hat and "
              "ESS are ArviZ's, of the label-invariant scalars (log joint, number of skills, number of switches).",
              ""]
    return "\n".join(lines)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], allow_abbrev=False)
    parser.add_argument("--json", metavar="PATH",
                        help="write (or update) the rows here (default: benchmarks/results/bench_worlds.json; "
                             "--quick needs a PATH of its own)")
    parser.add_argument("--worlds", default=",".join(WORLD_NAMES),
                        help=f"comma-separated worlds to run (default: {','.join(WORLD_NAMES)})")
    parser.add_argument("--quick", action="store_true", help="tiny worlds and short fits (a smoke test)")
    parser.add_argument("--seed", type=int, default=0, help="the worlds' seed (default 0)")
    parser.add_argument("--note", help="a line about this run (what library version, what load), kept in the "
                                       "JSON's meta and printed under the markdown's heading")
    parser.add_argument("--fit-options", default="{}", metavar="JSON",
                        help="the fitted model's options: fit's keyword arguments and its config's names, "
                             "e.g. '{\"switching\": \"state\", \"num_chains\": 2}'")
    parser.add_argument("--cache", action="store_true",
                        help="keep JAX's persistent compilation cache on (npbrs's folder); by default it is off, so "
                             "every fit compiles as on a new machine and wall times and peak memory compare across "
                             "runs (a warm cache hid a fit's compile and about 1 GB of its peak memory)")
    parser.add_argument("--child", metavar="WORLD", help=argparse.SUPPRESS)  # one world in this process
    args = parser.parse_args(argv)
    if args.json is None:
        if args.quick:
            parser.error("--quick: give --json PATH (the default file holds the measurement)")
        args.json = DEFAULT_JSON
    if not args.cache:
        os.environ["NPBRS_CACHE_DIR"] = "off"  # (the world processes inherit it)
    try:
        options = json.loads(args.fit_options)
    except json.JSONDecodeError as e:
        parser.error(f"--fit-options: not JSON ({e})")
    if not isinstance(options, dict):
        parser.error("--fit-options: expected a JSON object of fit's keyword arguments and config names")

    if args.child:
        row = run_world(args.child, args.seed, args.quick, options)
        with open(args.json, "w") as f:
            json.dump(row, f)
        return 0

    worlds = [w.strip() for w in args.worlds.split(",") if w.strip()]
    unknown = [w for w in worlds if w not in WORLD_NAMES]
    if unknown or not worlds:
        parser.error(f"--worlds: unknown world(s) {', '.join(unknown) or '(none given)'}; "
                     f"expected some of {', '.join(WORLD_NAMES)}")
    rows, meta = {}, {}
    if os.path.exists(args.json):
        with open(args.json) as f:
            old = json.load(f)
        rows = {k: v for k, v in old.items() if k in WORLD_NAMES}
        meta = old.get("meta", {})
    started = _now()
    print(f"[{started}] bench_worlds: {', '.join(worlds)}{' (quick)' if args.quick else ''}; seed {args.seed}")
    print(UNKNOWN_LOAD, flush=True)
    failed = []
    for name in worlds:
        with tempfile.TemporaryDirectory() as tmp:
            out = os.path.join(tmp, "row.json")
            command = [sys.executable, os.path.abspath(__file__), "--child", name, "--json", out,
                       "--seed", str(args.seed), "--fit-options", json.dumps(options)] + (["--quick"] if args.quick else [])
            start = time.perf_counter()
            code = subprocess.call(command)
            if code != 0 or not os.path.exists(out):
                print(f"[{_now()}] {name}: FAILED (exit status {code})", flush=True)
                failed.append(name)
                continue
            with open(out) as f:
                rows[name] = json.load(f)
            print(f"[{_now()}] {name}: done in {time.perf_counter() - start:.0f} s", flush=True)
    meta.update({"started": meta.get("started", started) if set(rows) - set(worlds) else started,
                 "finished": _now(), "machine": f"{platform.node()}, {os.cpu_count()} CPUs, {platform.platform()}",
                 "python": sys.version.split()[0], "seed": args.seed, "note": UNKNOWN_LOAD,
                 "processor": processor(), "command": " ".join([os.path.basename(sys.executable), *sys.argv])})
    meta.pop("run_note", None)  # a note describes the run that passes it
    meta["persistent_cache"] = bool(args.cache)
    if args.note:
        meta["run_note"] = args.note
    try:
        import jax
        import numpyro

        meta.update({"jax": jax.__version__, "numpyro": numpyro.__version__})
    except ImportError:  # pragma: no cover
        pass
    text = markdown(rows, meta)
    print(text)
    os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
    with open(args.json, "w") as f:
        json.dump({"meta": meta, **{k: rows[k] for k in WORLD_NAMES if k in rows}}, f, indent=1)
    with open(os.path.splitext(args.json)[0] + ".md", "w") as f:
        f.write(text)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
