"""The per-target table of the target extraction (CSV).

The per-target table has one row per detection, accepted or rejected, with the unit in every
numeric column's name (SPEC section 11's convention): ``scan, target, kind, accepted, reason,
size_mm, range_m, hz_deg, el_deg, sigma_range_mm, sigma_hz_arcsec, sigma_el_arcsec, x_m, y_m,
z_m, n_points, rms_mm, incidence_deg, coverage, radius_fit_mm, radius_sigma_mm,
plane_offset_mm, contrast_bias_mm, pattern_rms, contrast`` (empty where a value does not apply).
"""

from __future__ import annotations

import csv

import numpy as np

from .._units import ARCSEC, DEG
from ._outputs import atomic_output

_TABLE = (
    ("scan", None, None),
    ("target", None, None),
    ("kind", None, None),
    ("accepted", None, None),
    ("reason", None, None),
    ("size_mm", "size_m", 1e3),
    ("range_m", "range_m", 1.0),
    ("hz_deg", "hz_rad", 1 / DEG),
    ("el_deg", "el_rad", 1 / DEG),
    ("sigma_range_mm", "sigma_range_m", 1e3),
    ("sigma_hz_arcsec", "sigma_hz_rad", 1 / ARCSEC),
    ("sigma_el_arcsec", "sigma_el_rad", 1 / ARCSEC),
    ("x_m", "x_m", 1.0),
    ("y_m", "y_m", 1.0),
    ("z_m", "z_m", 1.0),
    ("n_points", None, None),
    ("rms_mm", "rms_m", 1e3),
    ("incidence_deg", "incidence_rad", 1 / DEG),
    ("coverage", "coverage", 1.0),
    ("radius_fit_mm", "radius_fit_m", 1e3),
    ("radius_sigma_mm", "radius_sigma_m", 1e3),
    ("plane_offset_mm", "plane_offset_m", 1e3),
    ("contrast_bias_mm", "contrast_bias_m", 1e3),
    ("pattern_rms", "pattern_rms", 1.0),
    ("contrast", "contrast", 1.0),
)


def _cell(value, factor):
    if factor is None:
        return str(value)
    v = float(value) * factor
    return "" if not np.isfinite(v) else f"{v:.10g}"


def write_target_table(path, targets) -> None:
    """Write the per-target table of :class:`~tlsjax.ExtractedTargets` (module docstring),
    atomically."""
    with atomic_output(path) as tmp, open(tmp, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow([c for c, _, _ in _TABLE])
        for row in targets.table():
            w.writerow([_cell(row[key or c], f) for c, key, f in _TABLE])
