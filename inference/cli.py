"""The ``npbrs`` command line."""

import argparse
import sys


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="npbrs", description="Nonparametric Bayesian reward segmentation")
    sub = parser.add_subparsers(dest="command", required=True)
    from . import cli_generate

    cli_generate.add_parser(sub)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
