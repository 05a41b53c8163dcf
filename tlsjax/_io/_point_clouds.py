"""Point-cloud files of single scans, read into scanner-space observations (SPEC sections 1, 11).

A scan's points are taken in the scanner's own frame (x = R (X - S)) and turned into the
observations of the chosen architecture: range ``rho = |x|``, ``theta = atan2(y, x)`` in
[0, 2pi), ``alpha = atan2(z, hypot(x, y))``; a panoramic scanner sees the directions with
hybrid ``theta >= pi`` in its second face, ``(theta - pi, pi - alpha)``.

Formats:

- PLY, PCD (open3d) and XYZ (plain text, read here so that errors name the line): coordinates
  in scanner space, no pose.
- PTX (Leica plain text; a file may hold several scans one after another). Each scan starts with
  a 10-line header: columns, rows, the scanner's registered position (3 numbers), its registered
  x, y, z axes (3 lines of 3), and a 4 x 4 transform written row-wise with the translation in its
  last row, so that ``[X Y Z 1] = [x y z 1] M``. Then columns x rows lines ``x y z [intensity
  [r g b]]`` in the scanner's own frame; "0 0 0" marks a direction without return and is skipped.
  Hence ``R = M[:3, :3]`` and ``S = M[3, :3]`` in tlsjax's ``x = R (X - S)``.
- E57 through ``pye57`` (optional; ``pip install pye57``): each scan's points are read untransformed
  with the scan's pose ``X = Q x + t`` (quaternion Q), so ``R = Q^T``, ``S = t``.
"""

from __future__ import annotations

import dataclasses
import errno
import io
import os
import warnings

import numpy as np

from .._model._geometry import TWO_PI, angles_from_matrix, rotation_matrix, spherical_from_cartesian
from .._model._scanner import ARCHITECTURES


@dataclasses.dataclass(frozen=True, eq=False)
class PointCloudScan:
    """One scan read from a file: scanner-space ``points`` (n, 3) [m], their ``observations``
    (n, 3) = (rho [m], theta [rad], alpha [rad]) in ``architecture``, and the ``pose`` (6,) =
    (Xs, Ys, Zs, omega, phi, kappa) stored in the file, or None."""

    name: str
    source: str
    points: np.ndarray
    observations: np.ndarray
    pose: np.ndarray | None
    architecture: str


def observations_from_points(points, architecture: str = "hybrid") -> np.ndarray:
    """(rho, theta, alpha) of scanner-space points (n, 3) in the convention of ``architecture``."""
    if architecture not in ARCHITECTURES:
        raise ValueError(f"scanner architecture {architecture!r} is not one of {ARCHITECTURES}")
    x = np.asarray(points, dtype=np.float64)
    hyb = spherical_from_cartesian(x, xp=np)
    hyb[:, 1] = np.where(hyb[:, 1] >= TWO_PI, 0.0, hyb[:, 1])
    if architecture == "hybrid":
        return hyb
    face2 = hyb[:, 1] >= np.pi
    out = hyb.copy()
    out[:, 1] = np.where(face2, hyb[:, 1] - np.pi, hyb[:, 1])
    out[:, 2] = np.where(face2, np.pi - hyb[:, 2], hyb[:, 2])
    return out


def _pose_from_transform(R_obj_from_scanner, translation) -> np.ndarray:
    """EOP (S, omega, phi, kappa) of ``X = A x + t``: ``R = A^T``, ``S = t``."""
    return np.concatenate(
        [
            np.asarray(translation, dtype=np.float64),
            angles_from_matrix(np.asarray(R_obj_from_scanner).T),
        ]
    )


def _scan(name, source, points, pose, architecture):
    if len(points) == 0:
        raise ValueError(f"{source}: scan {name} has no points")
    if not np.all(np.isfinite(points)):
        raise ValueError(f"{source}: scan {name} has non-finite coordinates")
    if np.any(np.all(points == 0.0, axis=1)):
        raise ValueError(f"{source}: scan {name} has points at the scanner origin (range 0)")
    return PointCloudScan(
        name, source, points, observations_from_points(points, architecture), pose, architecture
    )


def _numeric_block(lines, first_line: int, source: str, skip_comments: bool = False) -> np.ndarray:
    """First three numbers of each line of ``lines`` (list of str; the first is file line
    ``first_line``) as (n, 3). Errors name the file and the line."""
    comments = ("#", "//") if skip_comments else None
    try:
        # One C-level parse of the whole block; commas count as blanks.
        with warnings.catch_warnings():
            warnings.simplefilter(
                "ignore", UserWarning
            )  # "input contained no data": checked by the caller
            arr = np.loadtxt(
                io.StringIO("\n".join(lines).replace(",", " ")),
                usecols=(0, 1, 2),
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
        if len(fields) < 3:
            raise ValueError(
                f"{where}: expected at least 3 numbers, found {len(fields)}: {ln.strip()!r}"
            )
        try:
            vals = [float(f) for f in fields[:3]]
        except ValueError:
            raise ValueError(f"{where}: not a number in {ln.strip()!r}") from None
        if not all(np.isfinite(vals)):
            raise ValueError(f"{where}: non-finite coordinate in {ln.strip()!r}")
    raise ValueError(f"{source}: could not read the coordinates")  # pragma: no cover


def _read_xyz(path, source):
    with open(path, encoding="utf-8") as fh:
        lines = fh.read().splitlines()
    pts = _numeric_block(lines, 1, source, skip_comments=True) if lines else np.zeros((0, 3))
    if len(pts) == 0:
        raise ValueError(f"{source}: no points")
    return pts


def _read_open3d(path, source):
    try:
        import open3d as o3d
    except ImportError as err:
        raise ImportError(
            f"{source}: reading PLY/PCD needs open3d: pip install 'tlsjax[open3d]' ({err})"
        ) from err
    cloud = o3d.io.read_point_cloud(source)
    pts = np.asarray(cloud.points, dtype=np.float64)
    if len(pts) == 0:
        raise ValueError(
            f"{source}: open3d read no points (not a valid point-cloud file, or empty)"
        )
    return pts


def _read_ptx(path, source, architecture, stem):
    with open(path, encoding="utf-8") as fh:
        lines = fh.read().splitlines()
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
        pts = pts[~np.all(pts == 0.0, axis=1)]
        scans.append((pts, _pose_from_transform(A, M[3, :3])))
        i = first + n
    if not scans:
        raise ValueError(f"{source}: no PTX scan in the file")
    many = len(scans) > 1
    return tuple(
        _scan(f"{stem}_{k + 1}" if many else stem, source, p, pose, architecture)
        for k, (p, pose) in enumerate(scans)
    )


def _read_e57(path, source, architecture, stem):
    try:
        import pye57
    except ImportError as err:
        raise ImportError(
            f"{source}: reading E57 needs the pye57 package: pip install pye57 ({err})"
        ) from err
    try:
        e57 = pye57.E57(source)
    except Exception as err:  # libE57 raises its own exception type
        raise ValueError(f"{source}: not a readable E57 file ({err})") from None
    out = []
    try:
        n = e57.scan_count
        for k in range(n):
            header = e57.get_header(k)
            data = e57.read_scan(k, transform=False, ignore_missing_fields=True)
            if "cartesianX" in data:
                pts = np.stack([data["cartesianX"], data["cartesianY"], data["cartesianZ"]], axis=1)
            elif "sphericalRange" in data:
                r, az, el = (
                    data["sphericalRange"],
                    data["sphericalAzimuth"],
                    data["sphericalElevation"],
                )
                pts = np.stack(
                    [r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)],
                    axis=1,
                )
            else:
                raise ValueError(
                    f"{source}: scan {k} has neither Cartesian nor spherical coordinates"
                )
            pts = np.asarray(pts, dtype=np.float64)
            pts = pts[~np.all(pts == 0.0, axis=1)]
            pose = (
                _pose_from_transform(header.rotation_matrix, header.translation)
                if header.has_pose()
                else None
            )
            name = f"{stem}_{k + 1}" if n > 1 else stem
            out.append(_scan(name, source, pts, pose, architecture))
    finally:
        e57.close()
    if not out:
        raise ValueError(f"{source}: no scans in the E57 file")
    return tuple(out)


_FORMATS = {
    ".ply": "open3d",
    ".pcd": "open3d",
    ".xyz": "xyz",
    ".txt": "xyz",
    ".ptx": "ptx",
    ".e57": "e57",
}


def read_point_clouds(path, *, architecture: str = "hybrid") -> tuple[PointCloudScan, ...]:
    """Read the scans of a point-cloud file (PLY, PCD, XYZ, PTX, E57; by extension).

    Returns one :class:`PointCloudScan` per scan (PTX and E57 files may hold several; they are
    named ``<stem>_1``, ``<stem>_2``, ...; a single scan is named after the file's stem). Bad
    input raises ``ValueError`` naming the file (and the line for the text formats).
    """
    if architecture not in ARCHITECTURES:
        raise ValueError(f"scanner architecture {architecture!r} is not one of {ARCHITECTURES}")
    source = os.fspath(path)
    if not os.path.isfile(source):
        raise FileNotFoundError(errno.ENOENT, os.strerror(errno.ENOENT), source)
    stem, ext = os.path.splitext(os.path.basename(source))
    kind = _FORMATS.get(ext.lower())
    if kind is None:
        raise ValueError(
            f"{source}: unknown point-cloud format {ext!r}; accepted: {', '.join(sorted(_FORMATS))}"
        )
    if kind == "ptx":
        return _read_ptx(path, source, architecture, stem)
    if kind == "e57":
        return _read_e57(path, source, architecture, stem)
    pts = _read_xyz(path, source) if kind == "xyz" else _read_open3d(path, source)
    return (_scan(stem, source, pts, None, architecture),)


def write_xyz(path, points) -> None:
    """Write scanner-space points (n, 3) [m] as plain text ``x y z`` with 17 significant digits."""
    np.savetxt(path, np.asarray(points, dtype=np.float64), fmt="%.17g")


def write_ptx(path, scans) -> None:
    """Write scans as one PTX file. ``scans``: list of ``(points (n, 3) scanner space, pose (6,) or
    None)``; each scan is written as n columns x 1 row with intensity 0.5 and 17 digits."""
    with open(path, "w", encoding="utf-8") as fh:
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
