"""The settings and the result of :func:`tlsjax.calibrate_and_test` (SPEC sections 5 and 7):
:class:`TestingOptions`, :class:`VCEResult` (how variance component estimation ended, with its
message), :class:`Removal`, :class:`VarianceComponent` and :class:`TestedCalibration`.

The statistics are in :mod:`._statistics`, the steps that produce these in :mod:`._steps`.
"""

from __future__ import annotations

import dataclasses
import enum

import numpy as np

from .._adjustment._result import CalibrationResult
from .._stats import ALPHA0, POWER, non_centrality
from .._units import ARCSEC
from ._statistics import critical_value

#: Variance-component groups: the three observation groups and the levelling readings.
#: Variance groups (VCE, group tests): the three components of the target observations, then
#: the weighted constraints with observed values (eq. 7 of Chow et al. 2013, SPEC section 6):
#: tilt readings, observed headings (kappa) and AP priors, each its own group.
GROUPS = ("range", "hz", "el", "levelling", "heading", "ap_prior")
#: What one rejection removes: one scalar observation, or the target's three in that scan.
REMOVAL_UNITS = ("observation", "target")


@dataclasses.dataclass(frozen=True)
class TestingOptions:
    """Settings of :func:`calibrate_and_test`.

    ``vce``: estimate one variance factor per group (point-based networks). ``vce_tolerance``:
    stop when every ``|s_g^2 - 1|`` is below it; ``vce_min_redundancy``: a group with a smaller
    redundancy keeps its a priori sigma (its estimate would be mostly noise).
    ``robust_start``: before the least-squares steps, iteratively reweighted adjustments with a
    redescending weight (:func:`tlsjax._inference._steps.robust_start`) find and remove gross
    errors (metres, swapped names, a target in the wrong scan) that a first least-squares
    adjustment would spread over correct observations; on whenever ``screening`` is.
    ``screening``: remove gross errors before VCE and snooping, for any weighting (robust group scales,
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
    group tests. ``score_tests``: after the last adjustment, the score test of every candidate
    term not in the model (``candidates``, default every registered term of the model's naming;
    :mod:`._score`), family-wise level ``score_alpha``; screening compares them with the
    largest w-test (SPEC section 7) so that a systematic misfit is named, not removed.
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
    alpha0: float = ALPHA0
    power: float = POWER
    min_redundancy: float = 0.1
    ap_alpha: float = 0.05
    test_alpha: float = 0.05
    robust_start: bool = True
    score_tests: bool = True
    score_alpha: float = 0.05
    candidates: tuple | None = None

    def __post_init__(self):
        if self.removal not in REMOVAL_UNITS:
            raise ValueError(f"removal must be one of {REMOVAL_UNITS}, got {self.removal!r}")
        for name in ("alpha", "screening_alpha", "test_alpha", "score_alpha"):
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

    With planes (None without), per plane point in the network's plane row order: ``plane_mask``
    (m,) True where used, ``plane_w`` (m,) the w-test of its condition, ``plane_mdb`` (m, 3) the
    minimal detectable bias of each of its observations [m, rad], ``plane_external`` (m,) and
    ``plane_external_ap`` as ``external``; removed points are in ``outliers`` with group
    ``plane`` (``target`` names the plane, ``row`` the plane row) and their residuals in
    ``calibration.plane_residuals`` are those at the final unknowns (not 0).
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
    plane_mask: np.ndarray | None = None
    plane_w: np.ndarray | None = None
    plane_mdb: np.ndarray | None = None
    plane_external: np.ndarray | None = None
    plane_external_ap: np.ndarray | None = None
    score_tests: object = None  # ._score.ScoreTests, or None (off, failed or several scanners)

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
                "enabled": bool(self.options.screening),
                "robust_start": bool(self.options.screening and self.options.robust_start),
                "n_removed_robust_start": sum(
                    o.reason.startswith("robust start") for o in self.outliers
                ),
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
        if self.score_tests is not None:
            out["score_tests"] = self.score_tests.as_json()
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
            unit, f = {"range": ("mm", 1e3), "ap_prior": ("SI", 1.0)}.get(
                vc.group, ('"', 1 / ARCSEC)
            )
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
            what = f"plane {o.target} point {o.row}" if o.group == "plane" else f"target {o.target}"
            # A target left without redundancy has no test statistic: never printed as nan.
            w = f"w = {o.w:.4g}" if np.isfinite(o.w) else "no w-test"
            lines.append(
                f"    step {o.step}: scan {o.scan} {what} {o.group}: v = {o.residual:.4g} {o.unit}, "
                f"{w} ({o.reason})"
            )
        for w in self.warnings:
            lines.append(f"warning: {w}")
        if self.score_tests is not None:
            lines.append(self.score_tests.summary())
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
