"""The plane path on dense simulated clouds: time and peak memory per phase (issue 27 item 7).

Usage::

    python benchmarks/bench_dense_planes.py [--points 1e6 1e7] [--extract-points 3e5]
                                            [--all-points-max 1.1e6]
                                            [--out benchmarks/results/dense_planes.json]

Clouds: the simulated Chow room (14 x 11 x 3 m, three boards, two stations with three scans
each, two of them rolled by -45/+45 deg, hybrid scanner, APs A0 B6 B7 C0, 0.5 mm / 20" noise)
on one angular grid whose step gives ``--points`` points in all (0.5 deg: 1.08 million; 0.164
deg: 10 million).

Phases, each timed (wall and CPU seconds) with its own peak resident memory (VmRSS sampled
every 5 ms while the phase runs; VmHWM of the whole process beside it):

* ``simulate``: ray cast and observations of every scan (``tj.simulate_point_clouds``);
* ``table``: the plane observation table with the true plane labels (what ``extract-planes``
  writes after matching);
* ``thin``: :func:`tlsjax.thin_planes` at the default 0.1 m (``calibrate``'s default);
* ``network``: ``tj.make_plane_network`` of the thinned table with the compensator readings;
* ``calibrate``: ``tj.self_calibrate`` (what ``calibrate --planes`` runs by default: IGG-III
  rounds, then the final adjustment), the first call of the process, so compile included;
* ``calibrate_all_points`` (only up to ``--all-points-max`` points): the same on all points,
  without thinning, as the issue measured it (35 s, 2.5 GB at 1 million points).

Extraction (``--extract-points``, its own process): open3d RANSAC, DBSCAN and refit of each
scan (``tj.extract_planes``) and the matching across scans, on a cloud of that size; where the
whole 10 million do not fit the time of one benchmark, the JSON says which size ran.

Each size runs in its own child process (``--child N``), so each peak is its own; JAX's own
0.3 GB is in every figure. JAX_PLATFORMS defaults to cpu.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import loadavg, write_results  # noqa: E402

HERE = Path(__file__).resolve().parent
POINTS_AT_HALF_DEGREE = 1_084_320  # the default room's points at a 0.5 deg step


def _status_mb(field: str) -> float:
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith(field + ":"):
                return int(line.split()[1]) / 1024.0
    return float("nan")  # pragma: no cover - not Linux


class Phase:
    """Wall and CPU time and the peak VmRSS of a block (a sampling thread)."""

    def __init__(self, name: str, log: dict):
        self.name, self.log = name, log

    def _sample(self):
        while not self._stop.is_set():
            self.peak = max(self.peak, _status_mb("VmRSS"))
            self._stop.wait(0.005)

    def __enter__(self):
        self.peak, self._stop = _status_mb("VmRSS"), threading.Event()
        self.rss0 = self.peak
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._thread.start()
        self.t0, self.c0 = time.perf_counter(), time.process_time()
        print(f"# {self.name} ...", file=sys.stderr, flush=True)
        return self

    def __exit__(self, *exc):
        wall, cpu = time.perf_counter() - self.t0, time.process_time() - self.c0
        self._stop.set()
        self._thread.join()
        self.peak = max(self.peak, _status_mb("VmRSS"))
        self.log[self.name] = {
            "wall_s": round(wall, 3),
            "cpu_s": round(cpu, 3),
            "rss_before_mb": round(self.rss0, 1),
            "peak_rss_mb": round(self.peak, 1),
        }
        print(f"# {self.name}: {wall:.1f} s wall, {self.peak:.0f} MB peak", file=sys.stderr)


def _design(points: float):
    import tlsjax as tj

    step = 0.5 * (POINTS_AT_HALF_DEGREE / float(points)) ** 0.5
    return tj.CloudDesign(angular_step=step * 3.141592653589793 / 180.0), step


def child_path(points: float, all_points_max: float) -> dict:
    """The plane path on ``points`` simulated points, phase by phase (module docstring)."""
    import numpy as np

    import tlsjax as tj

    log, out = {}, {}
    design, step = _design(points)
    with Phase("simulate", log):
        pc = tj.simulate_point_clouds(design, seed=0)
    with Phase("table", log):
        table = pc.to_table()
    with Phase("thin", log):
        thinned = tj.thin_planes(table, tj.DEFAULT_PLANE_SPACING)
    with Phase("network", log):
        net = tj.make_plane_network(
            thinned,
            sigma_range=pc.sigma_range,
            sigma_hz=pc.sigma_angle,
            sigma_el=pc.sigma_angle,
            levelling=pc.levelling,
        )
    model = tj.CalibrationModel(pc.scanner)
    with Phase("calibrate", log):
        screened = tj.self_calibrate(net, model)
    res = screened.calibration
    truth = np.array([pc.true_aps[a] for a in res.ap_names])
    out["aps"] = {
        a: {"value": float(v), "sigma": float(s), "true": float(t), "error_over_sigma": float(z)}
        for a, v, s, t, z in zip(
            res.ap_names,
            res.ap_values,
            res.ap_sigmas,
            truth,
            (res.ap_values - truth) / res.ap_sigmas,
        )
    }
    out["iterations"], out["message"] = int(res.iterations), res.message
    n_all = len(table)
    if n_all <= all_points_max:
        del thinned, net, screened, res
        with Phase("calibrate_all_points", log):
            full = tj.self_calibrate(
                tj.make_plane_network(
                    table,
                    sigma_range=pc.sigma_range,
                    sigma_hz=pc.sigma_angle,
                    sigma_el=pc.sigma_angle,
                    levelling=pc.levelling,
                ),
                model,
            )
        out["all_points_ap_sigmas"] = dict(
            zip(full.calibration.ap_names, full.calibration.ap_sigmas.tolist())
        )
    out.update(
        points=n_all,
        kept_points=len(tj.thin_planes(table, tj.DEFAULT_PLANE_SPACING)) if n_all else 0,
        angular_step_deg=step,
        spacing_m=tj.DEFAULT_PLANE_SPACING,
        phases=log,
        process_peak_mb=round(_status_mb("VmHWM"), 1),
    )
    return out


def child_extract(points: float) -> dict:
    """Extraction and matching of ``points`` simulated points (module docstring)."""
    import tlsjax as tj

    log = {}
    design, step = _design(points)
    with Phase("simulate", log):
        pc = tj.simulate_point_clouds(design, seed=0)
    with Phase("extract", log):
        found = tj.extract_planes(pc.observations, tj.ExtractionOptions(), seed=0)
    with Phase("match", log):
        matched = tj.match_planes(found, pc.eops)
    return {
        "points": int(sum(len(o) for o in pc.observations)),
        "angular_step_deg": step,
        "patches": int(len(found.patch_scan)),
        "planes": int(len(matched.planes)),
        "points_on_patches": int(len(found.point_patch)),
        "true_planes": int(len(pc.plane_names)),
        "phases": log,
        "process_peak_mb": round(_status_mb("VmHWM"), 1),
    }


def _run_child(args: list) -> dict:
    env = dict(os.environ, JAX_PLATFORMS=os.environ.get("JAX_PLATFORMS", "cpu"))
    done = subprocess.run(
        [sys.executable, __file__, *args], env=env, capture_output=True, text=True, check=False
    )
    sys.stderr.write(done.stderr)
    if done.returncode != 0:
        return {"failed": f"exit {done.returncode}", "stderr_tail": done.stderr[-2000:]}
    return json.loads(done.stdout.strip().splitlines()[-1])


def _print_phases(r: dict, title: str) -> None:
    if "phases" in r:
        line = ", ".join(
            f"{k} {v['wall_s']:.1f} s / {v['peak_rss_mb']:.0f} MB" for k, v in r["phases"].items()
        )
        print(f"{title}: {line}")
    else:
        print(f"{title}: {r}")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--points", type=float, nargs="*", default=[1e6, 1e7])
    p.add_argument("--extract-points", type=float, nargs="*", default=[3e5])
    p.add_argument("--all-points-max", type=float, default=1.1e6)
    p.add_argument("--out", default=str(HERE / "results" / "dense_planes.json"))
    p.add_argument("--child", nargs=2, metavar=("KIND", "POINTS"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.child:
        kind, n = args.child[0], float(args.child[1])
        res = child_path(n, args.all_points_max) if kind == "path" else child_extract(n)
        print(json.dumps(res))
        return 0
    t0 = time.perf_counter()
    results = {
        "benchmark": "dense plane clouds (issue 27 item 7)",
        "date": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
        "cpus": len(os.sched_getaffinity(0)),
        "loadavg_before": loadavg(),
        "path": [
            _run_child(
                ["--child", "path", f"{n:g}", "--all-points-max", f"{args.all_points_max:g}"]
            )
            for n in args.points
        ],
        "extraction": [_run_child(["--child", "extract", f"{n:g}"]) for n in args.extract_points],
    }
    results["loadavg_after"] = loadavg()
    results["total_wall_s"] = round(time.perf_counter() - t0, 1)
    for r in results["path"]:
        _print_phases(r, f"{r.get('points')} points (kept {r.get('kept_points')})")
    for r in results["extraction"]:
        _print_phases(r, f"extraction of {r.get('points')} points ({r.get('planes')} planes)")
    write_results(results, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
