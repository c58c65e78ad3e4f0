"""What the commands share: argument types, the choice of MDP, and the form of a usage error."""

from __future__ import annotations

import argparse
import os
import sys

__all__ = ["at_least", "device_count", "add_world_arguments", "load_world_mdp", "command_error", "output_problem",
           "folder_problem"]


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


def output_problem(path, what: str = "file", overwrite: bool = False) -> str:
    """Why ``path`` cannot be written before a command starts its work ("" when it can): its
    folder does not exist, it is a folder, or it is an existing file and ``overwrite`` is off.

    Args:
        path: the file to write.
        what: what the file is, for the message ("run", "labels file", ...).
        overwrite: whether an existing file may be replaced.
    Returns:
        the message, or "".
    """
    folder = os.path.dirname(os.path.abspath(os.fspath(path)))
    if not os.path.isdir(folder):
        return f"cannot write the {what} {path}: the folder {os.path.dirname(os.fspath(path)) or folder} does not exist"
    if os.path.isdir(path):
        return f"cannot write the {what} {path}: it is a folder"
    if os.path.exists(path) and not overwrite:
        return f"{path} exists; give --overwrite to replace it, or write the {what} elsewhere"
    return ""


def folder_problem(path) -> str:
    """Why the folder ``path`` cannot be made or used for output ("" when it can): its parent
    folder does not exist (one level is made, never a chain of them), or it is a file."""
    parent = os.path.dirname(os.path.abspath(os.fspath(path)))
    if os.path.exists(path) and not os.path.isdir(path):
        return f"{path} is a file, not a folder"
    if not os.path.isdir(parent):
        return f"cannot make the folder {path}: its parent {os.path.dirname(os.fspath(path).rstrip(os.sep)) or parent} " \
               "does not exist"
    return ""


def command_error(command: str, message) -> int:
    """Print ``npbrs COMMAND: error: MESSAGE`` to stderr; the exit status of a usage error (2)."""
    print(f"npbrs {command}: error: {message}", file=sys.stderr)
    return 2
