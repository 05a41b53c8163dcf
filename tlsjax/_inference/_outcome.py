"""What the pipeline of :func:`tlsjax.self_calibrate` finds (SPEC sections 5 and 7):
:class:`VCEResult` (how variance component estimation ended, with its message),
:class:`Removal`, :class:`VarianceComponent` and :class:`TestedCalibration`, the outcome that
the public :class:`tlsjax.SelfCalibration` extends with its text and JSON.

The settings are in :mod:`._options`, the statistics in :mod:`tlsjax._stats` and
:mod:`tlsjax._adjustment._quality`, the steps that
produce these in :mod:`._steps`.
"""

from __future__ import annotations

import dataclasses
import enum

import numpy as np

from .._adjustment._config import CalibrationModel
from .._adjustment._result import CalibrationResult
from .._summary import to_json_value
from .._units import ARCSEC
from ._options import CalibrationOptions

#: Variance groups (VCE, group tests): the three components of the target observations, then
#: the weighted constraints with observed values (eq. 7 of Chow et al. 2013, SPEC section 6):
#: tilt readings, observed headings (kappa) and AP priors, each its own group.
GROUPS = ("range", "hz", "el", "levelling", "heading", "ap_prior")


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


@dataclasses.dataclass(frozen=True, eq=False)
class TestedCalibration:
    """What the pipeline of :func:`tlsjax.self_calibrate` found (the fields of
    :class:`tlsjax.SelfCalibration`). Arrays are in network row order, (n, 3).

    ``calibration``: the final adjustment (removed observations have weight 0, residual
    reported, redundancy 0); ``model``: its model (after selection: the chosen APs);
    ``options``: the settings of the run. ``mask``: True where an observation is used.
    ``sigmas``: the sigmas of the final adjustment (a priori times the VCE factor). ``w``:
    w-test statistics (NaN where removed or untestable); ``mdb``: minimal detectable bias [m,
    rad]; ``external``: largest AP change caused by an MDB-sized error, in AP sigmas, with
    ``external_ap`` naming that AP; ``uncontrolled``: (row, group) pairs with redundancy below
    ``tests.min_redundancy``. ``history``: one line per adjustment (sigma0, factors,
    removals). ``a_priori_tests``: the global test and the group tests with the a priori
    sigmas, for all observations and after screening and selection where they changed the
    observations or the model: the honest tests of the stochastic model. ``vce_result``
    (:class:`VCEResult`) says how VCE ended and ``vce_iterations`` counts its re-weighted
    adjustments; ``warnings`` name implausible variance factors (with a suspected unit
    mix-up) and other findings. ``selection`` (:class:`tlsjax.SelectionResult`),
    ``plane_screening`` (:class:`tlsjax.PlaneScreening`) and ``score_tests``
    (:class:`tlsjax.ScoreTests`): what those steps found (None where they did not run).

    With planes (None without), per plane point in the network's plane row order: ``plane_mask``
    (m,) True where used, ``plane_w`` (m,) the w-test of its condition, ``plane_mdb`` (m, 3) the
    minimal detectable bias of each of its observations [m, rad], ``plane_external`` (m,) and
    ``plane_external_ap`` as ``external``; points removed by screening or snooping are in
    ``outliers`` with group ``plane`` (``target`` names the plane, ``row`` the plane row), and
    the residuals of every removed point in ``calibration.plane_residuals`` are those at the
    final unknowns (not 0).
    """

    calibration: CalibrationResult
    model: CalibrationModel
    options: CalibrationOptions
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
    score_tests: object = None  # ._score.ScoreTests, or None (off, failed or planes)
    selection: object = None  # ._selection.SelectionResult, or None (no selection)
    plane_screening: object = None  # ._robust.PlaneScreening, or None (no IGG-III)

    @property
    def weights_fitted(self) -> bool:
        """True when the final weights were fitted to the residuals (a factor is not 1): then
        sigma0 of the final adjustment is no test of the a priori sigmas."""
        return any(vc.factor != 1.0 for vc in self.variance_components)

    def testing_fields(self) -> dict:
        """The result JSON's ``outliers`` and ``variance_components`` (SPEC section 11), how
        screening, VCE and snooping went, the a priori tests, the AP t-tests, the warnings, and
        what the selection, the plane screening and the score tests found; NaN becomes null
        (strict JSON). With VCE, ``global_test`` is the a priori test (before VCE, after
        screening): the test after VCE is not a test and is reported as such."""
        o = self.options
        screening, snooping = o.screening, o.snooping
        out = {
            "outliers": [to_json_value(dataclasses.asdict(r)) for r in self.outliers],
            "variance_components": {
                vc.group: to_json_value(dataclasses.asdict(vc)) for vc in self.variance_components
            },
            "vce": {
                "result": int(self.vce_result),
                "status": self.vce_result.name.lower(),
                "message": self.vce_result.message,
                "iterations": self.vce_iterations,
            },
            "a_priori_tests": list(self.a_priori_tests),
            "screening": {
                "enabled": screening is not None,
                "robust_start": screening is not None and screening.robust_start,
                "n_removed_robust_start": sum(
                    r.reason.startswith("robust start") for r in self.outliers
                ),
                "critical_value": self.screening_critical_value,
                "family_level": None if screening is None else screening.family_level,
                "n_removed": sum(r.reason.startswith("screening") for r in self.outliers),
            },
            "snooping": {
                "enabled": snooping is not None,
                "critical_value": self.critical_value,
                "removal": o.removal,
                "w_test_level": o.w_test_level,
                "bonferroni": snooping is not None and snooping.bonferroni,
                "n_removed": len(self.outliers),
                "pinned_targets": list(self.pinned_targets),
                "n_uncontrolled": len(self.uncontrolled),
                "n_adjustments": self.n_adjustments,
            },
            "ap_tests": [to_json_value(dataclasses.asdict(t)) for t in self.ap_tests],
            "warnings": list(self.warnings),
            "testing_message": self.message,
        }
        for name in ("selection", "plane_screening", "score_tests"):
            if getattr(self, name) is not None:
                out[name] = getattr(self, name).to_dict()
        if self.a_priori_tests and self.weights_fitted:
            out["global_test"] = {**self.a_priori_tests[-1]["global"], "stage": "a priori"}
            out["global_test_after_vce"] = {
                "sigma0": to_json_value(float(self.calibration.sigma0)),
                "note": "the variance factors were fitted to these residuals (sigma0 is 1 by "
                "construction once VCE converges): not a test",
            }
        return to_json_value(out)

    def testing_summary(self) -> str:
        """The text of what the steps found: the selection, the plane screening, the a priori
        tests, the variance components, the removals, the warnings, the score tests and the AP
        t-tests."""
        c = self.calibration
        lines = []
        if self.selection is not None:
            lines += [self.selection.summary(), ""]
        if self.plane_screening is not None:
            lines.append(self.plane_screening.summary())
        lines.append(f"testing: {self.message}")
        for stage in self.a_priori_tests:
            lines += _format_a_priori(stage)
        if self.options.vce is not None:
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
            lines.append(
                f"    step {o.step}: scan {o.scan} {what} {o.group}: v = {o.residual:.4g} {o.unit}, "
                f"w = {o.w:.4g} ({o.reason})"
            )
        for w in self.warnings:
            lines.append(f"warning: {w}")
        if self.score_tests is not None:
            lines.append(self.score_tests.summary())
        usable = self.calibration.ok and self.vce_result.ok
        if not usable:  # no t-tests of estimates that are not a calibration
            lines.append("  no AP t-tests: the run failed, its estimates are not a calibration")
        for t in self.ap_tests if usable else ():
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
