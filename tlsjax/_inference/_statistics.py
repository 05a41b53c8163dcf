"""Tests and reliability of an adjustment (SPEC section 7), host side on its results.

* Global test: ``T = v^T P v = s0^2 r ~ chi^2(r)`` when the a priori stochastic model is right
  (Koch 1999, sec. 4.2.2).
* Baarda (1968) w-test ``w_i = v_i / (sigma_i sqrt(r_i))`` and the internal reliability
  ``MDB_i = delta0 sigma_i / sqrt(r_i)``, ``delta0 = N^-1(1 - alpha0/2) + N^-1(power)``.
* t-tests of the APs: ``t = x_a / s_a`` against Student's t with the adjustment's dof.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .._stats import chi2_cdf, chi2_quantile, normal_critical_value, t_critical_value


def critical_value(alpha: float) -> float:
    """Two-sided standard-normal critical value ``N^-1(1 - alpha/2)`` (3.29 for alpha = 0.001)."""
    return normal_critical_value(alpha)


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
    name: str
    value: float
    sigma: float
    unit: str
    t: float
    critical: float
    significant: bool
    max_abs_corr: float
    max_corr_with: str


def w_tests(
    residuals: np.ndarray,
    sigmas: np.ndarray,
    redundancy: np.ndarray,
    *,
    min_redundancy: float = 1e-6,
) -> np.ndarray:
    """Baarda's ``w_i = v_i / (sigma_i sqrt(r_i))`` (Baarda 1968); NaN where ``r_i`` is below
    ``min_redundancy`` (an observation with no redundancy cannot be tested)."""
    r = np.asarray(redundancy, dtype=float)
    ok = r > min_redundancy
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(
            ok, np.asarray(residuals) / (np.asarray(sigmas) * np.sqrt(np.where(ok, r, 1.0))), np.nan
        )


def minimal_detectable_bias(
    sigmas: np.ndarray, redundancy: np.ndarray, delta0: float = 4.13
) -> np.ndarray:
    """Internal reliability ``MDB_i = delta0 sigma_i / sqrt(r_i)`` [units of sigma]; inf where r_i = 0."""
    r = np.asarray(redundancy, dtype=float)
    with np.errstate(divide="ignore"):
        return np.where(
            r > 0, delta0 * np.asarray(sigmas) / np.sqrt(np.where(r > 0, r, 1.0)), np.inf
        )


def ap_t_tests(result, alpha: float = 0.05) -> tuple:
    """t-test of every AP: ``t = x / s_x`` (a posteriori sigma) against Student's t with the
    adjustment's degrees of freedom, two-sided at ``alpha``. Non-estimable APs get NaN."""
    crit = t_critical_value(alpha, result.dof)
    out = []
    for i, name in enumerate(result.ap_names):
        t = float(result.ap_t[i])
        out.append(
            APTest(
                name,
                float(result.ap_values[i]),
                float(result.ap_sigmas[i]),
                result.ap_units[i],
                t,
                crit,
                bool(np.isfinite(t) and abs(t) > crit),
                float(result.ap_max_abs_corr[i]),
                result.ap_max_corr_with[i],
            )
        )
    return tuple(out)
