"""Target extraction on a 10-million-point scan: time and peak memory (issue 33).

Usage::

    python benchmarks/bench_targets.py [--points 10e6] [--out benchmarks/results/targets.json]
                                       [--scan /tmp/tlsjax_bench_targets.ply] [--keep]

Scan: one levelled scan from the first station of the simulated Chow room (14 x 11 x 3 m,
hybrid scanner, APs A0 B6 B7 C0 at SPEC section 8's values, 0.5 mm / 20" noise) with a random
field of targets (``tj.place_targets``: 10 spheres of 72.5 mm, 10 checkerboards and 4 circles
of 15 cm, seed 0), on one angular grid whose step gives ``--points`` points (0.067 deg for
10 million: 12 mm at 10 m), rendered chunk by chunk with the simulator's own ray cast and
written as E57 (pye57: single-precision x, y, z in the scanner frame and intensity; a
``--scan`` ending in .ply writes a binary PLY instead, which is memory-mapped when read, so that
the pages read count in the process's resident memory).

Timed (``tj.extract_targets_from_files`` with spheres, checkerboards and circles, streamed in
chunks of 2^20 points): a first call (includes compiling the fits) and a second call in the
same process, wall and CPU seconds (the CPU figure is the one to compare on a shared machine);
the peak resident memory of that process (VmHWM of /proc/self/status, JAX's own 0.3 GB
included). Beside
it, in its own process, the peak memory of reading the same scan whole with
``tj.read_point_clouds`` (what a non-streamed extraction would start from). The accepted
centres are compared with the simulation's truth (noise-free observation of each centre with
the APs applied): the error per kind (median and largest, mm).

Each part runs in its own child process (``--child data|extract|load``), so that each peak is
its own. JAX_PLATFORMS defaults to cpu.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import loadavg, write_results  # noqa: E402

HERE = Path(__file__).resolve().parent


def _vmhwm_mb() -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def _design(points):
    import tlsjax as tj

    lo, hi = -40.0, 85.0
    step = np.sqrt(360.0 * (hi - lo) / points)
    targets = tj.place_targets(spheres=10, checkerboards=10, circles=4, seed=0)
    return tj.CloudDesign(
        angular_step=float(np.radians(step)), tilted=False, elevation_limits=(np.radians(lo), np.radians(hi)),
        **targets,
    ), step  # fmt: skip


def child_data(args):
    """Render one scan in chunks and write it as a binary PLY, with the truth as JSON."""
    import jax.numpy as jnp

    from tlsjax._model._geometry import (
        TWO_PI,
        cartesian_from_spherical,
        rotation_matrix,
    )
    from tlsjax._simulation import _point_clouds as spc
    from tlsjax._simulation._room import default_true_value, room_scans

    design, step = _design(args.points)
    scene = spc._scene(design)
    eop = room_scans(design.room, False)[0]
    R = rotation_matrix(*eop[3:], xp=np)
    grid = spc.scan_directions(design)
    names = design.aps
    values = {n: default_true_value(n) for n in names}
    scanner = spc.Scanner(architecture="hybrid", aps=names, unit_length=design.unit_length)
    coeffs = jnp.asarray([values[n] for n in names])
    rng = np.random.default_rng(0)
    t0 = time.perf_counter()
    n_total = 0
    parts = []
    for a in range(0, len(grid), 1 << 20):
        h = spc.render_rays(design, scene, eop, grid[a : a + (1 << 20)])
        m, inc = len(h["X"]), h["incidence"]
        obs = spc._observe_scan(design, eop, h, rng, coeffs, scanner, names)
        rho = np.linalg.norm(h["X"] - eop[:3], axis=1)
        inten = h["refl"] * (0.25 + 0.75 * np.cos(inc)) * np.exp(-rho / 40.0)
        inten += rng.standard_normal(m) * design.intensity_noise
        parts.append((cartesian_from_spherical(obs, xp=np), inten.astype(np.float32)))
    x = np.concatenate([p for p, _ in parts])
    inten = np.concatenate([i for _, i in parts])
    del parts
    n_total = len(x)
    if args.scan.endswith(".e57"):
        import pye57

        w = pye57.E57(args.scan, mode="w")
        w.write_scan_raw(
            {
                "cartesianX": x[:, 0],
                "cartesianY": x[:, 1],
                "cartesianZ": x[:, 2],
                "intensity": inten,
            },
            name="bench",
        )
        w.close()
    else:
        import tlsjax as tj

        tj.write_ply(args.scan, x, attributes={"intensity": inten})
    # Truth: the fixed point of every target centre (no noise), as the extraction should see it.
    c = (scene.centres - eop[:3]) @ R.T
    truth = spc._observe_in_chunks(
        scene.centres, np.broadcast_to(eop, (len(c), 6)), np.zeros_like(c), np.zeros(len(c), bool),
        coeffs, scanner, names,
    )  # fmt: skip
    truth[:, 1] = np.mod(truth[:, 1], TWO_PI)
    json.dump(
        {
            "points": n_total,
            "angular_step_deg": step,
            "render_s": time.perf_counter() - t0,
            "file_bytes": os.path.getsize(args.scan),
            "targets": {n: [k, list(t)] for n, k, t in zip(scene.names, scene.kinds, truth)},
        },
        open(args.scan + ".json", "w"),
    )


def child_extract(args):
    import tlsjax as tj
    from tlsjax._model._geometry import cartesian_from_spherical

    truth = json.load(open(args.scan + ".json"))["targets"]
    options = tj.TargetExtractionOptions(spheres=(0.0725,), checkerboards=True, circles=True)
    times, cpu, found = [], [], None
    for _ in range(2):
        t0, c0 = time.perf_counter(), time.process_time()
        found = tj.extract_targets_from_files([args.scan], options)
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    err = {}
    T = {n: cartesian_from_spherical(np.array(v[1]), xp=np) for n, v in truth.items()}
    for i in np.flatnonzero(found.accepted):
        name, d = min(
            ((n, np.linalg.norm(x - found.centre[i])) for n, x in T.items()), key=lambda p: p[1]
        )
        err.setdefault(str(found.kind[i]), []).append(d * 1e3)
    print(
        json.dumps(
            {
                "first_call_s": times[0],
                "second_call_s": times[1],
                "first_call_cpu_s": cpu[0],
                "second_call_cpu_s": cpu[1],
                "peak_mb": _vmhwm_mb(),
                "candidates": len(found),
                "accepted": {k: len(v) for k, v in err.items()},
                "true_targets": {
                    k: sum(v[0] == k for v in truth.values())
                    for k in ("sphere", "checkerboard", "circle")
                },
                "centre_error_mm": {
                    k: {"median": float(np.median(v)), "max": float(np.max(v))}
                    for k, v in err.items()
                },
            }
        )
    )


def child_load(args):
    import tlsjax as tj

    t0 = time.perf_counter()
    scans = tj.read_point_clouds(args.scan)
    print(
        json.dumps(
            {
                "read_s": time.perf_counter() - t0,
                "peak_mb": _vmhwm_mb(),
                "points": len(scans[0].points),
            }
        )
    )


def _run_child(kind, args):
    cmd = [
        sys.executable,
        __file__,
        "--child",
        kind,
        "--scan",
        args.scan,
        "--points",
        str(args.points),
    ]
    env = dict(os.environ, JAX_PLATFORMS=os.environ.get("JAX_PLATFORMS", "cpu"))
    out = subprocess.run(cmd, check=True, capture_output=True, text=True, env=env)
    return json.loads(out.stdout.strip().splitlines()[-1]) if kind != "data" else None


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--points", type=float, default=10e6)
    ap.add_argument("--scan", default="/tmp/tlsjax_bench_targets.e57", help=".e57 or .ply")
    ap.add_argument("--out", default=str(HERE / "results" / "targets.json"))
    ap.add_argument("--keep", action="store_true", help="keep (and reuse) the scan file")
    ap.add_argument("--child", choices=("data", "extract", "load"))
    args = ap.parse_args()
    args.points = int(args.points)
    if args.child:
        return {"data": child_data, "extract": child_extract, "load": child_load}[args.child](args)
    if not (args.keep and os.path.exists(args.scan) and os.path.exists(args.scan + ".json")):
        print("# rendering the scan ...", flush=True)
        _run_child("data", args)
    data = json.load(open(args.scan + ".json"))
    print(f"# {data['points']} points, {data['file_bytes'] / 1e6:.0f} MB", flush=True)
    extract = _run_child("extract", args)
    print(f"# extract: {extract}", flush=True)
    load = _run_child("load", args)
    print(f"# whole read: {load}", flush=True)
    results = {
        "benchmark": "targets",
        "date": time.strftime("%Y-%m-%d"),
        "loadavg": loadavg(),
        "cpus": os.cpu_count(),
        "scan": {k: v for k, v in data.items() if k != "targets"},
        "extract": extract,
        "whole_read": load,
        "command": "python benchmarks/bench_targets.py --points 10e6",
    }
    write_results(results, args.out)
    if not args.keep:
        for p in (args.scan, args.scan + ".json"):
            os.remove(p)


if __name__ == "__main__":
    main()
