"""The public entry point: ``calibrate(network, model, options) -> CalibrationResult``.

Host side: validate the configuration, build the index plan and the approximate values, call
the compiled adjustment (:mod:`._solver`) and quality (:mod:`._quality`) once, and turn the
arrays into a result with names, units and result codes.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Mapping

import jax
import jax.numpy as jnp
import numpy as np

from ._aps import get_ap
from ._approx import approximate_network, approximate_values
from ._diagnose import confounded_partners
from ._models import Scanner
from ._network import Network
from ._quality import quality
from ._solver import (
    MAX_ITERATIONS, NONFINITE, NOT_ESTIMABLE, RANK_DEFICIENT, RESULT_MESSAGES, SUCCESS,
    Family, Options, Params, Problem, Spec, adjust,
)

DATUMS = ("auto", "inner", "fixed-scan", "control")
GROUP_NAMES = ("range", "hz", "el")
#: Weight of the unit-normal constraint ``|n|^2 - 1`` of a plane, as a pseudo-observation: with
#: it the constraint holds to ~1e-13 while the normal matrix stays well conditioned (a hard
#: constraint in a bordered system gives the same solution, tests/test_plane_adjustment.py).
UNIT_NORMAL_WEIGHT = 1e7
PLANE_PARAMETERS = ("nx", "ny", "nz", "d")


@dataclasses.dataclass(frozen=True)
class CalibrationModel:
    """Configuration of a self-calibration (SPEC sections 3, 6).

    ``scanner``: one :class:`Scanner` for every instrument, or a mapping instrument name ->
    Scanner (each instrument gets its own AP block). ``datum``: "inner" (inner constraints on
    the targets; free network), "fixed-scan" (the pose of ``fixed_scan`` is held; only its
    parameters the datum leaves free: all six, or X, Y, Z, kappa with levelling), "control"
    (control points with their sigmas), or "auto" (control if the network has control points,
    otherwise inner). ``correlation_threshold``: an AP whose largest absolute correlation
    exceeds it is flagged as weakly determined. ``fixed_aps``: AP labels held at zero (they keep
    their place in the parameter vector, so a model that differs only in which APs are fixed
    reuses the compiled adjustment: stepwise selection fits every candidate set this way).
    """

    scanner: Scanner | Mapping[str, Scanner] = dataclasses.field(default_factory=Scanner)
    datum: str = "auto"
    fixed_scan: str | None = None
    correlation_threshold: float = 0.99
    fixed_aps: tuple = ()

    def __post_init__(self):
        object.__setattr__(self, "fixed_aps", tuple(self.fixed_aps.split() if isinstance(self.fixed_aps, str) else self.fixed_aps))
        if self.datum not in DATUMS:
            raise ValueError(f"datum {self.datum!r} is not one of {DATUMS}")
        if self.datum == "fixed-scan" and self.fixed_scan is None:
            raise ValueError("datum 'fixed-scan' needs fixed_scan=<scan name>")
        if not 0 < self.correlation_threshold <= 1:
            raise ValueError(f"correlation_threshold must be in (0, 1], got {self.correlation_threshold}")


@dataclasses.dataclass(frozen=True)
class SolverOptions:
    """Numerical settings. ``tolerance``: convergence when the largest update is below this
    fraction of the parameter's standard deviation (cofactor ``sqrt(Q_ii)``);
    ``rank_tolerance``: smallest accepted Cholesky pivot ``1 - R^2`` of the unit-diagonal
    reduced normal matrix (below it a parameter is not estimable); ``full_covariance``: also form the inner-constraint cofactor matrix of all
    unknowns (needed for correlations with targets)."""

    max_iterations: int = 30
    tolerance: float = 1e-6
    rank_tolerance: float = 1e-6
    full_covariance: bool = True

    def arrays(self) -> Options:
        return Options(jnp.asarray(self.max_iterations), jnp.asarray(self.tolerance), jnp.asarray(self.rank_tolerance))


@dataclasses.dataclass(frozen=True, eq=False)
class Plan:
    """Host-built index plan and static spec of one (network, model) pair."""

    spec: Spec
    problem: Problem
    family_targets: tuple  # per family: (n, k) target indices
    ap_labels: tuple
    ap_units: tuple
    parameter_names: tuple
    fixed_scan_index: int | None
    plane_family: int | None = None  # index of the plane family among problem.families


def _scanner_for(model: CalibrationModel, instrument: str) -> Scanner:
    if isinstance(model.scanner, Scanner):
        return model.scanner
    try:
        return model.scanner[instrument]
    except KeyError:
        raise ValueError(f"no Scanner configured for instrument {instrument!r}; configured: {sorted(model.scanner)}") from None


def build_plan(net: Network, model: CalibrationModel) -> Plan:
    """Index plan (which observations share a target, which (target, scan) pairs exist)."""
    scanners = tuple(_scanner_for(model, ins) for ins in net.instruments)
    ap_names, ap_slices, labels, units = [], [], [], []
    off = 0
    for ins, sc in zip(net.instruments, scanners):
        ap_names.append(sc.aps)
        ap_slices.append((off, off + len(sc.aps)))
        off += len(sc.aps)
        for a in sc.aps:
            labels.append(a if len(net.instruments) == 1 else f"{a}[{ins}]")
            units.append(get_ap(a).unit)
    n_s = len(net.scans)
    levelled = net.is_levelled.any()

    datum = model.datum
    if datum == "auto":
        datum = "control" if len(net.control_index) else "inner"
    if datum == "control" and len(net.control_index) == 0:
        raise ValueError(f"{net.source}: datum 'control' needs control points")
    fixed = np.zeros(6 * n_s + off, dtype=bool)
    fixed_idx = None
    if datum == "fixed-scan":
        if model.fixed_scan not in net.scans:
            raise ValueError(f"fixed scan {model.fixed_scan!r} is not a scan of {net.source}; scans: {', '.join(net.scans)}")
        fixed_idx = net.scans.index(model.fixed_scan)
        cols = (0, 1, 2, 5) if levelled else tuple(range(6))
        fixed[[6 * fixed_idx + c for c in cols]] = True
    for name in model.fixed_aps:
        if name not in labels:
            raise ValueError(f"fixed AP {name!r} is not among the APs of the model: {' '.join(labels)}")
        fixed[6 * n_s + labels.index(name)] = True
    datum_columns = ((0, 1, 2, 5) if levelled else tuple(range(6))) if datum == "inner" else ()

    # Families: free targets (k=1) and scale bars (k=2: both end targets in one block).
    n_t = len(net.targets)
    bars = net.scale_bar_targets
    in_bar = np.zeros(n_t, dtype=bool)
    if len(bars):
        flat = bars.reshape(-1)
        if len(set(flat.tolist())) != len(flat):
            raise ValueError(f"{net.source}: a target may end at most one scale bar")
        in_bar[flat] = True
    fam_of = np.zeros(n_t, dtype=np.int32)
    prim_of = np.zeros(n_t, dtype=np.int32)
    point_of = np.zeros(n_t, dtype=np.int32)
    free = np.flatnonzero(~in_bar)
    prim_of[free] = np.arange(len(free))
    fam_targets = [free[:, None]]
    if len(bars):
        fam_of[bars.reshape(-1)] = 1
        prim_of[bars[:, 0]] = prim_of[bars[:, 1]] = np.arange(len(bars))
        point_of[bars[:, 1]] = 1
        fam_targets.append(bars)
    ctrl_w_t = np.zeros((n_t, 3))
    ctrl_x_t = np.zeros((n_t, 3))
    if datum != "inner" or len(net.control_index):
        ctrl_w_t[net.control_index] = 1.0 / net.control_sigma
        ctrl_x_t[net.control_index] = net.control_xyz
    families = []
    if not net.has_targets:
        fam_targets = []
    for fi, tg in enumerate(fam_targets):
        m = fam_of[net.target_index] == fi
        prim = prim_of[net.target_index[m]]
        scan = net.scan_index[m]
        pairs, pair = np.unique(np.stack([prim, scan], axis=1), axis=0, return_inverse=True)
        k = tg.shape[1]
        blen = np.zeros(len(tg))
        bw = np.zeros(len(tg))
        if k == 2:
            blen[:] = net.scale_bar_length
            bw[:] = 1.0 / net.scale_bar_sigma
        families.append(Family(
            obs=jnp.asarray(net.observations[m]), weight=jnp.asarray(1.0 / net.sigmas[m]),
            prim=jnp.asarray(prim), point=jnp.asarray(point_of[net.target_index[m]]),
            scan=jnp.asarray(scan), pair=jnp.asarray(pair.reshape(-1).astype(np.int32)),
            pair_prim=jnp.asarray(pairs[:, 0]), pair_scan=jnp.asarray(pairs[:, 1]),
            ctrl_xyz=jnp.asarray(ctrl_x_t[tg]), ctrl_weight=jnp.asarray(ctrl_w_t[tg]),
            bar_length=jnp.asarray(blen), bar_weight=jnp.asarray(bw), k=k,
        ))
    kinds = ["point"] * len(families)
    plane_family = None
    if net.has_planes:
        # Planes: one Gauss-Helmert condition per point (SPEC section 4), p = 4 per plane.
        n_k = len(net.planes)
        prim, scan = net.plane_index, net.plane_scan_index
        pairs, pair = np.unique(np.stack([prim, scan], axis=1), axis=0, return_inverse=True)
        plane_family = len(families)
        families.append(Family(
            obs=jnp.asarray(net.plane_observations), weight=jnp.asarray(1.0 / net.plane_sigmas),
            prim=jnp.asarray(prim), point=jnp.zeros(len(prim), dtype=jnp.int32), scan=jnp.asarray(scan),
            pair=jnp.asarray(pair.reshape(-1).astype(np.int32)), pair_prim=jnp.asarray(pairs[:, 0]),
            pair_scan=jnp.asarray(pairs[:, 1]), ctrl_xyz=jnp.zeros((n_k, 1, 3)), ctrl_weight=jnp.zeros((n_k, 1, 3)),
            bar_length=jnp.zeros(n_k), bar_weight=jnp.full(n_k, UNIT_NORMAL_WEIGHT), k=1, kind="plane",
        ))
        kinds.append("plane")
    spec = Spec(scanners, tuple(ap_names), tuple(ap_slices), n_s, datum_columns, datum == "inner", tuple(kinds))
    lw = np.where(np.isfinite(net.levelling_sigma), 1.0 / net.levelling_sigma, 0.0)
    problem = Problem(tuple(families), jnp.asarray(net.instrument_of_scan), jnp.asarray(net.levelling), jnp.asarray(lw), jnp.asarray(fixed))

    names = []
    for tg in fam_targets:
        for row in tg:
            for t in row:
                names += [f"{c}[{net.targets[t]}]" for c in "XYZ"]
    for k in net.planes:
        names += [f"{c}[{k}]" for c in PLANE_PARAMETERS]
    for s in net.scans:
        names += [f"{c}[{s}]" for c in ("Xs", "Ys", "Zs", "omega", "phi", "kappa")]
    names += labels
    return Plan(spec, problem, tuple(fam_targets), tuple(labels), tuple(units), tuple(names), fixed_idx, plane_family)


def initial_params(net: Network, plan: Plan, targets=None, eops=None, planes=None) -> Params:
    """Approximate values: computed from the observations (:mod:`._approx`) unless given."""
    if targets is None or eops is None or (net.has_planes and planes is None):
        t0, e0, p0 = approximate_network(net) if net.has_planes else (*approximate_values(net), None)
        targets = t0 if targets is None else np.asarray(targets, dtype=np.float64)
        eops = e0 if eops is None else np.asarray(eops, dtype=np.float64)
        planes = p0 if planes is None else planes
    prims = [jnp.asarray(np.asarray(targets)[tg].reshape(len(tg), -1)) for tg in plan.family_targets]
    if net.has_planes:
        P = np.array(planes, dtype=np.float64).reshape(len(net.planes), 4)
        P /= np.linalg.norm(P[:, :3], axis=1, keepdims=True)[:, [0, 0, 0, 0]]
        prims.append(jnp.asarray(P))
    return Params(tuple(prims), jnp.asarray(eops), jnp.zeros(plan.spec.n_aps))


@functools.partial(jax.jit, static_argnums=(0, 5))
def _run(spec, problem, params0, options, rank_tolerance, full_covariance):
    state = adjust(spec, problem, params0, options)
    q = quality(spec, problem, state.params, rank_tolerance, full_covariance)
    return state, q


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
    ap_covariance: np.ndarray | None = None  # (a, a) a posteriori; NaN rows/columns for non-estimable APs
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
            raise ValueError("no full covariance: run calibrate with SolverOptions(full_covariance=True)")
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
            pl = {name: {"mean": mean(rp[:, g], up[:, g]), "sum": float(rp[:, g].sum())} for g, name in enumerate(GROUP_NAMES)}
            pl["all"] = {"mean": mean(rp, up), "sum": float(rp.sum())}
            pl["per_point"] = {"mean": mean(rp.sum(axis=1), up.any(axis=1))}
            out["planes"] = pl
        lev = self.redundancy_levelling
        active = net.is_levelled
        if active.any():
            out["levelling"] = {"mean": float(lev[active].mean()), "sum": float(lev[active].sum())}
        per_scan = {}
        for j, s in enumerate(self.scans):
            a = np.concatenate([r[net.scan_index == j][used[net.scan_index == j]],
                                rp[net.plane_scan_index == j][up[net.plane_scan_index == j]]])
            per_scan[s] = {"mean": float(a.mean()) if a.size else float("nan")}
        out["per_scan"] = per_scan
        total = float(r.sum() + rp.sum() + lev.sum() + self.redundancy_prior_sum)
        out["total"] = {"mean": total / max(self.n_observations, 1), "sum": total}
        return out

    def ap(self, name: str) -> dict:
        i = self.ap_names.index(name)
        return {"value": self.ap_values[i], "sigma": self.ap_sigmas[i], "unit": self.ap_units[i], "t": self.ap_t[i],
                "max_abs_corr": self.ap_max_abs_corr[i], "max_corr_with": self.ap_max_corr_with[i]}


def calibrate(network: Network, model: CalibrationModel | None = None, options: SolverOptions | None = None, *,
              throw: bool = False, initial=None) -> CalibrationResult:
    """Self-calibrate a TLS network: one free-network adjustment of targets and/or planes, scan
    poses and APs.

    Targets: Gauss-Markov model of Chow et al. 2013 (eqs. 1-6). Planes: one Gauss-Helmert
    condition per point, ``n . (R^T x(l - Delta) + S) - d = 0`` (eq. 3; SPEC section 4), with
    the unit-normal constraint. Structured Gauss-Newton with LM damping (targets and planes
    eliminated by Schur complement), datum by inner constraints on the object-space primitives
    (or a fixed scan, or control points), quality from the compiled normal matrix. With
    ``throw=True`` a failed result raises ``RuntimeError``. ``initial`` optionally gives
    (targets (t, 3), eops (s, 6)[, planes (k, 4)]) instead of the computed approximate values.
    """
    model = model or CalibrationModel()
    options = options or SolverOptions()
    plan = build_plan(network, model)
    p0 = initial_params(network, plan, *(initial or (None, None)))
    state, q = _run(plan.spec, plan.problem, p0, options.arrays(), jnp.asarray(options.rank_tolerance), options.full_covariance)
    res = _assemble(network, model, plan, state, q)
    if throw and not res.ok:
        raise RuntimeError(res.message)
    return res


def _assemble(net, model, plan: Plan, state, q) -> CalibrationResult:
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

    not_est = _diagnose(plan, q, net, state, np.flatnonzero(ap_dep), names, n_p) if ap_dep.any() else ()
    weak = tuple((plan.ap_labels[i], partner[i], float(max_corr[i])) for i in range(na)
                 if not ap_dep[i] and max_corr[i] > model.correlation_threshold)
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
    fam_rows = _family_rows(net, plan)
    off_p = 0
    n_t_params = sum(3 * tg.size for tg in plan.family_targets)
    plane_out = {}
    if plan.plane_family is not None:
        fp = plan.plane_family
        P = np.asarray(state.params.prims[fp])
        psig = np.full(P.shape, np.nan)
        if cov is not None:
            psig = np.sqrt(np.clip(np.diag(cov)[n_t_params: n_t_params + P.size], 0, None)).reshape(P.shape)
        plane_out = dict(
            planes=net.planes, plane_params=P, plane_sigmas=psig,
            plane_residuals=np.asarray(q.residuals[fp]), plane_redundancy=np.asarray(q.redundancy[fp]),
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
            d = np.sqrt(np.clip(np.diag(cov)[off_p: off_p + P.size], 0, None)).reshape(-1, 3)
            tsig[tg.reshape(-1)] = d
        off_p += P.size
    eop_sig = np.sqrt(np.clip(zdiag[: 6 * ns], 0, None)).reshape(ns, 6)
    if cov is not None:
        eop_sig = np.sqrt(np.clip(np.diag(cov)[n_p: n_p + 6 * ns], 0, None)).reshape(ns, 6)
    prior_sum = float(sum(np.asarray(r).sum() for r in q.redundancy_prior))
    # Observations with weight 0 (removed by data snooping) are not counted (SPEC section 7).
    n_obs_total = int(round(float(q.n_observations))) if q.n_observations is not None else 3 * n_obs
    if plane_out:
        # The solver counts one condition per plane point; a point is three observations.
        n_obs_total += 2 * int(plane_out["plane_used"].any(axis=1).sum())
    return CalibrationResult(
        result=code, message=msg, converged=converged, iterations=int(state.iteration),
        sigma0=float(np.sqrt(s0sq)), dof=dof, n_observations=n_obs_total,
        n_unknowns=int(n_p + (~dep).sum()), datum=("inner" if spec.inner else ("fixed-scan" if plan.fixed_scan_index is not None else "control")),
        ap_names=plan.ap_labels, ap_units=plan.ap_units, ap_values=values, ap_sigmas=sig, ap_t=tstat,
        ap_max_abs_corr=max_corr, ap_max_corr_with=partner, not_estimable=not_est, weakly_determined=weak,
        rank_deficient=rank_def, scans=net.scans, eops=np.asarray(state.params.eops), eop_sigmas=eop_sig,
        targets=net.targets, target_xyz=txyz, target_sigmas=tsig, residuals=resid, redundancy=redund,
        redundancy_levelling=np.asarray(q.redundancy_levelling), redundancy_prior_sum=prior_sum,
        parameter_names=names, covariance=cov, network=net, ap_covariance=_ap_covariance(Qzz, ap_idx, ap_dep, s0sq),
        used=used, ap_fixed=tuple(plan.ap_labels[i] for i in np.flatnonzero(ap_fixed)), **plane_out,
    )


def _ap_covariance(Qzz, ap_idx, ap_dep, s0sq):
    # The AP block of the reduced cofactor matrix is datum invariant (SPEC section 6), so it
    # needs no S-transformation; scaled a posteriori like the sigmas.
    C = Qzz[np.ix_(ap_idx, ap_idx)] * s0sq
    C[ap_dep, :] = np.nan
    C[:, ap_dep] = np.nan
    return C


def _family_rows(net: Network, plan: Plan):
    n_t = len(net.targets)
    fam_of = np.zeros(n_t, dtype=int)
    for fi, tg in enumerate(plan.family_targets):
        fam_of[tg.reshape(-1)] = fi
    return [np.flatnonzero(fam_of[net.target_index] == fi) for fi in range(len(plan.family_targets))]


def _diagnose(plan: Plan, q, net, state, columns, names, n_p: int):
    """Name what each non-estimable AP (reduced indices ``6s + j``) is confounded with, in the
    inner-constraint datum on the targets (:mod:`._diagnose`)."""
    ns = plan.spec.n_scans
    found = confounded_partners(plan.spec, plan.problem, state.params, np.asarray(q.dependent),
                                np.asarray(plan.problem.fixed), [6 * ns + j for j in columns])
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
