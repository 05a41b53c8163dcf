"""AP-set compatibility test benchmark: one test of 1,000 simulations, 4 and 23 APs.

Usage::

    python benchmarks/bench_compat.py [--runs 1000] [--repeats 5] [--devices N]
                                      [--out benchmarks/results/compat.json]

Design: the default room (14 x 11 x 3 m), 100 targets, 10 control points, hybrid scanner,
0.5 mm / 20" noise; the AP sets are two sessions of the Chow et al. (2013) room calibrated by
``tj.calibrate`` (tilted variant, ``A0 B6 B7 C0`` and the 23-term ``chow2013-noscale``), so
their covariances are full and realistic (correlations up to 0.9997 in the 23-AP set).

What is timed (SPEC section 9): :func:`tlsjax.compatibility_test`, wall clock of the whole call
(the 1,000 simulations with their Jacobians and covariances, the zero-noise reference chunk of
the visibility report, the null's 1e5 draws, the report). Compilation is timed separately: the
first call of a design compiles (``compile_s``); every later call, with other AP values,
covariances, noise or seed, reuses the compiled function (``recompiled`` says whether a later
call compiled again). The two cases are timed alternately in one process, so a change of the
machine's load hits both. ``os.getloadavg()`` is recorded before and after: the machine is shared.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path


def _host_devices():
    """``--devices N`` (default: the CPUs available), set before JAX's backend starts."""
    from tlsjax._cli._common import available_cpus, use_host_devices

    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("--devices", type=int, default=available_cpus())
    use_host_devices(p.parse_known_args()[0].devices)


_host_devices()

import jax  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import loadavg, stats, write_results  # noqa: E402

import tlsjax as tj  # noqa: E402

CASES = {"4 APs": "A0 B6 B7 C0", "23 APs": "chow2013-noscale"}


def sessions(aps: str):
    """Two AP sets of one instrument: two simulated sessions, each self-calibrated."""
    model = tj.CalibrationModel(tj.Scanner(aps=aps))
    out = []
    for seed in (11, 12):
        res = tj.calibrate(tj.simulate(seed=seed, aps=aps).network, model)
        out.append(tj.APSet.from_result(res))
    return out


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=int, default=1000)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--devices", type=int, default=None, help="CPU devices (default: all CPUs)")
    p.add_argument("--out", default=str(Path(__file__).parent / "results" / "compat.json"))
    args = p.parse_args()
    load0 = loadavg()
    sets = {name: sessions(aps) for name, aps in CASES.items()}
    options = tj.CompatibilityOptions(runs=args.runs, progress=False)
    compile_s, first = {}, {}
    for name, (s1, s2) in sets.items():
        t0 = time.perf_counter()
        res = tj.compatibility_test(s1, s2, options=options)
        first[name] = time.perf_counter() - t0
        compile_s[name] = res.compile_s
    wall = {name: [] for name in sets}
    cpu = {name: [] for name in sets}
    recompiled = False
    results = {}
    for k in range(args.repeats):
        for name, (s1, s2) in sets.items():
            opts = tj.CompatibilityOptions(runs=args.runs, seed=k + 1, progress=False)
            t0, c0 = time.perf_counter(), time.process_time()
            res = tj.compatibility_test(s1, s2, options=opts)
            wall[name].append(time.perf_counter() - t0)
            cpu[name].append(time.process_time() - c0)
            recompiled |= res.compile_s > 0.05
            results[name] = res
    out = {
        "benchmark": "AP-set compatibility test, one test of N simulations (SPEC section 9)",
        "runs": args.runs,
        "devices": [str(d) for d in jax.devices()],
        "cpus": os.cpu_count(),
        "loadavg_before": load0,
        "loadavg_after": loadavg(),
        "recompiled_after_first_call": recompiled,
        "cases": {
            name: {
                "aps": CASES[name],
                "compile_s": compile_s[name],
                "first_call_s": first[name],
                "wall_s": stats(wall[name]),
                "process_cpu_s": stats(cpu[name]),
                "p_value": results[name].p_value,
                "compatible": results[name].compatible,
            }
            for name in sets
        },
    }
    ratio = out["cases"]["23 APs"]["wall_s"]["median"] / out["cases"]["4 APs"]["wall_s"]["median"]
    out["ratio_23_to_4"] = ratio
    for name, c in out["cases"].items():
        print(
            f"{name:7s} compile {c['compile_s']:.1f} s, test of {args.runs} simulations: "
            f"median {c['wall_s']['median']:.3f} s (min {c['wall_s']['min']:.3f}), "
            f"CPU {c['process_cpu_s']['median']:.3f} s"
        )
    print(f"23 APs / 4 APs: {ratio:.2f}; recompiled after the first call: {recompiled}")
    print(f"load average before {load0}, after {out['loadavg_after']}")
    write_results(out, args.out)


if __name__ == "__main__":
    main()
