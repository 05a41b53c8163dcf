"""Checks of the command-line options before any work: argparse types for numbers with a
range, options that cannot take effect together, and the cost of a long run stated (or a run
that cannot fit in memory refused) before it starts."""

from __future__ import annotations

import argparse
import math
import os
import sys


def _number(text: str, kind):
    try:
        value = kind(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"{text!r} is not {'an integer' if kind is int else 'a number'}"
        ) from None
    if kind is float and not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number")
    return value


def positive_int(text: str) -> int:
    """argparse type: an integer >= 1."""
    value = _number(text, int)
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text} must be at least 1")
    return value


def non_negative_int(text: str) -> int:
    """argparse type: an integer >= 0 (seeds)."""
    value = _number(text, int)
    if value < 0:
        raise argparse.ArgumentTypeError(f"{text} must be 0 or more")
    return value


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0 (sigmas, lengths, tolerances)."""
    value = _number(text, float)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"{text} must be a positive number")
    return value


def non_negative_float(text: str) -> float:
    """argparse type: a finite number >= 0 (a noise that may be zero)."""
    value = _number(text, float)
    if value < 0:
        raise argparse.ArgumentTypeError(f"{text} must be 0 or more")
    return value


def probability(text: str) -> float:
    """argparse type: a significance level in (0, 1)."""
    value = _number(text, float)
    if not 0 < value < 1:
        raise argparse.ArgumentTypeError(f"{text} must be between 0 and 1 (exclusive)")
    return value


def fraction(text: str) -> float:
    """argparse type: a share in [0, 1] (coverage)."""
    value = _number(text, float)
    if not 0 <= value <= 1:
        raise argparse.ArgumentTypeError(f"{text} must be between 0 and 1")
    return value


def correlation(text: str) -> float:
    """argparse type: an |correlation| threshold in (0, 1]."""
    value = _number(text, float)
    if not 0 < value <= 1:
        raise argparse.ArgumentTypeError(f"{text} must be in (0, 1]")
    return value


def refuse_unless(condition: bool, option: str, needs: str) -> None:
    """One-line ValueError: ``option`` takes effect only with ``needs``."""
    if not condition:
        raise ValueError(f"{option} takes effect only with {needs}; add it or leave {option} out")


# --- the cost of a run, from the problem size -----------------------------------------------

#: Seconds per observation row and per parameter of a row (6 pose parameters + the APs) of
#: one realisation on one CPU device, from the Monte Carlo benchmark (benchmarks/README.md:
#: 1,000 realisations of the 2,168-row Chow room in 1.02 s with 4 APs and 3.17 s with 23 APs
#: on 2 devices, i.e. about 1.0e-7 s per row and parameter).
SECONDS_PER_ROW_PARAMETER = 1.0e-7
#: A run whose estimate is beyond this states its cost before it starts [s].
ANNOUNCE_SECONDS = 120.0


def _duration(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.0f} s"
    if seconds < 7200:
        return f"{seconds / 60:.0f} min"
    if seconds < 2 * 86400:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / 86400:.3g} days"


def _bytes(n: float) -> str:
    for unit, f in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6)):
        if n >= f:
            return f"{n / f:.3g} {unit}"
    return f"{n / 1e3:.3g} kB"


def _memory_available() -> float:
    try:
        return float(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):  # pragma: no cover - not POSIX
        return math.inf


def state_cost(
    what: str,
    option: str,
    count: int,
    *,
    rows: int,
    parameters: int,
    devices: int,
    result_bytes: float,
    usual: str,
    out=None,
) -> float:
    """Estimate the time of ``count`` repetitions of an adjustment of ``rows`` observation rows
    with ``parameters`` per row, on ``devices`` devices, and the memory of their results
    (``result_bytes`` each). A run whose results cannot fit in the memory available is refused
    (ValueError naming ``option``); one that takes longer than :data:`ANNOUNCE_SECONDS` says
    so on ``out`` (stdout) before it starts. Returns the estimate [s]."""
    seconds = count * rows * parameters * SECONDS_PER_ROW_PARAMETER / max(devices, 1)
    memory = count * result_bytes
    if memory > 0.8 * _memory_available():
        raise ValueError(
            f"{option} {count}: {what} would hold {_bytes(memory)} of results (more than the "
            f"{_bytes(_memory_available())} of memory available) and run about "
            f"{_duration(seconds)}; use fewer ({usual})"
        )
    if seconds > ANNOUNCE_SECONDS:
        print(
            f"cost: {what} ({count:,} x {rows:,} observation rows x {parameters} parameters) "
            f"will take about {_duration(seconds)} on {devices} device(s) after compiling, and "
            f"{_bytes(memory)} for the results; Ctrl-C stops it cleanly (no file is written)",
            file=out or sys.stdout,
            flush=True,
        )
    return seconds


# --- warnings -------------------------------------------------------------------------------

_printed: set = set()


def reset_warnings() -> None:
    """Forget the warnings printed (one command run in a process that runs several)."""
    _printed.clear()


def warn(text: str) -> None:
    """Print ``warning: text`` on stderr, once per command run."""
    if text not in _printed:
        _printed.add(text)
        print(f"warning: {text}", file=sys.stderr, flush=True)
