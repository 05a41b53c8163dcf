"""Command line: ``tlsjax demo | simulate | calibrate | extract-planes | extract-targets |
correct | report | montecarlo | compare | design | import-targets | check-targets``.

Every subcommand is a thin layer over the public API. Bad input is reported as one line
naming the file, line, scan, target or parameter (exit code 2), and so is every file-system
failure (naming the path); a calibration that fails (non-convergence, rank defect, variance
components that stop early) exits with 1 after writing what it has. An unexpected error is one
line too (exit code 3); ``TLSJAX_DEBUG=1`` shows its traceback.
"""

from __future__ import annotations

import argparse
import os
import sys

from .._version import __version__
from ._calibrate import add_calibrate_parser
from ._common import EXIT_BAD_INPUT, EXIT_INTERNAL, use_host_devices
from ._compare import add_compare_parser
from ._correct import add_correct_parser
from ._design import add_design_parser
from ._extract import add_extract_parser
from ._extract_targets import add_targets_parser
from ._montecarlo import add_montecarlo_parser
from ._report import add_report_parser
from ._simulate import add_demo_parser, add_simulate_parser
from ._targets import add_check_targets_parser, add_import_targets_parser


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
    ap.add_argument("--version", action="version", version=f"tlsjax {__version__}")
    sub = ap.add_subparsers(dest="command", required=True)
    for add in (
        add_demo_parser,
        add_simulate_parser,
        add_calibrate_parser,
        add_extract_parser,
        add_targets_parser,
        add_correct_parser,
        add_report_parser,
        add_montecarlo_parser,
        add_compare_parser,
        add_design_parser,
        add_import_targets_parser,
        add_check_targets_parser,
    ):
        add(sub)
    return ap


def _one_line(text) -> str:
    lines = [x.strip() for x in str(text).splitlines() if x.strip()]
    return lines[0] if lines else ""


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    if getattr(args, "devices", None):
        use_host_devices(args.devices)
    _enable_compilation_cache()
    prefix = f"tlsjax {args.command}: error:"
    try:
        return args.func(args)
    except ValueError as exc:
        print(f"{prefix} {_one_line(exc)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except FileNotFoundError as exc:
        print(f"{prefix} {exc.filename}: no such file", file=sys.stderr)
        return EXIT_BAD_INPUT
    except OSError as exc:
        # Any other file-system failure (a directory, no permission, a full disk): one line.
        where = exc.filename if exc.filename is not None else "file system"
        print(f"{prefix} {where}: {exc.strerror or exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except ImportError as exc:
        # Optional dependencies (open3d, pye57) are named in the message.
        print(f"{prefix} {_one_line(exc)}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except Exception as exc:
        if os.environ.get("TLSJAX_DEBUG"):
            raise
        print(
            f"tlsjax {args.command}: internal error: {type(exc).__name__}: {_one_line(exc)} "
            "(please report it; TLSJAX_DEBUG=1 shows the traceback)",
            file=sys.stderr,
        )
        return EXIT_INTERNAL


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
