"""Cost of derivatives relative to one adjustment, and the design optimiser's wall time.

Usage::

    python benchmarks/bench_grad.py [--out benchmarks/results/grad.json] [--repeats N]
                                    [--starts S] [--steps K]

Network: the simulated Chow et al. (2013) room (seed 0, hybrid scanner, tilted variant: 120
targets, 6 scans, 4 APs A0 B6 B7 C0). All times after compilation (compile times reported
separately), medians of ``--repeats`` calls with ``jax.block_until_ready``:

* ``calibrate_run_s``: one compiled adjustment (LM loop + quality), ``Adjustment.run``;
* ``criterion_grad_s``: one gradient of the design criterion (largest sigma/tolerance of B6,
  p-norm) w.r.t. the whole design (poses, targets, sigmas): linearisation at the truth,
  structured normal equations, Cholesky, reverse mode; the goal is <= 3x ``calibrate_run_s``;
* ``criterion_s``: the criterion alone;
* ``implicit_grad_s``: one gradient of sigma(B6) + B6 of the *estimated* adjustment w.r.t.
  all observations and sigmas (the implicit adjoint through the converged adjustment);
* ``optimiser``: ``tj.optimize_design`` of notebook 05's problem (levelled room, scans 5 and 6
  free to tilt, both stations free, criterion sigma(B6) / 1"), ``--starts`` x ``--steps``.
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import jax
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import loadavg, timed, write_results  # noqa: E402

import tlsjax as tj  # noqa: E402
from tlsjax._jit import jit  # noqa: E402


def _compiled(fn, *args):
    t0 = time.perf_counter()
    c = jit(fn).lower(*args).compile()
    return c, time.perf_counter() - t0


def main(argv=None):
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default="benchmarks/results/grad.json")
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--starts", type=int, default=8)
    ap.add_argument("--steps", type=int, default=150)
    args = ap.parse_args(argv)

    sim = tj.simulate(seed=0, architecture="hybrid", tilted=True, aps="A0 B6 B7 C0")
    model = tj.CalibrationModel(sim.scanner, datum="inner")
    adj = tj.analyze(sim.network, model)
    run = lambda: jax.block_until_ready(adj.run())
    t0 = time.perf_counter()
    run()
    calib_compile = time.perf_counter() - t0
    calib, _ = timed(run, args.repeats)

    design = tj.TargetDesign.from_simulation(sim)
    dn = tj.DesignProblem.targets(design, sim.scanner)
    crit = tj.DesignCriterion("max_sigma", aps="B6", tolerances={"B6": np.pi / 180 / 3600})
    value = lambda d: tj.design_criterion(dn, d, crit)
    cval, cval_compile = _compiled(value, design)
    cgrad, cgrad_compile = _compiled(jax.grad(value), design)
    crit_s, _ = timed(lambda: jax.block_until_ready(cval(design)), args.repeats)
    grad_s, _ = timed(lambda: jax.block_until_ready(cgrad(design)), args.repeats)

    f = tj.differentiable_adjustment(adj)
    theta = tj.network_inputs(adj)
    scalar = lambda t: f(t).ap_sigmas[1] + f(t).aps[1]
    igrad, igrad_compile = _compiled(jax.grad(scalar), theta)
    igrad_s, _ = timed(lambda: jax.block_until_ready(igrad(theta)), args.repeats)

    levelled = tj.simulate(seed=0, architecture="hybrid", tilted=False, aps="A0 B6 B7 C0")
    mask = np.array([True, True, True, True, False, False])
    dnl = tj.DesignProblem.targets(
        tj.TargetDesign.from_simulation(levelled), levelled.scanner, levelled=mask
    )
    t0 = time.perf_counter()
    opt = tj.optimize_design(
        dnl, crit, tj.DesignSpace(), starts=args.starts, steps=args.steps, progress=False
    )
    opt_wall = time.perf_counter() - t0

    results = {
        "machine": {
            "platform": platform.platform(),
            "jax_devices": jax.device_count(),
            "loadavg": loadavg(),
        },
        "network": "Chow room, 120 targets, 6 scans (2 tilted), hybrid, A0 B6 B7 C0",
        "calibrate_compile_s": calib_compile,
        "calibrate_run_s": calib,
        "criterion_compile_s": cval_compile,
        "criterion_s": crit_s,
        "criterion_grad_compile_s": cgrad_compile,
        "criterion_grad_s": grad_s,
        "criterion_grad_over_calibrate": grad_s["median"] / calib["median"],
        "implicit_grad_compile_s": igrad_compile,
        "implicit_grad_s": igrad_s,
        "implicit_grad_over_calibrate": igrad_s["median"] / calib["median"],
        "optimiser": {
            "starts": args.starts,
            "steps": args.steps,
            "compile_s": opt.compile_s,
            "run_s": opt.run_s,
            "wall_s": opt_wall,
            "start_value": opt.start_value,
            "value": opt.value,
        },
    }
    for k in ("calibrate_run_s", "criterion_s", "criterion_grad_s", "implicit_grad_s"):
        print(f"{k:>28}: {results[k]['median'] * 1e3:8.2f} ms (median of {args.repeats})")
    print(f"criterion grad / calibrate: {results['criterion_grad_over_calibrate']:.2f}")
    print(f"implicit grad / calibrate:  {results['implicit_grad_over_calibrate']:.2f}")
    print(
        f"optimiser: {opt_wall:.1f} s wall ({opt.compile_s:.1f} s compile, {opt.run_s:.1f} s run)"
    )
    write_results(results, args.out)


if __name__ == "__main__":
    main()
