"""Command line: ``tlsjax demo | simulate | calibrate | extract-planes | montecarlo | compare |
design``.

Every subcommand is a thin layer over the public API. Bad input is reported as one line
naming the file, line, scan, target or parameter (exit code 2); a calibration that fails
(non-convergence, rank defect) exits with 1 after writing what it has.
"""

from __future__ import annotations

import argparse
import os
import sys

from ._calibrate import add_calibrate_parser
from ._common import EXIT_BAD_INPUT
from ._compare import add_compare_parser
from ._design import add_design_parser
from ._extract import add_extract_parser
from ._montecarlo import add_montecarlo_parser
from ._simulate import add_demo_parser, add_simulate_parser


def _enable_compilation_cache():
    # Compiling the adjustment costs seconds; the CLI is run again and again on the same
    # shapes, so JAX's persistent cache pays (PERFORMANCE.md).
    import jax

    path = os.environ.get(
        "TLSJAX_CACHE_DIR", os.path.join(os.path.expanduser("~"), ".cache", "tlsjax", "jax")
    )
    if path.lower() in ("", "0", "off", "none"):
        return
    try:
        os.makedirs(path, exist_ok=True)
        jax.config.update("jax_compilation_cache_dir", path)
    except OSError:
        pass


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="tlsjax", description="Terrestrial laser scanner self-calibration in JAX."
    )
    sub = ap.add_subparsers(dest="command", required=True)
    for add in (
        add_demo_parser,
        add_simulate_parser,
        add_calibrate_parser,
        add_extract_parser,
        add_montecarlo_parser,
        add_compare_parser,
        add_design_parser,
    ):
        add(sub)
    return ap


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    _enable_compilation_cache()
    try:
        return args.func(args)
    except ValueError as exc:
        print(f"tlsjax {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except FileNotFoundError as exc:
        print(f"tlsjax {args.command}: error: {exc.filename}: no such file", file=sys.stderr)
        return EXIT_BAD_INPUT
    except ImportError as exc:
        # Optional dependencies (open3d, pye57) are named in the message.
        print(f"tlsjax {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
