"""The ``npbrs`` command line: ``main`` and its commands (generate, fit, report, segment, score, compare, demo, reproduce)."""

from .main import build_parser, compilation_cache_dir, main
