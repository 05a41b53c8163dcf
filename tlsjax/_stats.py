"""Quantiles, distribution functions and the constants derived from them (scipy.stats), in one
place: every critical value, non-centrality and consistency constant of tlsjax comes from here.

Baarda's critical value and non-centrality (data snooping, reliability), Student's t for the AP
tests, chi-square for the global test and the variance factors, and the normal consistency
constant of the median absolute value (robust scales).
"""

from __future__ import annotations

from scipy import stats as _sps

#: Reliability defaults of SPEC section 7: significance level alpha0 of the w-test and power.
ALPHA0 = 0.001
POWER = 0.8


def normal_critical_value(alpha: float) -> float:
    """Two-sided standard-normal critical value ``N^-1(1 - alpha/2)`` (3.29 for alpha = 0.001)."""
    if not 0 < alpha < 1:
        raise ValueError(f"alpha must be in (0, 1), got {alpha}")
    return float(_sps.norm.ppf(1.0 - alpha / 2.0))


def non_centrality(alpha0: float = ALPHA0, power: float = POWER) -> float:
    """Baarda's ``delta0 = N^-1(1 - alpha0/2) + N^-1(power)``: 4.13 for 0.1 % and 80 %."""
    if not 0 < power < 1:
        raise ValueError(f"power must be in (0, 1), got {power}")
    return normal_critical_value(alpha0) + float(_sps.norm.ppf(power))


#: Baarda's reliability constant delta0 at the defaults alpha0 = 0.1 %, power 80 % (4.1321).
DELTA0 = non_centrality()

#: Normal consistency constant of the median absolute value, ``1 / N^-1(3/4)``
#: (median |N(0, 1)| = 0.6745): ``MAD_TO_SIGMA * median |u|`` estimates sigma robustly.
MAD_TO_SIGMA = 1.0 / float(_sps.norm.ppf(0.75))


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
