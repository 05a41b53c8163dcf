"""Plane-based self-calibration benchmark (Gauss-Helmert, ~100k observations): tlsjax vs. scipy.

Usage::

    python benchmarks/bench_plane.py [--out benchmarks/results/plane.json] [--repeats N]
                                     [--scipy-repeats M] [--scipy-max-nfev K]

Network: simulated point clouds of the Chow et al. (2013) room (``tj.simulate_point_clouds``,
seed 0, hybrid scanner, tilted variant: 6 scans of which 4 levelled, the room's 6 faces and 3
boards), sampled on a 0.5 deg grid and thinned to at most ``--max-points`` (730) random points
per plane and scan: 33,390 plane points = 100,170 observations (range, hz, el) plus 8 levelling
pseudo-observations. One Gauss-Helmert condition per point (SPEC section 4),
``g = n . (R^T x(l - Delta(l)) + S) - d``; AP set "A0 B6 B7 C0".

tlsjax is timed three ways (as in bench_point.py):
  * compile_s: ahead-of-time ``_run.lower(...).compile()`` of the whole compiled adjustment
    (Gauss-Newton loop + quality, ``full_covariance=False``);
  * run_s: calls of that compiled executable, ``jax.block_until_ready`` on the outputs;
  * calibrate_s: the public ``tj.calibrate`` after warm-up.

The peer is what a user would otherwise write: ``scipy.optimize.least_squares(method="trf",
jac_sparsity=<exact pattern>, x_scale="jac")`` in plain vectorised numpy, on the same
observations, sigmas, approximate values (``tlsjax._adjustment._approx.approximate_network``) and APs.
least_squares minimises a sum of squares (Gauss-Markov), so each point contributes its
condition divided by its propagated standard deviation, ``g / sqrt(B Sigma_l B^T)`` (the
weighted orthogonal distance), with ``B = dg/dl`` written out analytically. The weights are
held fixed within one least_squares call and re-evaluated at its solution, and the call is
repeated from there until the APs move by less than 1e-4 of their sigma ("iteratively
reweighted"): the fixed point is exactly the Gauss-Helmert estimate. ``--peer-weights current``
instead re-evaluates the weights inside every residual call (one call; the minimiser of
``sum g^2 / m(x)`` differs from the Gauss-Helmert estimate at second order). Planes: a minimal
parametrisation, two tangent-plane coordinates of the normal about its approximate value plus
d. Datum: Xs, Ys, Zs, kappa of scan S1 held at their approximate values (the levelling
pseudo-observations give the tilt); APs are datum invariant.

Each side runs in its own child process (``--child tlsjax|scipy``; the simulation in a third,
``--child data``) so that its peak resident memory is its own: VmHWM of /proc/self/status, with
``ru_maxrss`` recorded beside it (Linux carries a parent's ru_maxrss across fork + exec, so the
parent stays lean). The scipy child never imports JAX. JAX_PLATFORMS defaults to cpu.
"""

from __future__ import annotations

import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import argparse
import dataclasses
import json
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import scipy.sparse as sp
from _common import loadavg, rotations, timed, write_results
from scipy.optimize import least_squares

TWO_PI = 2.0 * np.pi
DEG = np.pi / 180.0
FIXED_SCAN = 0  # S1


# ---------------------------------------------------------------------------------------------
# The scipy peer: plain numpy, written from SPEC sections 1, 3, 4 and 6 (no tlsjax inside).
# ---------------------------------------------------------------------------------------------


def _ap_basis(name: str, rho, theta, alpha, architecture: str, U: float, U2: float):
    """(group index, basis b(l), (db/drho, db/dtheta, db/dalpha)) of one AP term (SPEC section 3).

    The corrections are evaluated at the observations, so the condition depends on l also
    through Delta(l): B = dg/dl needs the derivatives of the bases.
    """
    one, zero = np.ones_like(rho), np.zeros_like(rho)
    ca, sa, ct, st = np.cos(alpha), np.sin(alpha), np.cos(theta), np.sin(theta)
    k, k2 = 4 * np.pi / U, 4 * np.pi / U2
    sec = 1.0 / ca
    r = lambda f, df: (0, f, (df, zero, zero))  # range group, basis of rho
    h = lambda f, df: (1, f, (zero, df, zero))  # hz group, basis of theta
    ha = lambda f, df: (1, f, (zero, zero, df))  # hz group, basis of alpha
    e = lambda f, df: (2, f, (zero, zero, df))  # el group, basis of alpha
    et = lambda f, df: (2, f, (zero, df, zero))  # el group, basis of theta
    table = {
        "A0": (0, one, (zero, zero, zero)),
        "A1": r(rho, one),
        "A2": (0, sa, (zero, zero, ca)),
        "A3": r(np.sin(k * rho), k * np.cos(k * rho)),
        "A4": r(np.cos(k * rho), -k * np.sin(k * rho)),
        "A5": r(np.sin(k2 * rho), k2 * np.cos(k2 * rho)),
        "A6": r(np.cos(k2 * rho), -k2 * np.sin(k2 * rho)),
        "A7": (0, np.sin(4 * theta), (zero, 4 * np.cos(4 * theta), zero)),
        "A8": (0, np.cos(4 * theta), (zero, -4 * np.sin(4 * theta), zero)),
        "B1": h(theta, one),
        "B2": h(st, ct),
        "B3": h(ct, -st),
        "B4": h(np.sin(2 * theta), 2 * np.cos(2 * theta)),
        "B5": h(np.cos(2 * theta), -2 * np.sin(2 * theta)),
        "B6": ha(sec - (1.0 if architecture == "hybrid" else 0.0), sec * sa * sec),
        "B7": ha(sa * sec, sec * sec),
        "B8": (1, 1.0 / rho, (-1.0 / rho**2, zero, zero)),
        "B9": ha(sa, ca),
        "B10": ha(ca, -sa),
        "B11": ha(np.sin(3 * alpha), 3 * np.cos(3 * alpha)),
        "B12": ha(np.sin(4 * alpha), 4 * np.cos(4 * alpha)),
        "C0": (2, one, (zero, zero, zero)),
        "C1": e(alpha, one),
        "C2": e(sa, ca),
        "C3": e(ca, -sa),
        "C4": e(np.sin(2 * alpha), 2 * np.cos(2 * alpha)),
        "C5": e(np.cos(2 * alpha), -2 * np.sin(2 * alpha)),
        "C6": (2, 1.0 / rho, (-1.0 / rho**2, zero, zero)),
        "C7": et(st, ct),
        "C8": et(ct, -st),
        "C9": et(np.sin(3 * theta), 3 * np.cos(3 * theta)),
        "C10": et(np.cos(3 * theta), -3 * np.sin(3 * theta)),
    }
    g, b, db = table[name]
    return g, b, np.stack(db, axis=-1)


def _tangent_basis(n0):
    """Two unit vectors orthogonal to each unit normal n0 (k, 3) and to each other."""
    axis = np.eye(3)[np.argmin(np.abs(n0), axis=1)]
    u = np.cross(n0, axis)
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    return u, np.cross(n0, u)


class ScipyPlanePeer:
    """Whitened Gauss-Helmert conditions ``g / sqrt(B Sigma_l B^T)`` of the plane points plus the
    levelling pseudo-observations (compensator readings, as tlsjax), with S1's Xs, Ys, Zs, kappa
    held. Unknowns: per plane (a, b, d) with ``n = (n0 + a u + b v) / |.|``, the free EOPs, APs.

    ``data``: plain arrays (plane_observations, plane_sigmas, plane_index, plane_scan_index,
    levelling, levelling_sigma, planes0 (k, 4), eops0 (s, 6)); nothing from tlsjax.
    """

    def __init__(
        self,
        data,
        ap_names,
        architecture="hybrid",
        unit_length=1.2,
        unit_length_2=0.6,
        fixed_scan=FIXED_SCAN,
    ):
        self.obs = np.asarray(data["plane_observations"], dtype=np.float64)
        self.sig2 = np.asarray(data["plane_sigmas"], dtype=np.float64) ** 2
        self.pi = np.asarray(data["plane_index"]).astype(np.int64)
        self.si = np.asarray(data["plane_scan_index"]).astype(np.int64)
        self.eops0 = np.asarray(data["eops0"], dtype=np.float64)
        P0 = np.asarray(data["planes0"], dtype=np.float64)
        self.n0 = P0[:, :3] / np.linalg.norm(P0[:, :3], axis=1, keepdims=True)
        self.d0 = P0[:, 3] / np.linalg.norm(P0[:, :3], axis=1)
        self.u0, self.v0 = _tangent_basis(self.n0)
        self.n_k, self.n_s = len(self.n0), len(self.eops0)
        self.ap_names = tuple(ap_names)
        self.n_a = len(self.ap_names)
        rho, theta, alpha = self.obs.T
        m = len(rho)
        # Delta(l) = basis(l) @ AP per group, and dDelta/dl = dbasis(l) @ AP: both precomputed.
        self.basis = np.zeros((3, m, self.n_a))
        self.dbasis = np.zeros((3, m, 3, self.n_a))
        self.ap_group = np.zeros(self.n_a, dtype=int)
        for k, name in enumerate(self.ap_names):
            g, b, db = _ap_basis(name, rho, theta, alpha, architecture, unit_length, unit_length_2)
            self.basis[g, :, k] = b
            self.dbasis[g, :, :, k] = db
            self.ap_group[k] = g
        lev_sigma = np.asarray(data["levelling_sigma"], dtype=np.float64)
        self.lev_mask = np.isfinite(lev_sigma)
        self.lev = np.asarray(data["levelling"], dtype=np.float64)[self.lev_mask]
        self.lev_w = 1.0 / lev_sigma[self.lev_mask]
        self.lev_scan, self.lev_comp = np.nonzero(self.lev_mask)
        levelled = self.lev_mask.any()
        eop_free = np.ones((self.n_s, 6), dtype=bool)
        eop_free[fixed_scan, [0, 1, 2, 5] if levelled else list(range(6))] = False
        self.eop_free = eop_free
        self.n_cond = m
        self.n_res = m + len(self.lev)
        self.frozen_m = None  # None: weights re-evaluated in every call ("current")
        self.calls = 0
        self.residual_time = 0.0

    # -- parameter vector <-> (planes (k, 4), eops (s, 6), aps) --
    @property
    def n_unknowns(self):
        return 3 * self.n_k + int(self.eop_free.sum()) + self.n_a

    def planes_from(self, ab_d):
        ab_d = ab_d.reshape(self.n_k, 3)
        n = self.n0 + ab_d[:, :1] * self.u0 + ab_d[:, 1:2] * self.v0
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        return np.concatenate([n, ab_d[:, 2:]], axis=1)

    def pack(self, planes, eops, aps):
        """Planes (k, 4) (unit normal + d) -> (a, b, d) about the approximate normals."""
        n = planes[:, :3] / np.linalg.norm(planes[:, :3], axis=1, keepdims=True)
        c = np.einsum("ki,ki->k", n, self.n0)
        a = np.einsum("ki,ki->k", n, self.u0) / c
        b = np.einsum("ki,ki->k", n, self.v0) / c
        pl = np.stack([a, b, planes[:, 3] / np.linalg.norm(planes[:, :3], axis=1)], axis=1)
        return np.concatenate([pl.ravel(), np.asarray(eops)[self.eop_free], np.ravel(aps)])

    def unpack(self, x):
        n3 = 3 * self.n_k
        nf = int(self.eop_free.sum())
        E = self.eops0.copy()
        E[self.eop_free] = x[n3 : n3 + nf]
        return self.planes_from(x[:n3]), E, x[n3 + nf :]

    def x0(self):
        return self.pack(
            np.concatenate([self.n0, self.d0[:, None]], axis=1), self.eops0, np.zeros(self.n_a)
        )

    # -- the model --
    def conditions(self, P, E, A):
        """g (m,) [m] and its variance m = B Sigma_l B^T (m,) at planes P, poses E, APs A."""
        R = rotations(E[:, 3], E[:, 4], E[:, 5])
        Rn = np.einsum("kij,kj->ki", R[self.si], P[self.pi, :3])  # R n: n . R^T x = (R n) . x
        delta = self.basis @ A  # (3, m)
        rho = self.obs[:, 0] - delta[0]
        th = self.obs[:, 1] - delta[1]
        al = self.obs[:, 2] - delta[2]
        ca, sa, ct, st = np.cos(al), np.sin(al), np.cos(th), np.sin(th)
        u = np.stack([ca * ct, ca * st, sa], axis=1)
        nS = np.einsum("mi,mi->m", P[self.pi, :3], E[self.si, :3])
        Rnu = np.einsum("mi,mi->m", Rn, u)
        g = rho * Rnu + nS - P[self.pi, 3]
        # dg/dl' at the corrected observations l' = l - Delta(l) ...
        b_rho = Rnu
        b_th = rho * ca * (Rn[:, 1] * ct - Rn[:, 0] * st)
        b_al = rho * (Rn[:, 2] * ca - sa * (Rn[:, 0] * ct + Rn[:, 1] * st))
        bp = np.stack([b_rho, b_th, b_al], axis=1)
        # ... times dl'/dl = I - dDelta/dl.
        dD = self.dbasis @ A  # (3 groups, m, 3 obs)
        B = bp - np.einsum("gm,gmh->mh", bp.T, dD)
        return g, np.einsum("mh,mh->m", B * B, self.sig2)

    def levelling_residuals(self, E):
        R = rotations(E[:, 3], E[:, 4], E[:, 5])
        gv = R[:, :, 2]  # object-space vertical in scanner space (compensator, as tlsjax)
        gy = np.clip(gv[:, 1], -1.0, 1.0)
        reading = np.stack(
            [np.arcsin(gy), np.arcsin(np.clip(-gv[:, 0] / np.sqrt(1.0 - gy * gy), -1.0, 1.0))],
            axis=1,
        )
        return (reading[self.lev_scan, self.lev_comp] - self.lev) * self.lev_w

    def residual_full(self, P, E, A, m=None):
        g, m_here = self.conditions(P, E, A)
        m = m_here if m is None else m
        return np.concatenate([g / np.sqrt(m), self.levelling_residuals(E)])

    def residual(self, x):
        self.calls += 1
        t0 = time.perf_counter()
        r = self.residual_full(*self.unpack(x), m=self.frozen_m)
        self.residual_time += time.perf_counter() - t0
        return r

    def jac_sparsity(self):
        n3 = 3 * self.n_k
        eop_col = -np.ones((self.n_s, 6), dtype=int)
        eop_col[self.eop_free] = n3 + np.arange(int(self.eop_free.sum()))
        ap_col0 = n3 + int(self.eop_free.sum())
        r = np.arange(self.n_cond)
        rows, cols = [], []
        for c in range(3):  # the point's plane
            rows.append(r)
            cols.append(3 * self.pi + c)
        for c in range(6):  # the scan's pose
            cc = eop_col[self.si, c]
            ok = cc >= 0
            rows.append(r[ok])
            cols.append(cc[ok])
        for k in range(self.n_a):  # every AP enters every condition
            rows.append(r)
            cols.append(np.full(self.n_cond, ap_col0 + k))
        r_lev = self.n_cond + np.arange(len(self.lev))
        for c in (3, 4, 5):  # a compensator reading depends on omega, phi and kappa
            c_lev = eop_col[self.lev_scan, c]
            ok = c_lev >= 0
            rows.append(r_lev[ok])
            cols.append(c_lev[ok])
        rows, cols = np.concatenate(rows), np.concatenate(cols)
        return sp.csr_matrix(
            (np.ones(len(rows), dtype=np.int8), (rows, cols)), shape=(self.n_res, self.n_unknowns)
        )

    def prepare(self):
        self._sparsity = self.jac_sparsity()

    def ap_sigmas(self, sol):
        """A posteriori AP sigmas from the final Jacobian, (J^T J)^-1 s0^2 (fixed-scan datum)."""
        J = sol.jac
        N = (J.T @ J).toarray() if sp.issparse(J) else np.asarray(J).T @ np.asarray(J)
        Q = np.linalg.inv(N)
        s0sq = 2 * sol.cost / (self.n_res - self.n_unknowns)
        return np.sqrt(np.diag(Q)[-self.n_a :] * s0sq)

    def solve(self, weights="frozen", max_passes=10, ap_tol=1e-4, max_nfev=None, **kw):
        """``weights="frozen"``: m held within a least_squares call and re-evaluated at its
        solution, repeated until the APs move by < ap_tol of their sigma (the Gauss-Helmert
        estimate); ``"current"``: m re-evaluated in every residual call, one call.
        ``max_nfev`` bounds the function evaluations of all calls together."""
        x = self.x0()
        self.calls = 0
        self.residual_time = 0.0
        passes, nfev, njev = [], 0, 0
        for _ in range(max_passes if weights == "frozen" else 1):
            self.frozen_m = self.conditions(*self.unpack(x))[1] if weights == "frozen" else None
            left = None if max_nfev is None else max(max_nfev - nfev, 1)
            sol = least_squares(
                self.residual,
                x,
                method="trf",
                jac_sparsity=self._sparsity,
                x_scale="jac",
                max_nfev=left,
                **kw,
            )
            nfev += sol.nfev
            njev += sol.njev or 0
            dx = sol.x - x
            x = sol.x
            step = None
            if weights == "frozen":
                step = float(np.max(np.abs(dx[-self.n_a :]) / self.ap_sigmas(sol)))
            passes.append(
                {
                    "nfev": int(sol.nfev),
                    "status": int(sol.status),
                    "vtpv": float(2 * sol.cost),
                    "max_ap_step_sigma": step,
                }
            )
            if (
                weights != "frozen"
                or sol.status <= 0
                or step < ap_tol
                or (max_nfev is not None and nfev >= max_nfev)
            ):
                break
        self.frozen_m = None
        # The Gauss-Helmert v^T P v at the final estimate (weights evaluated there).
        r = self.residual_full(*self.unpack(x))
        converged = bool(sol.status > 0 and (weights != "frozen" or step < ap_tol))
        return {
            "x": x,
            "sol": sol,
            "passes": passes,
            "nfev": nfev,
            "njev": njev,
            "residual_calls": self.calls,
            "residual_time_s": self.residual_time,
            "converged": converged,
            "vtpv": float(r @ r),
            "status": int(sol.status),
            "message": sol.message,
        }


# ---------------------------------------------------------------------------------------------
# Helpers
# ---------------------------------------------------------------------------------------------


def _peak_mb():
    """Peak resident memory of this process [MB]: VmHWM of /proc/self/status where available.

    ``ru_maxrss`` (RUSAGE_SELF) is not used for the headline figure: Linux carries the parent's
    high-water mark across fork + exec into the child's ru_maxrss, so a child would report at
    least its parent's peak. VmHWM belongs to the exec'd address space only. Both are recorded.
    """
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmHWM:"):
                    return int(line.split()[1]) / 1024.0  # kB
    except OSError:  # pragma: no cover - not Linux
        pass
    return _ru_maxrss_mb()


def _ru_maxrss_mb():
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: KiB


def _rss_mb():
    try:
        with open("/proc/self/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1]) / 1024.0
    except OSError:  # pragma: no cover
        pass
    return None


def machine_info():
    # bench_point's record (CPU, Python, jax, numpy, scipy, tlsjax), imported here and not at the
    # top: the scipy child must not import JAX.
    from bench_point import machine_info as point_machine_info

    info = point_machine_info()
    info.update(
        JAX_PLATFORMS=os.environ.get("JAX_PLATFORMS", ""), XLA_FLAGS=os.environ.get("XLA_FLAGS", "")
    )
    return info


def build_data(a, workdir: Path) -> dict:
    """Simulate, build the plane network and its approximate values; save them for the children.

    Runs in a child process of its own: the simulation (over a million rays) would otherwise
    raise the benchmark parent's memory, which the measuring children inherit in ru_maxrss.
    """
    import pickle

    import tlsjax as tj
    from tlsjax._adjustment._approx import approximate_network

    t0 = time.perf_counter()
    design = tj.CloudDesign(
        angular_step=a.angular_step_deg * DEG, architecture="hybrid", tilted=True, aps=a.aps
    )
    clouds = tj.simulate_point_clouds(design, seed=a.seed)
    t1 = time.perf_counter()
    net = clouds.to_network(max_points=a.max_points, seed=a.seed, levelling=True)
    t2 = time.perf_counter()
    targets0, eops0, planes0 = approximate_network(net)
    t3 = time.perf_counter()
    with open(workdir / "net.pkl", "wb") as fh:
        pickle.dump(net, fh)
    np.savez(
        workdir / "data.npz",
        plane_observations=net.plane_observations,
        plane_sigmas=net.plane_sigmas,
        plane_index=net.plane_index,
        plane_scan_index=net.plane_scan_index,
        levelling=net.levelling,
        levelling_sigma=net.levelling_sigma,
        planes0=planes0,
        eops0=eops0,
    )
    counts = np.zeros((len(net.scans), len(net.planes)), dtype=int)
    np.add.at(counts, (net.plane_scan_index, net.plane_index), 1)
    return {
        "design": {
            "angular_step_deg": a.angular_step_deg,
            "architecture": "hybrid",
            "tilted": True,
            "seed": a.seed,
            "max_points_per_plane_per_scan": a.max_points,
            "aps": a.aps,
            "true_aps": {k: float(v) for k, v in clouds.true_aps.items()},
        },
        "simulated_points": int(sum(len(o) for o in clouds.observations)),
        "n_planes": len(net.planes),
        "planes": list(net.planes),
        "n_scans": len(net.scans),
        "scans": list(net.scans),
        "levelled_scans": [s for s, lv in zip(net.scans, net.is_levelled) if lv],
        "n_plane_points": int(net.plane_observations.shape[0]),
        "n_observations_network": int(net.n_observations),  # 3 per plane point
        "n_levelling_observations": int(2 * net.is_levelled.sum()),
        "points_per_scan_and_plane": {
            s: dict(zip(net.planes, map(int, row))) for s, row in zip(net.scans, counts)
        },
        "simulate_s": t1 - t0,
        "to_network_s": t2 - t1,
        "approximate_network_s": t3 - t2,
    }


# ---------------------------------------------------------------------------------------------
# Child processes: one side each, so that ru_maxrss is that side's peak.
# ---------------------------------------------------------------------------------------------


def child_tlsjax(a, workdir: Path) -> dict:
    import pickle

    import jax

    import tlsjax as tj
    from tlsjax._adjustment._calibrate import _run

    with open(workdir / "net.pkl", "rb") as fh:
        net = pickle.load(fh)
    out = {"setup_peak_mb": _peak_mb()}  # python + jax + tlsjax + the network
    scanner = tj.Scanner(architecture="hybrid", aps=a.aps)
    model = tj.CalibrationModel(scanner)
    opts = tj.SolverOptions(full_covariance=False)

    t0 = time.perf_counter()
    adj = tj.Adjustment(net, model, opts)
    plan = adj.plan  # the index plan with the layout the engine chose (grid or segments)
    p0 = adj.initial
    out["tlsjax_plan_s"] = time.perf_counter() - t0  # index plan + approximate values (host)
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
    out["compile_peak_mb"] = _peak_mb()
    try:
        ma = compiled.memory_analysis()
        out["xla_memory_analysis_mb"] = {
            k: getattr(ma, k) / 2**20
            for k in (
                "argument_size_in_bytes",
                "output_size_in_bytes",
                "temp_size_in_bytes",
                "generated_code_size_in_bytes",
            )
        }
    except Exception as exc:  # pragma: no cover - backend without memory analysis
        out["xla_memory_analysis_mb"] = repr(exc)
    dyn = (plan.problem, p0, opts.arrays())
    t0 = time.perf_counter()
    jax.block_until_ready(compiled(*dyn))  # first call (allocation, thread pools)
    out["run_first_call_s"] = time.perf_counter() - t0
    out["run_s"], res_c = timed(lambda: jax.block_until_ready(compiled(*dyn)), a.repeats)
    state, _ = res_c
    out["run_iterations"] = int(state.iteration)
    out["layout"] = ["grid" if lay is not None else "segments" for lay in plan.problem.layouts]
    out["run_ms_per_pass"] = 1e3 * out["run_s"]["median"] / (out["run_iterations"] + 1)

    t0 = time.perf_counter()
    res = tj.calibrate(net, model, opts)
    out["calibrate_first_call_s"] = time.perf_counter() - t0  # reuses the compilation cache
    # A new network object each call: the plan and approximate values computed, not memoised.
    out["calibrate_s"], res = timed(
        lambda: tj.calibrate(dataclasses.replace(net), model, opts), a.repeats
    )
    out["peak_mb"] = _peak_mb()  # everything above: imports, plan, compile, runs, calibrate
    out["ru_maxrss_mb"] = _ru_maxrss_mb()
    # Where an iteration's time goes (each phase compiled and timed on its own; after the
    # peak memory figure above, which it would otherwise raise).
    from _phases import arithmetic, matmul_gflops, phase_times

    costs = {}
    out["phases_ms"] = phase_times(plan.spec, plan.problem, p0, opts.arrays(), a.repeats, costs)
    n_it = out["run_iterations"]
    out["arithmetic"] = arithmetic(costs, n_it + 1, n_it, out["run_s"]["median"], matmul_gflops())
    out["machine"] = machine_info()
    out.update(
        iterations=res.iterations,
        converged=bool(res.converged),
        message=res.message,
        sigma0=res.sigma0,
        dof=res.dof,
        n_observations=res.n_observations,
        n_unknowns=res.n_unknowns,
        vtpv=float(res.sigma0**2 * res.dof),
        ap_names=list(res.ap_names),
    )
    # The identical problem to the peer's: S1's Xs, Ys, Zs, kappa held (after the peak above).
    resf = tj.calibrate(
        net,
        tj.CalibrationModel(scanner, datum="fixed-scan", fixed_scan=net.scans[FIXED_SCAN]),
        opts,
    )
    out.update(
        fixed_scan_converged=bool(resf.converged),
        fixed_scan_iterations=resf.iterations,
        fixed_scan_vtpv=float(resf.sigma0**2 * resf.dof),
    )
    np.savez(
        workdir / "tlsjax_solution.npz",
        planes=res.plane_params,
        eops=res.eops,
        aps=res.ap_values,
        ap_sigmas=res.ap_sigmas,
        planes_f=resf.plane_params,
        eops_f=resf.eops,
        aps_f=resf.ap_values,
        ap_sigmas_f=resf.ap_sigmas,
    )
    return out


def child_scipy(a, workdir: Path) -> dict:
    if "jax" in sys.modules:  # pragma: no cover - guard: the peer's memory must be its own
        raise RuntimeError("the scipy child must not import jax")
    data = dict(np.load(workdir / "data.npz"))
    out = {"setup_peak_mb": _peak_mb()}  # python + numpy + scipy + the data
    t0 = time.perf_counter()
    peer = ScipyPlanePeer(data, a.aps.split())
    peer.prepare()
    out["scipy_setup_s"] = time.perf_counter() - t0  # AP bases + sparsity pattern
    kw = dict(
        ftol=a.scipy_tol,
        xtol=a.scipy_tol,
        gtol=a.scipy_tol,
        tr_options=dict(atol=a.lsmr_tol, btol=a.lsmr_tol),
    )
    out["scipy_s"], r = timed(
        lambda: peer.solve(weights=a.peer_weights, max_nfev=a.scipy_max_nfev, **kw), a.scipy_repeats
    )
    out["peak_mb"] = _peak_mb()  # imports, data, sparsity pattern, the solves
    out["ru_maxrss_mb"] = _ru_maxrss_mb()
    sol = r["sol"]
    P, E, A = peer.unpack(r["x"])
    out.update(
        weights=a.peer_weights,
        converged=r["converged"],
        status=r["status"],
        message=r["message"],
        nfev=r["nfev"],
        njev=r["njev"],
        residual_calls=r["residual_calls"],
        residual_time_s=r["residual_time_s"],
        passes=r["passes"],
        jac_groups=int((r["residual_calls"] - r["nfev"]) / max(r["njev"], 1)),
        n_unknowns=peer.n_unknowns,
        n_residuals=peer.n_res,
        vtpv=r["vtpv"],
        sigma0=float(np.sqrt(r["vtpv"] / (peer.n_res - peer.n_unknowns))),
        jac_nnz=int(peer._sparsity.nnz),
    )
    out["ap_sigmas_scipy"] = peer.ap_sigmas(sol).tolist()
    np.savez(workdir / "scipy_solution.npz", planes=P, eops=E, aps=A)
    if a.peer_weights == "frozen":
        # For information (one run, after the peak above): weights re-evaluated in every call.
        t0 = time.perf_counter()
        rc = peer.solve(weights="current", max_nfev=a.scipy_max_nfev, **kw)
        dt = time.perf_counter() - t0
        out["current_weights"] = {
            "s": dt,
            "nfev": rc["nfev"],
            "status": rc["status"],
            "converged": rc["converged"],
            "vtpv": rc["vtpv"],
            "aps": peer.unpack(rc["x"])[2].tolist(),
        }
    return out


def _run_child(side: str, a, workdir: Path) -> dict:
    res = workdir / f"{side}.json"
    cmd = [
        sys.executable,
        os.path.abspath(__file__),
        "--child",
        side,
        "--workdir",
        str(workdir),
        "--angular-step-deg",
        repr(a.angular_step_deg),
        "--max-points",
        str(a.max_points),
        "--seed",
        str(a.seed),
        "--aps",
        a.aps,
        "--repeats",
        str(a.repeats),
        "--scipy-repeats",
        str(a.scipy_repeats),
        "--scipy-tol",
        repr(a.scipy_tol),
        "--lsmr-tol",
        repr(a.lsmr_tol),
        "--peer-weights",
        a.peer_weights,
    ]
    if a.scipy_max_nfev is not None:
        cmd += ["--scipy-max-nfev", str(a.scipy_max_nfev)]
    rss_parent = _rss_mb()
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True)
    out = json.loads(res.read_text())
    out["child_wall_s"] = time.perf_counter() - t0
    out["parent_rss_at_spawn_mb"] = rss_parent
    return out


# ---------------------------------------------------------------------------------------------


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", default="benchmarks/results/plane.json")
    ap.add_argument("--angular-step-deg", type=float, default=0.5, help="scanning grid step [deg]")
    ap.add_argument(
        "--max-points", type=int, default=730, help="points kept per plane and scan (random)"
    )
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--aps", default="A0 B6 B7 C0")
    ap.add_argument(
        "--repeats",
        type=int,
        default=20,
        help="timed runs of the compiled adjustment and of calibrate",
    )
    ap.add_argument("--scipy-repeats", type=int, default=3, help="timed runs of the scipy peer")
    ap.add_argument(
        "--scipy-tol", type=float, default=1e-10, help="ftol = xtol = gtol of least_squares"
    )
    ap.add_argument(
        "--lsmr-tol", type=float, default=1e-12, help="atol = btol of the LSMR trust-region solves"
    )
    ap.add_argument(
        "--scipy-max-nfev",
        type=int,
        default=200,
        help="max function evaluations of the peer (all passes)",
    )
    ap.add_argument(
        "--peer-weights",
        choices=("frozen", "current"),
        default="frozen",
        help="frozen: weights held per least_squares call, re-evaluated until the APs settle "
        "(Gauss-Helmert estimate); current: re-evaluated in every residual call",
    )
    ap.add_argument("--child", choices=("data", "tlsjax", "scipy"), help=argparse.SUPPRESS)
    ap.add_argument("--workdir", help=argparse.SUPPRESS)
    a = ap.parse_args(argv)

    if a.child:
        workdir = Path(a.workdir)
        out = {"data": build_data, "tlsjax": child_tlsjax, "scipy": child_scipy}[a.child](
            a, workdir
        )
        (workdir / f"{a.child}.json").write_text(json.dumps(out, indent=2, default=str))
        return

    results = {
        "benchmark": "plane-based self-calibration (Gauss-Helmert), simulated Chow 2013 room point clouds "
        "(hybrid, tilted), tlsjax vs scipy.optimize.least_squares",
        "repeats": a.repeats,
        "scipy_repeats": a.scipy_repeats,
        "loadavg_1_5_15_before": loadavg(),
    }
    # The parent stays lean (numpy and scipy only) until the children have run: see _peak_mb.
    with tempfile.TemporaryDirectory(prefix="bench_plane_") as tmp:
        workdir = Path(tmp)
        print("# simulating the point clouds (child) ...", flush=True)
        nw = results["network"] = _run_child("data", a, workdir)
        print(
            f"# {nw['n_plane_points']} plane points = {nw['n_observations_network']} observations "
            f"(+{nw['n_levelling_observations']} levelling), {nw['n_planes']} planes, {nw['n_scans']} scans",
            flush=True,
        )
        print("# tlsjax child ...", flush=True)
        tj_out = _run_child("tlsjax", a, workdir)
        info = results["machine"] = tj_out.pop("machine")
        print(
            f"# {info['cpu_model']} | {info['cpus_available']} CPUs | jax {info['jax_version']} "
            f"{info['jax_backend']} {info['jax_devices']}",
            flush=True,
        )
        results["loadavg_1_5_15_between"] = loadavg()
        print("# scipy child ...", flush=True)
        sc_out = _run_child("scipy", a, workdir)
        results["loadavg_1_5_15_after"] = loadavg()
        tsol = dict(np.load(workdir / "tlsjax_solution.npz"))
        ssol = dict(np.load(workdir / "scipy_solution.npz"))
        data = dict(np.load(workdir / "data.npz"))

    results["tlsjax"] = tj_out
    results["scipy"] = sc_out
    results["scipy_options"] = {
        "method": "trf",
        "x_scale": "jac",
        "tr_solver": "lsmr (default for a sparse Jacobian)",
        "jac": "2-point finite differences grouped by the exact jac_sparsity "
        "(plane (a, b, d) of the point, free EOPs of its scan, all APs; levelling rows: omega, phi, kappa)",
        "ftol": a.scipy_tol,
        "xtol": a.scipy_tol,
        "gtol": a.scipy_tol,
        "tr_options": {"atol": a.lsmr_tol, "btol": a.lsmr_tol},
        "max_nfev_all_passes": a.scipy_max_nfev,
        "weights": a.peer_weights,
        "plane_parametrisation": "n = (n0 + a u0 + b v0) / |.|, d (minimal, about the "
        "approximate normal n0 with tangents u0, v0)",
        "datum": "Xs, Ys, Zs, kappa of S1 held at approximate values",
    }

    # ---- checks ----
    peer = ScipyPlanePeer(data, a.aps.split())
    names = tj_out["ap_names"]
    r_tj = peer.residual_full(tsol["planes"], tsol["eops"], np.nan_to_num(tsol["aps"]))
    chk = {
        "numpy_vtpv_at_tlsjax_solution": float(r_tj @ r_tj),
        "tlsjax_vtpv": tj_out["vtpv"],
        "scipy_vtpv": sc_out["vtpv"],
        "tlsjax_fixed_scan_vtpv": tj_out["fixed_scan_vtpv"],
        "dof_tlsjax": tj_out["dof"],
        "dof_scipy": sc_out["n_residuals"] - sc_out["n_unknowns"],
    }
    diff = (ssol["aps"] - tsol["aps"]) / tsol["ap_sigmas"]
    diff_f = (ssol["aps"] - tsol["aps_f"]) / tsol["ap_sigmas_f"]
    chk["ap_tlsjax"] = dict(zip(names, map(float, tsol["aps"])))
    chk["ap_sigma_tlsjax"] = dict(zip(names, map(float, tsol["ap_sigmas"])))
    chk["ap_scipy"] = dict(zip(names, map(float, ssol["aps"])))
    chk["ap_sigma_scipy"] = dict(zip(names, sc_out["ap_sigmas_scipy"]))
    chk["ap_true"] = nw["design"]["true_aps"]
    chk["max_ap_diff_sigma"] = float(np.nanmax(np.abs(diff)))
    chk["max_ap_diff_name"] = names[int(np.nanargmax(np.abs(diff)))]
    chk["max_ap_diff_sigma_vs_tlsjax_fixed_scan"] = float(np.nanmax(np.abs(diff_f)))
    chk["max_ap_diff_sigma_tlsjax_inner_vs_fixed_scan"] = float(
        np.nanmax(np.abs((tsol["aps"] - tsol["aps_f"]) / tsol["ap_sigmas"]))
    )
    chk["max_ap_sigma_ratio_scipy_over_tlsjax"] = float(
        np.max(np.abs(np.array(sc_out["ap_sigmas_scipy"]) / tsol["ap_sigmas"] - 1)) + 1
    )
    if "current_weights" in sc_out:
        ac = np.array(sc_out["current_weights"]["aps"])
        chk["max_ap_diff_sigma_current_weights_vs_tlsjax"] = float(
            np.nanmax(np.abs((ac - tsol["aps"]) / tsol["ap_sigmas"]))
        )
    results["checks"] = chk
    results["speedup"] = sc_out["scipy_s"]["median"] / tj_out["run_s"]["median"]
    results["speedup_vs_calibrate"] = sc_out["scipy_s"]["median"] / tj_out["calibrate_s"]["median"]
    results["target"] = {
        "calibrate_s_max": 2.0,
        "peak_mb_max": 2048.0,
        "met": bool(tj_out["calibrate_s"]["median"] <= 2.0 and tj_out["peak_mb"] <= 2048.0),
    }

    t, s = tj_out, sc_out
    print(
        f"{'':10s} {'compile s':>9s} {'run s':>7s} {'(min)':>7s} {'calib s':>8s} {'it':>3s} {'peak MB':>8s} {'vtpv':>10s}"
    )
    print(
        f"{'tlsjax':10s} {t['compile_s']:9.2f} {t['run_s']['median']:7.3f} {t['run_s']['min']:7.3f} "
        f"{t['calibrate_s']['median']:8.3f} {t['iterations']:3d} {t['peak_mb']:8.0f} {t['vtpv']:10.2f}"
    )
    print(
        f"{'scipy':10s} {'':9s} {s['scipy_s']['median']:7.2f} {s['scipy_s']['min']:7.2f} {'':8s} "
        f"{s['nfev']:3d} {s['peak_mb']:8.0f} {s['vtpv']:10.2f}  (nfev; converged={s['converged']})"
    )
    print(
        f"# speedup {results['speedup']:.1f}x (vs calibrate {results['speedup_vs_calibrate']:.1f}x); "
        f"max |dAP|/sigma {chk['max_ap_diff_sigma']:.2e} (vs fixed-scan {chk['max_ap_diff_sigma_vs_tlsjax_fixed_scan']:.2e}); "
        f"numpy vtpv at tlsjax solution {chk['numpy_vtpv_at_tlsjax_solution']:.6f} vs tlsjax {chk['tlsjax_vtpv']:.6f}"
    )

    write_results(results, a.out)


if __name__ == "__main__":
    main()
