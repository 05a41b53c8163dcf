"""PLY files through ``plyfile``: every vertex property is kept, so a corrected file can be
written back with its intensity, colour and normals; a vertex element without an ``x``, ``y``
or ``z`` property is refused (open3d fills a missing z with uninitialised memory)."""

from __future__ import annotations

import io

import numpy as np

from .._optional import require
from ._raw_scan import RawScan

_XYZ = ("x", "y", "z")


def _plyfile():
    return require("plyfile", "reading and writing PLY")


def read_ply_data(source: str):
    """The ``plyfile.PlyData`` of ``source`` (binary vertex data memory-mapped where possible)
    and its vertex element, with one-line errors."""
    plyfile = _plyfile()
    try:
        data = plyfile.PlyData.read(source, mmap="r")
    except Exception as err:  # PlyHeaderParseError, PlyElementParseError, struct/EOF errors
        data = _read_lenient(plyfile, source)
        if data is None:
            text = str(err).splitlines()[0] if str(err) else type(err).__name__
            raise ValueError(f"{source}: not a readable PLY file ({text})") from None
    names = [e.name for e in data.elements]
    if "vertex" not in names:
        raise ValueError(
            f"{source}: PLY file has no 'vertex' element (elements: {', '.join(names) or 'none'})"
        )
    vertex = data["vertex"]
    props = [p.name for p in vertex.properties]
    missing = [c for c in _XYZ if c not in props]
    if missing:
        raise ValueError(
            f"{source}: PLY vertex element has no {'/'.join(missing)} propert"
            f"{'y' if len(missing) == 1 else 'ies'} (has: {', '.join(props)})"
        )
    return data, vertex


def _read_lenient(plyfile, source: str):
    """Retry with trailing blanks removed from the header lines (``"ply "`` is common in the
    wild and plyfile refuses it); None if that does not help either."""
    with open(source, "rb") as fh:
        raw = fh.read()
    end = raw.find(b"end_header")
    if not raw.startswith(b"ply") or end < 0:
        return None
    nl = raw.find(b"\n", end)
    nl = len(raw) if nl < 0 else nl + 1
    head = b"\n".join(ln.rstrip() for ln in raw[:nl].splitlines()) + b"\n"
    try:
        return plyfile.PlyData.read(io.BytesIO(head + raw[nl:]))
    except Exception:
        return None


def read_ply(source: str, stem: str) -> list[RawScan]:
    """One PLY file as one :class:`RawScan` (scanner frame, no pose)."""
    _, vertex = read_ply_data(source)
    v = vertex.data
    if len(v) == 0:
        raise ValueError(f"{source}: the PLY file holds no vertices")
    pts = np.stack([np.asarray(v[c], dtype=np.float64) for c in _XYZ], axis=1)
    return [RawScan(stem, pts)]


def write_ply(path, points, *, attributes=None, text: bool = False) -> None:
    """Write points (n, 3) [m] as a PLY vertex element with float64 x, y, z and the given
    per-point ``attributes`` (dict name -> array, e.g. ``intensity``, ``red``)."""
    plyfile = _plyfile()
    x = np.asarray(points, dtype=np.float64)
    attributes = attributes or {}
    dtype = [(c, "f8") for c in _XYZ] + [
        (k, np.asarray(a).dtype.str) for k, a in attributes.items()
    ]
    arr = np.empty(len(x), dtype=dtype)
    for i, c in enumerate(_XYZ):
        arr[c] = x[:, i]
    for k, a in attributes.items():
        arr[k] = a
    el = plyfile.PlyElement.describe(arr, "vertex")
    from ._outputs import atomic_output

    with atomic_output(path) as tmp:
        plyfile.PlyData([el], text=text).write(tmp)
