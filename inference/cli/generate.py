"""``npbrs generate``: write demonstrations of a registered domain to an ``.npz`` file."""

from __future__ import annotations

import argparse

from npbrs.domains.demos import generate_demonstrations
from npbrs.domains.registry import DOMAINS, get_domain

from ..analysis.metrics import num_switches
from .arguments import at_least

__all__ = ["add_parser", "generate_command"]


def _probability(text: str) -> float:
    value = float(text)
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"must lie in [0, 1], got {value}")
    return value


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``generate`` subcommand to an ``add_subparsers()`` object."""
    parser = subparsers.add_parser(
        "generate", help="generate expert demonstrations with random skill switches",
        description="Generate demonstrations as in the paper's section IV-A: optimal experts, one per skill, "
                    "switching skill with a fixed probability per step; the true skills are saved.")
    parser.add_argument("domain", choices=sorted(DOMAINS), help="the domain")
    parser.add_argument("--trajectories", type=at_least(1), default=16, help="number of trajectories (16)")
    parser.add_argument("--length", type=at_least(2), default=500, help="steps per trajectory (500)")
    parser.add_argument("--switch-prob", type=_probability, default=0.02,
                        help="probability of switching skill after each step (0.02)")
    parser.add_argument("--seed", type=int, default=0, help="random seed (0)")
    parser.add_argument("-o", "--output", default="demos.npz", help="output file (demos.npz)")
    parser.set_defaults(func=generate_command)
    return parser


def generate_command(args) -> int:
    domain = get_domain(args.domain)
    demos = generate_demonstrations(domain, num_trajectories=args.trajectories, length=args.length,
                                    switch_prob=args.switch_prob, seed=args.seed)
    demos.save(args.output)
    print(f"wrote {demos.num_trajectories} trajectories of {args.length} steps of {domain.name} to {args.output} "
          f"({num_switches(demos.skills):.2f} skill switches per trajectory; fingerprint {demos.fingerprint()[:12]})")
    return 0
