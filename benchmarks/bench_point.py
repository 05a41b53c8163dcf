"""Point-based self-calibration benchmark: tlsjax vs. a hand-written scipy peer.

Usage::

    python benchmarks/bench_point.py [--out benchmarks/results/point.json] [--repeats N]
                                     [--scipy-repeats M] [--cases physical,chow2013-noscale]

Network: the simulated Chow et al. (2013) room (seed 0, hybrid scanner, tilted variant: 120
targets, 6 scans of which 4 levelled, 720 target observations of (range, hz, el)).
Two AP sets: the 4 physical terms "A0 B6 B7 C0" and the 23-term "chow2013-noscale".

tlsjax is timed three ways:
  * compile_s: ahead-of-time ``_run.lower(...).compile()`` of the whole compiled adjustment
    (Gauss-Newton loop + quality, ``full_covariance=False``), split into trace/lower and XLA
    compile;
  * run_s: calls of that compiled executable on device arrays, ``jax.block_until_ready`` on the
    outputs, median and min of ``--repeats`` runs;
  * calibrate_s: the public ``tj.calibrate`` call after warm-up (host-side plan, approximate
    values, the compiled call and result assembly), median and min.

The peer is what a user would otherwise write: ``scipy.optimize.least_squares(method="trf",
jac_sparsity=..., x_scale="jac")`` on the same observations, the same approximate values
(``tlsjax._adjustment._approx.approximate_values``), the same unknowns (targets, 6 EOPs per scan, APs) and
the same whitened residuals ``wrap(F + Delta - l) / sigma`` plus the levelling
pseudo-observations, in plain vectorised numpy. The 4-dof datum defect (3 translations and
rotation about Z with levelling) is fixed by holding Xs, Ys, Zs, kappa of scan S1 at their
approximate values. AP estimates are datum invariant, so they must agree with tlsjax's.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import platform
import sys
import time

import jax
import numpy as np
import scipy
import scipy.sparse as sp
from _common import loadavg, rotations, timed, write_results
from _phases import arithmetic, matmul_gflops, phase_times
from scipy.optimize import least_squares

import tlsjax as tj
from tlsjax._adjustment._approx import approximate_values
from tlsjax._adjustment._calibrate import _run

TWO_PI = 2.0 * np.pi
CASES = {
    "physical": "A0 B6 B7 C0",
    "chow2013-noscale": "chow2013-noscale",
}


# ---------------------------------------------------------------------------------------------
# The scipy peer: plain numpy, written from SPEC sections 1-3 (independent of tlsjax internals).
# ---------------------------------------------------------------------------------------------


def _ap_basis(name: str, rho, theta, alpha, architecture: str, U: float, U2: float):
    """(group index, basis values) of one AP term (SPEC section 3), evaluated at observations."""
    one = np.ones_like(rho)
    table = {
        "A0": (0, one),
        "A1": (0, rho),
        "A2": (0, np.sin(alpha)),
        "A3": (0, np.sin(4 * np.pi * rho / U)),
        "A4": (0, np.cos(4 * np.pi * rho / U)),
        "A5": (0, np.sin(4 * np.pi * rho / U2)),
        "A6": (0, np.cos(4 * np.pi * rho / U2)),
        "A7": (0, np.sin(4 * theta)),
        "A8": (0, np.cos(4 * theta)),
        "B1": (1, theta),
        "B2": (1, np.sin(theta)),
        "B3": (1, np.cos(theta)),
        "B4": (1, np.sin(2 * theta)),
        "B5": (1, np.cos(2 * theta)),
        "B6": (1, 1.0 / np.cos(alpha) - (1.0 if architecture == "hybrid" else 0.0)),
        "B7": (1, np.tan(alpha)),
        "B8": (1, 1.0 / rho),
        "B9": (1, np.sin(alpha)),
        "B10": (1, np.cos(alpha)),
        "B11": (1, np.sin(3 * alpha)),
        "B12": (1, np.sin(4 * alpha)),
        "C0": (2, one),
        "C1": (2, alpha),
        "C2": (2, np.sin(alpha)),
        "C3": (2, np.cos(alpha)),
        "C4": (2, np.sin(2 * alpha)),
        "C5": (2, np.cos(2 * alpha)),
        "C6": (2, 1.0 / rho),
        "C7": (2, np.sin(theta)),
        "C8": (2, np.cos(theta)),
        "C9": (2, np.sin(3 * theta)),
        "C10": (2, np.cos(3 * theta)),
    }
    return table[name]


def _wrap(a):
    return a - TWO_PI * np.ceil((a - np.pi) / TWO_PI)


class ScipyPeer:
    """Whitened residuals of the point-based model with S1's Xs, Ys, Zs, kappa held fixed,
    levelling as compensator readings (as tlsjax)."""

    def __init__(self, net, scanner: tj.Scanner, fixed_scan: int = 0):
        self.obs = np.asarray(net.observations, dtype=np.float64)
        self.w = 1.0 / np.asarray(net.sigmas, dtype=np.float64)
        self.ti = np.asarray(net.target_index)
        self.si = np.asarray(net.scan_index)
        self.n_t, self.n_s = len(net.targets), len(net.scans)
        self.ap_names = tuple(scanner.aps)
        self.n_a = len(self.ap_names)
        rho, theta, alpha = self.obs.T
        # Delta is linear in the APs with bases evaluated at the observations: precompute them.
        self.basis = np.zeros((3, len(rho), self.n_a))  # per group
        self.ap_group = np.zeros(self.n_a, dtype=int)
        for k, name in enumerate(self.ap_names):
            g, b = _ap_basis(
                name,
                rho,
                theta,
                alpha,
                scanner.architecture,
                scanner.unit_length,
                scanner.unit_length_2,
            )
            self.basis[g, :, k] = b
            self.ap_group[k] = g
        lev_sigma = np.asarray(net.levelling_sigma, dtype=np.float64)
        self.lev_mask = np.isfinite(lev_sigma)  # (s, 2)
        self.lev = np.asarray(net.levelling, dtype=np.float64)[self.lev_mask]
        self.lev_w = 1.0 / lev_sigma[self.lev_mask]
        self.lev_scan, self.lev_comp = np.nonzero(self.lev_mask)  # scan, 0=omega / 1=phi
        # Datum: hold Xs, Ys, Zs, kappa of the fixed scan (levelled network: 4-dof defect).
        levelled = self.lev_mask.any()
        eop_free = np.ones((self.n_s, 6), dtype=bool)
        eop_free[fixed_scan, [0, 1, 2, 5] if levelled else list(range(6))] = False
        self.eop_free = eop_free
        self.n_obs = 3 * len(rho) + len(self.lev)

    # -- parameter vector <-> (targets, eops, aps) --
    def pack(self, targets, eops, aps):
        return np.concatenate([np.ravel(targets), np.asarray(eops)[self.eop_free], np.ravel(aps)])

    def unpack(self, x, eops0):
        n3 = 3 * self.n_t
        nf = int(self.eop_free.sum())
        T = x[:n3].reshape(self.n_t, 3)
        E = np.array(eops0, dtype=np.float64, copy=True)
        E[self.eop_free] = x[n3 : n3 + nf]
        A = x[n3 + nf :]
        return T, E, A

    @property
    def n_unknowns(self):
        return 3 * self.n_t + int(self.eop_free.sum()) + self.n_a

    # -- the model --
    def residual_full(self, T, E, A):
        """Whitened residuals for full (targets, eops, aps): 3 per observation + levelling."""
        R = rotations(E[:, 3], E[:, 4], E[:, 5])
        d = T[self.ti] - E[self.si, :3]
        x = np.einsum("nij,nj->ni", R[self.si], d)
        rho = np.sqrt(np.einsum("ni,ni->n", x, x))
        theta = np.mod(np.arctan2(x[:, 1], x[:, 0]), TWO_PI)
        alpha = np.arctan2(x[:, 2], np.hypot(x[:, 0], x[:, 1]))
        delta = self.basis @ A  # (3, n)
        f = (
            np.stack(
                [
                    rho + delta[0] - self.obs[:, 0],
                    _wrap(theta + delta[1] - self.obs[:, 1]),
                    _wrap(alpha + delta[2] - self.obs[:, 2]),
                ],
                axis=1,
            )
            * self.w
        )
        # Levelling as tlsjax models it: the dual-axis compensator reads the object-space
        # vertical in scanner space, g = R e3: omega_c = asin(g_y), phi_c = asin(-g_x / cos omega_c)
        # (it depends on kappa too, unlike the Cardan omega and phi).
        g = R[:, :, 2]
        gy = np.clip(g[:, 1], -1.0, 1.0)
        reading = np.stack(
            [np.arcsin(gy), np.arcsin(np.clip(-g[:, 0] / np.sqrt(1.0 - gy * gy), -1.0, 1.0))],
            axis=1,
        )
        lev = (reading[self.lev_scan, self.lev_comp] - self.lev) * self.lev_w
        return np.concatenate([f.ravel(), lev])

    def residual(self, x, eops0):
        self.calls += 1
        return self.residual_full(*self.unpack(x, eops0))

    def jac_sparsity(self):
        n3 = 3 * self.n_t
        eop_col = -np.ones((self.n_s, 6), dtype=int)
        eop_col[self.eop_free] = n3 + np.arange(int(self.eop_free.sum()))
        ap_col0 = n3 + int(self.eop_free.sum())
        rows, cols = [], []
        n = len(self.ti)
        for g in range(3):
            r = 3 * np.arange(n) + g
            for c in range(3):  # target
                rows.append(r)
                cols.append(3 * self.ti + c)
            for c in range(6):  # scan pose
                cc = eop_col[self.si, c]
                ok = cc >= 0
                rows.append(r[ok])
                cols.append(cc[ok])
            for k in np.flatnonzero(self.ap_group == g):  # APs of this group only
                rows.append(r)
                cols.append(np.full(n, ap_col0 + k))
        r_lev = 3 * n + np.arange(len(self.lev))
        for c in (3, 4, 5):  # a compensator reading depends on omega, phi and kappa
            c_lev = eop_col[self.lev_scan, c]
            ok = c_lev >= 0
            rows.append(r_lev[ok])
            cols.append(c_lev[ok])
        rows, cols = np.concatenate(rows), np.concatenate(cols)
        return sp.csr_matrix(
            (np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(self.n_obs, self.n_unknowns)
        )

    def solve(self, targets0, eops0, **kw):
        x0 = self.pack(targets0, eops0, np.zeros(self.n_a))
        self.calls = 0
        return least_squares(
            self.residual,
            x0,
            args=(eops0,),
            method="trf",
            jac_sparsity=self._sparsity,
            x_scale="jac",
            **kw,
        )

    def prepare(self):
        self._sparsity = self.jac_sparsity()


# ---------------------------------------------------------------------------------------------
# Timing helpers
# ---------------------------------------------------------------------------------------------


def machine_info():
    cpu_model = platform.processor() or ""
    try:
        with open("/proc/cpuinfo") as fh:
            for line in fh:
                if line.startswith("model name"):
                    cpu_model = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    from tlsjax._cli._common import available_cpus

    return {
        "platform": platform.platform(),
        "machine": platform.machine(),
        "cpu_model": cpu_model,
        "cpu_count": os.cpu_count(),
        "cpus_available": available_cpus(),
        "python": sys.version.split()[0],
        "jax_version": jax.__version__,
        "jaxlib_version": getattr(jax.lib, "__version__", None) or _jaxlib_version(),
        "jax_backend": jax.default_backend(),
        "jax_devices": [str(d) for d in jax.devices()],
        "jax_device_kind": jax.devices()[0].device_kind,
        "jax_x64": bool(jax.config.jax_enable_x64),
        "numpy_version": np.__version__,
        "scipy_version": scipy.__version__,
        "tlsjax_version": tj.__version__,
        "XLA_FLAGS": os.environ.get("XLA_FLAGS", ""),
    }


def _jaxlib_version():
    try:
        import jaxlib

        return jaxlib.__version__
    except Exception:  # pragma: no cover
        return None


def bench_case(
    label: str,
    aps: str,
    repeats: int,
    scipy_repeats: int,
    tol: float,
    lsmr_tol: float,
    max_nfev: int,
):
    load_before = loadavg()
    sim = tj.simulate(seed=0, architecture="hybrid", tilted=True, aps=aps)
    net = sim.network
    scanner = tj.Scanner(architecture="hybrid", aps=aps)
    model = tj.CalibrationModel(scanner)
    opts = tj.SolverOptions(full_covariance=False)
    out = {
        "aps": aps,
        "ap_names": list(scanner.aps),
        "n_aps": len(scanner.aps),
        "n_targets": len(net.targets),
        "n_scans": len(net.scans),
        "n_target_observations": int(net.observations.shape[0]),
    }

    # ---- tlsjax: host-side plan, AOT compile, compiled runs ----
    t0 = time.perf_counter()
    adj = tj.Adjustment(net, model, opts)
    plan = adj.plan  # the index plan with the layout the engine chose (grid or segments)
    p0 = adj.initial
    t1 = time.perf_counter()
    out["tlsjax_plan_s"] = t1 - t0  # index plan + approximate values (host)
    args = (
        plan.spec,
        plan.problem,
        p0,
        opts.arrays(),
        opts.full_covariance,
    )
    t0 = time.perf_counter()
    lowered = _run.lower(*args)
    t1 = time.perf_counter()
    compiled = lowered.compile()
    t2 = time.perf_counter()
    out["tlsjax_lower_s"] = t1 - t0
    out["tlsjax_xla_compile_s"] = t2 - t1
    out["compile_s"] = t2 - t0
    dyn = (plan.problem, p0, opts.arrays())
    jax.block_until_ready(compiled(*dyn))  # first call (allocation, thread pools)
    out["run_s"], res_c = timed(lambda: jax.block_until_ready(compiled(*dyn)), repeats)
    state, _ = res_c
    out["run_iterations"] = int(state.iteration)
    out["layout"] = ["grid" if lay is not None else "segments" for lay in plan.problem.layouts]
    # Where an iteration's time goes (each phase compiled and timed on its own).
    costs = {}
    out["phases_ms"] = phase_times(plan.spec, plan.problem, p0, opts.arrays(), repeats, costs)
    out["run_ms_per_pass"] = 1e3 * out["run_s"]["median"] / (out["run_iterations"] + 1)
    # The work beside the time: flops and bytes of the compiled run (iterations + 1 passes,
    # iterations steps, the quality pass) and the time at the machine's matmul rate.
    n_it = out["run_iterations"]
    out["arithmetic"] = arithmetic(costs, n_it + 1, n_it, out["run_s"]["median"], matmul_gflops())

    # ---- tlsjax: public calibrate after warm-up ----
    t0 = time.perf_counter()
    res = tj.calibrate(net, model, opts)
    # First call after the AOT compile above: jit's dispatch path finds the executable in
    # JAX's compilation cache, so this is not a cold start (that is compile_s + calibrate_s).
    out["calibrate_first_call_s"] = time.perf_counter() - t0
    # A new network object each call: the plan and approximate values computed, not memoised.
    out["calibrate_s"], res = timed(
        lambda: tj.calibrate(dataclasses.replace(net), model, opts), repeats
    )
    out["iterations"] = res.iterations
    out["converged"] = bool(res.converged)
    out["message"] = res.message
    out["sigma0"] = res.sigma0
    out["dof"] = res.dof
    out["n_observations"] = res.n_observations
    out["n_unknowns"] = res.n_unknowns  # incl. the 4 datum-defect parameters (free network)

    # ---- scipy peer ----
    peer = ScipyPeer(net, scanner, fixed_scan=0)
    t0 = time.perf_counter()
    targets0, eops0 = approximate_values(net)
    peer.prepare()
    out["scipy_setup_s"] = time.perf_counter() - t0  # approximate values + sparsity pattern
    out["scipy_n_unknowns"] = peer.n_unknowns
    out["scipy_n_residuals"] = peer.n_obs
    # Consistency of the two models: numpy residuals at tlsjax's estimate reproduce v^T P v.
    r_tj = peer.residual_full(res.target_xyz, res.eops, np.nan_to_num(res.ap_values))
    out["numpy_vtpv_at_tlsjax_solution"] = float(r_tj @ r_tj)
    out["tlsjax_vtpv"] = float(res.sigma0**2 * res.dof)
    # The timed peer: tight tolerances, including LSMR's (scipy's default atol = btol = 1e-6 of
    # the inner LSMR solves stalls on the 23-AP case: hundreds of steps, chi^2 not at the minimum).
    kw = dict(
        ftol=tol,
        xtol=tol,
        gtol=tol,
        tr_options=dict(atol=lsmr_tol, btol=lsmr_tol),
        max_nfev=max_nfev,
    )
    out["scipy_s"], sol = timed(lambda: peer.solve(targets0, eops0, **kw), scipy_repeats)
    out["scipy_options"] = {
        "method": "trf",
        "jac_sparsity": "exact pattern (targets, free EOPs, APs of the row's group)",
        "x_scale": "jac",
        "tr_solver": "lsmr (default for a sparse Jacobian)",
        "ftol": tol,
        "xtol": tol,
        "gtol": tol,
        "tr_options": {"atol": lsmr_tol, "btol": lsmr_tol},
        "max_nfev": max_nfev,
    }
    out["scipy_nfev"] = int(sol.nfev)
    out["scipy_njev"] = int(sol.njev) if sol.njev is not None else None
    out["scipy_residual_calls"] = peer.calls  # incl. the finite-difference Jacobian evaluations
    out["scipy_jac_groups"] = int((peer.calls - sol.nfev) / max(sol.njev or 1, 1))
    out["scipy_status"] = int(sol.status)
    out["scipy_message"] = sol.message
    dof_peer = peer.n_obs - peer.n_unknowns
    out["scipy_vtpv"] = float(2 * sol.cost)
    out["scipy_sigma0"] = float(np.sqrt(2 * sol.cost / dof_peer))
    _, _, ap_peer = peer.unpack(sol.x, eops0)
    diff = (ap_peer - res.ap_values) / res.ap_sigmas
    out["ap_tlsjax"] = dict(zip(res.ap_names, map(float, res.ap_values)))
    out["ap_sigma_tlsjax"] = dict(zip(res.ap_names, map(float, res.ap_sigmas)))
    out["ap_scipy"] = dict(zip(res.ap_names, map(float, ap_peer)))
    out["max_ap_diff_sigma"] = float(np.nanmax(np.abs(diff)))
    out["max_ap_diff_name"] = res.ap_names[int(np.nanargmax(np.abs(diff)))]
    out["ap_agree_1e-3_sigma"] = bool(out["max_ap_diff_sigma"] <= 1e-3)
    # The identical problem in tlsjax: datum "fixed-scan" holds S1's Xs, Ys, Zs, kappa at the same
    # approximate values, as the peer does.
    resf = tj.calibrate(
        net, tj.CalibrationModel(scanner, datum="fixed-scan", fixed_scan=net.scans[0]), opts
    )
    diff_f = (ap_peer - resf.ap_values) / resf.ap_sigmas
    out["tlsjax_fixed_scan_vtpv"] = float(resf.sigma0**2 * resf.dof)
    out["max_ap_diff_sigma_vs_tlsjax_fixed_scan"] = float(np.nanmax(np.abs(diff_f)))
    out["max_ap_diff_sigma_tlsjax_inner_vs_fixed_scan"] = float(
        np.nanmax(np.abs((res.ap_values - resf.ap_values) / res.ap_sigmas))
    )
    out["speedup"] = out["scipy_s"]["median"] / out["run_s"]["median"]
    out["speedup_vs_calibrate"] = out["scipy_s"]["median"] / out["calibrate_s"]["median"]

    # For information: the peer with scipy's default tolerances (one run).
    t0 = time.perf_counter()
    sol_d = peer.solve(targets0, eops0, max_nfev=max_nfev)
    dt = time.perf_counter() - t0
    _, _, ap_d = peer.unpack(sol_d.x, eops0)
    out["scipy_default_tolerances"] = {
        "s": dt,
        "nfev": int(sol_d.nfev),
        "residual_calls": peer.calls,
        "status": int(sol_d.status),
        "vtpv": float(2 * sol_d.cost),
        "max_ap_diff_sigma_vs_tlsjax_fixed_scan": float(
            np.nanmax(np.abs((ap_d - resf.ap_values) / resf.ap_sigmas))
        ),
    }
    out["loadavg_1_5_15_before"] = load_before
    out["loadavg_1_5_15_after"] = loadavg()
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="benchmarks/results/point.json")
    ap.add_argument(
        "--repeats",
        type=int,
        default=30,
        help="timed runs of the compiled adjustment and of calibrate (>= 20)",
    )
    ap.add_argument(
        "--scipy-repeats", type=int, default=3, help="timed runs of the scipy peer (>= 3)"
    )
    ap.add_argument(
        "--scipy-tol", type=float, default=1e-10, help="ftol = xtol = gtol of least_squares"
    )
    ap.add_argument(
        "--lsmr-tol", type=float, default=1e-12, help="atol = btol of the LSMR trust-region solves"
    )
    ap.add_argument("--max-nfev", type=int, default=1000, help="max_nfev of least_squares")
    ap.add_argument(
        "--cases", default=",".join(CASES), help=f"comma-separated subset of {list(CASES)}"
    )
    a = ap.parse_args(argv)

    info = machine_info()
    results = {
        "benchmark": "point-based self-calibration, Chow 2013 room (seed 0, hybrid, tilted)",
        "machine": info,
        "repeats": a.repeats,
        "scipy_repeats": a.scipy_repeats,
        "cases": {},
    }
    print(
        f"# {info['cpu_model']} | {info['cpus_available']} CPUs | jax {info['jax_version']} "
        f"{info['jax_backend']} {info['jax_devices']}",
        flush=True,
    )
    for label in a.cases.split(","):
        label = label.strip()
        print(f"# case {label} ...", flush=True)
        results["cases"][label] = bench_case(
            label, CASES[label], a.repeats, a.scipy_repeats, a.scipy_tol, a.lsmr_tol, a.max_nfev
        )

    hdr = (
        f"{'case':18s} {'n_obs':>6s} {'n_unk':>6s} {'compile s':>9s} {'run ms':>8s} {'(min)':>7s} "
        f"{'calib ms':>8s} {'it':>3s} {'scipy s':>8s} {'nfev':>5s} {'speedup':>8s} {'dAP/sig in':>10s} {'dAP/sig fx':>10s}"
    )
    print(hdr)
    print("-" * len(hdr))
    for label, c in results["cases"].items():
        print(
            f"{label:18s} {c['n_observations']:6d} {c['n_unknowns']:6d} {c['compile_s']:9.2f} "
            f"{1e3 * c['run_s']['median']:8.2f} {1e3 * c['run_s']['min']:7.2f} "
            f"{1e3 * c['calibrate_s']['median']:8.2f} {c['iterations']:3d} {c['scipy_s']['median']:8.3f} "
            f"{c['scipy_nfev']:5d} {c['speedup']:7.1f}x {c['max_ap_diff_sigma']:10.2e} "
            f"{c['max_ap_diff_sigma_vs_tlsjax_fixed_scan']:10.2e}"
        )
    print(
        "# dAP/sig in: peer vs tlsjax (inner-constraint datum); fx: peer vs tlsjax datum='fixed-scan' S1 (the identical problem)"
    )

    write_results(results, a.out)


if __name__ == "__main__":
    main()
