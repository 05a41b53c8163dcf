"""Command line: ``tlsjax demo | simulate | calibrate | extract-planes | extract-targets |
correct | report | montecarlo | compare | design | import-targets | check-targets |
field-check``.

Every subcommand is a thin layer over the public API. Bad input is reported as one line
naming the file, line, scan, target or parameter (exit code 2), and so is every file-system
failure (naming the path); a calibration that fails (non-convergence, rank defect, variance
components that stop early) exits with 1 after writing what it has. An unexpected error is one
line too (exit code 3); ``TLSJAX_DEBUG=1`` shows its traceback. Ctrl-C stops a command with
exit code 130 and leaves no half-written file (every output is written to a temporary file and
renamed when complete). A reader that goes away (``tlsjax calibrate ... | head``) only ends
the printing: the command completes, writes its files and exits with its own code.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
import threading
import warnings

import tlsjax as tj

from ._calibrate import add_calibrate_parser
from ._checks import reset_warnings, warn
from ._common import EXIT_BAD_INPUT, EXIT_INTERNAL, use_host_devices
from ._compare import add_compare_parser
from ._correct import add_correct_parser
from ._design import add_design_parser
from ._extract import add_extract_parser
from ._extract_targets import add_targets_parser
from ._field_check import add_field_check_parser
from ._montecarlo import add_montecarlo_parser
from ._report import add_report_parser
from ._simulate import add_demo_parser, add_simulate_parser
from ._targets import add_check_targets_parser, add_import_targets_parser

#: Exit code of a command stopped by Ctrl-C (128 + SIGINT, as shells report it).
EXIT_INTERRUPTED = 130


class _Parser(argparse.ArgumentParser):
    """argparse with a one-line error (the option and why, exit code 2) instead of the usage
    block: the usage is one ``--help`` away, and a long block hides the line that matters."""

    def error(self, message):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    ap = _Parser(prog="tlsjax", description="Terrestrial laser scanner self-calibration in JAX.")
    ap.add_argument("--version", action="version", version=f"tlsjax {tj.__version__}")
    sub = ap.add_subparsers(dest="command", required=True, parser_class=_Parser)
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
        add_field_check_parser,
    ):
        add(sub)
    return ap


def _one_line(text) -> str:
    lines = [x.strip() for x in str(text).splitlines() if x.strip()]
    return lines[0] if lines else ""


def _show_warning(message, category, filename, lineno, file=None, line=None):
    # Warnings of tlsjax (implausible magnitudes, point-cloud notes) are one "warning:" line
    # each, as the commands print their own; others keep Python's format.
    if issubclass(category, (tj.PlausibilityWarning, tj.PointCloudWarning)):
        warn(str(message))
    else:
        sys.stderr.write(warnings.formatwarning(message, category, filename, lineno, line))


class _Reader:
    """A standard stream whose reader may go away (a pipe into ``head``): from the first
    ``BrokenPipeError`` on, what is printed is dropped, so the command completes (its files
    written, its exit code its own) where Python would end it at the next print. The stream's
    descriptor then points to the null device, so that its buffered rest and the interpreter's
    last flush are dropped too (the recipe of Python's documentation, "Note on SIGPIPE")."""

    def __init__(self, stream):
        self._stream, self._gone = stream, False

    def write(self, text):
        if not self._gone:
            try:
                return self._stream.write(text)
            except BrokenPipeError:
                self._drop()
        return len(text)

    def flush(self):
        if not self._gone:
            try:
                self._stream.flush()
            except BrokenPipeError:
                self._drop()

    def _drop(self):
        self._gone = True
        try:
            null = os.open(os.devnull, os.O_WRONLY)
            os.dup2(null, self._stream.fileno())
            os.close(null)
        except (OSError, ValueError, AttributeError):  # a stream without a descriptor
            pass

    def __getattr__(self, name):
        return getattr(self._stream, name)


def main(argv=None) -> int:
    """The ``tlsjax`` command line (arguments ``argv``, default ``sys.argv[1:]``); returns
    the exit code. Standard output and error are read through :class:`_Reader` meanwhile."""
    stdout, stderr = sys.stdout, sys.stderr
    sys.stdout, sys.stderr = _Reader(stdout), _Reader(stderr)
    try:
        return _main(argv)
    finally:
        sys.stdout, sys.stderr = stdout, stderr


def _main(argv) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    args.argv = argv  # the command line, recorded in what a command writes
    if getattr(args, "devices", None):
        use_host_devices(args.devices)
    reset_warnings()
    prefix = f"tlsjax {args.command}: error:"
    try:
        with warnings.catch_warnings():
            warnings.showwarning = _show_warning
            return args.func(args)
    except KeyboardInterrupt:
        # Every output is written to a temporary file and renamed when complete, so an
        # interrupted run leaves the previous files as they were and no half-written one.
        print(
            f"tlsjax {args.command}: interrupted (Ctrl-C); no file was left half-written (an "
            "output not yet complete keeps its previous content)",
            file=sys.stderr,
        )
        return EXIT_INTERRUPTED
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


def console() -> None:
    """The ``tlsjax`` command: :func:`main`, then the process ends without the interpreter's
    teardown. After a calibration that teardown takes about 0.3 s (JAX's backends, the compiled
    programs and every module freed one by one, all of which the operating system reclaims at
    once): a sixth of a re-run's wall time spent after the last line is written. What a normal
    exit would do that matters is done first: our own threads end (e.g. a program still being
    prepared), JAX's pending work completes, logging and the standard streams are flushed;
    every file a command writes is already closed (written to a temporary file and renamed).
    Exit codes as ``sys.exit(main())``; an error escaping ``main`` exits as Python does."""
    try:
        code = main()
    except SystemExit as exc:
        code = exc.code
    if code is None:
        code = 0
    elif not isinstance(code, int):
        print(code, file=sys.stderr)
        code = 1
    _exit_now(code)


def _exit_now(code: int) -> None:
    for thread in threading.enumerate():
        if thread is not threading.current_thread() and not thread.daemon:
            thread.join()
    import jax

    jax.effects_barrier()
    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):  # a closed pipe (``| head``) or stream: nothing to lose
            pass
    os._exit(code)


if __name__ == "__main__":  # pragma: no cover
    console()
