"""Monte Carlo benchmark: 1,000 full point-based self-calibrations of the Chow et al. (2013) room.

Usage::

    python benchmarks/bench_montecarlo.py [--runs 1000] [--chunk-size N] [--scipy-runs 20]
                                          [--devices N]
                                          [--cases physical,chow2013-noscale]
                                          [--out benchmarks/results/montecarlo.json]

Design: ``tj.simulate(seed=0)`` (120 targets, 6 scans, tilted variant, hybrid scanner), APs
``A0 B6 B7 C0`` ("physical") and the 23-term ``chow2013-noscale``. Realisation k draws new
noise (and levelling readings) from ``fold_in(PRNGKey(seed), k)``.

tlsjax: :func:`tlsjax._simulation._montecarlo.monte_carlo`, one compiled vmapped chunk function (compile
time reported separately: ``compile_s``), then ``runs`` realisations in chunks (``run_s``,
wall clock of the whole batch including the host transfer of the results). Every realisation
starts from the simulated truth (the standard Monte Carlo choice; the estimates do not depend
on the start) and iterates Gauss-Newton to a per-member convergence test.

Peer: the scipy program of ``benchmarks/bench_point.py`` (``ScipyPeer``: numpy residuals,
exact sparse Jacobian pattern, ``least_squares(method="trf", x_scale="jac")`` with its
tolerances), run in a Python loop on the first ``--scipy-runs`` realisations (the same
observations), each also started from the truth; its levelling rows are compensator
readings, as in tlsjax. Its time per realisation is extrapolated to
``runs`` (a loop of 1,000 scipy runs would take minutes). Its APs are compared with tlsjax's
for the same realisations (datum invariant: the peer holds scan S1, tlsjax a minimal datum).

The realisations are sharded over ``--devices`` CPU devices (default: one per available CPU;
``XLA_FLAGS=--xla_force_host_platform_device_count``); the scipy loop runs on one core, as a
user's loop would. The device count is recorded (``tlsjax.devices``).

The machine is shared while this runs: ``os.getloadavg()`` is recorded before and after.
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path


def _host_devices():
    """``--devices N``: XLA reads the CPU device count when JAX's backend starts, so it is set
    before anything runs (default: the CPUs available; ``--devices 1`` for one device)."""
    from tlsjax._cli._common import available_cpus, use_host_devices

    p = argparse.ArgumentParser(add_help=False)
    p.add_argument("--devices", type=int, default=available_cpus())
    use_host_devices(p.parse_known_args()[0].devices)


_host_devices()

import numpy as np  # noqa: E402
from scipy.optimize import least_squares  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import write_results  # noqa: E402
from _phases import arithmetic, matmul_gflops, phase_times  # noqa: E402
from bench_point import ScipyPeer, machine_info  # noqa: E402

import tlsjax as tj  # noqa: E402
from tlsjax._simulation._montecarlo import (  # noqa: E402
    MonteCarloOptions,
    monte_carlo,
    monte_carlo_network,
)

CASES = {"physical": "A0 B6 B7 C0", "chow2013-noscale": "chow2013-noscale"}


def scipy_loop(sim, scanner, n, seed, tol, lsmr_tol, max_nfev):
    """Time the scipy peer on realisations 0..n-1; returns (seconds per run, AP estimates)."""
    nets = monte_carlo_network(sim, list(range(n)), seed=seed)
    aps, times, nfev = [], [], []
    for net, truth in nets:
        peer = ScipyPeer(net, scanner, fixed_scan=0)
        t0 = time.perf_counter()
        peer.prepare()
        x0 = peer.pack(
            sim.true_targets, sim.true_eops, np.array([truth.get(a, 0.0) for a in scanner.aps])
        )
        peer.calls = 0
        sol = least_squares(
            peer.residual,
            x0,
            args=(sim.true_eops,),
            method="trf",
            jac_sparsity=peer._sparsity,
            x_scale="jac",
            ftol=tol,
            xtol=tol,
            gtol=tol,
            tr_options=dict(atol=lsmr_tol, btol=lsmr_tol),
            max_nfev=max_nfev,
        )
        times.append(time.perf_counter() - t0)
        nfev.append(int(sol.nfev))
        aps.append(peer.unpack(sol.x, sim.true_eops)[2])
    return np.array(times), np.array(aps), nfev


def _arithmetic(sim, scanner, res):
    """The adjustments' work in the batch beside its time: every realisation's iterations each
    linearise, reduce and step once (no final pass, no quality pass; the draw is left out),
    with the phases' flops and bytes of the same room (:func:`_phases.phase_times`)."""
    opts = tj.SolverOptions(full_covariance=False)
    adj = tj.Adjustment(sim.network, tj.CalibrationModel(scanner), opts)
    costs = {}
    phase_times(adj.plan.spec, adj.plan.problem, adj.initial, opts.arrays(), 1, costs)
    n = float(np.sum(res.iterations))
    return arithmetic(costs, n, n, res.run_s, matmul_gflops(), quality=False)


def bench_case(label, aps, runs, chunk, scipy_runs, seed, tol, lsmr_tol, max_nfev):
    out = {"aps": aps, "loadavg_1_5_15_before": list(os.getloadavg())}
    sim = tj.simulate(seed=0, aps=aps)
    scanner = sim.scanner
    out["ap_names"] = list(scanner.aps)
    res = monte_carlo(
        sim, options=MonteCarloOptions(runs=runs, chunk_size=chunk, seed=seed, progress=False)
    )
    out["tlsjax"] = {
        "runs": runs,
        "chunk_size": res.chunk_size,
        "devices": res.n_devices,
        "compile_s": res.compile_s,
        "run_s": res.run_s,
        "realisations_per_s": runs / res.run_s,
        "iterations_histogram": np.bincount(res.iterations).tolist(),
        "failures": res.failures(),
    }
    out["arithmetic"] = _arithmetic(sim, scanner, res)
    sm = res.to_dict()  # strict JSON: None where undefined (no successful realisation)
    out["coverage"] = {
        "sigma0_sq_mean": sm["sigma0_sq_mean"],
        "sigma0_sq_std": sm["sigma0_sq_std"],
        "dof": sm["dof"],
        "empirical_over_formal_sigma": {n: a["ratio"] for n, a in sm["aps"].items()},
        "bias_over_formal_sigma": {
            n: None if None in (a["bias"], a["formal_sigma"]) else a["bias"] / a["formal_sigma"]
            for n, a in sm["aps"].items()
        },
        "ratio_sampling_sigma": 1.0 / np.sqrt(2 * (runs - 1)),
    }
    times, ap_sc, nfev = scipy_loop(sim, scanner, scipy_runs, seed, tol, lsmr_tol, max_nfev)
    per = float(np.mean(times))
    out["scipy"] = {
        "runs_timed": scipy_runs,
        "s_per_run_mean": per,
        "s_per_run_median": float(np.median(times)),
        "nfev": nfev,
        "extrapolated_s_for_runs": per * runs,
        "realisations_per_s": 1.0 / per,
        "options": {
            "method": "trf",
            "x_scale": "jac",
            "jac_sparsity": "exact pattern",
            "ftol=xtol=gtol": tol,
            "lsmr atol=btol": lsmr_tol,
            "start": "simulated truth",
        },
    }
    d = (ap_sc - res.ap_values[:scipy_runs]) / res.ap_sigmas[:scipy_runs]
    out["max_ap_diff_sigma_scipy_vs_tlsjax"] = float(np.nanmax(np.abs(d)))
    out["speedup"] = out["scipy"]["extrapolated_s_for_runs"] / res.run_s
    out["loadavg_1_5_15_after"] = list(os.getloadavg())
    return out


def level_study(tests, sims, shifts=(0.0, 3.0, 5.0, 8.0), seed=5):
    """Rejection rates of the AP-set compatibility test (SPEC section 9) over repeated tests.

    Pairs of AP sets come from pairs of Monte Carlo realisations of the Chow room (A0 B6 B7
    C0): both drawn from one truth. B6 of the second set is then shifted by ``shift`` sigma of
    the B6 difference. Each test uses ``sims`` simulations (the compiled test is reused).
    """
    from tlsjax._inference._compatibility import (
        APSet,
        CompatibilityOptions,
        compatibility_test,
    )

    sim = tj.simulate(seed=0)
    mc = monte_carlo(sim, options=MonteCarloOptions(runs=2 * tests, seed=seed, progress=False))
    out = {"tests_per_shift": tests, "simulations_per_test": sims, "alpha": 0.05, "rates": {}}
    t0 = time.perf_counter()
    for shift in shifts:
        rej, naive = [], []
        for k in range(tests):
            a, b = 2 * k, 2 * k + 1
            v = mc.ap_values[b].copy()
            v[1] += shift * np.sqrt(mc.ap_covariance[a, 1, 1] + mc.ap_covariance[b, 1, 1])
            r = compatibility_test(
                APSet(mc.ap_names, mc.ap_values[a], mc.ap_covariance[a]),
                APSet(mc.ap_names, v, mc.ap_covariance[b]),
                options=CompatibilityOptions(runs=sims, chunk_size=100, seed=k, progress=False),
            )
            rej.append(not r.compatible)
            naive.append(not r.naive_compatible)
        out["rates"][f"B6 shift {shift:g} sigma"] = {
            "group_test": float(np.mean(rej)),
            "naive_chi2": float(np.mean(naive)),
        }
        print(
            f"  B6 shift {shift:g} sigma: group test rejects {np.mean(rej):.3f}, naive chi2 {np.mean(naive):.3f}",
            flush=True,
        )
    out["s"] = time.perf_counter() - t0
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=1000)
    ap.add_argument(
        "--chunk-size",
        type=int,
        default=None,
        help="default: tlsjax's (from the design's working set)",
    )
    ap.add_argument("--scipy-runs", type=int, default=20)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--scipy-tol", type=float, default=1e-10)
    ap.add_argument("--lsmr-tol", type=float, default=1e-12)
    ap.add_argument("--max-nfev", type=int, default=1000)
    ap.add_argument("--cases", default=",".join(CASES))
    ap.add_argument(
        "--devices",
        type=int,
        default=None,
        help="CPU devices to shard the realisations over (default: the CPUs available)",
    )
    ap.add_argument("--out", default="benchmarks/results/montecarlo.json")
    ap.add_argument(
        "--level-study",
        type=int,
        default=0,
        metavar="TESTS",
        help="also measure the compatibility test's rejection rates over TESTS repeated tests per shift",
    )
    ap.add_argument(
        "--level-sims", type=int, default=200, help="simulations per test in the level study"
    )
    a = ap.parse_args(argv)
    results = {
        "benchmark": "Monte Carlo point-based self-calibration, Chow 2013 room (seed 0, hybrid, tilted)",
        "machine": machine_info(),
        "cases": {},
    }
    for label in a.cases.split(","):
        label = label.strip()
        print(f"# case {label} ...", flush=True)
        c = bench_case(
            label,
            CASES[label],
            a.runs,
            a.chunk_size,
            a.scipy_runs,
            a.seed,
            a.scipy_tol,
            a.lsmr_tol,
            a.max_nfev,
        )
        results["cases"][label] = c
        t = c["tlsjax"]
        print(
            f"{label:18s} compile {t['compile_s']:.2f} s | {a.runs} runs {t['run_s']:.2f} s = {t['realisations_per_s']:.0f}/s | "
            f"scipy {c['scipy']['s_per_run_mean'] * 1e3:.0f} ms/run ({a.scipy_runs} timed) -> {c['scipy']['extrapolated_s_for_runs']:.0f} s | "
            f"speedup {c['speedup']:.0f}x | s0^2 mean {c['coverage']['sigma0_sq_mean']:.4f} | "
            f"max |dAP|/sigma vs scipy {c['max_ap_diff_sigma_scipy_vs_tlsjax']:.1e} | load {c['loadavg_1_5_15_after'][0]:.1f}",
            flush=True,
        )
        ratios = c["coverage"]["empirical_over_formal_sigma"]
        print(
            "  emp/formal sigma: " + " ".join(f"{n} {r:.3f}" for n, r in ratios.items()), flush=True
        )
    if a.level_study:
        print("# compatibility test level study ...", flush=True)
        results["compatibility_level_study"] = level_study(a.level_study, a.level_sims)
    write_results(results, a.out)


if __name__ == "__main__":
    main()
