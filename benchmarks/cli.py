"""Command-line helper shared by the benchmark scripts."""
from __future__ import annotations


def split_passthrough(argv: list[str]) -> tuple[list[str], list[str]]:
    """`[own options..., "--", passed...]` -> (own options, passed); without "--" nothing is passed.

    The benchmarks hand everything after the first "--" to train.py (or the trainer) unread."""
    if "--" not in argv:
        return list(argv), []
    cut = argv.index("--")
    return list(argv[:cut]), list(argv[cut + 1:])
