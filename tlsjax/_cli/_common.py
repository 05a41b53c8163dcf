"""Shared pieces of the command-line handlers."""

from __future__ import annotations

EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT, EXIT_INTERNAL = 0, 1, 2, 3


def scanner_args(p):
    p.add_argument(
        "--architecture",
        choices=("hybrid", "panoramic"),
        default="hybrid",
        help="scanner architecture (default: hybrid)",
    )
    p.add_argument(
        "--unit-length",
        type=float,
        default=1.2,
        metavar="M",
        help="unit length U [m] of the cyclic range terms A3/A4 (default 1.2)",
    )
