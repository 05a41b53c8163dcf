"""Quantiles, distribution functions and the constants derived from them (scipy), in one
place: every critical value, non-centrality and consistency constant of tlsjax comes from here.

Baarda's critical value and non-centrality (data snooping, reliability), Student's t for the AP
tests, chi-square for the global test and the variance factors (:func:`global_test`,
:func:`group_variance_test`), and the normal consistency constant of the median absolute value
(robust scales).

The distribution functions are scipy.special's, the very functions that scipy.stats' ``chi2``
and ``t`` call (``chdtr``, ``chdtrc``, ``gammaincinv``, ``stdtrit``: equal to the last bit,
tests/test_statistics.py), imported at the first call that needs them: scipy.stats takes a
second or more to import, longer than the rest of tlsjax and a re-run's whole calibration
(issue 37). The normal quantiles of the constants come from the standard library
(``statistics.NormalDist``, Wichura's AS 241: within 1e-15 of scipy's ``ndtri``).
"""

from __future__ import annotations

import statistics

import numpy as np

_NORMAL = statistics.NormalDist()


def _special():
    from scipy import special

    return special


#: Reliability defaults of SPEC section 7: significance level alpha0 of the w-test and power.
ALPHA0 = 0.001
POWER = 0.8


def normal_critical_value(alpha: float) -> float:
    """Two-sided standard-normal critical value ``N^-1(1 - alpha/2)`` (3.29 for alpha = 0.001)."""
    if not 0 < alpha < 1:
        raise ValueError(f"alpha must be in (0, 1), got {alpha}")
    return _NORMAL.inv_cdf(1.0 - alpha / 2.0)


def non_centrality(alpha0: float = ALPHA0, power: float = POWER) -> float:
    """Baarda's ``delta0 = N^-1(1 - alpha0/2) + N^-1(power)``: 4.13 for 0.1 % and 80 %."""
    if not 0 < power < 1:
        raise ValueError(f"power must be in (0, 1), got {power}")
    return normal_critical_value(alpha0) + _NORMAL.inv_cdf(power)


#: Baarda's reliability constant delta0 at the defaults alpha0 = 0.1 %, power 80 % (4.1321).
DELTA0 = non_centrality()

#: Normal consistency constant of the median absolute value, ``1 / N^-1(3/4)``
#: (median |N(0, 1)| = 0.6745): ``MAD_TO_SIGMA * median |u|`` estimates sigma robustly.
MAD_TO_SIGMA = 1.0 / _NORMAL.inv_cdf(0.75)


def t_critical_value(alpha: float, dof: float) -> float:
    """Two-sided Student-t critical value ``t^-1(1 - alpha/2; dof)``."""
    if not 0 < alpha < 1:
        raise ValueError(f"alpha must be in (0, 1), got {alpha}")
    return float(_special().stdtrit(max(float(dof), 1.0), 1.0 - alpha / 2.0))


def chi2_cdf(x: float, dof: float) -> float:
    """``P(chi^2(dof) <= x)``."""
    return float(_special().chdtr(dof, x))


def chi2_sf(x: float, dof: float) -> float:
    """``P(chi^2(dof) > x)``."""
    return float(_special().chdtrc(dof, x))


def chi2_quantile(p: float, dof: float) -> float:
    """Quantile ``p`` of chi^2(dof)."""
    return float(2.0 * _special().gammaincinv(dof / 2.0, p))


#: ``sqrt(chi2_dim^-1(0.95))`` for dim 1, 2, 3 as scipy.stats gives them (tests/test_statistics.py
#: checks they are equal): the report's labels need them at import, before scipy is.
_CONFIDENCE_95 = {1: 1.9599639845400538, 2: 2.447746830680816, 3: 2.7954834829151074}


def confidence_scale(dim: int, level: float = 0.95) -> float:
    """``sqrt(chi2_dim^-1(level))``: the factor from the 1-sigma semi-axes of a ``dim``-variate
    normal estimate to its ``level`` confidence ellipsoid (known variance factor): 1.96, 2.4477
    and 2.7955 for one, two and three dimensions at 95 %."""
    if level == 0.95 and dim in _CONFIDENCE_95:
        return _CONFIDENCE_95[dim]
    return float(np.sqrt(chi2_quantile(level, dim)))


#: The factor from 1-sigma semi-axes of a 3D point's error ellipsoid to its 95 % confidence
#: ellipsoid (:func:`confidence_scale` of three dimensions, 2.7955).
ELLIPSOID_95 = round(confidence_scale(3), 4)


def global_test(sigma0: float, dof: float, level: float = 0.05) -> dict:
    """Global test of the adjustment: ``T = v^T P v = s0^2 r ~ chi^2(r)`` when the a priori
    stochastic model is right (Koch 1999, sec. 4.2.2). Two-sided: the model is accepted when
    ``chi^2_{level/2}(r) <= T <= chi^2_{1-level/2}(r)``; the p-value is two-sided too."""
    if not (dof > 0 and np.isfinite(sigma0)):
        return {
            "statistic": None,
            "dof": dof,
            "level": level,
            "lower": None,
            "upper": None,
            "p_value": None,
            "accepted": None,
        }
    T = sigma0**2 * dof
    lo, hi = chi2_quantile(level / 2, dof), chi2_quantile(1 - level / 2, dof)
    cdf = chi2_cdf(T, dof)
    return {
        "statistic": T,
        "dof": dof,
        "level": level,
        "lower": lo,
        "upper": hi,
        "p_value": 2 * min(cdf, 1 - cdf),
        "accepted": bool(lo <= T <= hi),
    }


def group_variance_test(omega: float, redundancy: float, level: float = 0.05) -> dict:
    """Test of one group's variance factor with its a priori sigmas (as JAG3D reports per
    group): ``Omega_g = v_g^T P_g v_g ~ chi^2(r_g)`` when the group's a priori sigmas are right,
    ``r_g`` the sum of its redundancy numbers; two-sided at ``level`` like :func:`global_test`.
    ``factor`` is the estimate ``Omega_g / r_g`` (None where r_g is 0)."""
    if not (redundancy > 0 and np.isfinite(omega)):
        return {**global_test(float("nan"), 0.0, level), "dof": redundancy, "factor": None}
    out = global_test(float(np.sqrt(omega / redundancy)), float(redundancy), level)
    return {**out, "factor": float(omega / redundancy)}


def snooping_critical_value(
    alpha: float, n_tested: int, *, bonferroni: bool = False, given: float | None = None
) -> float:
    """Critical value of data snooping: ``given`` if set, else ``N^-1(1 - alpha'/2)`` with
    ``alpha' = alpha / n_tested`` (Bonferroni: the family-wise level over the tested
    observations) or ``alpha`` per test."""
    if given is not None:
        return float(given)
    return normal_critical_value(alpha / max(n_tested, 1) if bonferroni else alpha)


def robust_scale(u: np.ndarray, keep: np.ndarray, min_count: int) -> float:
    """Robust scale of standardised residuals: ``median |u| / 0.6745`` over ``keep``
    (:data:`MAD_TO_SIGMA`; a few blunders do not move a median), NaN with fewer
    than ``min_count`` of them."""
    if keep.sum() < min_count:
        return float("nan")
    return MAD_TO_SIGMA * float(np.median(np.abs(u[keep])))


def weighted_chi2_sf(x: float, weights, noncentrality=None) -> float:
    """``P(sum_k w_k chi2_1(delta_k^2) > x)`` for weights ``w_k >= 0`` and noncentralities
    ``delta_k^2`` (default 0): Imhof's formula (Imhof 1961, Biometrika 48, eq. 3.2),

        P = 1/2 + (1/pi) int_0^inf sin(theta(u)) / (u rho(u)) du,
        theta(u) = 1/2 sum_k [arctan(w_k u) + delta_k^2 w_k u / (1 + w_k^2 u^2)] - x u / 2,
        rho(u) = prod_k (1 + w_k^2 u^2)^(1/4) exp(1/2 sum_k delta_k^2 w_k^2 u^2 / (1 + w_k^2 u^2)).

    The oscillating tail (period 4 pi / x) is integrated as two Fourier integrals of slowly
    varying amplitudes (QUADPACK's QAWF), the start by adaptive quadrature; absolute accuracy
    about 1e-10. Equal weights without noncentrality reduce to the chi-square distribution.
    """
    from scipy import integrate
    from scipy.special import gammaln

    w = np.asarray(weights, dtype=np.float64).reshape(-1)
    nc = np.zeros_like(w) if noncentrality is None else np.asarray(noncentrality, float).reshape(-1)
    keep = w > 1e-14 * max(float(w.max(initial=0.0)), 1e-300)
    w, nc = w[keep], nc[keep]
    if x <= 0.0:
        return 1.0
    if w.size == 0:
        return 0.0
    if not nc.any() and np.allclose(w, w[0], rtol=1e-13):
        return chi2_sf(x / w[0], w.size)
    # Far below the mass (e.g. two identical AP sets at zero noise, x at rounding level):
    # P(Q <= x) <= (x/2)^(r/2) / (Gamma(r/2 + 1) prod w^(1/2)), the integral of the density's
    # bound near 0; the oscillation period 4 pi / x would be beyond any quadrature there.
    log_head = 0.5 * w.size * np.log(0.5 * x) - gammaln(0.5 * w.size + 1.0)
    log_head -= 0.5 * np.sum(np.log(w))
    if log_head < np.log(1e-12):
        return float(1.0 - np.exp(log_head))

    def amplitude(u):
        wu2 = (w * u) ** 2
        return u * np.exp(0.25 * np.sum(np.log1p(wu2)) + 0.5 * np.sum(nc * wu2 / (1.0 + wu2)))

    def phase(u):
        wu = w * u
        return 0.5 * np.sum(np.arctan(wu) + nc * wu / (1.0 + wu * wu))

    def head(u):
        return np.sin(phase(u) - 0.5 * x * u) / amplitude(u)

    cut = 8.0 * np.pi / x  # a few periods: the amplitude varies slowly beyond it
    i0 = integrate.quad(head, 0.0, cut, limit=400, epsabs=1e-13, epsrel=1e-12)[0]
    i1 = integrate.quad(
        lambda u: np.sin(phase(u)) / amplitude(u), cut, np.inf, weight="cos", wvar=0.5 * x
    )[0]
    i2 = integrate.quad(
        lambda u: np.cos(phase(u)) / amplitude(u), cut, np.inf, weight="sin", wvar=0.5 * x
    )[0]
    return float(min(max(0.5 + (i0 + i1 - i2) / np.pi, 0.0), 1.0))
