"""Statistical testing of a self-calibration (SPEC sections 5 and 7).

* Tests with the a priori sigmas, before anything is fitted to the residuals: the global test
  ``v^T P v ~ chi^2(r)`` and one test per observation group ``Omega_g = v_g^T P_g v_g ~
  chi^2(r_g)`` (the group variance-factor test JAG3D reports). A global test computed after
  the variance factors were fitted to the same residuals cannot fail (its sigma0 is 1 by
  construction), so it is never called "accepted".
* Gross-error screening before VCE (Koch 1999, sec. 3.8, robust scale): VCE fitted to data with
  blunders inflates the factors until the blunders look normal (a 1 m range error turns the
  range factor into ~5,000 and hides itself). Before VCE, each group's scale is estimated
  robustly, ``s_g = median |u_i| / 0.6745`` of ``u_i = v_i / (sigma_i sqrt(r_i))`` (a few
  blunders do not move a median), the largest ``|u_i| / s_g`` above the family-wise critical
  value ``N^-1(1 - alpha_s / (2 n))`` is removed and the network re-adjusted, until none is.
  The robust scale makes the screening work when the a priori sigmas are off by any factor.
* Variance component estimation (VCE) per observation group, range, horizontal direction,
  elevation angle and levelling (Förstner 1979; Koch 1999, section 3.6): with whitened
  residuals ``e = v / sigma`` and the redundancy numbers ``r_i = (Q_vv P)_ii``,

      s_g^2 = v_g^T P_g v_g / r_g,     r_g = sum of the group's redundancy numbers,

  the group's sigmas are multiplied by ``s_g`` and the adjustment is repeated until every
  ``s_g^2`` is 1 within tolerance (the fixed point). Safeguards (host side, numpy): the
  iteration runs in log space with a bounded step, halved where it changes sign (oscillation);
  a group with too little redundancy is held; residuals at rounding level (noise-free data)
  stop it; a factor beyond :data:`VCE_FACTOR_LIMIT` stops it. Every stop is a
  :class:`VCEResult` with its reason, never a NaN. Factors that say the a priori sigmas are far
  off are named, with the unit mix-up they suggest ((180/pi)^2: degrees vs radians, 1e6:
  millimetres vs metres, ...). Only the weights change, and they are traced arrays of the
  compiled adjustment, so re-weighting never recompiles.
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
import enum

import jax.numpy as jnp
import numpy as np

from .._adjustment._calibrate import analyze
from .._adjustment._config import CalibrationModel, SolverOptions
from .._adjustment._network import Network, check_calibration_arguments
from .._adjustment._result import CalibrationResult, assemble
from .._stats import non_centrality
from .._units import ARCSEC, display_group
from ._statistics import (
    ap_t_tests,
    critical_value,
    global_test,
    group_variance_test,
    implausible_factor,
    minimal_detectable_bias,
    w_tests,
)

GROUPS = ("range", "hz", "el", "levelling")
REMOVAL_UNITS = ("observation", "target")
#: Pseudo-observation sigma [m] that holds a target which lost all its testable observations
#: at its last estimate; it carries no information about anything else (see _pin_targets).
PIN_SIGMA = 1.0
#: Residual sigma of a group [m, rad, rad, rad] below which the residuals are rounding, not
#: measurement noise (noise-free data: about 1e-15 m and 1e-16 rad in a float64 adjustment;
#: the best scanners measure to 1e-4 m and 1e-6 rad).
ROUNDING_SIGMA = (1e-9, 1e-11, 1e-11, 1e-11)
#: Largest change of a variance factor in one VCE iteration (a factor 100 in sigma).
VCE_MAX_STEP = np.log(1e4)
#: Variance factors beyond this (either way; a factor 1e10 in sigma) stop VCE.
VCE_FACTOR_LIMIT = 1e20
#: Normal consistency constant of the median absolute value: median |N(0, 1)| = 0.6745.
MAD_TO_SIGMA = 1.482602218505602
#: Fewest testable observations of a group for a robust scale.
MIN_SCREENED = 10
#: Robust re-weighting steps that balance the groups before screening.
ROBUST_REWEIGHTING = 4


@dataclasses.dataclass(frozen=True)
class TestingOptions:
    """Settings of :func:`calibrate_and_test`.

    ``vce``: estimate one variance factor per group (point-based networks). ``vce_tolerance``:
    stop when every ``|s_g^2 - 1|`` is below it; ``vce_min_redundancy``: a group with a smaller
    redundancy keeps its a priori sigma (its estimate would be mostly noise).
    ``screening``: with ``vce``, remove gross errors before VCE (robust group scales,
    family-wise level ``screening_alpha``, Bonferroni over the tested observations: a clean
    network loses an observation with probability ``screening_alpha``); it stops when more than
    ``screening_max_share`` of the observations would go (then the model, not a few blunders,
    is wrong, and the run says so).
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
    ``ap_alpha``: significance level of the AP t-tests; ``test_alpha``: level of the global and
    group tests.
    """

    vce: bool = True
    vce_tolerance: float = 1e-3
    vce_max_iterations: int = 30
    vce_min_redundancy: float = 3.0
    screening: bool = True
    screening_alpha: float = 0.001
    screening_max_share: float = 0.05
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
    test_alpha: float = 0.05

    def __post_init__(self):
        if self.removal not in REMOVAL_UNITS:
            raise ValueError(f"removal must be one of {REMOVAL_UNITS}, got {self.removal!r}")
        for name in ("alpha", "screening_alpha", "test_alpha"):
            if not 0 < getattr(self, name) < 1:
                raise ValueError(f"{name} must be in (0, 1), got {getattr(self, name)}")
        if self.critical_value is not None and not self.critical_value > 0:
            raise ValueError(f"critical_value must be positive, got {self.critical_value}")
        if not self.vce_tolerance > 0:
            raise ValueError(f"vce_tolerance must be positive, got {self.vce_tolerance}")
        if self.vce_max_iterations < 1:
            raise ValueError(f"vce_max_iterations must be >= 1, got {self.vce_max_iterations}")
        if not self.vce_min_redundancy > 0:
            raise ValueError(f"vce_min_redundancy must be positive, got {self.vce_min_redundancy}")
        if not 0 < self.screening_max_share <= 1:
            raise ValueError(
                f"screening_max_share must be in (0, 1], got {self.screening_max_share}"
            )
        if self.max_removals < 0:
            raise ValueError(f"max_removals must be >= 0, got {self.max_removals}")
        if not 0 <= self.min_redundancy < 1:
            raise ValueError(f"min_redundancy must be in [0, 1), got {self.min_redundancy}")
        non_centrality(self.alpha0, self.power)
        critical_value(self.ap_alpha)


class VCEResult(enum.IntEnum):
    """How variance component estimation ended; ``VCEResult(c).message`` says what it means.
    ``ok``: the weights of the final adjustment are usable (estimated, or a priori with the
    reason); the others stopped VCE early, and the run reports why."""

    CONVERGED = 0
    OFF = 1
    NOISE_FREE = 2
    NO_REDUNDANCY = 3
    MAX_ITERATIONS = 4
    OSCILLATING = 5
    FACTOR_LIMIT = 6
    ADJUSTMENT_FAILED = 7
    NONFINITE = 8

    @property
    def message(self) -> str:
        return _VCE_MESSAGES[self]

    @property
    def ok(self) -> bool:
        return self in (
            VCEResult.CONVERGED,
            VCEResult.OFF,
            VCEResult.NOISE_FREE,
            VCEResult.NO_REDUNDANCY,
        )


_VCE_MESSAGES = {
    VCEResult.CONVERGED: "variance components converged",
    VCEResult.OFF: "variance components not estimated (a priori sigmas)",
    VCEResult.NOISE_FREE: "residuals at rounding level (noise-free data?): variance components "
    "cannot be estimated; a priori sigmas kept",
    VCEResult.NO_REDUNDANCY: "no group has enough redundancy for a variance component; a priori "
    "sigmas kept",
    VCEResult.MAX_ITERATIONS: "variance components did not converge within the maximum number "
    "of iterations",
    VCEResult.OSCILLATING: "variance components oscillate and did not converge",
    VCEResult.FACTOR_LIMIT: "a variance factor left the plausible range; VCE stopped",
    VCEResult.ADJUSTMENT_FAILED: "VCE stopped: an adjustment failed (see the result message and the "
    "warnings); the last weights whose adjustment succeeded are kept",
    VCEResult.NONFINITE: "a variance factor was not finite; VCE stopped at the last finite weights",
}


@dataclasses.dataclass(frozen=True)
class Removal:
    """One observation removed by screening or data snooping (or as a consequence of one).

    ``residual`` in mm (range) or arc seconds (angles) at the adjustment in which it was
    rejected; ``w`` its test statistic (the robust one in screening; NaN for consequential
    removals); ``reason`` says why.
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
    the a priori ones. ``redundancy`` is r_g, ``n`` the number of active observations;
    ``note`` says why a group was held or why its factor is implausible."""

    group: str
    factor: float
    sigma_factor: float
    redundancy: float
    n: int
    estimated: bool
    a_priori_sigma: float  # median a priori sigma of the group [m or rad]
    sigma: float  # median re-estimated sigma [m or rad]
    note: str = ""

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
    ``a_priori_tests``: the global test and the group tests with the a priori sigmas, for all
    observations and (when screening removed some) after screening: the honest tests of the
    stochastic model. ``vce_result`` (:class:`VCEResult`) says how VCE ended and
    ``vce_iterations`` counts its re-weighted adjustments; ``warnings``
    name implausible variance factors (with a suspected unit mix-up) and other findings.
    ``ok``: the adjustment succeeded and VCE ended in a usable state.
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
    a_priori_tests: tuple = ()
    vce_result: VCEResult = VCEResult.OFF
    vce_iterations: int = 0
    screening_critical_value: float | None = None
    warnings: tuple = ()

    @property
    def ok(self) -> bool:
        return bool(self.calibration.ok and self.vce_result.ok)

    @property
    def weights_fitted(self) -> bool:
        """True when the final weights were fitted to the residuals (a factor is not 1): then
        sigma0 of the final adjustment is no test of the a priori sigmas."""
        return any(vc.factor != 1.0 for vc in self.variance_components)

    def outliers_json(self) -> list:
        return [_finite_or_none(o.as_dict()) for o in self.outliers]

    def variance_components_json(self) -> dict:
        return {vc.group: _finite_or_none(vc.as_dict()) for vc in self.variance_components}

    def json_fields(self) -> dict:
        """The result-JSON contract's ``outliers`` and ``variance_components`` (SPEC section 11),
        plus the testing settings, the a priori tests and how VCE ended; NaN becomes null
        (strict JSON). With VCE, ``global_test`` is the a priori test (before VCE, after
        screening): the test after VCE is not a test and is reported as such."""
        out = {
            "outliers": self.outliers_json(),
            "variance_components": self.variance_components_json(),
            "vce": {
                "result": int(self.vce_result),
                "status": self.vce_result.name.lower(),
                "message": self.vce_result.message,
                "iterations": self.vce_iterations,
            },
            "a_priori_tests": list(self.a_priori_tests),
            "screening": {
                "enabled": bool(self.options.vce and self.options.screening),
                "critical_value": self.screening_critical_value,
                "family_alpha": self.options.screening_alpha,
                "n_removed": sum(o.reason.startswith("screening") for o in self.outliers),
            },
            "snooping": {
                "enabled": self.options.snooping,
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
            "warnings": list(self.warnings),
            "testing_message": self.message,
        }
        if self.a_priori_tests and self.weights_fitted:
            out["global_test"] = {**self.a_priori_tests[-1]["global"], "stage": "a priori"}
            out["global_test_after_vce"] = {
                "sigma0": _finite(self.calibration.sigma0),
                "note": "the variance factors were fitted to these residuals (sigma0 is 1 by "
                "construction once VCE converges): not a test",
            }
        return out

    def summary(self) -> str:
        c = self.calibration
        lines = [f"testing: {self.message}"]
        for stage in self.a_priori_tests:
            lines += _format_a_priori(stage)
        if self.options.vce:
            lines.append(f"variance components: {self.vce_result.message}")
        for vc in self.variance_components if self.a_priori_tests else ():
            unit, f = ("mm", 1e3) if vc.group == "range" else ('"', 1 / ARCSEC)
            held = "" if vc.estimated else f" (held{': ' + vc.note if vc.note else ''})"
            lines.append(
                f"  {vc.group:9s} factor {vc.factor:10.4g}  sigma {vc.a_priori_sigma * f:.4g} -> {vc.sigma * f:.4g} {unit}"
                f"  r_g = {vc.redundancy:.1f} of n = {vc.n}{held}"
            )
        if self.weights_fitted:
            lines.append(
                f"  sigma0 with the fitted variance factors = {c.sigma0:.4f}: not a test (1 by "
                "construction once VCE converges; the a priori tests are above)"
            )
        lines.append(
            f"  {len(self.outliers)} removed observation(s); snooping critical value "
            f"{self.critical_value:.2f}"
            + (
                f", screening critical value {self.screening_critical_value:.2f}"
                if self.screening_critical_value is not None
                else ""
            )
        )
        for o in self.outliers:
            lines.append(
                f"    step {o.step}: scan {o.scan} target {o.target} {o.group}: v = {o.residual:.4g} {o.unit}, "
                f"w = {o.w:.4g} ({o.reason})"
            )
        for w in self.warnings:
            lines.append(f"warning: {w}")
        if not self.ok:  # no t-tests of estimates that are not a calibration
            lines.append("  no AP t-tests: the run failed, its estimates are not a calibration")
        for t in self.ap_tests if self.ok else ():
            lines.append(f"  {t.describe()}")
        return "\n".join(lines)


def _format_a_priori(stage: dict) -> list:
    """Text lines of one stage of a priori tests (global and per group)."""

    def verdict(t):
        if t["accepted"] is None:
            return "not testable"
        return ("accepted" if t["accepted"] else "REJECTED") + f" (p = {t['p_value']:.3g})"

    g = stage["global"]
    lines = [f"a priori tests ({stage['stage']}):"]
    if g["statistic"] is not None:
        lines.append(
            f"  global: s0^2 = {g['statistic'] / g['dof']:.4g}, chi^2 = {g['statistic']:.1f} with r = {g['dof']:.0f}, "
            f"interval [{g['lower']:.1f}, {g['upper']:.1f}]: {verdict(g)}"
        )
    for name, t in stage["groups"].items():
        if t["factor"] is None:
            lines.append(f"  {name:9s} no redundancy: not testable")
            continue
        lines.append(f"  {name:9s} factor {t['factor']:10.4g} (r_g = {t['dof']:.1f}): {verdict(t)}")
    return lines


def _finite(x):
    x = float(x)
    return x if np.isfinite(x) else None


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
# One testing session: the weights, the mask and the adjustments of one network


class _Session:
    """The state of :func:`calibrate_and_test`: group variance factors, the mask of used
    observations, pinned targets, removals, and the latest adjustment."""

    def __init__(self, net: Network, model, options, testing: TestingOptions):
        self.net, self.t = net, testing
        self.rw = _Reweighter(net, model, options)
        n = net.observations.shape[0]
        self.base_sigma = np.asarray(net.sigmas, dtype=float)
        self.lev_sigma = np.asarray(net.levelling_sigma, dtype=float)
        self.lev_active = np.isfinite(self.lev_sigma)
        self.factor = np.ones(4)  # variance factors: range, hz, el, levelling
        self.estimated = np.zeros(4, dtype=bool)
        self.notes = [""] * 4
        self.mask = np.ones((n, 3), dtype=bool)
        self.pinned: dict = {}
        self.removals: list = []
        self.history: list = []
        self.warnings: list = []
        self.stages: list = []
        self.n_adj = 0
        self.step = 0
        self.params = None
        self.res = self.state = self.infl = None
        self.last_ok = None
        self.vce_result = VCEResult.CONVERGED if testing.vce else VCEResult.OFF
        self.vce_iterations = 0
        self.screen_crit = None

    def sigmas_now(self):
        return self.base_sigma * np.sqrt(self.factor[:3])[None, :]

    def lev_sigma_now(self):
        return self.lev_sigma * np.sqrt(self.factor[3])

    def adjust(self):
        w = np.where(self.mask, 1.0 / self.sigmas_now(), 0.0)
        lw = np.where(self.lev_active, 1.0 / self.lev_sigma_now(), 0.0)
        self.res, self.state, self.infl = self.rw.run(w, lw, self.pinned, self.params)
        self.n_adj += 1
        if self.res.ok:
            # Warm start the next adjustment; the datum (inner constraints) stays the same
            # because the S-transformation is applied to every update.
            self.params = self.state.params
            self.last_ok = (self.res, self.state, self.infl, self.factor.copy())

    def restore_last_ok(self):
        """Back to the last successful adjustment and its variance factors (no re-run: the
        same weights need not converge again from another start)."""
        self.res, self.state, self.infl, self.factor = self.last_ok

    def group_factors(self):
        return _group_factors(
            self.res, self.sigmas_now(), self.mask, self.lev_sigma_now(), self.lev_active
        )

    def record_a_priori(self, stage: str):
        """Global and group tests at the current adjustment (a priori weights)."""
        s2, r_g, n_g = self.group_factors()
        groups = {
            g: group_variance_test(float(s2[i] * r_g[i]), float(r_g[i]), self.t.test_alpha)
            for i, g in enumerate(GROUPS)
            if n_g[i] > 0
        }
        self.stages.append(
            {
                "stage": stage,
                "global": global_test(self.res.sigma0, self.res.dof, self.t.test_alpha),
                "groups": groups,
            }
        )

    def remove(self, i: int, g: int, w, reason: str):
        """Weight 0 for observation (i, g) (or the target's three with removal="target")."""
        self.step += 1
        cols = (0, 1, 2) if self.t.removal == "target" else (g,)
        for c in cols:
            if self.mask[i, c]:
                val, unit = display_group(c, self.res.residuals[i, c])
                why = reason if c == g else "same target observation as the rejected one"
                self.removals.append(
                    Removal(
                        self.step,
                        int(i),
                        self.net.scans[self.net.scan_index[i]],
                        self.net.targets[self.net.target_index[i]],
                        GROUPS[c],
                        float(val),
                        unit,
                        float(w[i, c]),
                        why,
                    )
                )
                self.mask[i, c] = False
        self.removals.extend(
            _undetermined_targets(self.net, self.res, self.mask, self.pinned, self.step, w)
        )

    def rounding_groups(self, s2) -> list:
        """Groups whose residual sigma ``sqrt(factor s_g^2) * median sigma`` is rounding."""
        out = []
        for g in range(4):
            sig = self.base_sigma[:, g] if g < 3 else self.lev_sigma[self.lev_active]
            if sig.size and np.isfinite(s2[g]) and s2[g] >= 0:
                if np.sqrt(self.factor[g] * s2[g]) * np.median(sig) < ROUNDING_SIGMA[g]:
                    out.append(GROUPS[g])
        return out


def _robust_scales(s: _Session):
    """Standardised residuals ``u = v / (sigma sqrt(r))`` at the current weights and each
    group's robust scale ``median |u| / 0.6745`` (NaN for a group with too few testable
    observations)."""
    u = np.where(s.mask, w_tests(s.res.residuals, s.sigmas_now(), s.res.redundancy), np.nan)
    scale = np.full(3, np.nan)
    for g in range(3):
        keep = np.isfinite(u[:, g]) & (s.res.redundancy[:, g] >= s.t.min_redundancy)
        if keep.sum() >= MIN_SCREENED:
            scale[g] = MAD_TO_SIGMA * np.median(np.abs(u[keep, g]))
    return u, scale


def _balance_groups(s: _Session) -> bool:
    """Robust re-weighting before screening: a priori sigmas far off between the groups (e.g.
    ranges in mm read as m) distort the residuals of the others; each group's factor is set to
    its robust scale squared (bounded steps) until they agree within 10 %. False when the
    residuals are at rounding level (nothing to screen)."""
    for _ in range(ROBUST_REWEIGHTING):
        _, scale = _robust_scales(s)
        if s.rounding_groups(np.append(scale**2, np.nan)):
            return False
        ok = np.isfinite(scale) & (scale > 0)
        step = np.where(
            ok, np.clip(2 * np.log(np.where(ok, scale, 1.0)), -VCE_MAX_STEP, VCE_MAX_STEP), 0.0
        )
        if np.all(np.abs(step) < np.log(1.1)):
            return True
        # Levelling (a few readings, no robust scale of its own) moves with the others.
        step = np.append(step, step[ok].mean() if ok.any() else 0.0)
        limit = np.log(VCE_FACTOR_LIMIT)
        s.factor = np.exp(np.clip(np.log(s.factor) + step, -limit, limit))
        s.adjust()
        if not s.res.ok:
            s.restore_last_ok()
            return True
    return True


def _screen(s: _Session) -> None:
    """Gross-error screening before VCE (module docstring): robust group scales, family-wise
    critical value, largest first, re-adjusting after each removal."""
    t = s.t
    limit = max(1, int(t.screening_max_share * s.mask.sum()))
    removed = 0
    if not _balance_groups(s):
        return  # noise-free: nothing to screen; VCE says so
    while True:
        u, scale = _robust_scales(s)
        with np.errstate(invalid="ignore", divide="ignore"):
            w = u / np.where(scale > 0, scale, np.nan)[None, :]
        n_tested = int(np.isfinite(w).sum())
        if n_tested == 0:
            return
        s.screen_crit = critical_value(t.screening_alpha / n_tested)
        aw = np.where(np.isfinite(w), np.abs(w), -1.0)
        i, g = np.unravel_index(int(np.argmax(aw)), aw.shape)
        if aw[i, g] <= s.screen_crit:
            return
        if removed >= limit or len(s.removals) >= t.max_removals:
            s.warnings.append(
                f"screening stopped after {removed} removal(s) with |w| = {aw[i, g]:.1f} still above "
                f"{s.screen_crit:.2f}: more than {100 * t.screening_max_share:.0f}% of the observations "
                "fail; the functional model (APs, architecture) or the sigmas are wrong, not a few blunders"
            )
            return
        s.remove(i, g, w, "screening before VCE: robust |w| above the family-wise critical value")
        removed += 1
        s.adjust()
        if not s.res.ok:
            return


def _a_priori_after_screening(s: _Session) -> None:
    """The a priori tests again, on the screened observations (a priori weights)."""
    fitted = s.factor.copy()
    s.factor = np.ones(4)
    s.adjust()
    if s.res.ok:
        s.record_a_priori("after screening")
    s.factor = fitted
    s.adjust()


def _vce(s: _Session) -> None:
    """Variance component estimation with safeguards (module docstring); sets
    ``s.vce_result``. Every stop leaves the session at weights whose adjustment succeeded."""
    t = s.t
    prev_step = np.zeros(4)
    relax = np.ones(4)  # halved at every change of direction of a group's step
    flips = 0
    for it in range(t.vce_max_iterations):
        s2, r_g, n_g = s.group_factors()
        est = (r_g >= t.vce_min_redundancy) & (n_g > 0)
        s.estimated = est
        s.notes = [
            f"redundancy r_g = {r_g[g]:.2f} < {t.vce_min_redundancy:g}"
            if n_g[g] and not est[g]
            else ""
            for g in range(4)
        ]
        s.history.append(
            {
                "step": s.step,
                "vce_iteration": it,
                "sigma0": s.res.sigma0,
                "factors": s.factor.tolist(),
                "s2": s2.tolist(),
            }
        )
        if not est.any():
            return _stop(s, VCEResult.NO_REDUNDANCY)
        noise_free = s.rounding_groups(np.where(est, s2, np.nan))
        if noise_free:
            s.warnings.append(
                f"residuals of {', '.join(noise_free)} at rounding level: noise-free data?"
            )
            return _stop(s, VCEResult.NOISE_FREE, reset=True)
        if not np.all(np.isfinite(s2[est]) & (s2[est] > 0)):
            return _stop(s, VCEResult.NONFINITE)
        if np.all(np.abs(s2[est] - 1.0) < t.vce_tolerance):
            s.vce_result = VCEResult.CONVERGED
            return None
        step = np.where(
            est, np.clip(np.log(np.where(est, s2, 1.0)), -VCE_MAX_STEP, VCE_MAX_STEP), 0.0
        )
        flip = step * prev_step < 0
        relax = np.where(flip, 0.5 * relax, relax)  # damp an oscillation geometrically
        step = relax * step
        flips += int(flip.any())
        new = np.log(s.factor) + step
        if np.any(np.abs(new) > np.log(VCE_FACTOR_LIMIT)):
            g = int(np.argmax(np.abs(new)))
            s.warnings.append(
                f"{GROUPS[g]}: the variance factor would pass {np.exp(new[g]):.3g}, beyond "
                f"{VCE_FACTOR_LIMIT:.0e} either way: the a priori sigmas are not plausible"
            )
            return _stop(s, VCEResult.FACTOR_LIMIT)
        s.factor = np.exp(new)
        s.adjust()
        s.vce_iterations += 1
        if not s.res.ok:
            s.warnings.append(
                f"VCE stopped: with the re-estimated weights (variance factors "
                f"{', '.join(f'{GROUPS[g]} {s.factor[g]:.4g}' for g in range(4) if est[g])}) the "
                f"adjustment failed: {s.res.message}; the last weights whose adjustment succeeded are kept"
            )
            s.restore_last_ok()
            return _stop(s, VCEResult.ADJUSTMENT_FAILED)
        prev_step = step
    return _stop(s, VCEResult.OSCILLATING if flips >= 3 else VCEResult.MAX_ITERATIONS)


def _stop(s: _Session, result: VCEResult, reset: bool = False) -> None:
    """End VCE with ``result``; ``reset``: back to the a priori weights (re-adjusted)."""
    s.vce_result = result
    if reset and np.any(s.factor != 1.0):
        s.factor = np.ones(4)
        s.adjust()
    if reset:
        s.estimated = np.zeros(4, dtype=bool)
        s.notes = [result.message.split(":")[0]] * 4


def _snoop_once(s: _Session) -> bool:
    """One step of data snooping; True when an observation was removed."""
    t = s.t
    w = np.where(s.mask, w_tests(s.res.residuals, s.sigmas_now(), s.res.redundancy), np.nan)
    n_tested = int(np.isfinite(w).sum())
    s.crit = _snooping_critical_value(t, n_tested)
    s.history.append(
        {
            "step": s.step,
            "sigma0": s.res.sigma0,
            "max_abs_w": float(np.nanmax(np.abs(w))) if n_tested else None,
            "critical": s.crit,
            "factors": s.factor.tolist(),
        }
    )
    if not t.snooping or n_tested == 0:
        return False
    aw = np.where(np.isfinite(w), np.abs(w), -1.0)
    i, g = np.unravel_index(int(np.argmax(aw)), aw.shape)
    if aw[i, g] <= s.crit:
        return False
    if len(s.removals) >= t.max_removals:
        s.warnings.append(
            f"snooping stopped after max_removals = {t.max_removals} with |w| = {aw[i, g]:.2f} "
            f"still above {s.crit:.2f}"
        )
        return False
    s.remove(i, g, w, "largest |w| above critical value")
    return True


def _snooping_critical_value(t: TestingOptions, n_tested: int) -> float:
    if t.critical_value is not None:
        return float(t.critical_value)
    return critical_value(t.alpha / max(n_tested, 1) if t.bonferroni else t.alpha)


# ----------------------------------------------------------------------------------------
# The entry point


def calibrate_and_test(
    network: Network,
    model: CalibrationModel | None = None,
    options: SolverOptions | None = None,
    testing: TestingOptions | None = None,
) -> TestedCalibration:
    """Self-calibration with a priori tests, gross-error screening, variance component
    estimation, Baarda data snooping, reliability and AP t-tests (SPEC sections 5 and 7).

    Order: adjust with the a priori sigmas and test them (global test and one test per
    group); with ``testing.vce`` screen out gross errors (robust group scales, family-wise
    level) and then re-estimate the group variance factors ``s_g^2 = v_g^T P_g v_g / r_g``
    (Förstner 1979) until all are 1 within ``vce_tolerance``, or until a safeguard stops it
    with a :class:`VCEResult` and its reason; with ``testing.snooping`` compute
    ``w_i = v_i / (sigma_i sqrt(r_i))`` (Baarda 1968), give the largest ``|w_i|`` above the
    critical value weight 0 (or, with ``removal="target"``, the target's three observations in
    that scan), re-estimate the variance components and repeat. A target left with observations
    in fewer than two scans (or fewer than four observations) can no longer be checked: its
    remaining observations are removed too, it is held at its last estimate by a weak
    pseudo-observation (no rank defect, no effect on the rest), and this is reported. Weights
    are traced arrays of the compiled adjustment: nothing recompiles.
    """
    check_calibration_arguments(network, model, options, "calibrate_and_test")
    if testing is not None and not isinstance(testing, TestingOptions):
        raise TypeError(
            f"calibrate_and_test: testing must be a TestingOptions or None, got {type(testing).__name__}"
        )
    model = model or CalibrationModel()
    options = options or SolverOptions(full_covariance=False)
    testing = testing or TestingOptions()
    if network.has_planes:
        raise ValueError(
            f"{network.source}: variance components and data snooping are for target networks; with "
            "planes the weights are held fixed (SPEC section 5); screen plane points for outliers "
            "with tlsjax.screen_planes(network, model)"
        )
    s = _Session(network, model, options, testing)
    s.crit = _snooping_critical_value(testing, int(network.observations.size))
    s.adjust()
    if s.res.ok:
        s.record_a_priori("all observations")
        if testing.vce and testing.screening:
            n_before = len(s.removals)
            _screen(s)
            if len(s.removals) > n_before and s.res.ok:
                _a_priori_after_screening(s)
    elif np.isfinite(s.res.sigma0):
        hint = implausible_factor("all groups", s.res.sigma0**2)
        if hint:
            s.warnings.append(f"at the failed first adjustment: {hint}")
    while s.res.ok:
        if testing.vce and s.vce_result == VCEResult.CONVERGED:
            _vce(s)
        if not s.res.ok or not _snoop_once(s):
            break
        s.adjust()
    if testing.vce and not s.res.ok and s.vce_result == VCEResult.CONVERGED:
        s.vce_result = VCEResult.ADJUSTMENT_FAILED
    return _finish(s)


def _finish(s: _Session) -> TestedCalibration:
    """Final quantities at the last adjustment: w-tests, reliability, variance components,
    warnings and the message."""
    t, res, net, mask = s.t, s.res, s.net, s.mask
    delta0 = non_centrality(t.alpha0, t.power)
    sig = s.sigmas_now()
    w = np.where(mask, w_tests(res.residuals, sig, res.redundancy), np.nan)
    mdb = np.where(mask, minimal_detectable_bias(sig, res.redundancy, delta0), np.nan)
    ext, ext_ap = _external_reliability(s, delta0)
    unc = tuple(
        (int(i), GROUPS[g]) for i, g in zip(*np.nonzero(mask & (res.redundancy < t.min_redundancy)))
    )
    vcs = _variance_components(s)
    _factor_warnings(s, vcs)
    parts = [res.message]
    if t.vce:
        parts.append(s.vce_result.message)
    if s.removals:
        parts.append(f"{len(s.removals)} observation(s) removed")
    if s.warnings:
        parts.append(f"{len(s.warnings)} warning(s)")
    return TestedCalibration(
        calibration=res,
        options=t,
        outliers=tuple(s.removals),
        variance_components=tuple(vcs),
        mask=mask,
        sigmas=sig,
        w=w,
        critical_value=float(s.crit),
        mdb=mdb,
        external=ext,
        external_ap=ext_ap,
        uncontrolled=unc,
        ap_tests=ap_t_tests(res, t.ap_alpha),
        pinned_targets=tuple(net.targets[i] for i in s.pinned),
        history=tuple(s.history),
        n_adjustments=s.n_adj,
        message="; ".join(parts),
        a_priori_tests=tuple(s.stages),
        vce_result=s.vce_result,
        vce_iterations=s.vce_iterations,
        screening_critical_value=s.screen_crit,
        warnings=tuple(s.warnings),
    )


def _external_reliability(s: _Session, delta0: float):
    """Largest AP change (in AP sigmas) caused by an MDB-sized error, and which AP."""
    res, mask, infl = s.res, s.mask, s.infl
    n = mask.shape[0]
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(
            res.redundancy > 0,
            delta0 / np.sqrt(np.where(res.redundancy > 0, res.redundancy, 1.0)),
            np.inf,
        )
    if not infl.shape[-1]:
        return np.zeros((n, 3)), np.full((n, 3), "", dtype=object)
    ext_all = np.abs(infl) * np.where(np.isfinite(scale), scale, 0.0)[..., None]
    ext = np.where(mask & np.isfinite(scale), ext_all.max(axis=-1), np.where(mask, np.inf, np.nan))
    ext_ap = np.array(res.ap_names, dtype=object)[ext_all.argmax(axis=-1)]
    return ext, ext_ap


def _variance_components(s: _Session) -> list:
    """One :class:`VarianceComponent` per group with observations, at the final weights."""
    s2, r_g, n_g = s.group_factors()
    out = []
    for gi, gname in enumerate(GROUPS):
        if n_g[gi] == 0:
            continue
        base = s.base_sigma[:, gi] if gi < 3 else s.lev_sigma[s.lev_active]
        ap = float(np.median(base))
        f = float(s.factor[gi])
        out.append(
            VarianceComponent(
                gname,
                f,
                float(np.sqrt(f)),
                float(r_g[gi]),
                int(n_g[gi]),
                bool(s.estimated[gi]) if s.t.vce else False,
                ap,
                ap * float(np.sqrt(f)),
                s.notes[gi] if s.t.vce else "",
            )
        )
    return out


def _factor_warnings(s: _Session, vcs) -> None:
    """Name implausible variance factors: the estimated ones, or (without VCE, or where a group
    was held) the a priori group factors of the last a priori test."""
    groups = s.stages[-1]["groups"] if s.stages else {}
    for vc in vcs:
        if vc.estimated:
            text = implausible_factor(vc.group, vc.factor)
        elif vc.group in groups and groups[vc.group]["factor"] is not None:
            text = implausible_factor(vc.group + " (a priori)", groups[vc.group]["factor"])
        else:
            text = None
        if text and s.vce_result != VCEResult.NOISE_FREE:
            s.warnings.append(text)


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
