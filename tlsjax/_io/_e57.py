"""E57 files (ASTM E2807) through pye57: scans read in chunks, errors as one line.

libE57Format reports a corrupt file as an ``E57Exception`` whose text carries a multi-line debug
dump (source file, line, function of the C++ library); the user needs the first line (what is
wrong) and the file's name, so every call into pye57 goes through :func:`_e57_call`.

A scan's points are read untransformed (scanner frame) with its pose ``X = Q x + t``, so
``R = Q^T`` and ``S = t`` in tlsjax's ``x = R (X - S)``. Cartesian coordinates are used when the
scan has them, else spherical ones (``r, azimuth, elevation`` -> ``r (cos e cos a, cos e sin a,
sin e)``). Points flagged ``*InvalidState != 0`` (no return, or direction only) are dropped and
counted.
"""

from __future__ import annotations

import os

import numpy as np

from .._optional import require
from ._raw_scan import RawScan, pose_from_transform

#: Points read per call into libE57 (the reader's memory is a few arrays of this length).
E57_CHUNK = 1 << 20

_MAGIC = b"ASTM-E57"
_CARTESIAN = ("cartesianX", "cartesianY", "cartesianZ")
_SPHERICAL = ("sphericalRange", "sphericalAzimuth", "sphericalElevation")


def _first_line(err: BaseException) -> str:
    lines = [ln.strip() for ln in str(err).splitlines() if ln.strip()]
    return lines[0] if lines else type(err).__name__


def _e57_call(source: str, what: str, fn, *args, **kw):
    """Run a pye57 call; any failure becomes one ValueError line naming the file."""
    try:
        return fn(*args, **kw)
    except (ValueError, ImportError):
        raise
    except Exception as err:  # libE57's E57Exception, and pye57's own slips (NameError, ...)
        raise ValueError(f"{source}: {what}: {_first_line(err)}") from None


def _check_magic(source: str) -> None:
    with open(source, "rb") as fh:
        head = fh.read(48)
    if len(head) < 48 or not head.startswith(_MAGIC):
        raise ValueError(
            f"{source}: not an E57 file (it does not start with the E57 signature "
            f"{_MAGIC.decode()!r}; the file has {os.path.getsize(source)} bytes)"
        )


def open_e57(source: str, mode: str = "r"):
    """A ``pye57.E57`` of ``source``, with a one-line error if the file cannot be opened."""
    pye57 = require("pye57", "reading and writing E57")
    if mode == "r":
        _check_magic(source)
    return _e57_call(source, "not a readable E57 file", pye57.E57, source, mode=mode)


def _scan_pose(header):
    if not header.has_pose():
        return None
    return pose_from_transform(header.rotation_matrix, header.translation)


def iter_e57_chunks(e57, source: str, k: int, fields, chunk: int = E57_CHUNK):
    """Yield dicts field -> array (copies) of consecutive chunks of scan ``k``."""
    header = _e57_call(source, f"scan {k + 1}: unreadable header", e57.get_header, k)
    buffers, arrays = None, {}
    pye57 = require("pye57", "reading E57")
    buffers = pye57.libe57.VectorSourceDestBuffer()
    n_total = int(header.point_count)
    cap = max(1, min(chunk, n_total))
    for f in fields:
        arr, buf = _e57_call(source, f"scan {k + 1}: field {f}", e57.make_buffer, f, cap)
        arrays[f] = arr
        buffers.append(buf)
    reader = _e57_call(source, f"scan {k + 1}: cannot read points", header.points.reader, buffers)
    try:
        done = 0
        while done < n_total:
            n = int(_e57_call(source, f"scan {k + 1}: points unreadable", reader.read))
            if n == 0:
                break
            done += n
            yield {f: a[:n].copy() for f, a in arrays.items()}
        if done != n_total:
            raise ValueError(
                f"{source}: scan {k + 1}: {done} of the {n_total} points in the header could be read"
            )
    finally:
        try:
            reader.close()
        except Exception:  # pragma: no cover - closing after an error may fail again
            pass


def _points_of(chunk: dict) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) scanner-space points and a validity mask of one chunk."""
    if all(f in chunk for f in _CARTESIAN):
        pts = np.stack([chunk[f] for f in _CARTESIAN], axis=1).astype(np.float64)
        state = chunk.get("cartesianInvalidState")
    else:
        r, az, el = (chunk[f].astype(np.float64) for f in _SPHERICAL)
        ce = np.cos(el)
        pts = np.stack([r * ce * np.cos(az), r * ce * np.sin(az), r * np.sin(el)], axis=1)
        state = chunk.get("sphericalInvalidState")
    valid = np.ones(len(pts), dtype=bool) if state is None else np.asarray(state) == 0
    return pts, valid


def coordinate_fields(header, source: str, k: int) -> list[str]:
    """The coordinate (and invalid-state) fields to read from scan ``k``."""
    fields = list(header.point_fields)
    if all(f in fields for f in _CARTESIAN):
        want = list(_CARTESIAN) + [f for f in ("cartesianInvalidState",) if f in fields]
    elif all(f in fields for f in _SPHERICAL):
        want = list(_SPHERICAL) + [f for f in ("sphericalInvalidState",) if f in fields]
    else:
        raise ValueError(
            f"{source}: scan {k + 1} has neither Cartesian nor spherical coordinates "
            f"(fields: {', '.join(fields) or 'none'})"
        )
    return want


def read_e57(source: str, stem: str) -> list[RawScan]:
    """All scans of an E57 file as :class:`RawScan` (scanner frame, pose from the file)."""
    e57 = open_e57(source)
    out = []
    try:
        n_scans = int(_e57_call(source, "cannot count the scans", lambda: e57.scan_count))
        if n_scans == 0:
            raise ValueError(f"{source}: the E57 file holds no scans (data3D is empty)")
        for k in range(n_scans):
            header = _e57_call(source, f"scan {k + 1}: unreadable header", e57.get_header, k)
            fields = coordinate_fields(header, source, k)
            pose = _e57_call(source, f"scan {k + 1}: unreadable pose", _scan_pose, header)
            parts, masks = [], []
            for chunk in iter_e57_chunks(e57, source, k, fields):
                pts, valid = _points_of(chunk)
                parts.append(pts)
                masks.append(valid)
            pts = np.concatenate(parts) if parts else np.zeros((0, 3))
            valid = np.concatenate(masks) if masks else np.zeros(0, dtype=bool)
            name = f"{stem}_{k + 1}" if n_scans > 1 else stem
            raw = RawScan(name, pts[valid], pose, n_stored=len(pts))
            raw.index = np.flatnonzero(valid)
            if (~valid).any():
                raw.notes.append(
                    f"{source}: scan {name}: dropped {int((~valid).sum())} point(s) flagged invalid "
                    "(no return or direction only)"
                )
            if len(pts) == 0:
                raise ValueError(f"{source}: scan {name} has no points")
            out.append(raw)
    finally:
        try:
            e57.close()
        except Exception:  # pragma: no cover
            pass
    return out
