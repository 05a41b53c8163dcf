"""Scaling benchmark: wall time and peak memory of one adjustment against the network's size.

Usage::

    python benchmarks/bench_scaling.py [--targets 100,1000,3334,10000,33334]
                                       [--plane-obs 1000,10000,100000,1000000]
                                       [--out benchmarks/results/scaling.json]

Point-based: ``tj.simulate(tj.Room(n_targets=N))`` (6 scans, every target in every scan: 6 N
target observations of (range, hz, el)), APs ``A0 B6 B7 C0``. Plane-based: the simulated point
clouds of the same room (``tj.simulate_point_clouds``), thinned to about M / 3 points
(``to_network(max_points=...)``). Each point runs in its own child process, so that its peak
resident memory (VmHWM) is its own; it records the host-side plan and approximate values, the
ahead-of-time compile of the adjustment, the compiled run (median of ``--repeats``), one
public ``tj.calibrate`` after the compile (end to end on the host) and XLA's own account of the
executable's temporaries. Memory is recorded per phase, the peak restarted between phases
(Linux ``clear_refs``): ``import_peak_mb`` (JAX and tlsjax imported), ``simulate_peak_mb``
(after drawing the network), ``network_rss_mb`` (resident before the adjustment),
``compile_peak_mb`` (plan, approximate values and XLA's compile: a transient of a few hundred
MB that does not grow with the network), ``run_peak_mb`` (the compiled runs) and ``peak_mb``
(runs and ``calibrate``). A plot of time and memory per point is written beside the JSON.
"""

from __future__ import annotations

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import argparse
import dataclasses
import json
import subprocess
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import loadavg, write_results  # noqa: E402

DEG = 3.141592653589793 / 180


def _peak_mb():
    with open("/proc/self/status") as fh:
        for line in fh:
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    return float("nan")


def _reset_peak():
    """Return freed heap to the system and restart the peak (VmHWM) from the current resident
    size (Linux ``clear_refs`` 5), so that each phase's peak is its own."""
    import ctypes
    import gc

    gc.collect()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
        with open("/proc/self/clear_refs", "w") as fh:
            fh.write("5")
    except OSError:  # pragma: no cover - not Linux: peaks then accumulate
        pass


def _network(kind, size, seed=0):
    import tlsjax as tj

    if kind == "targets":
        return tj.simulate(tj.Room(n_targets=int(size)), seed=seed).network
    points = int(size) // 3
    step = (0.25 if points > 300_000 else 0.5 if points > 100_000 else 1.0) * DEG
    clouds = tj.simulate_point_clouds(tj.CloudDesign(angular_step=step), seed=seed)
    per_pair = max(int(points / (len(clouds.plane_names) * len(clouds.scans))), 6)
    return clouds.to_network(max_points=per_pair, seed=seed)


def child(kind: str, size: int, repeats: int) -> dict:
    import jax

    import tlsjax as tj
    from tlsjax._adjustment._calibrate import _run

    out = {"kind": kind, "size": size, "import_peak_mb": _peak_mb()}
    t0 = time.perf_counter()
    net = _network(kind, size)
    out["simulate_s"] = time.perf_counter() - t0
    out["n_observations"] = int(net.n_observations)
    out["n_targets"] = len(net.targets)
    out["n_plane_points"] = int(net.plane_observations.shape[0])
    out["simulate_peak_mb"] = _peak_mb()
    model = tj.CalibrationModel(tj.Scanner(aps="A0 B6 B7 C0"))
    opts = tj.SolverOptions(full_covariance=False)
    _reset_peak()
    out["network_rss_mb"] = _peak_mb()
    t0 = time.perf_counter()
    adj = tj.Adjustment(net, model, opts)
    p0 = adj.initial
    out["plan_and_approximate_values_s"] = time.perf_counter() - t0
    out["layout"] = ["grid" if x is not None else "segments" for x in adj.plan.problem.layouts]
    args = (adj.plan.spec, adj.plan.problem, p0, opts.arrays(), False)
    t0 = time.perf_counter()
    compiled = _run.lower(*args).compile()
    out["compile_s"] = time.perf_counter() - t0
    try:
        out["xla_temp_mb"] = compiled.memory_analysis().temp_size_in_bytes / 2**20
    except Exception:  # pragma: no cover - backend without memory analysis
        out["xla_temp_mb"] = None
    out["compile_peak_mb"] = _peak_mb()
    dyn = args[1:4]
    _reset_peak()
    state, _ = jax.block_until_ready(compiled(*dyn))
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(compiled(*dyn))
        ts.append(time.perf_counter() - t0)
    out["run_s"] = sorted(ts)[len(ts) // 2]
    out["run_min_s"] = min(ts)
    out["iterations"] = int(state.iteration)
    out["run_peak_mb"] = _peak_mb()
    t0 = time.perf_counter()
    res = tj.calibrate(dataclasses.replace(net), model, opts)  # nothing memoised
    out["calibrate_s"] = time.perf_counter() - t0
    out["result"] = res.message
    out["sigma0"] = res.sigma0
    out["peak_mb"] = _peak_mb()
    return out


def _plot(results, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for kind, marker in (("targets", "o"), ("planes", "s")):
        pts = [r for r in results if r["kind"] == kind and "run_s" in r]
        if not pts:
            continue
        x = [r["n_observations"] for r in pts]
        axes[0].loglog(x, [r["run_s"] for r in pts], marker + "-", label=f"{kind}: compiled run")
        axes[0].loglog(
            x, [r["calibrate_s"] for r in pts], marker + "--", label=f"{kind}: calibrate"
        )
        axes[1].loglog(x, [r["peak_mb"] for r in pts], marker + "-", label=f"{kind}: run peak")
        axes[1].loglog(
            x, [r["compile_peak_mb"] for r in pts], marker + "--", label=f"{kind}: compile peak"
        )
        axes[1].loglog(
            x,
            [r["peak_mb"] - r["network_rss_mb"] for r in pts],
            marker + ":",
            label=f"{kind}: run, above the network",
        )
    axes[0].set_xlabel("observations (range, hz, el)")
    axes[0].set_ylabel("wall time of one adjustment [s]")
    axes[1].set_xlabel("observations (range, hz, el)")
    axes[1].set_ylabel("peak resident memory [MB]")
    for ax in axes:
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--targets", default="100,1000,3334,10000,33334")
    ap.add_argument("--plane-obs", default="1000,10000,100000,1000000")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--timeout", type=int, default=900, help="seconds per child")
    ap.add_argument("--out", default="benchmarks/results/scaling.json")
    ap.add_argument("--child", nargs=2, metavar=("KIND", "SIZE"), help=argparse.SUPPRESS)
    a = ap.parse_args(argv)
    if a.child:
        print(json.dumps(child(a.child[0], int(a.child[1]), a.repeats)))
        return
    points = [("targets", int(n)) for n in a.targets.split(",") if n] + [
        ("planes", int(float(m))) for m in a.plane_obs.split(",") if m
    ]
    results = []
    for kind, size in points:
        t0 = time.perf_counter()
        load = loadavg()
        cmd = [sys.executable, __file__, "--child", kind, str(size), "--repeats", str(a.repeats)]
        try:
            p = subprocess.run(cmd, capture_output=True, text=True, timeout=a.timeout)
            r = (
                json.loads(p.stdout.strip().splitlines()[-1])
                if p.returncode == 0
                else {"kind": kind, "size": size, "error": p.stderr[-2000:]}
            )
        except subprocess.TimeoutExpired:
            r = {"kind": kind, "size": size, "error": f"killed after {a.timeout} s"}
        r["child_wall_s"] = time.perf_counter() - t0
        r["loadavg_before"] = load
        results.append(r)
        print(
            f"{kind:8s} {size:>8d}: "
            + (
                f"{r['n_observations']} obs, run {r['run_s']:.3f} s, calibrate {r['calibrate_s']:.3f} s, "
                f"compile {r['compile_s']:.1f} s, peak {r['peak_mb']:.0f} MB (compile {r['compile_peak_mb']:.0f} MB, "
                f"network {r['network_rss_mb']:.0f} MB) ({r['layout']})"
                if "run_s" in r
                else r["error"][-300:]
            ),
            flush=True,
        )
    out = Path(a.out)
    write_results({"benchmark": "scaling of one adjustment", "points": results}, out)
    _plot(results, out.with_suffix(".png"))
    print(f"# plot {out.with_suffix('.png')}")


if __name__ == "__main__":
    main()
