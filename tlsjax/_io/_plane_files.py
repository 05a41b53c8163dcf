"""Files of extracted planes: the ``.npz`` of ``tlsjax extract-planes`` and the scan poses CSV."""

from __future__ import annotations

import os

import numpy as np

from .._units import UNITS
from ._csv import Located, number, parse_unit_column, read_rows
from ._extracted import ExtractedPlanes
from ._outputs import atomic_output

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


def write_extracted_planes(path, planes: ExtractedPlanes) -> None:
    """Write extracted (and possibly matched) planes to an ``.npz`` (no pickled objects)."""
    arrays = {k: getattr(planes, k) for k in _NPZ_ARRAYS}
    arrays["format"] = np.array(_NPZ_FORMAT)
    arrays["scans"] = np.array(planes.scans, dtype=str)
    if planes.poses is not None:
        arrays["poses"] = planes.poses
    if planes.planes is not None:
        arrays["planes"] = planes.planes
    with atomic_output(path) as tmp, open(tmp, "wb") as fh:  # a file object: no ".npz" added
        np.savez(fh, **arrays)


#: Array -> (trailing shape, kind): "i" integer indices, "f" finite floats.
_NPZ_SHAPES = {
    "patch_scan": ((), "i"),
    "patch_normal": ((3,), "f"),
    "patch_distance": ((), "f"),
    "patch_rms": ((), "f"),
    "patch_inliers": ((), "i"),
    "patch_plane": ((), "i"),
    "point_patch": ((), "i"),
    "point_index": ((), "i"),
    "observations": ((3,), "f"),
    "incidence": ((), "f"),
}


def _check_npz(data: dict, source: str) -> None:
    """Shapes, kinds and index ranges of the arrays agree with each other (a truncated or
    edited file is named here, not as an IndexError deep inside)."""
    for k, (tail, kind) in _NPZ_SHAPES.items():
        a = data[k]
        if a.ndim != 1 + len(tail) or a.shape[1:] != tail:
            raise ValueError(f"{source}: array {k} has shape {a.shape}, expected (n, {tail})")
        if kind == "i" and not np.issubdtype(a.dtype, np.integer):
            raise ValueError(f"{source}: array {k} holds {a.dtype}, not integer indices")
        if kind == "f" and not (np.issubdtype(a.dtype, np.number) and np.isfinite(a).all()):
            raise ValueError(f"{source}: array {k} is not all finite numbers")
    if data["scans"].ndim != 1:
        raise ValueError(f"{source}: array scans must list the scan names")
    n_patch, n_point = len(data["patch_scan"]), len(data["point_patch"])
    for k in ("patch_normal", "patch_distance", "patch_rms", "patch_inliers", "patch_plane"):
        if len(data[k]) != n_patch:
            raise ValueError(f"{source}: {k} has {len(data[k])} rows for {n_patch} patches")
    for k in ("point_index", "observations", "incidence"):
        if len(data[k]) != n_point:
            raise ValueError(f"{source}: {k} has {len(data[k])} rows for {n_point} points")
    n_planes = len(data["planes"]) if data.get("planes") is not None else 0
    for k, n, low in (
        ("point_patch", n_patch, 0),
        ("patch_scan", len(data["scans"]), 0),
        ("patch_plane", n_planes, -1),
    ):
        a = data[k]
        if a.size and (a.min() < low or a.max() >= max(n, 0)):
            raise ValueError(f"{source}: {k} indexes outside 0..{n - 1}")
    for k, width in (("planes", 4), ("poses", 6)):
        a = data.get(k)
        if a is not None and (a.ndim != 2 or a.shape[1] != width or not np.isfinite(a).all()):
            raise ValueError(f"{source}: array {k} must be finite (n, {width}), got {a.shape}")


def read_extracted_planes(path) -> ExtractedPlanes:
    """Read an ``.npz`` written by :func:`write_extracted_planes`; a file that is not one, or whose
    arrays disagree, is a one-line ValueError naming it."""
    import zipfile

    source = os.fspath(path)
    try:
        with np.load(source, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except FileNotFoundError:
        raise
    except (OSError, ValueError, EOFError, zipfile.BadZipFile, KeyError) as err:
        raise ValueError(f"{source}: not a tlsjax planes .npz file ({err})") from None
    except Exception as err:  # a corrupt archive raises whatever its decompressor raises
        raise ValueError(
            f"{source}: not a readable .npz file ({type(err).__name__}: {err})"
        ) from None
    if data.get("format") is None or str(data["format"]) != _NPZ_FORMAT:
        raise ValueError(
            f"{source}: not a tlsjax planes .npz file (missing format tag {_NPZ_FORMAT!r})"
        )
    missing = [k for k in _NPZ_ARRAYS + ("scans",) if k not in data]
    if missing:
        raise ValueError(f"{source}: missing arrays {', '.join(missing)}")
    _check_npz(data, source)
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
