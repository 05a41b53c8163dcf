"""Scans read chunk by chunk, with their intensities, for passes over clouds too large to hold.

:func:`open_scans` lists the scans of a point-cloud file (named as
:func:`~tlsjax.read_point_clouds` names them) without reading their points; each
:class:`ScanChunks` then yields its points in chunks as often as a caller passes over it:
scanner-space coordinates (n, 3) [m] (object-space files taken to scanner space with the pose,
as the reader does), the intensity (n,) when the file has one, and the row of each point in the
scan as stored. Points the reader drops (non-finite, exactly (0, 0, 0), flagged invalid in E57)
are dropped here too and counted.

Streamed: E57 (libE57 reads in chunks), LAS/LAZ (laspy's chunk iterator), PLY (memory-mapped),
PTX and XYZ/TXT (text, a chunk of lines at a time). PCD files are read whole by the reader (no
intensity). Intensity fields, by name wherever the file names them: E57 ``intensity``; LAS
``intensity``; PLY ``intensity``, ``scalar_intensity``, ``reflectance`` (any case); text files
(XYZ, TXT, ASC, CSV, PTS) the column their header names so
(:func:`~tlsjax._io._point_clouds.text_layout`), else the fourth of four unnamed columns or of
a PTS file (its format); PTX the fourth column (its format). Unnamed text columns beyond that
are refused with the fix (``columns``), never guessed.
"""

from __future__ import annotations

import dataclasses
import io
import itertools
import warnings
from collections.abc import Callable, Iterator

import numpy as np

from .._model._geometry import cartesian_from_spherical
from ._point_clouds import checked_source, to_scanner

#: Points per chunk of the streamed passes.
CHUNK_POINTS = 1 << 20

_PLY_INTENSITY = ("intensity", "scalar_intensity", "reflectance", "scalar_reflectance")


@dataclasses.dataclass(frozen=True, eq=False)
class ScanChunks:
    """One scan whose points are read in chunks (:meth:`chunks`), as often as needed.

    ``pose`` (6,) or None; ``n_stored`` points stored (None where the format does not say
    before reading); ``has_intensity``; ``object_frame``: the file holds object-space
    coordinates (taken to scanner space with ``pose``).
    """

    name: str
    source: str
    pose: np.ndarray | None
    n_stored: int | None
    has_intensity: bool
    object_frame: bool
    _read: Callable[[int], Iterator[tuple]]

    def chunks(self, size: int = CHUNK_POINTS):
        """Yield ``(points (m, 3) scanner space [m], intensity (m,) or None, rows (m,))`` per
        chunk of about ``size`` stored points; dropped points are left out."""
        start = 0
        for pts, inten, valid in self._read(size):
            pts = np.asarray(pts, dtype=np.float64).reshape(-1, 3)
            rows = np.arange(start, start + len(pts), dtype=np.int64)
            start += len(pts)
            keep = np.all(np.isfinite(pts), axis=1) & ~np.all(pts == 0.0, axis=1)
            if valid is not None:
                keep &= valid
            if inten is not None:
                inten = np.asarray(inten, dtype=np.float64)[keep]
            pts = pts[keep]
            if self.object_frame and self.pose is not None:
                pts = to_scanner(pts, self.pose)
            yield pts, inten, rows[keep]


def scan_from_arrays(name: str, points, intensity=None) -> ScanChunks:
    """A :class:`ScanChunks` over scanner-space ``points`` (n, 3) [m] held in memory."""
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"scan {name}: points must be an (n, 3) array, got {pts.shape}")
    inten = None if intensity is None else np.asarray(intensity, dtype=np.float64).reshape(-1)
    if inten is not None and len(inten) != len(pts):
        raise ValueError(
            f"scan {name}: {len(inten)} intensities for {len(pts)} points (one per point)"
        )

    def read(size):
        for a in range(0, len(pts), size):
            yield pts[a : a + size], None if inten is None else inten[a : a + size], None

    return ScanChunks(name, "<arrays>", None, len(pts), inten is not None, False, read)


def scan_from_observations(name: str, observations, intensity=None) -> ScanChunks:
    """A :class:`ScanChunks` over observations (n, 3) = (rho, theta, alpha) of either
    architecture (both faces map to the same scanner-space point)."""
    obs = np.asarray(observations, dtype=np.float64)
    if obs.ndim != 2 or obs.shape[1] != 3:
        raise ValueError(f"scan {name}: observations must be an (n, 3) array, got {obs.shape}")
    return scan_from_arrays(name, cartesian_from_spherical(obs, xp=np), intensity)


def _e57_scans(source, stem):
    from ._e57 import (
        _e57_call,
        _points_of,
        _scan_pose,
        coordinate_fields,
        iter_e57_chunks,
        open_e57,
    )

    e57 = open_e57(source)
    try:
        n_scans = int(_e57_call(source, "cannot count the scans", lambda: e57.scan_count))
        if n_scans == 0:
            raise ValueError(f"{source}: the E57 file holds no scans (data3D is empty)")
        heads = []
        for k in range(n_scans):
            h = _e57_call(source, f"scan {k + 1}: unreadable header", e57.get_header, k)
            fields = coordinate_fields(h, source, k)
            has_i = "intensity" in list(h.point_fields)
            pose = _e57_call(source, f"scan {k + 1}: unreadable pose", _scan_pose, h)
            heads.append((fields + ["intensity"] * has_i, has_i, pose, int(h.point_count)))
    finally:
        e57.close()

    def reader(k, fields, has_i):
        def read(size):
            f = open_e57(source)
            try:
                for chunk in iter_e57_chunks(f, source, k, fields, size):
                    pts, valid = _points_of(chunk)
                    yield pts, chunk["intensity"] if has_i else None, valid
            finally:
                f.close()

        return read

    return [
        ScanChunks(
            f"{stem}_{k + 1}" if n_scans > 1 else stem,
            source,
            pose,
            n,
            has_i,
            False,
            reader(k, fields, has_i),
        )
        for k, (fields, has_i, pose, n) in enumerate(heads)
    ]


def _las_scans(source, stem):
    from ._las import iter_las_chunks, open_las, pose_from_header

    with open_las(source) as r:
        pose = pose_from_header(r.header, source)
        n = int(r.header.point_count)

    def read(size):
        with open_las(source) as r:
            for p in iter_las_chunks(r, source, size):
                xyz = np.stack([np.asarray(p.x), np.asarray(p.y), np.asarray(p.z)], axis=1)
                yield xyz, np.asarray(p.intensity, dtype=np.float64), None

    if n == 0:
        raise ValueError(f"{source}: the LAS/LAZ file holds no points")
    return [ScanChunks(stem, source, pose, n, True, True, read)]


def _ply_scans(source, stem):
    from ._ply import read_ply_data

    _, vertex = read_ply_data(source)
    props = {p.name.lower(): p.name for p in vertex.properties}
    key = next((props[k] for k in _PLY_INTENSITY if k in props), None)
    n = len(vertex.data)
    if n == 0:
        raise ValueError(f"{source}: the PLY file holds no vertices")

    def read(size):
        v = read_ply_data(source)[1].data  # memory-mapped where the file is binary
        for a in range(0, n, size):
            part = v[a : a + size]
            xyz = np.stack([np.asarray(part[c], dtype=np.float64) for c in "xyz"], axis=1)
            yield xyz, None if key is None else np.asarray(part[key], dtype=np.float64), None

    return [ScanChunks(stem, source, None, n, key is not None, False, read)]


def _text_block(lines, first_line, source, ncols):
    """Columns ``ncols`` (a count: 0..ncols-1, or a tuple of indices) of text lines as float64
    (m, k); errors name the line."""
    cols = tuple(range(ncols)) if isinstance(ncols, int) else tuple(ncols)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            arr = np.loadtxt(
                io.StringIO("".join(lines).replace(",", " ")),
                usecols=cols,
                ndmin=2,
                dtype=np.float64,
            )
        if len(arr) == len(lines):
            return arr
    except ValueError:
        pass
    for k, ln in enumerate(lines):
        fields = ln.replace(",", " ").split()
        try:
            ok = len(fields) > max(cols) and all(np.isfinite([float(fields[c]) for c in cols]))
        except ValueError:
            ok = False
        if not ok:
            raise ValueError(
                f"{source}, line {first_line + k}: expected numbers in columns "
                f"{', '.join(str(c + 1) for c in cols)}, got {ln.strip()!r}"
            )
    raise ValueError(f"{source}: could not read the points")  # pragma: no cover


def _ptx_scans(source, stem):
    from ._raw_scan import pose_from_transform as _pose_from_transform

    scans = []
    with open(source, encoding="utf-8") as fh:
        line_no = 0
        while True:
            top = fh.readline()
            line_no += 1
            while top and not top.strip():
                top = fh.readline()
                line_no += 1
            if not top:
                break
            head = [top] + list(itertools.islice(fh, 9))
            where = f"{source}, line {line_no}"
            line_no += len(head) - 1
            if len(head) < 10:
                raise ValueError(f"{where}: PTX header needs 10 lines, the file ends first")
            try:
                cols, rows = int(head[0].split()[0]), int(head[1].split()[0])
                M = np.array([[float(v) for v in ln.replace(",", " ").split()] for ln in head[6:]])
                if M.shape != (4, 4) or cols <= 0 or rows <= 0:
                    raise ValueError
            except (ValueError, IndexError):
                raise ValueError(f"{where}: not a PTX scan header") from None
            first, n = line_no + 1, cols * rows
            probe = fh.readline()
            rest = sum(1 for _ in itertools.islice(fh, n - 1))
            if not probe or rest != n - 1:
                raise ValueError(
                    f"{where}: PTX scan needs {n} point lines ({cols} x {rows}), the file has "
                    f"{rest + bool(probe)}"
                )
            pose = _pose_from_transform(M[:3, :3].T, M[3, :3])
            scans.append((first, n, pose, len(probe.replace(",", " ").split()) >= 4))
            line_no += n

    def reader(first, n, has_i):
        def read(size):
            with open(source, encoding="utf-8") as fh:
                for _ in itertools.islice(fh, first - 1):
                    pass
                done = 0
                while done < n:
                    lines = list(itertools.islice(fh, min(size, n - done)))
                    arr = _text_block(lines, first + done, source, 4 if has_i else 3)
                    done += len(lines)
                    yield arr[:, :3], arr[:, 3] if has_i else None, None

        return read

    many = len(scans) > 1
    if not scans:
        raise ValueError(f"{source}: no PTX scan in the file")
    return [
        ScanChunks(
            f"{stem}_{k + 1}" if many else stem, source, pose, n, has_i, False, reader(f, n, has_i)
        )
        for k, (f, n, pose, has_i) in enumerate(scans)
    ]


def _xyz_scans(source, stem, columns=None):
    """A text point file (XYZ, TXT, ASC, CSV, PTS): columns by the header's names, the format
    or ``columns`` (:func:`~tlsjax._io._point_clouds.text_layout`)."""
    from ._point_clouds import text_layout

    with open(source, encoding="utf-8") as fh:
        head = list(itertools.islice(fh, 1000))
    layout = text_layout(head, source, pts=source.lower().endswith(".pts"), columns=columns)
    cols = layout.usecols

    def data_lines(fh):
        for no, ln in enumerate(fh, 1):
            t = ln.strip()
            if no > layout.skip and t and not t.startswith(("#", "//")):
                yield no, ln.replace(";", " ")

    def read(size):
        with open(source, encoding="utf-8") as fh:
            it = data_lines(fh)
            while True:
                block = list(itertools.islice(it, size))
                if not block:
                    return
                arr = _text_block([ln for _, ln in block], block[0][0], source, cols)
                yield arr[:, :3], arr[:, 3] if layout.has_intensity else None, None

    return [ScanChunks(stem, source, None, None, layout.has_intensity, False, read)]


def _whole_file_scans(source):
    from ._point_clouds import read_point_clouds

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scans = read_point_clouds(source)
    return [scan_from_arrays(s.name, s.points) for s in scans]


def open_scans(path, *, poses=None, columns=None) -> list[ScanChunks]:
    """The scans of a point-cloud file as :class:`ScanChunks` (by extension, as
    :func:`~tlsjax.read_point_clouds`); ``poses`` (scan name -> pose) replace the file's;
    ``columns`` names the columns of a text file ("x,y,z,r,g,b,intensity")."""
    source, kind, stem = checked_source(path)
    try:
        if kind == "xyz":
            scans = _xyz_scans(source, stem, columns)
        else:
            scans = {
                "e57": _e57_scans,
                "las": _las_scans,
                "ply": _ply_scans,
                "ptx": _ptx_scans,
            }.get(kind, lambda s, _: _whole_file_scans(s))(source, stem)
    except UnicodeDecodeError as err:
        raise ValueError(f"{source}: not a text file ({err.reason} at byte {err.start})") from None
    except OSError as err:
        raise ValueError(f"{source}: cannot read the file ({err.strerror or err})") from None
    poses = poses or {}
    out = []
    for s in scans:
        pose = poses.get(s.name, s.pose)
        if pose is not None:
            pose = np.asarray(pose, dtype=np.float64)
            if pose.shape != (6,) or not np.all(np.isfinite(pose)):
                raise ValueError(f"{source}: scan {s.name}: the pose must be 6 finite numbers")
        out.append(dataclasses.replace(s, pose=pose))
    return out
