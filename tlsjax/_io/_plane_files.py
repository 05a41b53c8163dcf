"""Files of extracted planes: the ``.npz`` of ``tlsjax extract-planes`` and the scan poses CSV."""

from __future__ import annotations

import os

import numpy as np

from .._units import UNITS
from ._csv import Located, number, parse_unit_column, read_rows
from ._extracted import ExtractedPlanes

_NPZ_ARRAYS = (
    "patch_scan",
    "patch_normal",
    "patch_distance",
    "patch_rms",
    "patch_inliers",
    "patch_plane",
    "point_patch",
    "point_index",
    "observations",
    "incidence",
)
_NPZ_FORMAT = "tlsjax-planes-1"


def save_planes(path, planes: ExtractedPlanes) -> None:
    """Write extracted (and possibly matched) planes to an ``.npz`` (no pickled objects)."""
    arrays = {k: getattr(planes, k) for k in _NPZ_ARRAYS}
    arrays["format"] = np.array(_NPZ_FORMAT)
    arrays["scans"] = np.array(planes.scans, dtype=str)
    if planes.poses is not None:
        arrays["poses"] = planes.poses
    if planes.planes is not None:
        arrays["planes"] = planes.planes
    with open(path, "wb") as fh:
        np.savez(fh, **arrays)


def load_planes(path) -> ExtractedPlanes:
    """Read an ``.npz`` written by :func:`save_planes`."""
    source = os.fspath(path)
    try:
        with np.load(source, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (OSError, ValueError) as err:
        raise ValueError(f"{source}: not a tlsjax planes .npz file ({err})") from None
    if data.get("format") is None or str(data["format"]) != _NPZ_FORMAT:
        raise ValueError(
            f"{source}: not a tlsjax planes .npz file (missing format tag {_NPZ_FORMAT!r})"
        )
    missing = [k for k in _NPZ_ARRAYS + ("scans",) if k not in data]
    if missing:
        raise ValueError(f"{source}: missing arrays {', '.join(missing)}")
    return ExtractedPlanes(
        scans=tuple(str(s) for s in data["scans"]),
        **{k: data[k] for k in _NPZ_ARRAYS},
        poses=data.get("poses"),
        planes=data.get("planes"),
    )


_POSE_NUMERIC = ("x", "y", "z", "omega", "phi", "kappa")


def read_poses(path) -> dict[str, np.ndarray]:
    """Scan poses CSV: columns ``scan, x_<len>, y_<len>, z_<len>, omega_<ang>, phi_<ang>,
    kappa_<ang>`` (units as in SPEC section 11, e.g. ``x_m``, ``omega_deg``), meaning
    ``x = R3(kappa) R2(phi) R1(omega) (X - S)``. Returns scan -> (Xs, Ys, Zs, omega, phi, kappa)."""
    source = os.fspath(path)
    loc = Located(source)
    header_line, names, data = read_rows(path, loc)
    columns = {}
    for i, name in enumerate(names):
        if name.lower() == "scan":
            key, factor = "scan", None
        else:
            try:
                key, unit, factor = parse_unit_column(name.lower())
            except ValueError as err:
                raise loc.error(str(err), header_line) from None
            if key not in _POSE_NUMERIC:
                raise loc.error(
                    f"unknown column '{name}'; accepted: scan, "
                    + ", ".join(q + "_<unit>" for q in _POSE_NUMERIC),
                    header_line,
                    name,
                )
            want = "length" if key in ("x", "y", "z") else "angle"
            if UNITS[unit][0] != want:
                raise loc.error(
                    f"'{key}' is an {want} but '_{unit}' is a unit of {UNITS[unit][0]}",
                    header_line,
                    name,
                )
        if key in columns:
            raise loc.error(f"'{key}' given twice", header_line, name)
        columns[key] = (i, name, factor)
    for q in ("scan",) + _POSE_NUMERIC:
        if q not in columns:
            raise loc.error(
                "missing required column", header_line, q if q == "scan" else q + "_<unit>"
            )
    poses: dict[str, np.ndarray] = {}
    for line, fields in data:
        if len(fields) != len(names):
            raise loc.error(f"expected {len(names)} fields, found {len(fields)}", line)
        i, name, _ = columns["scan"]
        scan = fields[i].strip()
        if not scan:
            raise loc.error("empty scan name", line, name)
        if scan in poses:
            raise loc.error(f"duplicate scan '{scan}'", line, name)
        poses[scan] = np.array(
            [
                number(fields[columns[q][0]], line, columns[q][1], loc, True) * columns[q][2]
                for q in _POSE_NUMERIC
            ]
        )
    if not poses:
        raise loc.error("no data rows after the header", header_line + 1)
    return poses
