"""Variance factors of observation groups (SPEC sections 5 and 7): pure functions, host side.

* Their estimate (Förstner 1979; Koch 1999, sec. 3.6): ``s_g^2 = v_g^T P_g v_g / r_g``,
  ``r_g`` the sum of the group's redundancy numbers, and the bounded step in log space that VCE
  (and the robust balancing of screening) takes towards it.
* An implausible factor named, with the unit mix-up it suggests.

The other statistics have one home each: distributions, critical values, the global and group
tests and robust scales in :mod:`tlsjax._stats`; the w-test and reliability (MDB, external) in
:mod:`tlsjax._adjustment._quality`; the AP t-tests in :mod:`tlsjax._adjustment._ap_tests`.
"""

from __future__ import annotations

import numpy as np

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
