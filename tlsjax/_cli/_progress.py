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
        self.held = None

    def hold(self) -> None:
        """Keep the lines until :meth:`release`: input that is refused then gets its one error
        line on stderr and nothing else (the CLI's contract)."""
        self.held = []

    def release(self) -> None:
        held, self.held = self.held or [], None
        for line in held:
            self._line(line, stamped=True)

    def _line(self, text: str, stamped: bool = False) -> None:
        if not self.enabled:
            return
        line = text if stamped else f"[{time.perf_counter() - self.t0:7.1f} s] {text}"
        if self.held is not None:
            self.held.append(line)
        else:
            print(line, file=self.stream, flush=True)

    def start(self, text: str) -> None:
        self.t_phase = time.perf_counter()
        self._line(f"{text} ...")

    def done(self, text: str = "done") -> None:
        self._line(f"{text} ({time.perf_counter() - self.t_phase:.1f} s)")

    def note(self, text: str) -> None:
        self._line(text)
