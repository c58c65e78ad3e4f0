"""What the commands share: argument types, the choice of MDP, and the form of a usage error."""

from __future__ import annotations

import argparse
import sys

__all__ = ["at_least", "device_count", "add_world_arguments", "load_world_mdp", "command_error"]


def at_least(minimum: int):
    """An argparse type: an integer of at least ``minimum`` (the commands' counts and seeds)."""

    def parse(text: str) -> int:
        value = int(text)
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be at least {minimum}, got {value}")
        return value

    return parse


def device_count(text: str):
    """An argparse type: a number of devices (at least 1) or ``all``."""
    if text == "all":
        return text
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number of devices or 'all', got {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1 device, got {value}")
    return value


def add_world_arguments(p, what: str = "the demonstrations live in"):
    """The required choice of MDP: ``--domain NAME`` or ``--mdp FILE``."""
    world = p.add_mutually_exclusive_group(required=True)
    world.add_argument("--domain", help=f"a registered domain whose MDP {what}")
    world.add_argument("--mdp", help=f"an MDP file {what} (.npz: successors, probs, features, feature_names, "
                                     "discount[, initial, state_vectors, name])")


def load_world_mdp(args):
    """The MDP named by ``--domain`` or ``--mdp``."""
    from ..driver.runs import load_mdp

    if args.mdp is not None:
        return load_mdp(args.mdp)
    from npbrs.domains.registry import get_domain

    return get_domain(args.domain).mdp


def command_error(command: str, message) -> int:
    """Print ``npbrs COMMAND: error: MESSAGE`` to stderr; the exit status of a usage error (2)."""
    print(f"npbrs {command}: error: {message}", file=sys.stderr)
    return 2
