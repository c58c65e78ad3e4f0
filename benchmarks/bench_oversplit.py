"""Is over-splitting the posterior's preference or the sampler's failure to mix?

On the paper's domains (16 trajectories of 500 steps, 3 true skills), each seed's
demonstrations are fitted twice with the same sampler settings: from the default start
(random windows) and from the true segmentation (``fit(init_segmentation=...)``). For each
start it prints the skills of the best draw, its Hungarian accuracy, and the mean and
maximum log joint over the sampling sweeps. When the chain started at the truth keeps 3
skills with a log joint at least as high as the default start's, the extra skills of the
default start are a mixing failure, not what the posterior prefers.

    python benchmarks/bench_oversplit.py --domain quadcopter --seeds 0 1 2 [--chains 1]
        [--warmup 20] [--samples 20] [--moves '{"split_merge": 1}'] [--starts default truth]
        [--json PATH]

writes the rows, with the command and the machine, to ``--json PATH`` (default
``benchmarks/results/bench_oversplit.json``).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from runinfo import run_info  # noqa: E402


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--domain", choices=("highway", "quadcopter"), default="quadcopter")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--chains", type=int, default=1)
    parser.add_argument("--warmup", type=int, default=20)
    parser.add_argument("--samples", type=int, default=20)
    parser.add_argument("--moves", type=json.loads, default=None, help="the kernel's moves, as JSON")
    parser.add_argument("--starts", nargs="+", choices=("default", "truth"), default=["default", "truth"],
                        help="which starts to fit from")
    parser.add_argument("--json", metavar="PATH", help="write the rows as JSON (default: benchmarks/results/bench_oversplit.json)",
                        default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "bench_oversplit.json"))
    args = parser.parse_args(argv)

    from npbrs.domains.demos import generate_demonstrations
    from npbrs.inference import fit
    from npbrs.inference.analysis.metrics import hungarian_accuracy

    if args.domain == "highway":
        from npbrs.domains.highway import highway as make
    else:
        from npbrs.domains.quadcopter import quadcopter as make
    domain = make()
    rows = []
    print(f"{args.domain}: {args.chains} chain(s) x ({args.warmup} + {args.samples}) sweeps, moves {args.moves}")
    print(f"{'seed':>4} {'start':>8} {'skills':>6} {'hungarian':>9} {'mean log joint':>15} {'max log joint':>14} "
          f"{'wall':>7}  skill sizes")
    for seed in args.seeds:
        demos = generate_demonstrations(domain, num_trajectories=16, length=500, seed=seed)
        for start, init in (("default", None), ("truth", demos.skills)):
            if start not in args.starts:
                continue
            t = time.perf_counter()
            config = {"max_skills": 8, **({"moves": args.moves} if args.moves is not None else {})}
            result = fit(domain.mdp, demos, config, num_chains=args.chains, num_warmup=args.warmup,
                         num_samples=args.samples, seed=seed, init_segmentation=init, progress_bar=False)
            wall = time.perf_counter() - t
            lj = np.asarray(result.stats["log_joint"])
            sizes = sorted((int(sum(np.sum(np.asarray(s) == k) for s in result.segmentation))
                            for k in range(result.num_skills)), reverse=True)
            row = {"seed": seed, "start": start, "skills": int(result.num_skills),
                   "hungarian": float(hungarian_accuracy(demos.skills, result.segmentation)),
                   "mean_log_joint": float(lj.mean()), "max_log_joint": float(lj.max()), "wall_s": wall,
                   "sizes": sizes}
            rows.append(row)
            print(f"{seed:>4} {start:>8} {row['skills']:>6} {row['hungarian']:>9.3f} {row['mean_log_joint']:>15.1f} "
                  f"{row['max_log_joint']:>14.1f} {wall:>6.0f}s  {sizes}", flush=True)
    if args.json:
        os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
        with open(args.json, "w") as f:
            json.dump({"meta": run_info(), "domain": args.domain, "chains": args.chains, "warmup": args.warmup,
                       "samples": args.samples, "moves": args.moves, "rows": rows}, f, indent=1)
    return rows


if __name__ == "__main__":
    sys.exit(0 if main() is not None else 1)
