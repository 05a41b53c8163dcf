"""Numpy-only helpers shared by the benchmarks. No JAX here: the scipy peer's child process of
``bench_plane.py`` imports this module and must keep JAX out of its memory figure."""

from __future__ import annotations

import json
import os
import statistics
import time
from pathlib import Path

import numpy as np


def rotations(om, ph, ka):
    """R = R3(kappa) R2(phi) R1(omega), passive (SPEC section 1); (s, 3, 3)."""
    cw, sw, cp, sp_, ck, sk = np.cos(om), np.sin(om), np.cos(ph), np.sin(ph), np.cos(ka), np.sin(ka)
    R = np.empty(om.shape + (3, 3))
    # Rows of R2 R1, then the kappa rotation of the first two.
    r0 = np.stack([cp, sp_ * sw, -sp_ * cw], -1)
    r1 = np.stack([np.zeros_like(cw), cw, sw], -1)
    r2 = np.stack([sp_, -cp * sw, cp * cw], -1)
    R[..., 0, :] = ck[..., None] * r0 + sk[..., None] * r1
    R[..., 1, :] = -sk[..., None] * r0 + ck[..., None] * r1
    R[..., 2, :] = r2
    return R


def stats(times):
    return {
        "median": statistics.median(times),
        "min": min(times),
        "max": max(times),
        "n": len(times),
    }


def loadavg():
    try:
        return list(os.getloadavg())
    except OSError:  # pragma: no cover - not available on this platform
        return None


def write_results(results: dict, path) -> None:
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(results, indent=2, default=str) + "\n")
    print(f"# written {out}")


def timed(fn, repeats: int):
    """Wall time of ``repeats`` calls of ``fn`` (which must block until its result is ready):
    their statistics and the last result."""
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return stats(times), out
