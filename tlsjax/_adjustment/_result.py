"""The result of a calibration: result codes, names, units, and the arrays of the adjustment
turned into a :class:`CalibrationResult` on the host."""

from __future__ import annotations

import dataclasses
import enum

import numpy as np

from ._diagnose import confounded_partners
from ._network import Network
from ._plan import Plan

GROUP_NAMES = ("range", "hz", "el")


class ResultCode(enum.IntEnum):
    """Result codes of an adjustment (SPEC section 7); ``ResultCode(c).message`` says what each
    means. Value-dependent failures come back as codes, never as NaN or an exception."""

    SUCCESS = 0
    MAX_ITERATIONS = 1
    NOT_ESTIMABLE = 2
    RANK_DEFICIENT = 3
    NONFINITE = 4

    @property
    def message(self) -> str:
        return _MESSAGES[self]


_MESSAGES = {
    ResultCode.SUCCESS: "converged",
    ResultCode.MAX_ITERATIONS: "did not converge within the maximum number of iterations",
    ResultCode.NOT_ESTIMABLE: "converged; some APs are not estimable and were held at zero",
    ResultCode.RANK_DEFICIENT: "the network does not determine all scan poses (rank defect beyond the datum)",
    ResultCode.NONFINITE: "non-finite values in the adjustment (bad approximate values or observations)",
}
#: Code -> message, for users who keep codes as plain integers.
RESULT_MESSAGES = {int(c): c.message for c in ResultCode}
SUCCESS, MAX_ITERATIONS, NOT_ESTIMABLE, RANK_DEFICIENT, NONFINITE = (int(c) for c in ResultCode)


@dataclasses.dataclass(frozen=True, eq=False)
class CalibrationResult:
    """Result of :func:`calibrate`. Angles in radians and lengths in metres (SI) throughout.

    ``result`` is a code (0 success, 1 max iterations, 2 some APs not estimable, 3 rank
    defect, 4 non-finite) with ``message``. AP sigmas are a posteriori (scaled by sigma0^2).
    Non-estimable APs have NaN value and sigma and are listed in ``not_estimable`` with the
    parameter they are confounded with; they are never reported as numbers.

    ``n_observations`` counts scalar observations, three per target observation and per plane
    point (plus the pseudo-observations); a plane point gives one condition, so with planes
    ``dof = conditions + unit-normal constraints + other pseudo-observations - unknowns + datum
    defect`` (Gauss-Helmert) rather than ``n_observations - n_unknowns + defect``.
    """

    result: int
    message: str
    converged: bool
    iterations: int
    sigma0: float
    dof: float
    n_observations: int
    n_unknowns: int
    datum: str
    ap_names: tuple
    ap_units: tuple
    ap_values: np.ndarray
    ap_sigmas: np.ndarray
    ap_t: np.ndarray
    ap_max_abs_corr: np.ndarray
    ap_max_corr_with: tuple
    not_estimable: tuple  # ((name, confounded_with, reason), ...)
    weakly_determined: tuple  # ((name, partner, |corr|), ...)
    rank_deficient: tuple  # parameters other than APs that the network does not determine
    scans: tuple
    eops: np.ndarray  # (s, 6)
    eop_sigmas: np.ndarray
    targets: tuple
    target_xyz: np.ndarray  # (t, 3)
    target_sigmas: np.ndarray
    residuals: np.ndarray  # (n, 3) v = F + Delta - l, in network row order
    redundancy: np.ndarray  # (n, 3)
    redundancy_levelling: np.ndarray  # (s, 2)
    redundancy_prior_sum: float
    parameter_names: tuple
    covariance: np.ndarray | None  # a posteriori, inner-constraint datum, all unknowns
    network: Network = dataclasses.field(repr=False, default=None)
    ap_covariance: np.ndarray | None = (
        None  # (a, a) a posteriori; NaN rows/columns for non-estimable APs
    )
    used: np.ndarray | None = None  # (n, 3) False where an observation was removed (weight 0)
    ap_fixed: tuple = ()  # APs held at zero (CalibrationModel.fixed_aps): value 0, sigma 0
    # Plane networks (SPEC section 4), in the network's plane row order; empty without planes.
    planes: tuple = ()
    plane_params: np.ndarray | None = None  # (k, 4) = (nx, ny, nz, d [m]), n . X = d
    plane_sigmas: np.ndarray | None = None  # (k, 4) a posteriori, inner-constraint datum
    plane_residuals: np.ndarray | None = None  # (m, 3) Gauss-Helmert residuals v [m, rad, rad]
    plane_redundancy: np.ndarray | None = None  # (m, 3); the three of a point sum to <= 1
    plane_used: np.ndarray | None = None  # (m, 3)

    @property
    def ok(self) -> bool:
        return self.result in (SUCCESS, NOT_ESTIMABLE)

    def correlation(self) -> np.ndarray:
        if self.covariance is None:
            raise ValueError(
                "no full covariance: run calibrate with SolverOptions(full_covariance=True)"
            )
        s = np.sqrt(np.clip(np.diag(self.covariance), 0, None))
        with np.errstate(invalid="ignore", divide="ignore"):
            c = self.covariance / np.outer(s, s)
        return np.where(np.outer(s, s) > 0, c, 0.0)

    def redundancy_summary(self) -> dict:
        """Mean and sum of redundancy numbers per group, per scan and in total."""
        net = self.network
        r = self.redundancy
        used = np.ones(r.shape, dtype=bool) if self.used is None else self.used
        rp = np.zeros((0, 3)) if self.plane_redundancy is None else self.plane_redundancy
        up = np.ones(rp.shape, dtype=bool) if self.plane_used is None else self.plane_used
        # Means over the observations in the adjustment: a removed one has redundancy 0 by
        # construction and would pull the mean down.
        mean = lambda a, keep: float(a[keep].mean()) if keep.any() else float("nan")
        out = {}
        if r.shape[0] or not rp.shape[0]:
            for g, name in enumerate(GROUP_NAMES):
                out[name] = {"mean": mean(r[:, g], used[:, g]), "sum": float(r[:, g].sum())}
        if rp.shape[0]:
            # Plane points (Gauss-Helmert): a point's three numbers share one condition's
            # redundancy, so the mean over plane observations never exceeds 1/3 (SPEC 4).
            pl = {
                name: {"mean": mean(rp[:, g], up[:, g]), "sum": float(rp[:, g].sum())}
                for g, name in enumerate(GROUP_NAMES)
            }
            pl["all"] = {"mean": mean(rp, up), "sum": float(rp.sum())}
            pl["per_point"] = {"mean": mean(rp.sum(axis=1), up.any(axis=1))}
            out["planes"] = pl
        lev = self.redundancy_levelling
        active = net.is_levelled
        if active.any():
            out["levelling"] = {"mean": float(lev[active].mean()), "sum": float(lev[active].sum())}
        per_scan = {}
        for j, s in enumerate(self.scans):
            a = np.concatenate(
                [
                    r[net.scan_index == j][used[net.scan_index == j]],
                    rp[net.plane_scan_index == j][up[net.plane_scan_index == j]],
                ]
            )
            per_scan[s] = {"mean": float(a.mean()) if a.size else float("nan")}
        out["per_scan"] = per_scan
        total = float(r.sum() + rp.sum() + lev.sum() + self.redundancy_prior_sum)
        out["total"] = {"mean": total / max(self.n_observations, 1), "sum": total}
        return out

    def ap(self, name: str) -> dict:
        i = self.ap_names.index(name)
        return {
            "value": self.ap_values[i],
            "sigma": self.ap_sigmas[i],
            "unit": self.ap_units[i],
            "t": self.ap_t[i],
            "max_abs_corr": self.ap_max_abs_corr[i],
            "max_corr_with": self.ap_max_corr_with[i],
        }


def assemble(net, model, plan: Plan, state, q) -> CalibrationResult:
    spec = plan.spec
    ns, na = spec.n_scans, spec.n_aps
    dep = np.asarray(q.dependent)
    fixed = np.asarray(plan.problem.fixed)
    dof = float(q.dof)
    vtpv = float(q.vtpv)
    s0sq = vtpv / dof if dof > 0 else np.nan
    finite = bool(state.finite) and np.isfinite(vtpv)
    n_p = sum(int(np.prod(P.shape)) for P in state.params.prims)

    names = plan.parameter_names
    Qzz = np.asarray(q.Qzz)
    cov = None if q.Qfull is None else np.asarray(q.Qfull) * (s0sq if np.isfinite(s0sq) else 1.0)
    zdiag = np.diag(Qzz) * s0sq
    ap_idx = 6 * ns + np.arange(na)
    ap_dep = dep[ap_idx] & ~fixed[ap_idx]
    eop_dep = dep[: 6 * ns] & ~fixed[: 6 * ns]
    values = np.asarray(state.params.aps).copy()
    sig = np.sqrt(np.clip(zdiag[ap_idx], 0, None))
    ap_fixed = fixed[ap_idx]
    values[ap_dep] = np.nan
    sig[ap_dep] = np.nan
    sig[ap_fixed] = 0.0
    with np.errstate(invalid="ignore", divide="ignore"):
        tstat = values / sig

    # Largest absolute correlation of each AP with any other unknown (inner-constraint datum).
    if cov is not None:
        full_dep = np.concatenate([np.zeros(n_p, dtype=bool), dep])
        s = np.sqrt(np.clip(np.diag(cov), 0, None))
        rows = n_p + ap_idx
        with np.errstate(invalid="ignore", divide="ignore"):
            C = cov[rows] / np.outer(s[rows], s)
        C[:, full_dep | (s == 0)] = 0.0
    else:
        s = np.sqrt(np.clip(np.diag(Qzz), 0, None))
        with np.errstate(invalid="ignore", divide="ignore"):
            C = Qzz[ap_idx] / np.outer(s[ap_idx], s)
        C[:, dep | (s == 0)] = 0.0
    C = np.nan_to_num(C)
    off = n_p if cov is not None else 0
    for i in range(na):
        C[i, off + ap_idx[i] if cov is None else n_p + ap_idx[i]] = 0.0
    max_corr = np.abs(C).max(axis=1) if C.size else np.zeros(na)
    arg = np.abs(C).argmax(axis=1) if C.size else np.zeros(na, dtype=int)
    partner = tuple(names[(a if cov is not None else n_p + a)] for a in arg)
    max_corr[ap_dep | ap_fixed] = np.nan
    partner = tuple("" if ap_dep[i] or ap_fixed[i] else partner[i] for i in range(na))

    not_est = (
        _diagnose(plan, q, net, state, np.flatnonzero(ap_dep), names, n_p) if ap_dep.any() else ()
    )
    weak = tuple(
        (plan.ap_labels[i], partner[i], float(max_corr[i]))
        for i in range(na)
        if not ap_dep[i] and max_corr[i] > model.correlation_threshold
    )
    rank_def = tuple(names[n_p + j] for j in np.flatnonzero(eop_dep))

    converged = bool(state.converged)
    if not finite:
        code = NONFINITE
    elif rank_def:
        code = RANK_DEFICIENT
    elif not converged:
        code = MAX_ITERATIONS
    elif not_est:
        code = NOT_ESTIMABLE
    else:
        code = SUCCESS
    msg = RESULT_MESSAGES[code]
    if rank_def:
        msg += ": " + ", ".join(rank_def[:12])
    if not_est:
        msg += "; " + "; ".join(f"{n} is not estimable: {reason}" for n, _, reason in not_est)

    # Back to network row order and target order.
    n_obs = net.observations.shape[0]
    resid = np.zeros((n_obs, 3))
    redund = np.zeros((n_obs, 3))
    used = np.ones((n_obs, 3), dtype=bool)
    txyz = np.zeros((len(net.targets), 3))
    tsig = np.full((len(net.targets), 3), np.nan)
    fam_rows = family_rows(net, plan)
    off_p = 0
    n_t_params = sum(3 * tg.size for tg in plan.family_targets)
    plane_out = {}
    if plan.plane_family is not None:
        fp = plan.plane_family
        P = np.asarray(state.params.prims[fp])
        psig = np.full(P.shape, np.nan)
        if cov is not None:
            psig = np.sqrt(
                np.clip(np.diag(cov)[n_t_params : n_t_params + P.size], 0, None)
            ).reshape(P.shape)
        plane_out = dict(
            planes=net.planes,
            plane_params=P,
            plane_sigmas=psig,
            plane_residuals=np.asarray(q.residuals[fp]),
            plane_redundancy=np.asarray(q.redundancy[fp]),
            plane_used=np.asarray(plan.problem.families[fp].weight) > 0,
        )
    for fi, tg in enumerate(plan.family_targets):
        rows = fam_rows[fi]
        resid[rows] = np.asarray(q.residuals[fi])
        redund[rows] = np.asarray(q.redundancy[fi])
        used[rows] = np.asarray(plan.problem.families[fi].weight) > 0
        P = np.asarray(state.params.prims[fi]).reshape(-1, 3)
        txyz[tg.reshape(-1)] = P
        if cov is not None:
            d = np.sqrt(np.clip(np.diag(cov)[off_p : off_p + P.size], 0, None)).reshape(-1, 3)
            tsig[tg.reshape(-1)] = d
        off_p += P.size
    eop_sig = np.sqrt(np.clip(zdiag[: 6 * ns], 0, None)).reshape(ns, 6)
    if cov is not None:
        eop_sig = np.sqrt(np.clip(np.diag(cov)[n_p : n_p + 6 * ns], 0, None)).reshape(ns, 6)
    prior_sum = float(sum(np.asarray(r).sum() for r in q.redundancy_prior))
    # Observations with weight 0 (removed by data snooping) are not counted (SPEC section 7).
    n_obs_total = int(round(float(q.n_observations))) if q.n_observations is not None else 3 * n_obs
    if plane_out:
        # The solver counts one condition per plane point; a point is three observations.
        n_obs_total += 2 * int(plane_out["plane_used"].any(axis=1).sum())
    return CalibrationResult(
        result=code,
        message=msg,
        converged=converged,
        iterations=int(state.iteration),
        sigma0=float(np.sqrt(s0sq)),
        dof=dof,
        n_observations=n_obs_total,
        n_unknowns=int(n_p + (~dep).sum()),
        datum=(
            "inner"
            if spec.inner
            else ("fixed-scan" if plan.fixed_scan_index is not None else "control")
        ),
        ap_names=plan.ap_labels,
        ap_units=plan.ap_units,
        ap_values=values,
        ap_sigmas=sig,
        ap_t=tstat,
        ap_max_abs_corr=max_corr,
        ap_max_corr_with=partner,
        not_estimable=not_est,
        weakly_determined=weak,
        rank_deficient=rank_def,
        scans=net.scans,
        eops=np.asarray(state.params.eops),
        eop_sigmas=eop_sig,
        targets=net.targets,
        target_xyz=txyz,
        target_sigmas=tsig,
        residuals=resid,
        redundancy=redund,
        redundancy_levelling=np.asarray(q.redundancy_levelling),
        redundancy_prior_sum=prior_sum,
        parameter_names=names,
        covariance=cov,
        network=net,
        ap_covariance=_ap_covariance(Qzz, ap_idx, ap_dep, s0sq),
        used=used,
        ap_fixed=tuple(plan.ap_labels[i] for i in np.flatnonzero(ap_fixed)),
        **plane_out,
    )


def _ap_covariance(Qzz, ap_idx, ap_dep, s0sq):
    # The AP block of the reduced cofactor matrix is datum invariant (SPEC section 6), so it
    # needs no S-transformation; scaled a posteriori like the sigmas.
    C = Qzz[np.ix_(ap_idx, ap_idx)] * s0sq
    C[ap_dep, :] = np.nan
    C[:, ap_dep] = np.nan
    return C


def family_rows(net: Network, plan: Plan):
    n_t = len(net.targets)
    fam_of = np.zeros(n_t, dtype=int)
    for fi, tg in enumerate(plan.family_targets):
        fam_of[tg.reshape(-1)] = fi
    return [
        np.flatnonzero(fam_of[net.target_index] == fi) for fi in range(len(plan.family_targets))
    ]


def _diagnose(plan: Plan, q, net, state, columns, names, n_p: int):
    """Name what each non-estimable AP (reduced indices ``6s + j``) is confounded with, in the
    inner-constraint datum on the targets (:mod:`._diagnose`)."""
    ns = plan.spec.n_scans
    found = confounded_partners(
        plan.spec,
        plan.problem,
        state.params,
        np.asarray(q.dependent),
        np.asarray(plan.problem.fixed),
        [6 * ns + j for j in columns],
    )
    out = []
    for j in columns:
        partner_col, _, scale_like = found[6 * ns + j]
        name = plan.ap_labels[j]
        if scale_like:
            out.append((name, "scale", "scale is undefined; add scale bars or control points"))
        else:
            partner = names[n_p + partner_col]
            out.append((name, partner, f"confounded with {partner}"))
    return tuple(out)
