"""PCD files (Point Cloud Library), read here for ``ascii`` and ``binary`` data.

Written by hand because open3d refuses headers it does not expect (upper-case ``X Y Z`` field
names, as PDAL writes them) and drops every field but the coordinates; the format is a short
text header and either text rows or packed records, which numpy reads directly. Compressed
(``binary_compressed``, LZF) files go to open3d.
"""

from __future__ import annotations

import io

import numpy as np

from .._optional import require
from ._raw_scan import RawScan

_KEYS = ("VERSION", "FIELDS", "SIZE", "TYPE", "COUNT", "WIDTH", "HEIGHT", "VIEWPOINT", "POINTS")
_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4",
          ("I", 8): "i8", ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8"}  # fmt: skip


def _header(source: str, fh):
    head, lines = {}, 0
    while True:
        raw = fh.readline()
        lines += 1
        if not raw:
            raise ValueError(f"{source}: PCD header has no DATA line (file ends at line {lines})")
        text = raw.decode("ascii", errors="replace").strip()
        if not text or text.startswith("#"):
            continue
        key, _, rest = text.partition(" ")
        key = key.upper()
        if key == "DATA":
            return head, rest.strip().lower(), lines
        if key not in _KEYS:
            raise ValueError(
                f"{source}, line {lines}: not a PCD header line: {text[:60]!r} (a PCD file starts "
                "with VERSION, FIELDS, SIZE, TYPE, COUNT, WIDTH, HEIGHT, VIEWPOINT, POINTS, DATA)"
            )
        head[key] = rest.split()


def _dtype(source, head):
    for k in ("FIELDS", "SIZE", "TYPE"):
        if k not in head:
            raise ValueError(f"{source}: PCD header has no {k} line")
    fields, sizes, types = head["FIELDS"], head["SIZE"], head["TYPE"]
    counts = head.get("COUNT", ["1"] * len(fields))
    if not (len(fields) == len(sizes) == len(types) == len(counts)):
        raise ValueError(
            f"{source}: PCD header's FIELDS, SIZE, TYPE and COUNT differ in length "
            f"({len(fields)}, {len(sizes)}, {len(types)}, {len(counts)})"
        )
    dt = []
    for f, s, t, c in zip(fields, sizes, types, counts):
        code = _TYPES.get((t.upper(), int(s)))
        if code is None:
            raise ValueError(f"{source}: PCD field {f} has unknown TYPE {t} / SIZE {s}")
        dt.append((f, "<" + code, (int(c),)) if int(c) > 1 else (f, "<" + code))
    return np.dtype(dt)


def read_pcd(source: str, stem: str) -> list[RawScan]:
    """One PCD file as one :class:`RawScan` (scanner frame; the VIEWPOINT is not a pose)."""
    with open(source, "rb") as fh:
        head, data_kind, n_lines = _header(source, fh)
        dtype = _dtype(source, head)
        try:
            n = int(head.get("POINTS", [0])[0]) or int(head["WIDTH"][0]) * int(head["HEIGHT"][0])
        except (KeyError, ValueError):
            raise ValueError(
                f"{source}: PCD header gives no POINTS (nor WIDTH and HEIGHT)"
            ) from None
        names = {f.lower(): f for f in dtype.names}
        missing = [c for c in "xyz" if c not in names]
        if missing:
            raise ValueError(
                f"{source}: PCD file has no {'/'.join(missing)} field (fields: {', '.join(dtype.names)})"
            )
        if data_kind == "ascii":
            cols = [sum(int(np.prod(dtype[f].shape or (1,))) for f in dtype.names[:i])
                    for i in range(len(dtype.names))]  # fmt: skip
            use = [cols[dtype.names.index(names[c])] for c in "xyz"]
            try:
                text = fh.read().decode("ascii", errors="replace").replace(",", " ")
                pts = np.loadtxt(
                    io.StringIO(text), usecols=use, ndmin=2, dtype=np.float64, max_rows=n
                )
            except ValueError as err:
                raise ValueError(f"{source}: PCD ascii data unreadable ({err})") from None
        elif data_kind == "binary":
            buf = fh.read(n * dtype.itemsize)
            if len(buf) < n * dtype.itemsize:
                raise ValueError(
                    f"{source}: PCD binary data holds {len(buf) // dtype.itemsize} of the {n} "
                    "points in the header (truncated)"
                )
            rec = np.frombuffer(buf, dtype=dtype, count=n)
            pts = np.stack([rec[names[c]].astype(np.float64) for c in "xyz"], axis=1)
        elif data_kind == "binary_compressed":
            return [RawScan(stem, _open3d_pcd(source))]
        else:
            raise ValueError(f"{source}, line {n_lines}: unknown PCD DATA kind {data_kind!r}")
    if len(pts) != n:
        raise ValueError(f"{source}: PCD data holds {len(pts)} of the {n} points in the header")
    if n == 0:
        raise ValueError(f"{source}: the PCD file holds no points")
    return [RawScan(stem, pts)]


def _open3d_pcd(source):
    o3d = require("open3d", "reading compressed PCD")
    cloud = o3d.io.read_point_cloud(source)
    pts = np.asarray(cloud.points, dtype=np.float64)
    if len(pts) == 0:
        raise ValueError(f"{source}: open3d read no points from the compressed PCD file")
    return pts
