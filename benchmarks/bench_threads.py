"""The ``--threads`` option the benchmarks here take: torch threads, default 1.

On this project's shared 2-core CPU more threads made steps far slower (thread hand-offs
with other jobs), so every benchmark runs one torch thread unless told otherwise.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence

import torch

THREADS_HELP = (
    "torch threads (default 1: one per job; on a shared 2-core CPU more made steps far slower)"
)


def add_threads_argument(parser: argparse.ArgumentParser) -> None:
    """Adds ``--threads`` to ``parser``."""
    parser.add_argument("--threads", type=int, default=1, help=THREADS_HELP)


def parse_with_threads(
    parser: argparse.ArgumentParser, argv: Sequence[str] | None = None
) -> argparse.Namespace:
    """Parses ``argv`` and sets torch's thread count to ``--threads``."""
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    return args
