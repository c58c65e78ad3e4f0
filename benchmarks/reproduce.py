"""Reproduce the paper's Figure 7 (highway) or Figure 10 (quadcopter) table and the Figure 4/9
segmentation plots, writing them to ``benchmarks/results/``.

    python benchmarks/reproduce.py [--domain highway|quadcopter] [--length 128|500] [--runs 10]
        [--trajectories 16] [--methods npbrs subgoal irl lds] [--resume] [--quick]
        [--json PATH] [--markdown PATH] [--plots DIR]

By default it writes benchmarks/results/{domain}-{length}.json and .md (after every run, so a
stopped reproduction keeps its finished runs; ``--resume`` continues it) and the per-run
segmentation plots to benchmarks/results/{domain}-{length}/. The same as ``npbrs reproduce``,
with those default outputs; see :mod:`npbrs.inference.cli.reproduce` for what is measured.
"""

from __future__ import annotations

import argparse
import os
import sys

from npbrs.inference.cli.reproduce import configure_parser

RESULTS = os.path.join(os.path.dirname(os.path.abspath(__file__)), "results")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="benchmarks/reproduce.py", description=__doc__.split("\n\n")[0])
    configure_parser(parser, default_output=os.path.relpath(RESULTS))
    args = parser.parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
