"""The Ceres peer (``benchmarks/ceres/peer.cc``): build it, write its problem files, run it.

No JAX here: the data are numpy arrays that the benchmark prepares with tlsjax.

Problem file (little-endian, written by :func:`write_problem`, read by ``peer.cc``):
``int64[7]`` magic 0x7153A1, scans s, targets t, observations n, APs K, architecture (0 hybrid,
1 panoramic), realisations R; ``float64[2]`` unit lengths U, U2 of the cyclic terms;
``int64[K]`` AP codes (:data:`AP_CODES`); ``int64[n]`` scan and ``int64[n]`` target of every
observation; ``float64[n, 3]`` sigmas (range [m], hz, el [rad], incidence applied);
``float64[s, 2]`` levelling sigmas (inf: not levelled); the start: ``float64[t, 3]`` targets,
``float64[s, 6]`` poses, ``float64[K]`` APs; then per realisation ``float64[R, n, 3]``
observations and ``float64[R, s, 2]`` levelling readings.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
SOURCE = HERE / "ceres" / "peer.cc"
BINARY = HERE / "ceres" / "tlsjax_ceres_peer"
MAGIC = 0x7153A1

#: AP names in the order of the codes of ``peer.cc`` (21 is unused).
AP_CODES = (
    "A0 A1 A2 A3 A4 A5 A6 A7 A8 B1 B2 B3 B4 B5 B6 B7 B8 B9 B10 B11 B12 - "
    "C0 C1 C2 C3 C4 C5 C6 C7 C8 C9 C10"
).split()

#: The compiler command; ``setup_ceres`` runs the same.
COMPILE = [
    "g++",
    "-O3",
    "-march=native",
    "-std=c++17",
    "-I/usr/include/eigen3",
    str(SOURCE),
    "-o",
    str(BINARY),
    "-lceres",
    "-lglog",
    "-lgflags",
    "-lpthread",
]


def build() -> tuple[Path | None, str]:
    """The peer's binary, compiled when missing or older than its source: (path, "") or
    (None, why it cannot be built)."""
    if BINARY.exists() and BINARY.stat().st_mtime >= SOURCE.stat().st_mtime:
        return BINARY, ""
    if shutil.which("g++") is None:
        return None, "no C++ compiler (g++); run benchmarks/setup_ceres"
    if not Path("/usr/include/ceres/ceres.h").exists():
        return None, "Ceres is not installed (libceres-dev); run benchmarks/setup_ceres"
    out = subprocess.run(COMPILE, capture_output=True, text=True)
    if out.returncode:
        return None, "the peer does not compile: " + out.stderr.strip().splitlines()[-1]
    return BINARY, ""


def supported(scanner) -> str:
    """Why the peer cannot model this scanner's APs ("" when it can)."""
    missing = [a for a in scanner.aps if a not in AP_CODES]
    if missing:
        return f"the peer has no basis for {' '.join(missing)}"
    if not 1 <= len(scanner.aps) <= 32:
        return "the peer takes 1 to 32 APs"
    return ""


def write_problem(path, net, scanner, start, observations, levelling) -> None:
    """``start`` = (targets (t, 3), poses (s, 6), APs (K,)); ``observations`` (R, n, 3) and
    ``levelling`` (R, s, 2) of each realisation."""
    targets, eops, aps = (np.asarray(a, dtype=np.float64) for a in start)
    obs = np.asarray(observations, dtype=np.float64).reshape(-1, len(net.observations), 3)
    lev = np.asarray(levelling, dtype=np.float64).reshape(-1, len(net.scans), 2)
    head = [MAGIC, len(net.scans), len(net.targets), len(net.observations), len(scanner.aps)]
    head += [0 if scanner.architecture == "hybrid" else 1, obs.shape[0]]
    parts = [
        np.asarray(head, dtype=np.int64),
        np.asarray([scanner.unit_length, scanner.unit_length_2], dtype=np.float64),
        np.asarray([AP_CODES.index(a) for a in scanner.aps], dtype=np.int64),
        np.asarray(net.scan_index, dtype=np.int64),
        np.asarray(net.target_index, dtype=np.int64),
        np.asarray(net.sigmas, dtype=np.float64),
        np.where(np.isfinite(net.levelling_sigma), net.levelling_sigma, np.inf).astype(np.float64),
        targets,
        eops,
        aps,
        obs,
        lev,
    ]
    with open(path, "wb") as f:
        for p in parts:
            f.write(np.ascontiguousarray(p).tobytes())


def run(binary, mode: str, problem, *, repeats: int = 1, threads: int = 1) -> dict:
    """Run the peer (``mode`` "single" or "mc") and return its JSON: ``wall_s`` (the solve
    times of "single", the whole loop of "mc"), ``results`` (APs, AP covariance, s0^2,
    iterations and linear solves per solve)."""
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "out.json")
        cmd = [str(binary), mode, str(problem), out, "--repeats", str(repeats)]
        cmd += ["--threads", str(threads)]
        proc = subprocess.run(cmd, capture_output=True, text=True)
        if proc.returncode:
            raise RuntimeError(f"Ceres peer failed: {proc.stderr.strip()}")
        with open(out) as f:
            return json.load(f)
