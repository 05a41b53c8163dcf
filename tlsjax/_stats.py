"""Quantiles and distribution functions of the tests (scipy.stats), in one place.

Baarda's critical value and non-centrality (data snooping, reliability), Student's t for the AP
tests and chi-square for the global test and the variance factors.
"""

from __future__ import annotations

from scipy import stats as _sps


def normal_critical_value(alpha: float) -> float:
    """Two-sided standard-normal critical value ``N^-1(1 - alpha/2)`` (3.29 for alpha = 0.001)."""
    if not 0 < alpha < 1:
        raise ValueError(f"alpha must be in (0, 1), got {alpha}")
    return float(_sps.norm.ppf(1.0 - alpha / 2.0))


def non_centrality(alpha0: float = 0.001, power: float = 0.8) -> float:
    """Baarda's ``delta0 = N^-1(1 - alpha0/2) + N^-1(power)``: 4.13 for 0.1 % and 80 %."""
    if not 0 < power < 1:
        raise ValueError(f"power must be in (0, 1), got {power}")
    return normal_critical_value(alpha0) + float(_sps.norm.ppf(power))


def t_critical_value(alpha: float, dof: float) -> float:
    """Two-sided Student-t critical value ``t^-1(1 - alpha/2; dof)``."""
    if not 0 < alpha < 1:
        raise ValueError(f"alpha must be in (0, 1), got {alpha}")
    return float(_sps.t.ppf(1.0 - alpha / 2.0, max(float(dof), 1.0)))


def chi2_cdf(x: float, dof: float) -> float:
    """``P(chi^2(dof) <= x)``."""
    return float(_sps.chi2.cdf(x, dof))


def chi2_sf(x: float, dof: float) -> float:
    """``P(chi^2(dof) > x)``."""
    return float(_sps.chi2.sf(x, dof))


def chi2_quantile(p: float, dof: float) -> float:
    """Quantile ``p`` of chi^2(dof)."""
    return float(_sps.chi2.ppf(p, dof))
