"""Files of the target extraction: the per-target table (CSV) and a user's target list.

The per-target table has one row per detection, accepted or rejected, with the unit in every
numeric column's name (SPEC section 11's convention): ``scan, target, kind, accepted, reason,
size_mm, range_m, hz_deg, el_deg, sigma_range_mm, sigma_hz_arcsec, sigma_el_arcsec, x_m, y_m,
z_m, n_points, rms_mm, incidence_deg, coverage, radius_fit_mm, radius_sigma_mm,
plane_offset_mm, contrast_bias_mm, pattern_rms, contrast`` (empty where a value does not apply).

A target list names targets with approximate coordinates in any one frame (a total station
survey, a previous registration): columns ``target`` and ``x``, ``y``, ``z`` with a length
unit suffix (``x_m`` or ``x_mm``), optionally ``kind`` (sphere, checkerboard, circle).
"""

from __future__ import annotations

import csv

import numpy as np

from .._units import ARCSEC, DEG
from ._tables import open_text, parse_unit_column

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
    """Write the per-target table of :class:`~tlsjax.ExtractedTargets` (module docstring)."""
    with open(path, "w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh, lineterminator="\n")
        w.writerow([c for c, _, _ in _TABLE])
        for row in targets.table():
            w.writerow([_cell(row[key or c], f) for c, key, f in _TABLE])


def read_target_list(path) -> dict:
    """A target list (module docstring) as ``{name: (x, y, z[, kind])}`` in metres; errors name
    the file, line and column."""
    source = str(path)
    with open_text(path, "target list") as fh:
        rows = list(csv.reader(fh))
    rows = [(k + 1, r) for k, r in enumerate(rows) if r and any(c.strip() for c in r)]
    if not rows:
        raise ValueError(f"{source}: the target list is empty")
    head = [c.strip() for c in rows[0][1]]
    cols = {}
    for i, h in enumerate(head):
        if h.lower() in ("target", "name", "kind"):
            cols[h.lower().replace("name", "target")] = (i, None)
            continue
        try:
            q, unit, factor = parse_unit_column(h)
        except ValueError as err:
            raise ValueError(f"{source}, line {rows[0][0]}: {err}") from None
        if q in ("x", "y", "z"):
            if unit not in ("m", "mm"):
                raise ValueError(f"{source}, line {rows[0][0]}: column {h!r} needs a length unit")
            cols[q] = (i, factor)
    missing = [c for c in ("target", "x", "y", "z") if c not in cols]
    if missing:
        raise ValueError(
            f"{source}, line {rows[0][0]}: the target list needs columns target, x_m, y_m, z_m "
            f"(missing: {', '.join(missing)})"
        )
    out = {}
    for line, r in rows[1:]:
        try:
            name = r[cols["target"][0]].strip()
            xyz = [float(r[cols[c][0]]) * cols[c][1] for c in "xyz"]
        except (IndexError, ValueError):
            raise ValueError(
                f"{source}, line {line}: not a target and three numbers: {r}"
            ) from None
        if not name or not np.all(np.isfinite(xyz)):
            raise ValueError(f"{source}, line {line}: empty name or non-finite coordinate")
        if name in out:
            raise ValueError(f"{source}, line {line}: target {name!r} is listed twice")
        kind = r[cols["kind"][0]].strip() if "kind" in cols and cols["kind"][0] < len(r) else ""
        out[name] = (*xyz, kind) if kind else tuple(xyz)
    if len(out) < 3:
        raise ValueError(f"{source}: a target list needs at least 3 targets, got {len(out)}")
    return out
