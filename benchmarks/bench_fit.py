"""Where a fit's time goes: compiling against sampling, and what a second dataset costs.

In one process (JAX's persistent compilation cache off, so every program compiles as on a new
machine, unless ``--cache``):

- ``import_s``: ``import npbrs.inference`` (and the domains);
- ``tiny``: highway, 8 trajectories x 128 steps, 2 chains, 20 + 20 sweeps, the reward emission
  with ``fit``'s other defaults: the first fit (``first_total_s``, ``first_compile_s``,
  ``first_sweep_ms``), a second dataset of the same shapes (``second_total_s``,
  ``second_compile_s``) and a dataset of other sizes in the same shape bucket, 8 x 115
  (``bucket_total_s``, ``bucket_compile_s``); these three fits pad to shape buckets
  (``bucket=True``); ``unbucketed_*``: the 8 x 115 data again without buckets (it compiles);
- ``highway500`` and ``quadcopter500``: 16 x 500 steps, 4 chains, the reproduction's sweeps for
  NPBRS (20 + 20 highway, 15 + 15 quadcopter), ``fit``'s other defaults: ``total_s``,
  ``compile_s``, ``sweep_ms``, with the skills found and the accuracy.

``compile_s`` is the wall time during which JAX reports tracing, lowering or compiling (its
monitoring events) during the fit: the union of those events' intervals, since the sweep
compiles on a thread of its own beside the initial state (``compile_sum_s`` is their sum,
larger when they overlap); ``sweep_ms`` = (total - compile) / sweeps (all chains sweep
together, on the chains' threads by ``fit``'s default ``chain_method="auto"`` on a CPU).

    python benchmarks/bench_fit.py [--json benchmarks/results/bench_fit.json] [--only tiny] [--cache]
        [--note "what else was running"]

Times are absolute wall-clock seconds on the machine that runs this; the JSON records the load
average before and after each part and ``--note``.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from datetime import datetime, timezone

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from runinfo import run_info  # noqa: E402


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--json", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "bench_fit.json"),
                   help="where to write the figures (JSON; default: benchmarks/results/bench_fit.json)")
    p.add_argument("--only", default="tiny,highway500,quadcopter500",
                   help="comma-separated parts: tiny, highway500, quadcopter500")
    p.add_argument("--cache", action="store_true", help="keep JAX's persistent cache on (npbrs's folder)")
    p.add_argument("--note", default="", help="what else was running on the machine")
    p.add_argument("--reference", default="", metavar="METHOD",
                   help="also fit highway500 and quadcopter500 with this chain_method (e.g. vectorized) after "
                        "the default's fit, and print the ratio")
    args = p.parse_args(argv)
    if not args.cache:
        os.environ["NPBRS_CACHE_DIR"] = "off"
    parts = [s.strip() for s in args.only.split(",") if s.strip()]

    start = time.perf_counter()
    import jax
    from jax._src.dispatch import BACKEND_COMPILE_EVENT, JAXPR_TO_MLIR_MODULE_EVENT, JAXPR_TRACE_EVENT

    import npbrs.inference  # noqa: F401
    from npbrs.domains import generate_demonstrations, highway, quadcopter
    from npbrs.inference import fit, hungarian_accuracy
    out = {"meta": {**run_info(), "date": datetime.now(timezone.utc).isoformat(timespec="seconds"),
                    "jax": jax.__version__, "machine": platform.platform(), "cpus": os.cpu_count(),
                    "cache": bool(args.cache), "note": args.note},
           "import_s": round(time.perf_counter() - start, 2)}
    print(f"import: {out['import_s']:.1f} s", flush=True)

    intervals = []  # (start, end) of every tracing, lowering and compiling event

    def listen(event, duration, **_):
        if event in (BACKEND_COMPILE_EVENT, JAXPR_TRACE_EVENT, JAXPR_TO_MLIR_MODULE_EVENT):
            end = time.perf_counter()
            intervals.append((end - duration, end))

    def union(spans) -> float:
        total, reach = 0.0, float("-inf")
        for a, b in sorted(spans):
            if b > reach:
                total += b - max(a, reach)
                reach = b
        return total

    jax.monitoring.register_event_duration_secs_listener(listen)

    def timed(domain, demos, chains, warmup, samples, **config):
        intervals.clear()
        load = os.getloadavg()[0]
        t = time.perf_counter()
        result = fit(domain.mdp, demos, config or None, num_chains=chains, num_warmup=warmup, num_samples=samples,
                     seed=0, progress_bar=False)
        total = time.perf_counter() - t
        sweeps = warmup + samples
        compiling = union(intervals)
        row = {"total_s": round(total, 2), "compile_s": round(compiling, 2),
               "compile_sum_s": round(sum(b - a for a, b in intervals), 2),
               "sweep_ms": round(1000 * max(total - compiling, 0.0) / sweeps, 1), "skills": result.num_skills,
               "hungarian": round(float(hungarian_accuracy(demos.skills, result.segmentation)), 4),
               "load_before": round(load, 2), "load_after": round(os.getloadavg()[0], 2)}
        return row

    if "tiny" in parts:
        dom = highway()
        rows = {}
        runs = {"first": (8, 128, 0, True), "second": (8, 128, 1, True), "bucket": (8, 115, 2, True),
                "unbucketed": (8, 115, 2, False)}
        for name, (n, length, seed, bucket) in runs.items():
            demos = generate_demonstrations(dom, num_trajectories=n, length=length, seed=seed)
            rows[name] = timed(dom, demos, 2, 20, 20, bucket=bucket)
            print(f"tiny {name} ({n} x {length}): {rows[name]}", flush=True)
        out["tiny"] = {"first_total_s": rows["first"]["total_s"], "first_compile_s": rows["first"]["compile_s"],
                       "first_sweep_ms": rows["first"]["sweep_ms"], "second_total_s": rows["second"]["total_s"],
                       "second_compile_s": rows["second"]["compile_s"], "bucket_total_s": rows["bucket"]["total_s"],
                       "bucket_compile_s": rows["bucket"]["compile_s"],
                       "unbucketed_total_s": rows["unbucketed"]["total_s"],
                       "unbucketed_compile_s": rows["unbucketed"]["compile_s"], "runs": rows}
    for name, make, sweeps in (("highway500", highway, 20), ("quadcopter500", quadcopter, 15)):
        if name not in parts:
            continue
        dom = make()
        demos = generate_demonstrations(dom, num_trajectories=16, length=500, seed=0)
        out[name] = timed(dom, demos, 4, sweeps, sweeps)
        print(f"{name}: {out[name]}", flush=True)
        if args.reference:  # (its programs are other programs: it compiles as the default's fit did)
            ref = out[name]["reference"] = dict(timed(dom, demos, 4, sweeps, sweeps, chain_method=args.reference),
                                                chain_method=args.reference)
            out[name]["ratio_to_reference"] = round(out[name]["total_s"] / ref["total_s"], 3)
            print(f"{name} with chain_method={args.reference!r}: {ref}; the default's time / its: "
                  f"{out[name]['ratio_to_reference']:.3f}", flush=True)

    os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
    with open(args.json, "w") as f:
        json.dump(out, f, indent=2)
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
