"""The result of a calibration: result codes, names, units, and the arrays of the adjustment
turned into a :class:`CalibrationResult` on the host."""

from __future__ import annotations

import dataclasses
import enum
import math

import jax
import jax.numpy as jnp
import numpy as np

from .._model._aps import get_ap
from .._model._plausibility import ap_findings, implausible_summary, likely_causes
from .._pytree import kept
from .._stats import ALPHA0, normal_critical_value
from ._diagnose import confounded_partners, failure_diagnosis
from ._json import result_to_dict
from ._network import Network
from ._plan import Plan
from ._quality import w_tests
from ._text import ap_table, not_estimable_sentence, summary

#: The critical value of a weighted constraint's w-test: Baarda's, at the reliability level
#: ALPHA0 (3.29 at 0.1 %).
W_CRITICAL = normal_critical_value(ALPHA0)


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


def result_code_of(*, finite, rank_deficient, converged, not_estimable):
    """The :class:`ResultCode` of an adjustment from what it found, in the one order of
    precedence (the first that applies): non-finite values, a rank defect of the scan poses,
    no convergence, APs not estimable; success otherwise. Traceable (``jnp.where`` on booleans
    or traced booleans), so the host-side assembly of a result and the compiled batch of a
    Monte Carlo (:func:`._calibrate.result_code`) share it; an int32 code."""
    flags = (finite, rank_deficient, converged, not_estimable)
    # On the host (Python booleans) plain Python: no array operation at all.
    host = not any(isinstance(f, jax.Array) for f in flags)
    negate = (lambda f: not f) if host else jnp.logical_not
    rules = (
        (negate(finite), NONFINITE),
        (rank_deficient, RANK_DEFICIENT),
        (negate(converged), MAX_ITERATIONS),
        (not_estimable, NOT_ESTIMABLE),
    )
    if host:
        return np.int32(next((code for applies, code in rules if applies), SUCCESS))
    code = SUCCESS
    for applies, then in reversed(rules):  # the first rule that applies decides
        code = jnp.where(applies, then, code)
    return jnp.asarray(code).astype(jnp.int32)


@dataclasses.dataclass(frozen=True, eq=False)
class CalibrationResult:
    """Result of :func:`calibrate`. Angles in radians and lengths in metres (SI) throughout.

    ``result`` is a code (0 success, 1 max iterations, 2 some APs not estimable, 3 rank
    defect, 4 non-finite) with ``message``. AP sigmas are a posteriori (scaled by sigma0^2).
    Non-estimable APs have NaN value and sigma and are listed in ``not_estimable`` with the
    parameter they are confounded with; they are never reported as numbers.

    Counting (as the papers do, Chow et al. 2013, Table 5): ``n_observations`` counts scalar
    observations, three per target observation and per plane point, plus the
    pseudo-observations (levelling, orientation and AP priors, control, scale bars);
    ``n_unknowns`` counts four per plane ``(n, d)``, three per target, six per scan and the
    estimable APs. A plane point gives one condition, so with planes the degrees of freedom are
    those of the Gauss-Helmert model, ``dof = n_conditions - n_unknowns + n_constraints + d``,
    with ``n_conditions`` the condition equations (three per target observation, one per plane
    point, one per pseudo-observation), ``n_constraints`` the hard constraints on the unknowns
    (one unit normal per plane) and d the datum defect; without planes ``n_conditions =
    n_observations`` and ``n_constraints = 0``.
    """

    result: int
    message: str
    converged: bool
    iterations: int
    sigma0: float
    dof: float
    n_observations: int
    n_unknowns: int
    n_conditions: int
    n_constraints: int
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
    redundancy_levelling: np.ndarray  # (s, 2) of the tilt readings (omega_c, phi_c)
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
    # (k, 4, 4) a posteriori covariance of each plane (n, d) [1, m] in the datum used: the
    # constrained (tangent-plane) blocks, n^T C_nn = 0 and n^T C_nd = 0 to rounding.
    plane_covariance: np.ndarray | None = dataclasses.field(default=None, repr=False)
    plane_residuals: np.ndarray | None = None  # (m, 3) Gauss-Helmert residuals v [m, rad, rad]
    plane_redundancy: np.ndarray | None = None  # (m, 3); the three of a point sum to <= 1
    plane_used: np.ndarray | None = None  # (m, 3)
    # Weighted constraints with observed values (eq. 7, SPEC section 6): residuals ``v = f(x) -
    # l`` [rad, SI] and redundancy numbers; NaN where there is no such observation. Per scan
    # (s, 3): tilt readings (omega_c, phi_c) and kappa; per AP (a,): its prior.
    orientation_residuals: np.ndarray | None = None
    redundancy_orientation: np.ndarray | None = None
    ap_prior_residuals: np.ndarray | None = None
    redundancy_ap_prior: np.ndarray | None = None
    ap_prior_values: np.ndarray | None = None  # (a,) the priors [SI], NaN where none
    ap_prior_sigmas: np.ndarray | None = None  # (a,) their sigmas [SI], NaN where none
    # What a person can act on when the adjustment fails (largest normalised misclosures,
    # sigma0 per scan and per primitive, suspicious plane matches); see _diagnose.
    diagnosis: dict = dataclasses.field(default_factory=dict)
    # (t, 3, 3) a posteriori covariance of each target [m^2] in the datum used (the diagonal
    # blocks the quality pass computes anyway): confidence ellipsoids at no extra cost.
    target_covariance: np.ndarray | None = dataclasses.field(default=None, repr=False)
    # The CalibrationModel adjusted (scanner architecture, unit lengths, datum): what a result
    # file must record so that the calibration is applied as it was estimated.
    model: object = dataclasses.field(default=None, repr=False)

    @property
    def ok(self) -> bool:
        return self.result in (SUCCESS, NOT_ESTIMABLE)

    def correlation(self) -> np.ndarray:
        if self.covariance is None:
            raise ValueError(
                "no full covariance matrix (u^2 memory): run calibrate with "
                "SolverOptions(full_covariance=True)"
            )
        s = np.sqrt(np.clip(np.diag(self.covariance), 0, None))
        with np.errstate(invalid="ignore", divide="ignore"):
            c = self.covariance / np.outer(s, s)
        return np.where(np.outer(s, s) > 0, c, 0.0)

    def summary(self, truth: dict | None = None) -> str:
        """The result as text: result code, degrees of freedom, sigma0 and the global test,
        mean redundancy numbers, weighted constraints, confoundings and implausible estimates,
        then the papers' AP table (Chow et al. 2013, tables 3-6; no numbers for a failed
        adjustment), with a column of true values where ``truth`` (AP name -> SI value, e.g.
        a simulation's ``true_aps``) is given."""
        return summary(self) + "\n\n" + ap_table(self, truth=truth)

    def to_dict(self) -> dict:
        """The result JSON of SPEC section 11 (SI units, strict JSON): estimates, sigmas,
        t-values and correlations of the APs, scan poses, targets and planes with their
        precision, redundancy, the global test, confoundings; a failed adjustment's estimates
        are null (``estimates`` says why)."""
        return result_to_dict(self)

    def weighted_constraints(self, critical_value: float = W_CRITICAL) -> list[dict]:
        """The weighted constraints with observed values (tilt readings, observed kappa, AP
        priors; eq. 7, SPEC section 6), one dict each: ``kind`` ("omega", "phi", "kappa" or
        "ap"), ``name`` (scan or AP), ``observed``, ``sigma`` (a priori), ``residual`` (``v =
        estimate - observed``), ``redundancy`` r, the w-test ``v / (sigma sqrt(r))`` (None where
        r is 0: the constraint is not controlled; :func:`._quality.w_tests`) and whether ``|w|``
        exceeds ``critical_value`` (Baarda's 3.29 at the reliability level 0.1 %). SI units (m,
        rad, or 1)."""
        out = []

        def add(kind, name, observed, sigma, v, r):
            w = float(w_tests(np.array([v]), np.array([sigma]), np.array([r]))[0])
            w = w if np.isfinite(w) else None
            out.append(
                dict(
                    kind=kind,
                    name=name,
                    observed=float(observed),
                    sigma=float(sigma),
                    residual=float(v),
                    redundancy=float(r),
                    w=w,
                    rejected=w is not None and abs(w) > critical_value,
                )
            )

        net, v, r = self.network, self.orientation_residuals, self.redundancy_orientation
        if v is not None:
            obs = np.concatenate([net.levelling, net.heading_values[:, None]], axis=1)
            sig = np.concatenate([net.levelling_sigma, net.heading_sigmas[:, None]], axis=1)
            for j, scan in enumerate(self.scans):
                for c, kind in enumerate(("omega", "phi", "kappa")):
                    if np.isfinite(v[j, c]):
                        add(kind, scan, obs[j, c], sig[j, c], v[j, c], r[j, c])
        if self.ap_prior_residuals is not None:
            for i, name in enumerate(self.ap_names):
                if np.isfinite(self.ap_prior_residuals[i]):
                    add(
                        "ap",
                        name,
                        self.ap_prior_values[i],
                        self.ap_prior_sigmas[i],
                        self.ap_prior_residuals[i],
                        self.redundancy_ap_prior[i],
                    )
        return out

    def plausibility(self) -> tuple:
        """``(findings, summary)``: the APs whose estimate is beyond what instruments have
        (:mod:`tlsjax._model._plausibility`, level "warning" or "impossible") and one line
        naming them with the likely cause in the design or the data; ``((), "")`` when every
        estimate is plausible or the adjustment failed (it has no estimates)."""
        if not self.ok:
            return (), ""
        base = [n.split("[")[0] for n in self.ap_names]
        findings = ap_findings(
            self.ap_names, self.ap_values, self.ap_units, [get_ap(b).description for b in base]
        )
        if not findings:
            return (), ""
        net = self.network
        ranges = [] if net is None else [net.observations[:, 0], net.plane_observations[:, 0]]
        ranges = np.concatenate(ranges) if ranges else np.zeros(0)
        causes = likely_causes(
            n_scans=len(self.scans),
            n_stations=_n_stations(self.eops),
            n_primitives=len(self.targets) + len(self.planes),
            n_aps=len(self.ap_names),
            kind="targets"
            if not self.planes
            else "planes"
            if not self.targets
            else "targets and planes",
            not_estimable=self.not_estimable,
            weakly_determined=self.weakly_determined,
            median_range=float(np.median(ranges)) if ranges.size else None,
        )
        return findings, implausible_summary(findings, causes)

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


def _n_stations(eops, tolerance: float = 0.05) -> int | None:
    """Distinct scanner positions among the scans (within ``tolerance`` metres)."""
    if eops is None or not len(eops) or not np.all(np.isfinite(eops[:, :3])):
        return None
    stations: list = []
    for x in np.asarray(eops)[:, :3]:
        if not any(np.linalg.norm(x - y) < tolerance for y in stations):
            stations.append(x)
    return len(stations)


def _on_host(problem) -> dict:
    """numpy copies of the problem's arrays a result reads: cached on the (immutable) problem,
    so that a solve() again does not convert them anew (a few microseconds each, on the host
    path after every adjustment)."""
    prior = problem.ap_prior_weight is not None
    return kept(
        problem,
        "_on_host",
        lambda: dict(
            fixed=np.asarray(problem.fixed),
            used=tuple(np.asarray(f.weight) > 0 for f in problem.families),
            ap_prior_weight=np.asarray(problem.ap_prior_weight) if prior else None,
            ap_prior=np.asarray(problem.ap_prior) if prior else None,
        ),
    )


def _ap_estimates(plan: Plan, q, state, s0sq, absent=()):
    """AP values, a posteriori sigmas, t, the dependent (non-estimable) and fixed masks and the
    AP covariance; non-estimable APs are NaN, never numbers. ``absent``: AP indices an earlier
    pass found not estimable and removed (held in this one; reported as not estimable)."""
    n6 = 6 * plan.spec.n_scans
    fixed = _on_host(plan.problem)["fixed"][n6:]
    ap_dep = np.asarray(q.dependent)[n6:] & ~fixed
    ap_fixed = fixed
    if absent:
        gone = np.zeros(plan.spec.n_aps, dtype=bool)
        gone[list(absent)] = True
        ap_dep, ap_fixed = ap_dep | gone, fixed & ~gone
    # The AP block is datum invariant (SPEC section 6); scaled a posteriori like the sigmas.
    cov = np.asarray(q.Qzz)[n6:, n6:] * s0sq
    sig = np.sqrt(np.maximum(cov.diagonal(), 0.0))
    values = np.array(state.params.aps)
    if ap_dep.any():
        values[ap_dep] = np.nan
        sig[ap_dep] = np.nan
        cov[ap_dep, :] = np.nan
        cov[:, ap_dep] = np.nan
    sig[ap_fixed] = 0.0
    with np.errstate(invalid="ignore", divide="ignore"):
        return values, sig, values / sig, ap_dep, ap_fixed, cov


def _max_correlations(plan: Plan, q, skip):
    """Largest |correlation| of every AP with any other unknown, and that unknown's name, in the
    datum (inner constraints on the primitives): each AP's row of the cofactor matrix against
    the primitives (``prim_cross``) and the reduced unknowns, over the sigmas; NaN and no name
    where ``skip``. Few numpy calls: this runs after every adjustment."""
    n6, na = 6 * plan.spec.n_scans, plan.spec.n_aps
    if na == 0:
        return np.zeros(0), ()
    Qzz = np.asarray(q.Qzz)
    var = Qzz.diagonal()
    R = [np.asarray(X)[:, :, n6:].reshape(-1, na) for X in q.prim_cross] + [Qzz[:, n6:]]
    s = [np.diagonal(np.asarray(D), axis1=1, axis2=2).reshape(-1) for D in q.prim_cofactor]
    s = np.sqrt(np.maximum(np.concatenate(s + [np.where(q.dependent, 0.0, var)]), 0.0))
    sz = np.sqrt(np.maximum(var, 0.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        C = np.abs(np.concatenate(R) / np.outer(s, sz[n6:]))  # (u, a)
    C[s.size - na + np.arange(na), np.arange(na)] = 0.0  # the AP itself
    C[~np.isfinite(C)] = 0.0  # a sigma 0: a dependent or held unknown
    arg = C.argmax(axis=0)
    names = plan.parameter_names
    partner = tuple("" if k else names[i] for k, i in zip(skip.tolist(), arg.tolist()))
    best = C[arg, np.arange(na)]
    return np.where(skip, np.nan, best), partner


def _result_code(state, q, rank_def, not_est):
    code = result_code_of(
        finite=bool(state.finite) and math.isfinite(float(q.vtpv)),
        rank_deficient=bool(rank_def),
        converged=bool(state.converged),
        not_estimable=bool(not_est),
    )
    return ResultCode(int(code))


def _message(code, rank_def, not_est, state, diagnosis):
    msg = code.message
    if code == ResultCode.MAX_ITERATIONS:
        msg += f" ({int(state.iteration)} iterations; last update {float(state.size):.3g} x the tolerance)"
    if rank_def:
        msg += ": " + ", ".join(rank_def[:12])
    if not_est:
        msg += "; " + "; ".join(not_estimable_sentence(n, reason) for n, _, reason in not_est)
    if code in (ResultCode.MAX_ITERATIONS, ResultCode.NONFINITE) and diagnosis.get("summary"):
        msg += "; " + diagnosis["summary"]
    return msg


def _point_blocks(cof):
    """The 3x3 diagonal blocks of per-primitive cofactors (n, 3k, 3k), one per point, in the
    order of the primitives' points (a scale bar carries k = 2 points)."""
    k = cof.shape[-1] // 3
    idx = np.arange(k)
    return cof.reshape(-1, k, 3, k, 3)[:, idx, :, idx, :].transpose(1, 0, 2, 3).reshape(-1, 3, 3)


def _in_order(net: Network, plan: Plan) -> bool:
    """Whether the network's observation rows and targets are all those of the plan's one
    target family, in order: the result's per-observation arrays are then copies of the
    quality's. Kept with the plan (memoised per network, :func:`._network.memoised`)."""
    rows, tg = plan.family_rows, plan.family_targets
    return kept(
        plan,
        "_in_order",
        lambda: (
            len(tg) == 1
            and tg[0].shape[1] == 1
            and np.array_equal(tg[0][:, 0], np.arange(len(net.targets)))
            and np.array_equal(rows[0], np.arange(net.observations.shape[0]))
        ),
    )


def _observation_arrays(net: Network, plan: Plan, q, state, s0sq):
    """Residuals, redundancy numbers and used masks in network row order; target and plane
    estimates with a posteriori sigmas (datum blocks of the cofactor matrix)."""
    n_obs = net.observations.shape[0]
    host = _on_host(plan.problem)
    if _in_order(net, plan):
        resid, redund = np.array(q.residuals[0]), np.array(q.redundancy[0])
        used = host["used"][0].copy()
        txyz = np.array(state.params.prims[0]).reshape(-1, 3)
        tcov = np.asarray(q.prim_cofactor[0]) * s0sq
    else:
        resid, redund = np.zeros((n_obs, 3)), np.zeros((n_obs, 3))
        used = np.ones((n_obs, 3), dtype=bool)
        txyz = np.zeros((len(net.targets), 3))
        tcov = np.full((len(net.targets), 3, 3), np.nan)
        for fi, tg in enumerate(plan.family_targets):
            rows = plan.family_rows[fi]
            resid[rows] = np.asarray(q.residuals[fi])
            redund[rows] = np.asarray(q.redundancy[fi])
            used[rows] = host["used"][fi]
            txyz[tg.reshape(-1)] = np.asarray(state.params.prims[fi]).reshape(-1, 3)
            tcov[tg.reshape(-1)] = _point_blocks(np.asarray(q.prim_cofactor[fi])) * s0sq
    tsig = np.sqrt(np.clip(np.diagonal(tcov, axis1=1, axis2=2), 0, None))
    planes = {}
    fp = plan.plane_family
    if fp is not None:
        cof = np.asarray(q.prim_cofactor[fp])
        planes = dict(
            planes=net.planes,
            plane_params=np.asarray(state.params.prims[fp]),
            plane_sigmas=np.sqrt(np.clip(np.diagonal(cof, axis1=1, axis2=2) * s0sq, 0, None)),
            plane_covariance=cof * s0sq,
            plane_residuals=np.asarray(q.residuals[fp]),
            plane_redundancy=np.asarray(q.redundancy[fp]),
            plane_used=host["used"][fp].copy(),
        )
    return resid, redund, used, txyz, tsig, tcov, planes


def assemble(net, model, plan: Plan, state, q, absent: tuple = ()) -> CalibrationResult:
    """The arrays of one adjustment (state, quality) as a :class:`CalibrationResult` with
    names, units, result code and message. ``absent``: the ``(name, confounded_with, reason)``
    of the APs that earlier passes found not estimable and removed from the unknowns
    (:meth:`tlsjax.Adjustment.run_estimable`): held in this pass, reported as not estimable.

    Long because a result holds some forty named fields, set here in one place; the computations
    are the helpers of this module.
    """
    spec = plan.spec
    ns = spec.n_scans
    dof = float(q.dof)
    s0sq = float(q.vtpv) / dof if dof > 0 else np.nan
    s0sq_scale = s0sq if np.isfinite(s0sq) else 1.0
    gone = [plan.ap_labels.index(n) for n, *_ in absent]
    values, sig, tstat, ap_dep, ap_fixed, ap_cov = _ap_estimates(plan, q, state, s0sq, gone)
    max_corr, partner = _max_correlations(plan, q, ap_dep | ap_fixed)
    dep = np.asarray(q.dependent)
    fixed = _on_host(plan.problem)["fixed"]
    n_p = sum(P.size for P in state.params.prims)
    names = plan.parameter_names
    eop_dep = dep[: 6 * ns] & ~fixed[: 6 * ns]
    rank_def = tuple(names[n_p + j] for j in np.flatnonzero(eop_dep)) if eop_dep.any() else ()
    # Few statements from here on: each costs several microseconds right after the compiled
    # call (the host's caches hold its data then), a sixth of a small network's adjustment.
    new = [j for j in np.flatnonzero(ap_dep).tolist() if j not in gone] if ap_dep.any() else ()
    not_est = tuple(absent) + (not_estimable_aps(plan, q, state, new) if new else ())
    if len(not_est) > 1:
        not_est = tuple(sorted(not_est, key=lambda t: plan.ap_labels.index(t[0])))
    weak = tuple(
        (plan.ap_labels[i], partner[i], c)
        for i, (c, d) in enumerate(zip(max_corr.tolist(), ap_dep.tolist()))
        if not d and c > model.correlation_threshold
    )
    code = _result_code(state, q, rank_def, not_est)
    diagnosis = failure_diagnosis(net, plan, q) if code != ResultCode.SUCCESS else {}
    if code == ResultCode.MAX_ITERATIONS:
        _name_nearly_absorbed(plan, q, ap_dep | ap_fixed, diagnosis)
    resid, redund, used, txyz, tsig, tcov, plane_out = _observation_arrays(
        net, plan, q, state, s0sq_scale
    )
    eop_sig = np.sqrt(np.maximum(np.asarray(q.Qzz).diagonal()[: 6 * ns] * s0sq_scale, 0.0))
    eop_sig = eop_sig.reshape(ns, 6)
    eop_sig[eop_dep.reshape(ns, 6)] = np.nan
    cov = None if q.Qfull is None else np.asarray(q.Qfull) * s0sq_scale
    # The solver counts one condition per plane point and the hard constraints; a point is
    # three observations.
    n_constraints = sum(fam.hard_constraints() for fam in plan.problem.families)
    n_conditions = int(round(float(q.n_observations))) - n_constraints
    n_obs_total = n_conditions
    if plane_out:
        n_obs_total += 2 * int(plane_out["plane_used"].any(axis=1).sum())
    return CalibrationResult(
        result=code,
        message=_message(code, rank_def, not_est, state, diagnosis),
        converged=bool(state.converged),
        iterations=int(state.iteration),
        sigma0=float(np.sqrt(s0sq)),
        dof=dof,
        n_observations=n_obs_total,
        n_unknowns=int(n_p + (~dep).sum()),
        n_conditions=n_conditions,
        n_constraints=n_constraints,
        datum=plan.datum,
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
        redundancy_levelling=np.asarray(q.redundancy_levelling)[:, :2],
        **_constraint_arrays(plan, q, state),
        redundancy_prior_sum=float(sum(np.asarray(r).sum() for r in q.redundancy_prior)),
        parameter_names=names,
        covariance=cov,
        network=net,
        ap_covariance=ap_cov,
        used=used,
        ap_fixed=tuple(plan.ap_labels[i] for i in np.flatnonzero(ap_fixed)),
        diagnosis=diagnosis,
        target_covariance=tcov,
        model=model,
        **plane_out,
    )


def _constraint_arrays(plan: Plan, q, state) -> dict:
    """Residuals and redundancy numbers of the weighted constraints with observed values
    (orientation readings and AP priors), NaN where there is none."""

    # Computed in the compiled quality: here only numpy (nothing eager on the host path).
    observed = np.asarray(q.orientation_weight) > 0
    nan = lambda a, m: np.where(m, a, np.nan)
    wa = np.zeros(plan.spec.n_aps)
    prior = np.zeros(plan.spec.n_aps)
    host = _on_host(plan.problem)
    if host["ap_prior_weight"] is not None:
        wa, prior = host["ap_prior_weight"], host["ap_prior"]
    r_prior = q.redundancy_ap_prior
    return dict(
        orientation_residuals=nan(np.asarray(q.orientation_residuals), observed),
        redundancy_orientation=nan(np.asarray(q.redundancy_levelling), observed),
        ap_prior_residuals=nan(np.asarray(state.params.aps) - prior, wa > 0),
        redundancy_ap_prior=nan(
            np.zeros(plan.spec.n_aps) if r_prior is None else np.asarray(r_prior), wa > 0
        ),
        ap_prior_values=nan(prior, wa > 0),
        ap_prior_sigmas=nan(1.0 / np.where(wa > 0, wa, 1.0), wa > 0),
    )


#: A failed adjustment names the APs whose columns the primitives explain to all but this share
#: (1 - R^2 of the AP on the targets or planes): an AP the design separates only through the
#: noise of the scan positions (one station) leaves a nearly flat direction.
NEARLY_ABSORBED = 1e-2


def _name_nearly_absorbed(plan: Plan, q, held, diagnosis: dict) -> None:
    ns = plan.spec.n_scans
    share = np.asarray(q.K_over_N)[6 * ns :]
    near = [
        (plan.ap_labels[i], float(share[i]))
        for i in range(plan.spec.n_aps)
        if not held[i] and np.isfinite(share[i]) and share[i] < NEARLY_ABSORBED
    ]
    if not near:
        return
    primitives = "plane" if plan.plane_family is not None and not plan.family_targets else "target"
    text = (
        f"the {primitives} parameters nearly absorb "
        + ", ".join(f"{n} (1 - R^2 = {v:.1e})" for n, v in near)
        + ": this design barely separates them; add stations or tilts"
    )
    diagnosis["nearly_absorbed"] = {n: v for n, v in near}
    diagnosis["summary"] = text + (f"; {diagnosis['summary']}" if diagnosis.get("summary") else "")


def not_estimable_aps(plan: Plan, q, state, columns) -> tuple:
    """``(name, confounded_with, reason)`` of each non-estimable AP (``columns``: indices among
    the APs): what it is confounded with, in the inner-constraint datum on the primitives
    (:mod:`._diagnose`)."""
    ns = plan.spec.n_scans
    n_p = sum(int(np.prod(P.shape)) for P in state.params.prims)
    cols = [6 * ns + j for j in columns]
    found = confounded_partners(
        plan.spec,
        plan.problem,
        state.params,
        np.asarray(q.dependent),
        np.asarray(plan.problem.fixed),
        cols,
        np.asarray(q.K_over_N),
    )
    primitives = "plane" if plan.plane_family is not None and not plan.family_targets else "target"
    out = []
    for j, col in zip(columns, cols):
        partner_col, _, kind = found[col]
        name = plan.ap_labels[j]
        if kind == "scale":
            out.append((name, "scale", "scale is undefined; add scale bars or control points"))
        elif kind == "primitives":
            out.append(
                (
                    name,
                    f"{primitives} coordinates",
                    f"its effect is absorbed by the {primitives} parameters: this design cannot separate "
                    f"them (e.g. every scan from one station, or no tilted scans); add stations or tilts",
                )
            )
        else:
            partner = plan.parameter_names[n_p + partner_col]
            out.append((name, partner, f"confounded with {partner}"))
    return tuple(out)
