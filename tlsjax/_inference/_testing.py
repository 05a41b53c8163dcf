"""Statistical testing of a self-calibration (SPEC sections 5 and 7).

* Variance component estimation (VCE) per observation group, range, horizontal direction,
  elevation angle and levelling (Förstner 1979; Koch 1999, section 3.6): with whitened
  residuals ``e = v / sigma`` and the redundancy numbers ``r_i = (Q_vv P)_ii``,

      s_g^2 = v_g^T P_g v_g / r_g,     r_g = sum of the group's redundancy numbers,

  the group's sigmas are multiplied by ``s_g`` and the adjustment is repeated until every
  ``s_g^2`` is 1 within tolerance (the fixed point). Only the weights change, and they are
  traced arrays of the compiled adjustment, so re-weighting never recompiles.
* Baarda (1968) data snooping: ``w_i = v_i / (sigma_i sqrt(r_i))`` with the a priori sigma
  (after VCE: the re-estimated group sigma); the largest ``|w_i|`` above the critical value
  ``k = N^-1(1 - alpha / 2)`` (3.29 for alpha = 0.1 %) is removed and the network re-adjusted,
  until no test rejects. Removal is a weight of zero (a mask), never a new network, so shapes
  stay static and nothing recompiles. Every removal is reported.
* Reliability (Baarda 1968; Förstner 1987): minimal detectable bias
  ``MDB_i = delta0 sigma_i / sqrt(r_i)``, ``delta0 = N^-1(1 - alpha0/2) + N^-1(power)`` (4.13 for
  alpha0 = 0.1 %, power 80 %); external reliability: the change of each AP caused by an MDB-sized
  error, ``dx_a = Q_(a, u_i) J_i^T P_i MDB_i``, in units of the AP's a priori sigma
  (``delta0 / sqrt(r_i)`` times the AP influence of :mod:`._quality`).
* t-tests of the APs: ``t = x_a / s_a`` (a posteriori sigma) against Student's t with the
  degrees of freedom of the adjustment.

Units: SI inside, millimetres and arc seconds in the reports.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from .._adjustment._calibrate import analyze
from .._adjustment._config import CalibrationModel, SolverOptions
from .._adjustment._network import Network
from .._adjustment._result import CalibrationResult, assemble
from .._stats import non_centrality
from .._units import ARCSEC, display_group
from ._statistics import ap_t_tests, critical_value, minimal_detectable_bias, w_tests

GROUPS = ("range", "hz", "el", "levelling")
REMOVAL_UNITS = ("observation", "target")
#: Pseudo-observation sigma [m] that holds a target which lost all its testable observations
#: at its last estimate; it carries no information about anything else (see _pin_targets).
PIN_SIGMA = 1.0


@dataclasses.dataclass(frozen=True)
class TestingOptions:
    """Settings of :func:`calibrate_and_test`.

    ``vce``: estimate one variance factor per group (point-based networks). ``vce_tolerance``:
    stop when every ``|s_g^2 - 1|`` is below it; ``vce_min_redundancy``: a group with a smaller
    redundancy keeps its a priori sigma (its estimate would be mostly noise).
    ``snooping``: Baarda data snooping; ``alpha``: per-test significance level (0.001 -> 3.29),
    or ``critical_value`` directly; ``bonferroni``: divide alpha by the number of tested
    observations (family-wise level: no clean observation removed with probability 1 - alpha).
    The per-test default 3.29 (SPEC section 7) rejects about 0.1 % of clean observations, i.e.
    about two per 2,000-observation network (measured: 63 false removals in 30 networks of 2,160
    observations, benchmarks/stats_rates.py); ``bonferroni=True, alpha=0.05`` (k = 4.23 there)
    removed none while finding all 150 injected 20-sigma blunders.
    ``removal``: "observation" (one scalar observation) or "target" (all three observations of
    the target in that scan). ``alpha0``, ``power``: reliability (delta0 = 4.13).
    ``min_redundancy``: observations with a smaller redundancy number are flagged uncontrolled.
    ``ap_alpha``: significance level of the AP t-tests.
    """

    vce: bool = True
    vce_tolerance: float = 1e-3
    vce_max_iterations: int = 30
    vce_min_redundancy: float = 3.0
    snooping: bool = True
    alpha: float = 0.001
    critical_value: float | None = None
    bonferroni: bool = False
    removal: str = "observation"
    max_removals: int = 100
    alpha0: float = 0.001
    power: float = 0.8
    min_redundancy: float = 0.1
    ap_alpha: float = 0.05

    def __post_init__(self):
        if self.removal not in REMOVAL_UNITS:
            raise ValueError(f"removal must be one of {REMOVAL_UNITS}, got {self.removal!r}")
        if not 0 < self.alpha < 1:
            raise ValueError(f"alpha must be in (0, 1), got {self.alpha}")
        if self.critical_value is not None and not self.critical_value > 0:
            raise ValueError(f"critical_value must be positive, got {self.critical_value}")
        if not self.vce_tolerance > 0:
            raise ValueError(f"vce_tolerance must be positive, got {self.vce_tolerance}")
        if self.vce_max_iterations < 1:
            raise ValueError(f"vce_max_iterations must be >= 1, got {self.vce_max_iterations}")
        if self.max_removals < 0:
            raise ValueError(f"max_removals must be >= 0, got {self.max_removals}")
        if not 0 <= self.min_redundancy < 1:
            raise ValueError(f"min_redundancy must be in [0, 1), got {self.min_redundancy}")
        non_centrality(self.alpha0, self.power)
        critical_value(self.ap_alpha)


@dataclasses.dataclass(frozen=True)
class Removal:
    """One observation removed by data snooping (or as a consequence of a removal).

    ``residual`` in mm (range) or arc seconds (angles) at the adjustment in which it was
    rejected; ``w`` its w-test statistic (NaN for consequential removals); ``reason`` says why.
    """

    step: int
    row: int
    scan: str
    target: str
    group: str
    residual: float
    unit: str
    w: float
    reason: str

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclasses.dataclass(frozen=True)
class VarianceComponent:
    """Estimated variance factor of one group: the group's sigmas are ``sqrt(factor)`` times
    the a priori ones. ``redundancy`` is r_g, ``n`` the number of active observations."""

    group: str
    factor: float
    sigma_factor: float
    redundancy: float
    n: int
    estimated: bool
    a_priori_sigma: float  # median a priori sigma of the group [m or rad]
    sigma: float  # median re-estimated sigma [m or rad]

    def as_dict(self) -> dict:
        return dataclasses.asdict(self)


@dataclasses.dataclass(frozen=True, eq=False)
class TestedCalibration:
    """Result of :func:`calibrate_and_test`. Arrays are in network row order, (n, 3).

    ``calibration``: the final adjustment (removed observations have weight 0, residual
    reported, redundancy 0). ``mask``: True where an observation is used. ``sigmas``: the
    sigmas of the final adjustment (a priori times the VCE factor). ``w``: w-test statistics
    (NaN where removed or untestable); ``mdb``: minimal detectable bias [m, rad];
    ``external``: largest AP change caused by an MDB-sized error, in AP sigmas, with
    ``external_ap`` naming that AP; ``uncontrolled``: (row, group) pairs with redundancy
    below ``min_redundancy``. ``history``: one line per adjustment (sigma0, factors, removals).
    """

    calibration: CalibrationResult
    options: TestingOptions
    outliers: tuple
    variance_components: tuple
    mask: np.ndarray
    sigmas: np.ndarray
    w: np.ndarray
    critical_value: float
    mdb: np.ndarray
    external: np.ndarray
    external_ap: np.ndarray
    uncontrolled: tuple
    ap_tests: tuple
    pinned_targets: tuple
    history: tuple
    n_adjustments: int
    message: str

    def outliers_json(self) -> list:
        return [_finite_or_none(o.as_dict()) for o in self.outliers]

    def variance_components_json(self) -> dict:
        return {vc.group: _finite_or_none(vc.as_dict()) for vc in self.variance_components}

    def json_fields(self) -> dict:
        """The result-JSON contract's ``outliers`` and ``variance_components`` (SPEC section 11),
        plus the testing settings; NaN becomes null (strict JSON)."""
        return {
            "outliers": self.outliers_json(),
            "variance_components": self.variance_components_json(),
            "snooping": {
                "critical_value": self.critical_value,
                "removal": self.options.removal,
                "alpha": self.options.alpha,
                "bonferroni": self.options.bonferroni,
                "n_removed": len(self.outliers),
                "pinned_targets": list(self.pinned_targets),
                "n_uncontrolled": len(self.uncontrolled),
                "n_adjustments": self.n_adjustments,
            },
            "ap_tests": [_finite_or_none(dataclasses.asdict(t)) for t in self.ap_tests],
        }

    def summary(self) -> str:
        c = self.calibration
        lines = [
            f"sigma0 = {c.sigma0:.4f}, dof = {c.dof:.0f}, adjustments = {self.n_adjustments}: {self.message}"
        ]
        for vc in self.variance_components:
            unit, f = ("mm", 1e3) if vc.group == "range" else ('"', 1 / ARCSEC)
            lines.append(
                f"  {vc.group:9s} factor {vc.factor:8.4f}  sigma {vc.a_priori_sigma * f:.3f} -> {vc.sigma * f:.3f} {unit}"
                f"  r_g = {vc.redundancy:.1f} of n = {vc.n}{'' if vc.estimated else ' (held)'}"
            )
        lines.append(
            f"  {len(self.outliers)} removed observation(s), critical value {self.critical_value:.2f}"
        )
        for o in self.outliers:
            lines.append(
                f"    step {o.step}: scan {o.scan} target {o.target} {o.group}: v = {o.residual:.2f} {o.unit}, w = {o.w:.2f} ({o.reason})"
            )
        for t in self.ap_tests:
            lines.append(
                f"  {t.name}: t = {t.t:.2f} ({'significant' if t.significant else 'not significant'} at |t| > {t.critical:.2f})"
            )
        return "\n".join(lines)


def _finite_or_none(d: dict) -> dict:
    return {
        k: (
            None
            if isinstance(v, float) and not np.isfinite(v)
            else (bool(v) if isinstance(v, np.bool_) else v)
        )
        for k, v in d.items()
    }


# ----------------------------------------------------------------------------------------
# Building blocks on a finished adjustment (host side, numpy)


# ----------------------------------------------------------------------------------------
# The compiled adjustment with other weights (no recompilation)


class _Reweighter:
    """One analysed adjustment (:class:`tlsjax.Adjustment`), re-solved with other weights and
    pinned targets; nothing recompiles."""

    def __init__(self, net: Network, model: CalibrationModel, options: SolverOptions):
        self.net, self.model, self.options = net, model, options
        self.adjustment = analyze(net, model, options)
        self.plan = self.adjustment.plan
        self.params0 = self.adjustment.initial

    def run(self, weight: np.ndarray, levelling_weight: np.ndarray, pinned: dict, params0=None):
        """``weight`` (n, 3) = 1/sigma or 0 (removed); ``pinned`` maps target -> xyz."""
        adj = self.adjustment
        control = {t: (xyz, PIN_SIGMA) for t, xyz in pinned.items()}
        problem = adj.problem(weights=weight, levelling_weights=levelling_weight, control=control)
        state, q = adj.run(problem, params0)
        plan = dataclasses.replace(self.plan, problem=problem)
        res = assemble(self.net, self.model, plan, state, q)
        infl = np.zeros((self.net.observations.shape[0], 3, plan.spec.n_aps))
        for fi, rows in enumerate(plan.family_rows[: len(plan.family_targets)]):
            infl[rows] = np.asarray(q.ap_influence[fi])
        return res, state, infl


# ----------------------------------------------------------------------------------------
# The entry point


def calibrate_and_test(
    network: Network,
    model: CalibrationModel | None = None,
    options: SolverOptions | None = None,
    testing: TestingOptions | None = None,
) -> TestedCalibration:
    """Self-calibration with variance component estimation, Baarda data snooping,
    reliability and AP t-tests (SPEC sections 5 and 7).

    Loop: adjust; if ``testing.vce``, re-estimate the group variance factors
    ``s_g^2 = v_g^T P_g v_g / r_g`` (Förstner 1979) and re-adjust until all are 1 within
    ``vce_tolerance``; compute ``w_i = v_i / (sigma_i sqrt(r_i))`` (Baarda 1968); if the largest
    ``|w_i|`` exceeds the critical value, give that observation (or, with
    ``removal="target"``, the target's three observations in that scan) weight 0 and repeat.
    A target left with observations in fewer than two scans (or fewer than four observations)
    can no longer be checked: its remaining observations are removed too, it is held at its last
    estimate by a weak pseudo-observation (no rank defect, no effect on the rest), and this is
    reported. Weights are traced arrays of the compiled adjustment: nothing recompiles.
    """
    model = model or CalibrationModel()
    options = options or SolverOptions(full_covariance=False)
    testing = testing or TestingOptions()
    if network.has_planes:
        raise ValueError(
            f"{network.source}: variance components and data snooping are for target networks; with "
            "planes the weights are held fixed (SPEC section 5); use calibrate()"
        )
    net = network
    rw = _Reweighter(net, model, options)
    n = net.observations.shape[0]
    base_sigma = np.asarray(net.sigmas, dtype=float)
    lev_sigma = np.asarray(net.levelling_sigma, dtype=float)
    lev_active = np.isfinite(lev_sigma)
    factor = np.ones(4)  # variance factors: range, hz, el, levelling
    estimated = np.zeros(4, dtype=bool)
    mask = np.ones((n, 3), dtype=bool)
    pinned: dict = {}
    removals: list = []
    history: list = []
    delta0 = non_centrality(testing.alpha0, testing.power)
    n_adj = 0
    params = None
    res = state = infl = None
    crit = np.nan

    def sigmas_now():
        return base_sigma * np.sqrt(factor[:3])[None, :]

    def weights_now():
        w = np.where(mask, 1.0 / sigmas_now(), 0.0)
        lw = np.where(lev_active, 1.0 / (lev_sigma * np.sqrt(factor[3])), 0.0)
        return w, lw

    def adjust():
        nonlocal res, state, infl, n_adj, params
        w, lw = weights_now()
        res, state, infl = rw.run(w, lw, pinned, params)
        n_adj += 1
        if res.ok:
            # Warm start the next adjustment; the datum (inner constraints) stays the same
            # because the S-transformation is applied to every update.
            params = state.params

    vce_note = ""
    step = 0
    while True:
        adjust()
        if not res.ok:
            break
        if testing.vce:
            for it in range(testing.vce_max_iterations):
                s2, r_g, n_g = _group_factors(
                    res, sigmas_now(), mask, lev_sigma * np.sqrt(factor[3]), lev_active
                )
                est = r_g >= testing.vce_min_redundancy
                estimated = est
                s2 = np.where(est, s2, 1.0)
                history.append(
                    {
                        "step": step,
                        "vce_iteration": it,
                        "sigma0": res.sigma0,
                        "factors": factor.tolist(),
                        "s2": s2.tolist(),
                    }
                )
                if np.all(np.abs(s2 - 1.0) < testing.vce_tolerance):
                    break
                factor = factor * s2
                adjust()
                if not res.ok:
                    break
            else:
                vce_note = f"; VCE did not converge in {testing.vce_max_iterations} iterations"
            if not res.ok:
                break
        sig = sigmas_now()
        w = w_tests(res.residuals, sig, res.redundancy)
        w = np.where(mask, w, np.nan)
        n_tested = int(np.isfinite(w).sum())
        if testing.critical_value is not None:
            crit = float(testing.critical_value)
        else:
            crit = critical_value(
                testing.alpha / max(n_tested, 1) if testing.bonferroni else testing.alpha
            )
        history.append(
            {
                "step": step,
                "sigma0": res.sigma0,
                "max_abs_w": float(np.nanmax(np.abs(w))) if n_tested else np.nan,
                "critical": crit,
                "factors": factor.tolist(),
            }
        )
        if not testing.snooping or n_tested == 0:
            break
        aw = np.where(np.isfinite(w), np.abs(w), -1.0)
        i, g = np.unravel_index(int(np.argmax(aw)), aw.shape)
        if aw[i, g] <= crit:
            break
        if len(removals) >= testing.max_removals:
            vce_note += f"; stopped after max_removals = {testing.max_removals} with |w| = {aw[i, g]:.2f} still above {crit:.2f}"
            break
        step += 1
        cols = (0, 1, 2) if testing.removal == "target" else (g,)
        for c in cols:
            if mask[i, c]:
                val, unit = display_group(c, res.residuals[i, c])
                reason = (
                    "largest |w| above critical value"
                    if c == g
                    else "same target observation as the rejected one"
                )
                removals.append(
                    Removal(
                        step,
                        int(i),
                        net.scans[net.scan_index[i]],
                        net.targets[net.target_index[i]],
                        GROUPS[c],
                        float(val),
                        unit,
                        float(w[i, c]),
                        reason,
                    )
                )
                mask[i, c] = False
        removals.extend(_undetermined_targets(net, res, mask, pinned, step, w))

    # Final quantities at the last adjustment.
    sig = sigmas_now()
    w = np.where(mask, w_tests(res.residuals, sig, res.redundancy), np.nan)
    mdb = np.where(mask, minimal_detectable_bias(sig, res.redundancy, delta0), np.nan)
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(
            res.redundancy > 0,
            delta0 / np.sqrt(np.where(res.redundancy > 0, res.redundancy, 1.0)),
            np.inf,
        )
    if infl.shape[-1]:
        ext_all = np.abs(infl) * np.where(np.isfinite(scale), scale, 0.0)[..., None]
        ext = np.where(
            mask & np.isfinite(scale), ext_all.max(axis=-1), np.where(mask, np.inf, np.nan)
        )
        arg = ext_all.argmax(axis=-1)
        ext_ap = np.array(res.ap_names, dtype=object)[arg]
    else:
        ext = np.zeros((n, 3))
        ext_ap = np.full((n, 3), "", dtype=object)
    unc = tuple(
        (int(i), GROUPS[g])
        for i, g in zip(*np.nonzero(mask & (res.redundancy < testing.min_redundancy)))
    )
    s2, r_g, n_g = _group_factors(res, sig, mask, lev_sigma * np.sqrt(factor[3]), lev_active)
    vcs = []
    for gi, gname in enumerate(GROUPS):
        if n_g[gi] == 0:
            continue
        if gi < 3:
            ap = float(np.median(base_sigma[:, gi]))
        else:
            ap = float(np.median(lev_sigma[lev_active]))
        vcs.append(
            VarianceComponent(
                gname,
                float(factor[gi]),
                float(np.sqrt(factor[gi])),
                float(r_g[gi]),
                int(n_g[gi]),
                bool(estimated[gi]) if testing.vce else False,
                ap,
                ap * float(np.sqrt(factor[gi])),
            )
        )
    msg = res.message + vce_note
    return TestedCalibration(
        calibration=res,
        options=testing,
        outliers=tuple(removals),
        variance_components=tuple(vcs),
        mask=mask,
        sigmas=sig,
        w=w,
        critical_value=float(crit),
        mdb=mdb,
        external=ext,
        external_ap=ext_ap,
        uncontrolled=unc,
        ap_tests=ap_t_tests(res, testing.ap_alpha),
        pinned_targets=tuple(net.targets[t] for t in pinned),
        history=tuple(history),
        n_adjustments=n_adj,
        message=msg,
    )


def _group_factors(res: CalibrationResult, sigmas, mask, lev_sigma, lev_active):
    """One VCE step: ``s_g^2 = sum e^2 / r_g`` per group with the current sigmas."""
    e2 = np.where(mask, (res.residuals / sigmas) ** 2, 0.0)
    r = np.where(mask, res.redundancy, 0.0)
    s2 = np.ones(4)
    r_g = np.zeros(4)
    n_g = np.zeros(4, dtype=int)
    for g in range(3):
        r_g[g] = r[:, g].sum()
        n_g[g] = int(mask[:, g].sum())
        s2[g] = e2[:, g].sum() / r_g[g] if r_g[g] > 0 else 1.0
    if lev_active.any():
        # Levelling residuals from the compensator readings of the final poses.
        import jax

        from .._model._levelling import compensator_reading

        read = np.asarray(jax.vmap(compensator_reading)(jnp.asarray(res.eops)))
        v = read - res.network.levelling
        e2l = np.where(lev_active, (v / np.where(lev_active, lev_sigma, 1.0)) ** 2, 0.0)
        r_g[3] = float(res.redundancy_levelling[lev_active].sum())
        n_g[3] = int(lev_active.sum())
        s2[3] = e2l.sum() / r_g[3] if r_g[3] > 0 else 1.0
    return s2, r_g, n_g


def _undetermined_targets(net: Network, res: CalibrationResult, mask, pinned: dict, step: int, w):
    """Remove (and report) the remaining observations of targets that the removals left
    without redundancy: observed in fewer than two scans or by fewer than four observations.
    Such a target would otherwise be determined exactly by its last observations (nothing to
    test) or not at all (a rank defect); it is held at its last estimate instead."""
    out = []
    active = mask.any(axis=1)
    for t in np.unique(net.target_index[~mask.all(axis=1)]):
        if int(t) in pinned:
            continue
        rows = np.flatnonzero(net.target_index == t)
        n_scans = len(np.unique(net.scan_index[rows[active[rows]]]))
        n_obs = int(mask[rows].sum())
        if n_scans >= 2 and n_obs >= 4:
            continue
        for i in rows:
            for c in range(3):
                if mask[i, c]:
                    val, unit = display_group(c, res.residuals[i, c])
                    out.append(
                        Removal(
                            step,
                            int(i),
                            net.scans[net.scan_index[i]],
                            net.targets[t],
                            GROUPS[c],
                            float(val),
                            unit,
                            float("nan"),
                            "target left without redundancy by the removals; held at its last estimate",
                        )
                    )
                    mask[i, c] = False
        pinned[int(t)] = res.target_xyz[t].copy()
    return out
