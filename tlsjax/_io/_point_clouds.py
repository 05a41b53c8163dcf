"""Point-cloud files of single scans, read into scanner-space observations (SPEC sections 1, 11).

A scan's points are taken in the scanner's own frame (x = R (X - S)) and turned into the
observations of the chosen architecture: range ``rho = |x|``, ``theta = atan2(y, x)`` in
[0, 2pi), ``alpha = atan2(z, hypot(x, y))``; a panoramic scanner sees the directions with
hybrid ``theta >= pi`` in its second face, ``(theta - pi, pi - alpha)``.

Formats (by extension):

- XYZ/TXT (plain text, read here so that errors name the line), PLY (``plyfile``) and PCD (read
  here: ascii and binary; open3d for ``binary_compressed``): coordinates in scanner space; the
  pose, if any, comes from a poses file (used to match planes across scans).
- PTX (Leica plain text; a file may hold several scans one after another). Each scan starts with
  a 10-line header: columns, rows, the scanner's registered position (3 numbers), its registered
  x, y, z axes (3 lines of 3), and a 4 x 4 transform written row-wise with the translation in its
  last row, so that ``[X Y Z 1] = [x y z 1] M``. Then columns x rows lines ``x y z [intensity
  [r g b]]`` in the scanner's own frame; "0 0 0" marks a direction without return.
  Hence ``R = M[:3, :3]`` and ``S = M[3, :3]`` in tlsjax's ``x = R (X - S)``.
- E57 (``pye57``): each scan's points are read untransformed, in chunks, with the scan's pose
  ``X = Q x + t`` (quaternion Q), so ``R = Q^T``, ``S = t``; points flagged invalid by
  ``cartesianInvalidState``/``sphericalInvalidState`` are dropped and counted.
- LAS/LAZ (``laspy``, LAZ through its ``lazrs`` backend): a LAS file holds *object-space*
  (registered, often map) coordinates. With the scan's pose, from a poses file or from the
  ``tlsjax`` pose record that :func:`~tlsjax._io._las.write_las` stores in the header, the points
  are taken to scanner space by ``x = R (X - S)``; without a pose they are taken as scanner space.

A pose given in a poses file (``poses`` argument) replaces the one stored in the file.

Readers never guess silently: a failure is one ``ValueError`` line naming the file and the cause;
points dropped (non-finite, flagged invalid, exactly at the origin, i.e. "no return") are counted
in :attr:`PointCloudScan.notes`, and so are coordinates that look like a map frame (median range
beyond :data:`MAP_SCALE_RANGE`) without a pose; each note is also issued as a
:class:`PointCloudWarning`.
"""

from __future__ import annotations

import dataclasses
import errno
import io
import os
import warnings

import numpy as np

from .._model._geometry import rotation_matrix, scanner_observations
from .._model._scanner import ARCHITECTURES
from ._outputs import atomic_output
from ._raw_scan import RawScan, pose_from_transform

#: A median range beyond this [m] is not a terrestrial laser scan in its own frame: the
#: coordinates are in a map or project frame and the scan's pose is missing or wrong.
MAP_SCALE_RANGE = 5000.0


class PointCloudWarning(UserWarning):
    """Suspicious content of a point-cloud file (dropped points, map-scale coordinates)."""


@dataclasses.dataclass(frozen=True, eq=False)
class PointCloudScan:
    """One scan read from a file: scanner-space ``points`` (n, 3) [m], their ``observations``
    (n, 3) = (rho [m], theta [rad], alpha [rad]) in ``architecture``, and the ``pose`` (6,) =
    (Xs, Ys, Zs, omega, phi, kappa) stored in the file or given, or None.

    ``index`` (n,): row of each kept point in the scan as stored in the file; ``n_stored``:
    points stored for the scan; ``notes``: what was dropped or looks suspicious, with counts;
    ``frame``: "scanner" when the file holds scanner-space coordinates, "object" when they were
    taken to scanner space with ``pose`` (LAS/LAZ).
    """

    name: str
    source: str
    points: np.ndarray
    observations: np.ndarray
    pose: np.ndarray | None
    architecture: str
    index: np.ndarray | None = None
    n_stored: int = 0
    notes: tuple = ()
    frame: str = "scanner"


def observations_from_points(points, architecture: str = "hybrid") -> np.ndarray:
    """(rho, theta, alpha) of scanner-space points (n, 3) in the convention of ``architecture``."""
    if architecture not in ARCHITECTURES:
        raise ValueError(f"scanner architecture {architecture!r} is not one of {ARCHITECTURES}")
    return scanner_observations(np.asarray(points, dtype=np.float64), architecture, xp=np)


def to_scanner(X, pose) -> np.ndarray:
    """Scanner-space points ``x = R (X - S)`` of object-space points X (n, 3)."""
    R = rotation_matrix(*np.asarray(pose, dtype=np.float64)[3:], xp=np)
    return (np.asarray(X, dtype=np.float64) - pose[:3]) @ R.T


def to_object(x, pose) -> np.ndarray:
    """Object-space points ``X = R^T x + S`` of scanner-space points x (n, 3)."""
    R = rotation_matrix(*np.asarray(pose, dtype=np.float64)[3:], xp=np)
    return np.asarray(x, dtype=np.float64) @ R + pose[:3]


def _finish(raw: RawScan, source: str, architecture: str, pose_given) -> PointCloudScan:
    """Drop and count invalid points, take object-space files to scanner space, check scale."""
    pts = np.asarray(raw.points, dtype=np.float64).reshape(-1, 3)
    n_stored = raw.n_stored if raw.n_stored is not None else len(pts)
    index = raw.index if raw.index is not None else np.arange(len(pts), dtype=np.int64)
    notes = list(raw.notes)
    where = f"{source}: scan {raw.name}"
    finite = np.all(np.isfinite(pts), axis=1)
    if not finite.all():
        notes.append(
            f"{where}: dropped {int((~finite).sum())} point(s) with non-finite coordinates"
        )
    zero = finite & np.all(pts == 0.0, axis=1)
    if zero.any():
        notes.append(
            f"{where}: dropped {int(zero.sum())} point(s) at exactly (0, 0, 0) (no return)"
        )
    keep = finite & ~zero
    pts, index = pts[keep], index[keep]
    if len(pts) == 0:
        why = "; ".join(n.split(": ", 2)[-1] for n in notes)
        raise ValueError(
            f"{where} has no valid points ({n_stored} stored{': ' if why else ''}{why})"
        )
    pose = raw.pose if pose_given is None else np.asarray(pose_given, dtype=np.float64)
    if pose is not None and (pose.shape != (6,) or not np.all(np.isfinite(pose))):
        raise ValueError(f"{where}: the pose must be 6 finite numbers, got {pose}")
    frame = "scanner"
    if raw.object_frame and pose is not None:
        pts, frame = to_scanner(pts, pose), "object"
    median = float(np.median(np.linalg.norm(pts, axis=1)))
    if median > MAP_SCALE_RANGE:
        why = (
            "the pose does not bring them near the scanner"
            if frame == "object"
            else "taken as scanner space without a pose; give the scan's pose (--poses)"
        )
        notes.append(
            f"{where}: {len(pts)} point(s) have a median range of {median:.4g} m, like map "
            f"coordinates: {why}"
        )
    for note in notes:
        warnings.warn(note, PointCloudWarning, stacklevel=3)
    return PointCloudScan(
        raw.name,
        source,
        pts,
        observations_from_points(pts, architecture),
        pose,
        architecture,
        index=index,
        n_stored=int(n_stored),
        notes=tuple(notes),
        frame=frame,
    )


def _numeric_block(
    lines, first_line: int, source: str, skip_comments: bool = False, usecols=(0, 1, 2)
) -> np.ndarray:
    """Numbers ``usecols`` (default the first three) of each line of ``lines`` (list of str;
    the first is file line ``first_line``) as (n, 3). Errors name the file and the line."""
    comments = ("#", "//") if skip_comments else None
    try:
        # One C-level parse of the whole block; commas count as blanks.
        with warnings.catch_warnings():
            warnings.simplefilter(
                "ignore", UserWarning
            )  # "input contained no data": checked by the caller
            arr = np.loadtxt(
                io.StringIO("\n".join(lines).replace(",", " ")),
                usecols=tuple(usecols),
                ndmin=2,
                dtype=np.float64,
                comments=comments,
            )
        if (skip_comments or len(arr) == len(lines)) and np.all(np.isfinite(arr)):
            return arr
    except ValueError:
        pass
    # Slow path, only to name the offending line.
    for k, ln in enumerate(lines):
        text = ln.replace(",", " ")
        if skip_comments and (not text.strip() or text.lstrip().startswith(comments)):
            continue
        fields = text.split()
        where = f"{source}, line {first_line + k}"
        if len(fields) <= max(usecols):
            raise ValueError(
                f"{where}: expected at least {max(usecols) + 1} numbers, found {len(fields)}: "
                f"{ln.strip()!r}"
            )
        try:
            vals = [float(fields[c]) for c in usecols]
        except ValueError:
            raise ValueError(f"{where}: not a number in {ln.strip()!r}") from None
        if not all(np.isfinite(vals)):
            raise ValueError(f"{where}: non-finite coordinate in {ln.strip()!r}")
    raise ValueError(f"{source}: could not read the coordinates")  # pragma: no cover


#: Header names of the intensity column, most specific first (CloudCompare "Intensity" and
#: "Scalar field", RiSCAN PRO "Reflectance" and "Amplitude", PCL "intensity", "I").
INTENSITY_NAMES = ("intensity", "scalar_intensity", "reflectance", "amplitude", "i", "inten")
_COORDINATE_NAMES = {"x": 0, "y": 1, "z": 2, "//x": 0}


@dataclasses.dataclass(frozen=True)
class TextLayout:
    """Where the numbers of a text point file are: ``skip`` lines before the data (header,
    a PTS point count), ``usecols`` (x, y, z[, intensity]) of each data line, ``how``: how the
    columns were told (named by the header, by ``columns``, or by the format)."""

    skip: int
    usecols: tuple
    how: str

    @property
    def has_intensity(self) -> bool:
        return len(self.usecols) == 4


def _tokens(line: str) -> list:
    return [
        t.strip().strip('"').strip("'") for t in line.replace(",", " ").replace(";", " ").split()
    ]


def _is_number(t: str) -> bool:
    try:
        float(t)
        return True
    except ValueError:
        return False


def _name(t: str) -> str:
    """A header name without comment marks, units ("X[m]", "Reflectance(dB)") and case."""
    t = t.lower().lstrip("/#").strip()
    for mark in ("[", "("):
        t = t.split(mark)[0]
    t = t.strip()
    return t[len("scalar_") :] if t.startswith("scalar_") and t != "scalar_intensity" else t


def parse_columns(columns: str, source: str, n: int | None = None) -> tuple:
    """``columns`` ("x,y,z,r,g,b,intensity"; any name other than x, y, z, intensity is
    skipped) as usecols (x, y, z[, intensity])."""
    names = [c.strip().lower() for c in str(columns).split(",")]
    if n is not None and len(names) != n:
        raise ValueError(
            f"{source}: --columns names {len(names)} columns, the file's lines have {n}"
        )
    try:
        cols = [names.index(k) for k in ("x", "y", "z")]
    except ValueError:
        raise ValueError(
            f"{source}: --columns {columns!r} must name x, y and z (e.g. 'x,y,z,r,g,b,intensity')"
        ) from None
    if "intensity" in names:
        cols.append(names.index("intensity"))
    return tuple(cols)


def text_layout(lines, source: str, *, pts: bool = False, columns=None, need_intensity=True):
    """The :class:`TextLayout` of a text point file from its first lines (list of str).

    A header line (``//X Y Z R G B Intensity`` of CloudCompare, ``X,Y,Z,Intensity``, ``# x y z
    reflectance``, RiSCAN's ``X[m] Y[m] Z[m] Reflectance[dB]``) names the columns: x, y and z,
    and the intensity by name (:data:`INTENSITY_NAMES`; red, green and blue are never taken
    for it). Without names: 3 columns are x y z; 4 are x y z intensity; a PTS file (Leica
    Cyclone: a point count, then ``x y z intensity [r g b]``) is read by its format; any other
    count of unnamed columns cannot be told apart (x y z r g b intensity? x y z intensity r g
    b? normals?) and is refused with the fix, ``columns`` (CLI ``--columns``), unless
    ``need_intensity`` is False (then only x y z, the first three in every convention)."""
    k = 0
    header = None
    while k < len(lines):
        t = lines[k].strip()
        if not t:
            k += 1
            continue
        toks = _tokens(t)
        if t.startswith(("#", "//")) or not all(_is_number(x) for x in toks):
            names = [_name(x) for x in toks if _name(x)]
            if {"x", "y", "z"} <= set(names):
                header = names
            elif not t.startswith(("#", "//")):
                raise ValueError(
                    f"{source}, line {k + 1}: neither numbers nor a header naming x, y and z: "
                    f"{t[:80]!r}"
                )
            k += 1
            continue
        if pts and len(toks) == 1 and header is None and k + 1 < len(lines):
            k += 1  # the PTS point count
            continue
        break
    if k >= len(lines):
        raise ValueError(f"{source}: no points")
    n = len(_tokens(lines[k]))
    if columns is not None:
        return TextLayout(k, parse_columns(columns, source, n), "as given by --columns")
    if header is not None:
        if len(header) != n:
            raise ValueError(
                f"{source}, line {k + 1}: the header names {len(header)} columns, the data lines "
                f"have {n}; give them with --columns (e.g. 'x,y,z,r,g,b,intensity')"
            )
        cols = [header.index(c) for c in ("x", "y", "z")]
        inten = next((header.index(c) for c in INTENSITY_NAMES if c in header), None)
        return TextLayout(k, tuple(cols + ([inten] if inten is not None else [])), "by the header")
    if n == 3 or (n == 4 and not pts) or (pts and n in (4, 7)):
        return TextLayout(k, tuple(range(min(n, 4))), "by the column count")
    if not need_intensity:
        return TextLayout(k, (0, 1, 2), "x y z: the first three columns")
    raise ValueError(
        f"{source}: {n} unnamed columns: which holds the intensity cannot be told (x y z r g b "
        "intensity? x y z intensity r g b?); name them, e.g. --columns x,y,z,r,g,b,intensity "
        "(columns='...' in Python), or export the file with a header line"
    )


def _read_text(path, source):
    try:
        with open(path, encoding="utf-8") as fh:
            return fh.read().splitlines()
    except UnicodeDecodeError as err:
        raise ValueError(f"{source}: not a text file ({err.reason} at byte {err.start})") from None


def _read_xyz(path, source, stem):
    lines = _read_text(path, source)
    if not lines:
        raise ValueError(f"{source}: no points")
    pts_format = source.lower().endswith(".pts")
    layout = text_layout(lines[:1000], source, pts=pts_format, need_intensity=False)
    first = layout.skip
    block = [ln.replace(";", " ") for ln in lines[first:]]
    pts = _numeric_block(block, first + 1, source, skip_comments=True, usecols=layout.usecols[:3])
    if len(pts) == 0:
        raise ValueError(f"{source}: no points")
    return [RawScan(stem, pts)]


def _read_ptx(path, source, stem):
    """Scans of a PTX file (several may follow one another), each after its 10-line header. A
    little over 60 lines: the header's fields are checked one by one, each with its own message."""
    lines = _read_text(path, source)
    scans = []
    i = 0
    while True:
        while i < len(lines) and not lines[i].strip():
            i += 1
        if i >= len(lines):
            break
        start = i + 1  # 1-based line of the scan's header
        if len(lines) - i < 10:
            raise ValueError(
                f"{source}, line {start}: PTX header needs 10 lines, the file ends at line {len(lines)}"
            )
        try:
            cols, rows = int(lines[i].split()[0]), int(lines[i + 1].split()[0])
        except (ValueError, IndexError):
            raise ValueError(
                f"{source}, line {start}: PTX scan must start with the number of columns and rows, "
                f"got {lines[i].strip()!r} and {lines[i + 1].strip()!r}"
            ) from None
        if cols <= 0 or rows <= 0:
            raise ValueError(
                f"{source}, line {start}: PTX columns and rows must be positive, got {cols} x {rows}"
            )
        head = []
        for k in range(2, 10):
            want = 3 if k < 6 else 4
            fields = lines[i + k].replace(",", " ").split()
            try:
                vals = [float(f) for f in fields]
            except ValueError:
                vals = []
            if len(vals) != want or not all(np.isfinite(vals)):
                raise ValueError(
                    f"{source}, line {i + k + 1}: PTX header line needs {want} numbers, got "
                    f"{lines[i + k].strip()!r}"
                )
            head.append(vals)
        M = np.array(head[4:8])
        A = M[:3, :3].T  # X = A x + t from the row-vector convention [X 1] = [x 1] M
        if np.abs(A @ A.T - np.eye(3)).max() > 1e-6 or np.linalg.det(A) < 0:
            raise ValueError(
                f"{source}, line {i + 7}: PTX transform's rotation part is not a rotation matrix"
            )
        n = cols * rows
        first = i + 10
        if len(lines) - first < n:
            raise ValueError(
                f"{source}, line {len(lines)}: PTX scan at line {start} needs {n} point lines "
                f"({cols} x {rows}), the file has {len(lines) - first}"
            )
        pts = _numeric_block(lines[first : first + n], first + 1, source)
        scans.append((pts, pose_from_transform(A, M[3, :3])))
        i = first + n
    if not scans:
        raise ValueError(f"{source}: no PTX scan in the file")
    many = len(scans) > 1
    return [
        RawScan(f"{stem}_{k + 1}" if many else stem, p, pose) for k, (p, pose) in enumerate(scans)
    ]


_FORMATS = {
    ".ply": "ply",
    ".pcd": "pcd",
    ".xyz": "xyz",
    ".txt": "xyz",
    ".pts": "xyz",
    ".asc": "xyz",
    ".csv": "xyz",
    ".ptx": "ptx",
    ".e57": "e57",
    ".las": "las",
    ".laz": "las",
}


def point_cloud_format(path) -> str:
    """The format of a point-cloud file by its extension, or a ValueError naming the file."""
    source = os.fspath(path)
    ext = os.path.splitext(source)[1]
    kind = _FORMATS.get(ext.lower())
    if kind is None:
        raise ValueError(
            f"{source}: unknown point-cloud format {ext!r}; accepted: {', '.join(sorted(_FORMATS))}"
        )
    return kind


def _raw_scans(path, source, kind, stem):
    if kind == "xyz":
        return _read_xyz(path, source, stem)
    if kind == "ptx":
        return _read_ptx(path, source, stem)
    if kind == "e57":
        from ._e57 import read_e57

        return read_e57(source, stem)
    if kind == "las":
        from ._las import read_las

        return read_las(source, stem)
    if kind == "pcd":
        from ._pcd import read_pcd

        return read_pcd(source, stem)
    from ._ply import read_ply

    return read_ply(source, stem)


def checked_source(path) -> tuple[str, str, str]:
    """(path as text, format, stem) of a point-cloud file that exists and is not empty; a
    folder, an empty file or an unknown extension is a one-line ValueError."""
    source = os.fspath(path)
    kind = point_cloud_format(source)
    if os.path.isdir(source):
        raise ValueError(f"{source}: is a folder, not a point-cloud file")
    if not os.path.isfile(source):
        raise FileNotFoundError(errno.ENOENT, os.strerror(errno.ENOENT), source)
    if os.path.getsize(source) == 0:
        raise ValueError(f"{source}: the file is empty")
    return source, kind, os.path.splitext(os.path.basename(source))[0]


def read_point_clouds(
    path, *, architecture: str = "hybrid", poses=None
) -> tuple[PointCloudScan, ...]:
    """Read the scans of a point-cloud file (XYZ, PTX, PLY, PCD, E57, LAS, LAZ; by extension).

    Returns one :class:`PointCloudScan` per scan (PTX and E57 files may hold several; they are
    named ``<stem>_1``, ``<stem>_2``, ...; a single scan is named after the file's stem).
    ``poses``: optional mapping scan name -> (Xs, Ys, Zs, omega, phi, kappa) (e.g. from
    :func:`~tlsjax._io._plane_files.read_poses`) that replaces a pose stored in the file. Bad input
    raises one-line ``ValueError`` naming the file (and the line for the text formats); dropped or
    suspicious points are counted in each scan's ``notes`` and issued as
    :class:`PointCloudWarning`.
    """
    if architecture not in ARCHITECTURES:
        raise ValueError(f"scanner architecture {architecture!r} is not one of {ARCHITECTURES}")
    source, kind, stem = checked_source(path)
    poses = poses or {}
    try:
        raws = _raw_scans(path, source, kind, stem)
    except (FileNotFoundError, ImportError, ValueError):
        raise
    except OSError as err:  # permissions, a device error: one line, never a traceback
        raise ValueError(f"{source}: cannot read the file ({err.strerror or err})") from None
    return tuple(_finish(raw, source, architecture, poses.get(raw.name)) for raw in raws)


def write_xyz(path, points) -> None:
    """Write scanner-space points (n, 3) [m] as plain text ``x y z`` with 17 significant digits."""
    with atomic_output(path) as tmp:
        np.savetxt(tmp, np.asarray(points, dtype=np.float64), fmt="%.17g")


def write_ptx(path, scans) -> None:
    """Write scans as one PTX file. ``scans``: list of ``(points (n, 3) scanner space, pose (6,) or
    None)``; each scan is written as n columns x 1 row with intensity 0.5 and 17 digits."""
    with atomic_output(path) as tmp, open(tmp, "w", encoding="utf-8") as fh:
        for points, pose in scans:
            pts = np.asarray(points, dtype=np.float64)
            pose = np.zeros(6) if pose is None else np.asarray(pose, dtype=np.float64)
            A = rotation_matrix(*pose[3:], xp=np).T
            M = np.zeros((4, 4))
            M[:3, :3] = A.T
            M[3, :3] = pose[:3]
            M[3, 3] = 1.0
            fh.write(f"{len(pts)}\n1\n")
            fh.write(" ".join(f"{v:.17g}" for v in pose[:3]) + "\n")
            for row in A.T:  # the scanner's axes in object space: columns of A
                fh.write(" ".join(f"{v:.17g}" for v in row) + "\n")
            for row in M:
                fh.write(" ".join(f"{v:.17g}" for v in row) + "\n")
            np.savetxt(fh, np.column_stack([pts, np.full(len(pts), 0.5)]), fmt="%.17g")
