"""Phase lines on stderr for the long commands (dense plane clouds: reading, thinning,
extraction, adjustment), so that a run of minutes shows where it is. stdout keeps the results
alone (it is what scripts parse)."""

from __future__ import annotations

import sys
import time


class Phases:
    """``phases.start("reading x")`` prints ``[  0.0 s] reading x ...`` on stderr;
    ``phases.done("12 points")`` prints the elapsed time of that phase. ``enabled=False``
    prints nothing (``--quiet``)."""

    def __init__(self, enabled: bool = True, stream=None):
        self.enabled = enabled
        self.stream = stream or sys.stderr
        self.t0 = time.perf_counter()
        self.t_phase = self.t0

    def _line(self, text: str) -> None:
        if self.enabled:
            print(f"[{time.perf_counter() - self.t0:7.1f} s] {text}", file=self.stream, flush=True)

    def start(self, text: str) -> None:
        self.t_phase = time.perf_counter()
        self._line(f"{text} ...")

    def done(self, text: str = "done") -> None:
        self._line(f"{text} ({time.perf_counter() - self.t_phase:.1f} s)")

    def note(self, text: str) -> None:
        self._line(text)
