"""Same seed, same draws: fingerprints of fit's draws on the paper's domains and the worlds.

    python benchmarks/same_draws.py --save benchmarks/results/same_draws.json   # record
    python benchmarks/same_draws.py --check benchmarks/results/same_draws.json  # compare

Fits, with fit's defaults and seed 0, the paper's highway and quadcopter (16 trajectories of
500 steps, the reproduction's sampler settings) and the three ``bench_worlds`` worlds (world
seed 0), and records a SHA-256 of every array a run holds (segmentation, skill parameters,
per-draw statistics, samples, each chain's best segmentation, warmup statistics, step counts,
the switching evidence and the restart record; timings excluded). ``--check`` fails, naming
the setups and fields that differ, when the draws are not the recorded ones bit for bit.
``--quick`` uses small data and a few sweeps (a minute); the full set takes about 10 minutes
on 2 cores. Fingerprints are those of one machine type: XLA's CPU code may round differently
on another.
"""

import argparse
import hashlib
import json
import platform
import sys
import time

import numpy as np

SKIP = ("time", "wall", "elapsed", "seconds", "started", "load")


def digest(value, prefix, out):
    """Flatten ``value`` into {path: sha256 of its bytes}; timing fields skipped."""
    if any(s in prefix.rsplit(".", 1)[-1] for s in SKIP):
        return
    if isinstance(value, dict):
        for k in sorted(value, key=str):
            digest(value[k], f"{prefix}.{k}", out)
    elif isinstance(value, (list, tuple)) and any(isinstance(v, (np.ndarray, dict, list, tuple)) for v in value):
        for i, v in enumerate(value):
            digest(v, f"{prefix}[{i}]", out)
    elif value is not None:
        arr = np.asarray(value)
        if arr.dtype == object:
            data = repr(value).encode()
        else:
            data = arr.dtype.str.encode() + str(arr.shape).encode() + np.ascontiguousarray(arr).tobytes()
        out[prefix] = hashlib.sha256(data).hexdigest()[:16]


FIELDS = ("segmentation", "num_skills", "skill_params", "skill_slots", "best_chain", "best_log_joint", "stats",
          "samples", "chain_best_z", "warmup_stats", "step_skill_counts", "switching", "restart", "run_length",
          "truncation")


def setups(quick):
    from npbrs.domains.demos import generate_demonstrations
    from npbrs.domains.registry import get_domain
    from npbrs.domains.worlds import WORLDS

    for name, sweeps in (("highway", 20), ("quadcopter", 15)):
        domain = get_domain(name)
        demos = generate_demonstrations(domain, num_trajectories=4 if quick else 16, length=60 if quick else 500,
                                        switch_prob=0.02, seed=0)
        yield name, domain.mdp, demos, dict(num_chains=4, num_warmup=4 if quick else sweeps,
                                            num_samples=4 if quick else sweeps), {"max_skills": 8}
    quick_sizes = {"tabular_grid": dict(num_trajectories=8, length=60, num_heldout=4),
                   "labyrinth": dict(num_trajectories=20, num_heldout=10),
                   "rooms": dict(num_trajectories=8, min_length=30, max_length=50, num_heldout=4)}
    for name in ("tabular_grid", "labyrinth", "rooms"):
        world = WORLDS[name](seed=0, **(quick_sizes[name] if quick else {}))
        yield name, world.mdp, world.demos, (dict(num_chains=2, num_warmup=8, num_samples=8) if quick else {}), None


def run(quick):
    from npbrs.inference import fit

    out = {}
    for name, mdp, demos, sizes, config in setups(quick):
        start = time.perf_counter()
        result = fit(mdp, demos, config, seed=0, progress_bar=False, **sizes)
        fields = {}
        for f in FIELDS:
            digest(getattr(result, f, None), f, fields)
        out[name] = fields
        print(f"{name}: {len(fields)} fields, {result.num_skills} skills, {time.perf_counter() - start:.0f} s",
              flush=True)
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    group = parser.add_mutually_exclusive_group(required=True)
    group.add_argument("--save", metavar="JSON")
    group.add_argument("--check", metavar="JSON")
    parser.add_argument("--quick", action="store_true", help="small data, a few sweeps")
    args = parser.parse_args(argv)
    mode = "quick" if args.quick else "full"
    got = run(args.quick)
    if args.save:
        try:
            with open(args.save) as f:
                record = json.load(f)
        except FileNotFoundError:
            record = {}
        record[mode] = got
        record.setdefault("machine", {})[mode] = {"platform": platform.platform(), "processor": platform.processor(),
                                                  "python": platform.python_version()}
        record.setdefault("command", {})[mode] = "python benchmarks/same_draws.py --save " + args.save + (
            " --quick" if args.quick else "")
        with open(args.save, "w") as f:
            json.dump(record, f, indent=1, sort_keys=True)
        return 0
    with open(args.check) as f:
        want = json.load(f)[mode]
    bad = [f"{name}.{k}" for name in want for k in sorted(set(want[name]) | set(got.get(name, {})))
           if want[name].get(k) != got.get(name, {}).get(k)]
    print("same draws, bit for bit" if not bad else "DIFFERENT: " + ", ".join(bad))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
