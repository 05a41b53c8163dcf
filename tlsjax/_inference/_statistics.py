"""Tests, reliability and variance components of an adjustment (SPEC sections 5 and 7): pure
functions, host side, on the arrays of its results. The pipeline of :func:`tlsjax.self_calibrate`
(:mod:`._steps`) decides when to call them; nothing here holds state.

* Global test: ``T = v^T P v = s0^2 r ~ chi^2(r)`` when the a priori stochastic model is right
  (Koch 1999, sec. 4.2.2); the same test per observation group, ``Omega_g = v_g^T P_g v_g ~
  chi^2(r_g)`` (the group variance-factor test JAG3D reports).
* Baarda (1968) w-test ``w_i = v_i / (sigma_i sqrt(r_i))`` and its critical value; the robust
  scale of a group's w's, ``median |w| / 0.6745`` (Koch 1999, sec. 3.8), for screening.
* Reliability (Baarda 1968; Förstner 1987): the internal one, ``MDB_i = delta0 sigma_i /
  sqrt(r_i)`` (:func:`tlsjax._adjustment._quality.minimal_detectable_bias`), and the external
  one, the change of each AP caused by an MDB-sized error, ``delta0 / sqrt(r_i)`` times the AP
  influence of :mod:`tlsjax._adjustment._quality`, in AP sigmas.
* Variance components (Förstner 1979; Koch 1999, sec. 3.6): ``s_g^2 = v_g^T P_g v_g / r_g``,
  ``r_g`` the sum of the group's redundancy numbers, and the bounded step in log space that VCE
  takes towards it.
* t-tests of the APs: ``t = x_a / s_a`` against Student's t with the adjustment's dof.
* Implausible variance factors named with the unit mix-up they suggest.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .._adjustment._quality import MIN_TESTABLE_REDUNDANCY
from .._stats import MAD_TO_SIGMA, chi2_cdf, chi2_quantile, normal_critical_value, t_critical_value


def critical_value(alpha: float) -> float:
    """Two-sided standard-normal critical value ``N^-1(1 - alpha/2)`` (3.29 for alpha = 0.001)."""
    return normal_critical_value(alpha)


def snooping_critical_value(
    alpha: float, n_tested: int, *, bonferroni: bool = False, given: float | None = None
) -> float:
    """Critical value of data snooping: ``given`` if set, else ``N^-1(1 - alpha'/2)`` with
    ``alpha' = alpha / n_tested`` (Bonferroni: the family-wise level over the tested
    observations) or ``alpha`` per test."""
    if given is not None:
        return float(given)
    return critical_value(alpha / max(n_tested, 1) if bonferroni else alpha)


def global_test(sigma0: float, dof: float, alpha: float = 0.05) -> dict:
    """Global test of the adjustment: ``T = v^T P v = s0^2 r ~ chi^2(r)`` when the a priori
    stochastic model is right (Koch 1999, sec. 4.2.2). Two-sided: the model is accepted when
    ``chi^2_{alpha/2}(r) <= T <= chi^2_{1-alpha/2}(r)``; the p-value is two-sided too."""
    if not (dof > 0 and np.isfinite(sigma0)):
        return {
            "statistic": None,
            "dof": dof,
            "alpha": alpha,
            "lower": None,
            "upper": None,
            "p_value": None,
            "accepted": None,
        }
    T = sigma0**2 * dof
    lo, hi = chi2_quantile(alpha / 2, dof), chi2_quantile(1 - alpha / 2, dof)
    cdf = chi2_cdf(T, dof)
    return {
        "statistic": T,
        "dof": dof,
        "alpha": alpha,
        "lower": lo,
        "upper": hi,
        "p_value": 2 * min(cdf, 1 - cdf),
        "accepted": bool(lo <= T <= hi),
    }


@dataclasses.dataclass(frozen=True)
class APTest:
    """The t-test of one AP. ``note`` says why there is no verdict (not estimable, held fixed,
    weakly determined: a t of an AP with |corr| near 1 is not interpretable, undefined t);
    then ``significant`` is False and the text never shows a number where none is defined."""

    name: str
    value: float
    sigma: float
    unit: str
    t: float
    critical: float
    significant: bool
    max_abs_corr: float
    max_corr_with: str
    note: str = ""

    def describe(self) -> str:
        """One line: ``B6: t = 12.30 (significant at |t| > 1.96)`` or the reason for none."""
        if self.note:
            return f"{self.name}: {self.note}"
        verdict = "significant" if self.significant else "not significant"
        return f"{self.name}: t = {self.t:.2f} ({verdict} at |t| > {self.critical:.2f})"


def _no_verdict(result, i: int, name: str) -> str:
    """Why AP ``i`` has no t-test verdict, or "" when it has one."""
    for n, _, reason in result.not_estimable:
        if n == name:
            return f"not estimable ({reason}): no t"
    if name in getattr(result, "ap_fixed", ()):
        return "held at 0 (fixed): no t"
    for n, partner, c in result.weakly_determined:
        if n == name:
            return (
                f"t = {float(result.ap_t[i]):.2f}, no verdict: weakly determined (|corr| = "
                f"{c:.3f} with {partner}), so its t is not interpretable"
            )
    if not np.isfinite(result.ap_t[i]):
        return "t undefined (the estimate or its sigma is not a number)"
    return ""


def w_tests(
    residuals: np.ndarray,
    sigmas: np.ndarray,
    redundancy: np.ndarray,
    *,
    min_redundancy: float = MIN_TESTABLE_REDUNDANCY,
) -> np.ndarray:
    """Baarda's ``w_i = v_i / (sigma_i sqrt(r_i))`` (Baarda 1968); NaN where ``r_i`` is at most
    ``min_redundancy`` (an observation with no redundancy cannot be tested; the minimal
    detectable bias is infinite there, :func:`tlsjax._adjustment._quality.minimal_detectable_bias`)."""
    r = np.asarray(redundancy, dtype=float)
    ok = r > min_redundancy
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(
            ok, np.asarray(residuals) / (np.asarray(sigmas) * np.sqrt(np.where(ok, r, 1.0))), np.nan
        )


def condition_w_tests(
    residuals: np.ndarray,
    sigmas: np.ndarray,
    redundancy: np.ndarray,
    *,
    min_redundancy: float = MIN_TESTABLE_REDUNDANCY,
) -> np.ndarray:
    """Baarda's w-test of one Gauss-Helmert condition per point (a plane point, SPEC sections 4
    and 7), (m,): ``w_i = e_i / sqrt(r_i)`` with ``e_i`` the whitened condition at the solution,
    ``e_i^2 = sum_k (v_k / sigma_k)^2`` (its share of ``v^T P v``), and ``r_i = sum_k r_k`` the
    condition's redundancy number; signed as the range residual. ``residuals``, ``sigmas``,
    ``redundancy`` (m, 3). NaN where ``r_i`` is at most ``min_redundancy``."""
    v, s = np.asarray(residuals, dtype=float), np.asarray(sigmas, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        e = np.sqrt(np.sum(np.where(s > 0, v / np.where(s > 0, s, 1.0), 0.0) ** 2, axis=-1))
    return w_tests(
        np.where(v[:, 0] < 0, -e, e),
        np.ones(len(e)),
        np.sum(redundancy, axis=-1),
        min_redundancy=min_redundancy,
    )


def ap_notes(result) -> dict:
    """AP name -> why it has no ordinary estimate and t-test verdict (not estimable, held
    fixed, weakly determined, undefined t); APs with an ordinary verdict are left out. The
    same words in the text table, the JSON (``aps.<name>.note``) and the report."""
    out = {}
    for i, name in enumerate(result.ap_names):
        note = _no_verdict(result, i, name)
        if note:
            out[name] = note
    return out


def ap_t_tests(result, alpha: float = 0.05) -> tuple:
    """t-test of every AP: ``t = x / s_x`` (a posteriori sigma) against Student's t with the
    adjustment's degrees of freedom, two-sided at ``alpha``. Non-estimable, fixed and weakly
    determined APs get no verdict (``significant`` False) and a ``note`` saying why."""
    crit = t_critical_value(alpha, result.dof)
    out = []
    for i, name in enumerate(result.ap_names):
        t = float(result.ap_t[i])
        note = _no_verdict(result, i, name)
        out.append(
            APTest(
                name,
                float(result.ap_values[i]),
                float(result.ap_sigmas[i]),
                result.ap_units[i],
                t,
                crit,
                bool(not note and np.isfinite(t) and abs(t) > crit),
                float(result.ap_max_abs_corr[i]),
                result.ap_max_corr_with[i],
                note,
            )
        )
    return tuple(out)


def group_variance_test(omega: float, redundancy: float, alpha: float = 0.05) -> dict:
    """Test of one group's variance factor with its a priori sigmas (as JAG3D reports per
    group): ``Omega_g = v_g^T P_g v_g ~ chi^2(r_g)`` when the group's a priori sigmas are right,
    ``r_g`` the sum of its redundancy numbers; two-sided at ``alpha`` like :func:`global_test`.
    ``factor`` is the estimate ``Omega_g / r_g`` (None where r_g is 0)."""
    if not (redundancy > 0 and np.isfinite(omega)):
        return {**global_test(float("nan"), 0.0, alpha), "dof": redundancy, "factor": None}
    out = global_test(float(np.sqrt(omega / redundancy)), float(redundancy), alpha)
    return {**out, "factor": float(omega / redundancy)}


#: Sigma ratios that a unit mix-up produces, the dimension they apply to, and what each
#: suggests (the units of SPEC section 11).
UNIT_MIXUPS = (
    (180.0 / np.pi, "angle", "degrees vs radians"),
    (200.0 / np.pi, "angle", "gon vs radians"),
    (3600.0, "angle", "degrees vs arc seconds"),
    (648000.0 / np.pi, "angle", "radians vs arc seconds"),
    (1000.0, "length", "millimetres vs metres"),
)
#: A variance factor whose sigma ratio is beyond this (either way) is named in a warning.
PLAUSIBLE_SIGMA_RATIO = 5.0
#: A sigma ratio within this factor of a unit ratio is named as that unit mix-up.
UNIT_MATCH = 1.15


def suspected_units(sigma_ratio: float, dimension: str | None = None) -> tuple[str, ...]:
    """The unit mix-ups of :data:`UNIT_MIXUPS` (of ``dimension``, "length" or "angle", or any)
    whose ratio (or its inverse) is within :data:`UNIT_MATCH` of ``sigma_ratio`` (e.g. 57.3 ->
    degrees vs radians)."""
    if not (np.isfinite(sigma_ratio) and sigma_ratio > 0):
        return ()
    lr = abs(np.log(sigma_ratio))
    return tuple(
        what
        for r, dim, what in UNIT_MIXUPS
        if dimension in (None, dim) and abs(lr - np.log(r)) < np.log(UNIT_MATCH)
    )


def implausible_factor(group: str, factor: float) -> str | None:
    """A sentence for a variance factor that says the a priori sigmas of ``group`` are far off
    (sigma ratio beyond :data:`PLAUSIBLE_SIGMA_RATIO`), naming a suspected unit mix-up; None
    for a plausible factor."""
    if not np.isfinite(factor) or factor <= 0:
        return f"{group}: the variance factor {factor} is not a variance"
    ratio = float(np.sqrt(factor))
    if 1 / PLAUSIBLE_SIGMA_RATIO <= ratio <= PLAUSIBLE_SIGMA_RATIO:
        return None
    size = f"{ratio:.3g} times too small" if ratio > 1 else f"{1 / ratio:.3g} times too large"
    text = f"{group}: variance factor {factor:.4g}: the a priori sigmas are about {size}"
    dimension = (
        "length" if group.startswith("range") else None if group.startswith("all") else "angle"
    )
    units = suspected_units(ratio, dimension)
    if units:
        text += f"; a factor of {max(ratio, 1 / ratio):.4g} in sigma suggests a unit mix-up ({' or '.join(units)})"
    return text


# --- Variance components and robust scales -------------------------------------------------


def variance_factor(whitened_sq: np.ndarray, redundancy: np.ndarray) -> tuple[float, float]:
    """One group's variance factor ``s_g^2 = sum e_i^2 / r_g`` (Förstner 1979) from the squared
    whitened residuals ``e_i^2 = (v_i / sigma_i)^2`` and redundancy numbers of its used
    observations (zeros elsewhere), with ``r_g = sum r_i``; ``s_g^2 = 1`` when ``r_g = 0``
    (nothing to estimate). Returns ``(s_g^2, r_g)``."""
    r_g = float(np.sum(redundancy))
    return (float(np.sum(whitened_sq)) / r_g if r_g > 0 else 1.0), r_g


def bounded_log_step(value: np.ndarray, ok: np.ndarray, max_step: float, power: float = 1.0):
    """``clip(power log(value), -max_step, max_step)`` where ``ok``, 0 elsewhere: the step of a
    variance factor in log space towards ``value**power`` (VCE and the robust balancing of the
    groups), bounded so that one far-off group cannot move its factor by more than
    ``exp(max_step)`` at once."""
    return np.where(ok, np.clip(power * np.log(np.where(ok, value, 1.0)), -max_step, max_step), 0.0)


def robust_scale(u: np.ndarray, keep: np.ndarray, min_count: int) -> float:
    """Robust scale of standardised residuals: ``median |u| / 0.6745`` over ``keep``
    (:data:`tlsjax._stats.MAD_TO_SIGMA`; a few blunders do not move a median), NaN with fewer
    than ``min_count`` of them."""
    if keep.sum() < min_count:
        return float("nan")
    return MAD_TO_SIGMA * float(np.median(np.abs(u[keep])))


def external_reliability(influence, redundancy, mask, delta0: float, ap_names):
    """Baarda's external reliability of every observation: the largest change of an AP caused
    by an undetected MDB-sized error, ``delta0 / sqrt(r_i)`` times the AP influence of a
    one-sigma error (:mod:`tlsjax._adjustment._quality`), in a priori AP sigmas, and the name of
    that AP. ``influence`` (n, 3, a), ``redundancy`` and ``mask`` (n, 3). Inf where an observation
    has no redundancy (no error of any size is detected), NaN where it is not used."""
    n = mask.shape[0]
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(
            redundancy > 0, delta0 / np.sqrt(np.where(redundancy > 0, redundancy, 1.0)), np.inf
        )
    if not influence.shape[-1]:
        return np.zeros((n, 3)), np.full((n, 3), "", dtype=object)
    ext_all = np.abs(influence) * np.where(np.isfinite(scale), scale, 0.0)[..., None]
    ext = np.where(mask & np.isfinite(scale), ext_all.max(axis=-1), np.where(mask, np.inf, np.nan))
    ext_ap = np.array(ap_names, dtype=object)[ext_all.argmax(axis=-1)]
    return ext, ext_ap
