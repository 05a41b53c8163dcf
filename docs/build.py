"""Build the documentation site and run its examples, in one Python process.

``python docs/build.py [OUT]`` (default ``out/docs``) writes ``OUT/html/index.html`` and runs
every example of the pages and docstrings (``sphinx.ext.doctest``), both with warnings as
errors (``-W --keep-going``) and nitpicky references. The doctest builder reuses the HTML
build's parsed pages (same doctree folder), and both share this process's compiled JAX
programs, so each program compiles once. Exit status 0 only when both pass.
"""

import os
import pathlib
import sys
import time

os.environ.setdefault("JAX_PLATFORMS", "cpu")
# Compiling dominates the examples' time: they compile with the test suite's quick-compile
# flags (no backend optimisation, tlsjax's code generators; tlsjax._jit.QUICK_COMPILE_FLAGS),
# which change no result beyond rounding. Added to flags already set (a device count, say),
# unless the caller named them.
from tlsjax._jit import quick_compile_flags  # noqa: E402

os.environ["XLA_FLAGS"] = quick_compile_flags(os.environ.get("XLA_FLAGS", ""))

from sphinx.cmd.build import build_main  # noqa: E402

DOCS = pathlib.Path(__file__).resolve().parent


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    out = pathlib.Path(argv[0] if argv else DOCS.parent / "out" / "docs").resolve()
    common = ["-W", "--keep-going", "-n", "-q", "-d", str(out / "doctrees"), str(DOCS)]
    for builder in ("html", "doctest"):
        t0, c0 = time.perf_counter(), time.process_time()
        # A fresh read for the HTML build (-E): an incremental one would not repeat the warnings
        # of unchanged pages; the doctest build then reuses what it read.
        fresh = ["-E"] if builder == "html" else []
        rc = build_main(["-b", builder, *fresh, *common, str(out / builder)])
        print(
            f"docs: {builder} {'ok' if rc == 0 else 'FAILED'} in {time.perf_counter() - t0:.1f} s "
            f"({time.process_time() - c0:.1f} CPU s)"
        )
        if rc:
            return rc
    print(f"docs: open {out / 'html' / 'index.html'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
