"""How many sweeps the BP-HMM sampler needs to recover planted reward skills, with and without
its trans-dimensional moves.

Three corner-seeking reward skills in a 4 x 4 gridworld (``tests/gridworld.py``), 6
demonstrations of 60 steps; every chain starts over-segmented (5 skills on random windows; ``--init-skills 1``: one skill).
For each move setting, 8 chains run 40 sweeps; a chain has *recovered* the skills at the first
sweep where it uses at most 3 skills and labels at least 90% of the steps correctly under
one-to-one matching. Prints, per setting, the sweeps each chain needed (41: not within 40),
their median, the skills each chain ends with, and the wall time (compilation included);
``--json PATH`` (default ``benchmarks/results/bench_moves.json``) gets the same, with the command
and the machine.

    python benchmarks/bench_moves.py [--seed 0] [--chains 8] [--sweeps 40] [--json PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import jax
import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(__file__), "..", "tests"))
sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from gridworld import gridworld  # noqa: E402

from npbrs.domains.demos import generate_demonstrations  # noqa: E402
from npbrs.domains.util.precision import float64  # noqa: E402
from npbrs.inference.sampler.kernel import BPHMMKernel  # noqa: E402
from npbrs.inference.analysis.metrics import hungarian_accuracy  # noqa: E402
from npbrs.models.emissions import HMMData, make_emission  # noqa: E402
from runinfo import run_info  # noqa: E402

SETTINGS = {"gibbs only": {}, "birth/death 2": {"birth_death": 2}, "split-merge 1": {"split_merge": 1},
            "both": {"birth_death": 2, "split_merge": 1}}


def sweeps_to_recover(data, true, emission, moves, chains, sweeps, seed, init_skills=5):
    kernel = BPHMMKernel(emission, data, max_skills=5, init_skills=init_skills, moves=moves)

    def run(key):
        def body(s, _):
            s = kernel.sweep(s)
            return s, (s.z, s.num_skills)

        return jax.lax.scan(body, kernel.initial_state(key), None, length=sweeps)[1]

    start = time.perf_counter()
    # (npbrs computes in float64 in its own calls only; this script composes the kernel's methods
    # in a program of its own, so it runs that program in npbrs's float64 scope)
    zs, ks = float64(lambda: jax.jit(jax.vmap(run))(jax.random.split(jax.random.PRNGKey(seed), chains)))()
    zs, ks = np.asarray(zs), np.asarray(ks)
    wall = time.perf_counter() - start
    mask = np.asarray(data.mask)
    hits = []
    for c in range(chains):
        hit = sweeps + 1
        for t in range(sweeps):
            seq = [zs[c, t, i][mask[i]] for i in range(mask.shape[0])]
            if ks[c, t] <= 3 and hungarian_accuracy(true, seq) >= 0.9:
                hit = t + 1
                break
        hits.append(hit)
    return hits, ks[:, -1].tolist(), wall


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--chains", type=int, default=8)
    parser.add_argument("--sweeps", type=int, default=40)
    parser.add_argument("--json", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", "bench_moves.json"),
                        help="write the figures here (default: benchmarks/results/bench_moves.json)")
    parser.add_argument("--init-skills", type=int, default=5, help="skills of the initial state (5: over-segmented)")
    parser.add_argument("--settings", nargs="+", choices=list(SETTINGS), default=list(SETTINGS))
    args = parser.parse_args(argv)
    dom = gridworld()
    demos = generate_demonstrations(dom, num_trajectories=6, length=60, switch_prob=0.05, seed=args.seed)
    data = HMMData.from_demonstrations(demos)
    true = [np.asarray(t) for t in demos.skills]
    emission = make_emission("reward", dom.mdp)
    out = {"meta": {**run_info(), "jax": jax.__version__, "seed": args.seed, "chains": args.chains,
                    "sweeps": args.sweeps, "init_skills": args.init_skills}}
    for name in args.settings:
        moves = SETTINGS[name]
        hits, final, wall = sweeps_to_recover(data, true, emission, moves, args.chains, args.sweeps, args.seed,
                                              args.init_skills)
        out[name] = {"moves": moves, "sweeps_to_recover": hits, "median": float(np.median(hits)),
                     "final_skills": final, "wall_s": wall}
        print(f"{name:14s} sweeps to recover {hits}  median {np.median(hits):4.1f}  final skills {final}  "
              f"wall {wall:6.1f} s", flush=True)
    if args.json:
        os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
        with open(args.json, "w") as fh:
            json.dump(out, fh, indent=1)


if __name__ == "__main__":
    main()
