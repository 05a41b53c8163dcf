"""Plane extraction from scans and matching of planes across scans (host side, numpy + open3d).

Extraction works per scan in scanner space, before any calibration, as in Chow et al. 2013
(section 3: planes segmented in each scan, outliers removed in scanner space, then the points of
each plane observed in each scan enter the plane-based adjustment, Lichti 2007):

1. RANSAC (open3d ``segment_plane``) finds the plane with most inliers among the points left,
   drawing its samples from the points whose neighbourhood is locally planar (surface variation,
   Pauly et al. 2002), so that clutter does not hide small planes;
2. the inliers are split into disjoint patches by DBSCAN (open3d ``cluster_dbscan``) on the unit
   line-of-sight vectors: points of one plane patch are neighbours in the scanner's angular grid,
   whatever their range, so one density threshold (a few grid steps) serves near and far;
3. each patch is refined by a least-squares plane (eigenvector of the smallest eigenvalue of the
   points' covariance) with iterated rejection of points whose orthogonal distance exceeds
   ``rejection`` times the RMS; rejected points stay available to later planes;
4. patches with too few points, too narrow to define a plane (a strip along an edge of two
   planes) or too thick to be a surface (a slab of scattered points) are dropped; the rest is downsampled to a point budget with a seeded generator.

Matching turns every patch into object space with the scan poses, ``n = R^T n_s``,
``d = d_s + n . S`` (from ``x = R (X - S)``), and joins patches (union-find) whose normals agree
within ``max_angle``, whose centroids lie within ``max_offset`` of each other's plane and whose
points come within ``overlap_distance`` of each other. Each joined set is one global plane.

Normals point towards the scanner that saw the patch (``n . 0 - d > 0`` in scanner space), so the
faces of a room get inward normals, as in the simulation.
"""

from __future__ import annotations

import argparse
import dataclasses
import os
from typing import Sequence

import numpy as np

from ._geometry import cartesian_from_spherical, rotation_matrix
from ._io import UNITS, ObservationTable, _Located, _number, _read_rows, parse_unit_column

DEG = np.pi / 180.0


@dataclasses.dataclass(frozen=True)
class ExtractionConfig:
    """Settings of the per-scan plane extraction (lengths in metres).

    ``distance_threshold``: RANSAC inlier distance; it must cover noise and the plane's
    distortion by the uncalibrated systematic errors (a 10 mm range offset bends a plane by up to
    10 mm). ``min_points``: smallest patch kept. ``min_extent``: smallest RMS spread of a patch
    along its shorter in-plane axis. ``max_rms``: largest RMS of the orthogonal distances after
    refinement; a slab of scattered points (vegetation, clutter, people) fills the RANSAC
    threshold evenly and has an RMS near ``distance_threshold / sqrt(3)``, a surface a few mm.
    ``max_rounds``: most RANSAC rounds per scan. RANSAC draws its samples only from points
    whose ``planarity_neighbours`` nearest neighbours have a surface variation
    ``lambda_0 / sum(lambda)`` of at most ``max_surface_variation``. ``cluster_steps``: DBSCAN radius in median angular grid
    spacings. ``rejection``: outlier threshold in RMS of the orthogonal distances.
    ``budget``: most points kept per patch (None keeps all).
    """

    distance_threshold: float = 0.03
    ransac_iterations: int = 1000
    max_rounds: int = 200
    min_points: int = 30
    min_extent: float = 0.05
    max_rms: float = 0.01
    planarity_neighbours: int = 10
    max_surface_variation: float = 0.05
    cluster_steps: float = 5.0
    cluster_min_points: int = 4
    rejection: float = 3.0
    budget: int | None = None

    def __post_init__(self):
        for name in ("distance_threshold", "min_extent", "max_rms", "cluster_steps", "rejection"):
            v = getattr(self, name)
            if not (np.isfinite(v) and v > 0):
                raise ValueError(f"ExtractionConfig.{name} must be positive, got {v}")
        if not 0 < self.max_surface_variation <= 1.0 / 3.0:
            raise ValueError(f"ExtractionConfig.max_surface_variation must be in (0, 1/3], got {self.max_surface_variation}")
        for name in ("ransac_iterations", "max_rounds", "min_points", "cluster_min_points", "planarity_neighbours"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"ExtractionConfig.{name} must be a positive integer, got {getattr(self, name)}")
        if self.min_points < 3:
            raise ValueError(f"ExtractionConfig.min_points must be at least 3, got {self.min_points}")
        if self.budget is not None and int(self.budget) < 3:
            raise ValueError(f"ExtractionConfig.budget must be None or at least 3 points, got {self.budget}")


@dataclasses.dataclass(frozen=True)
class MatchingConfig:
    """Thresholds for joining patches into global planes: ``max_angle`` [rad] between normals,
    ``max_offset`` [m] of a centroid from the other plane, ``overlap_distance`` h [m] between
    the nearest points of two patches, tested on a voxel grid of size h (patches closer than h
    are always joined, patches farther apart than 2 sqrt(3) h never; ``None`` skips the test)."""

    max_angle: float = 3.0 * DEG
    max_offset: float = 0.05
    overlap_distance: float | None = 0.5

    def __post_init__(self):
        if not (0 < self.max_angle < np.pi / 2):
            raise ValueError(f"MatchingConfig.max_angle must be in (0, 90 deg), got {self.max_angle / DEG:g} deg")
        if not self.max_offset > 0:
            raise ValueError(f"MatchingConfig.max_offset must be positive, got {self.max_offset}")
        if self.overlap_distance is not None and not self.overlap_distance > 0:
            raise ValueError(f"MatchingConfig.overlap_distance must be positive or None, got {self.overlap_distance}")


@dataclasses.dataclass(frozen=True, eq=False)
class ExtractedPlanes:
    """Plane patches of a set of scans and the points kept on them.

    Per patch p: ``patch_scan[p]`` (scan index), ``patch_normal[p]`` and ``patch_distance[p]``
    in scanner space (``n . x = d``), ``patch_rms[p]`` [m] of the orthogonal distances,
    ``patch_inliers[p]`` (points after refinement, before the budget), ``patch_plane[p]`` (global
    plane index, -1 before matching). Per kept point i: ``point_patch[i]``, ``point_index[i]``
    (row in its scan's input), ``observations[i]`` (rho, theta, alpha) and ``incidence[i]``
    [rad]. After matching: ``poses`` (s, 6) and ``planes`` (g, 4) = (n, d) in object space,
    fitted to all points of each global plane.
    """

    scans: tuple
    patch_scan: np.ndarray
    patch_normal: np.ndarray
    patch_distance: np.ndarray
    patch_rms: np.ndarray
    patch_inliers: np.ndarray
    patch_plane: np.ndarray
    point_patch: np.ndarray
    point_index: np.ndarray
    observations: np.ndarray
    incidence: np.ndarray
    poses: np.ndarray | None = None
    planes: np.ndarray | None = None

    @property
    def point_plane(self) -> np.ndarray:
        """Global plane index of every kept point (-1 before matching)."""
        return self.patch_plane[self.point_patch]

    @property
    def point_scan(self) -> np.ndarray:
        return self.patch_scan[self.point_patch]

    def to_table(self) -> ObservationTable:
        """Plane observations (SPEC section 11): one row per kept point of a matched plane.

        Planes are named ``P1``, ``P2``, ... in the order of ``planes``.
        """
        if self.planes is None:
            raise ValueError("planes are not matched across scans yet: call match_planes(planes, poses) first")
        plane = self.point_plane
        keep = plane >= 0
        scans = tuple(self.scans[s] for s in self.point_scan[keep])
        prims = tuple(f"P{g + 1}" for g in plane[keep])
        return ObservationTable(kind="plane", source="<extracted planes>", scans=scans, primitives=prims,
                                observations=self.observations[keep], sigmas=None,
                                incidence=self.incidence[keep], instruments=None,
                                rows=np.arange(2, int(keep.sum()) + 2, dtype=np.int64))


def _require_open3d():
    try:
        import open3d as o3d
    except ImportError as err:  # also raised when a system library of open3d is missing
        raise ImportError(f"plane extraction needs open3d: pip install 'tlsjax[open3d]' ({err})") from err
    return o3d


def _fit_plane(x):
    """Least-squares plane of points x (n, 3): unit normal, d, eigenvalues (ascending)."""
    c = x.mean(axis=0)
    w, V = np.linalg.eigh(np.cov((x - c).T, bias=True))
    n = V[:, 0]
    return n, float(n @ c), w


def _refine(x, rejection, max_iter=20):
    """Iterated least-squares plane with rejection beyond ``rejection`` x RMS: (mask, n, d, rms, eig)."""
    keep = np.ones(len(x), dtype=bool)
    for _ in range(max_iter):
        n, d, w = _fit_plane(x[keep])
        r = x @ n - d
        rms = float(np.sqrt(np.mean(r[keep] ** 2)))
        new = np.abs(r) <= rejection * max(rms, 1e-12)
        if new.sum() < 3 or np.array_equal(new, keep):
            break
        keep = new
    n, d, w = _fit_plane(x[keep])
    rms = float(np.sqrt(np.mean((x[keep] @ n - d) ** 2)))
    return keep, n, d, rms, w


def _extract_scan(o3d, obs, config: ExtractionConfig, seed_seq):
    """Patches of one scan: list of (indices, n, d, rms)."""
    x = cartesian_from_spherical(np.asarray(obs, dtype=np.float64), xp=np)
    rho = np.linalg.norm(x, axis=1)
    u = x / rho[:, None]
    o3d.utility.random.seed(int(seed_seq.generate_state(1)[0] % (2**31 - 1)))
    # Median angular spacing of the grid: DBSCAN radius on the unit sphere.
    unit = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(u))
    spacing = float(np.median(np.asarray(unit.compute_nearest_neighbor_distance())))
    eps = config.cluster_steps * max(spacing, 1e-9)

    # Surface variation lambda_0 / (lambda_0 + lambda_1 + lambda_2) of each point's k nearest
    # neighbours (Pauly et al. 2002): near 0 on a surface, near 1/3 in scattered clutter. RANSAC
    # samples only the points that look planar, so that a small board is not drowned by
    # clutter; the inliers are then taken among all points left.
    full = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(x))
    full.estimate_covariances(o3d.geometry.KDTreeSearchParamKNN(config.planarity_neighbours))
    lam = np.linalg.eigvalsh(np.asarray(full.covariances))
    planar = lam[:, 0] <= config.max_surface_variation * np.maximum(lam.sum(axis=1), 1e-300)

    # pool: points not yet on a patch; tried: points that were inliers of a RANSAC round once.
    # Only untried points seed RANSAC (so every round makes progress), but any pooled point can
    # join a later plane: a slab of clutter that cuts through a board takes no board points.
    pool = np.ones(len(x), dtype=bool)
    tried = np.zeros(len(x), dtype=bool)
    patches = []
    for _ in range(config.max_rounds):
        cand = np.flatnonzero(pool & planar & ~tried)
        if len(cand) < config.min_points:
            break
        cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(x[cand]))
        model, inl = cloud.segment_plane(config.distance_threshold, 3, config.ransac_iterations)
        if len(inl) < config.min_points:
            break
        tried[cand[np.asarray(inl, dtype=np.int64)]] = True
        model = np.asarray(model, dtype=np.float64)
        model /= np.linalg.norm(model[:3])
        idx = np.flatnonzero(pool)
        inl = idx[np.abs(x[idx] @ model[:3] + model[3]) <= config.distance_threshold]
        tried[inl] = True
        sphere = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(u[inl]))
        labels = np.asarray(sphere.cluster_dbscan(eps, config.cluster_min_points))
        for lab in np.unique(labels[labels >= 0]):
            members = inl[labels == lab]
            if len(members) < config.min_points:
                continue
            keep, n, d, rms, w = _refine(x[members], config.rejection)
            # A strip along the edge of two planes fits any plane through that edge.
            if keep.sum() < config.min_points or np.sqrt(max(w[1], 0.0)) < config.min_extent or rms > config.max_rms:
                continue
            pool[members[keep]] = False
            if d > 0:  # normal towards the scanner at the origin
                n, d = -n, -d
            patches.append((members[keep], n, d, rms))
    return patches


def extract_planes(scans: Sequence, config: ExtractionConfig | None = None, *, names: Sequence[str] | None = None,
                   seed: int = 0) -> ExtractedPlanes:
    """Extract plane patches from each scan's observations (see the module docstring).

    ``scans``: one (n_j, 3) array of (rho [m], theta [rad], alpha [rad]) per scan, hybrid or
    panoramic (both faces map to the same scanner-space point). ``names``: scan names (default
    S1, S2, ...). ``seed`` makes RANSAC and the budget sampling repeatable.
    """
    o3d = _require_open3d()
    config = config or ExtractionConfig()
    names = tuple(names) if names is not None else tuple(f"S{j + 1}" for j in range(len(scans)))
    if len(names) != len(scans):
        raise ValueError(f"{len(names)} scan names for {len(scans)} scans")
    root = np.random.SeedSequence(seed)
    children = root.spawn(len(scans))
    p_scan, p_n, p_d, p_rms, p_cnt, pt_patch, pt_index, pt_obs, pt_inc = [], [], [], [], [], [], [], [], []
    for j, (obs, ss) in enumerate(zip(scans, children)):
        obs = np.asarray(obs, dtype=np.float64)
        if obs.ndim != 2 or obs.shape[1] != 3 or not np.all(np.isfinite(obs)):
            raise ValueError(f"scan {names[j]}: observations must be a finite (n, 3) array of (rho, theta, alpha)")
        ransac_seed, budget_seed = ss.spawn(2)
        rng = np.random.default_rng(budget_seed)
        x = cartesian_from_spherical(obs, xp=np)
        for members, n, d, rms in _extract_scan(o3d, obs, config, ransac_seed):
            sel = members
            if config.budget is not None and len(members) > config.budget:
                sel = np.sort(rng.choice(members, size=int(config.budget), replace=False))
            p = len(p_scan)
            p_scan.append(j)
            p_n.append(n)
            p_d.append(d)
            p_rms.append(rms)
            p_cnt.append(len(members))
            pt_patch.append(np.full(len(sel), p))
            pt_index.append(sel)
            pt_obs.append(obs[sel])
            xs = x[sel]
            pt_inc.append(np.arccos(np.clip(np.abs(xs @ n) / np.linalg.norm(xs, axis=1), 0.0, 1.0)))
    def cat(parts, empty_shape):
        return np.concatenate(parts) if parts else np.zeros(empty_shape)

    return ExtractedPlanes(
        scans=names,
        patch_scan=np.asarray(p_scan, dtype=np.int64),
        patch_normal=np.asarray(p_n, dtype=np.float64).reshape(-1, 3),
        patch_distance=np.asarray(p_d, dtype=np.float64),
        patch_rms=np.asarray(p_rms, dtype=np.float64),
        patch_inliers=np.asarray(p_cnt, dtype=np.int64),
        patch_plane=np.full(len(p_scan), -1, dtype=np.int64),
        point_patch=cat(pt_patch, (0,)).astype(np.int64),
        point_index=cat(pt_index, (0,)).astype(np.int64),
        observations=cat(pt_obs, (0, 3)),
        incidence=cat(pt_inc, (0,)),
    )


def _union_find(n, edges):
    parent = np.arange(n)

    def find(a):
        while parent[a] != a:
            parent[a] = parent[parent[a]]
            a = parent[a]
        return a

    for a, b in edges:
        ra, rb = find(a), find(b)
        if ra != rb:
            parent[max(ra, rb)] = min(ra, rb)
    return np.array([find(a) for a in range(n)])


def match_planes(planes: ExtractedPlanes, poses, config: MatchingConfig | None = None) -> ExtractedPlanes:
    """Join the patches of all scans into global planes, given scan poses (s, 6) =
    (Xs, Ys, Zs, omega, phi, kappa) with ``x = R (X - S)`` (SPEC section 1).

    Returns a copy with ``patch_plane``, ``poses`` and ``planes`` (object space, fitted to all
    points of each plane; normals oriented like the largest patch) set. Planes are numbered by
    decreasing number of kept points.
    """
    config = config or MatchingConfig()
    poses = np.asarray(poses, dtype=np.float64)
    if poses.shape != (len(planes.scans), 6) or not np.all(np.isfinite(poses)):
        raise ValueError(f"poses must be a finite ({len(planes.scans)}, 6) array "
                         f"(Xs, Ys, Zs, omega, phi, kappa), got shape {poses.shape}")
    P = len(planes.patch_scan)
    R = np.stack([rotation_matrix(*p[3:], xp=np) for p in poses]) if len(poses) else np.zeros((0, 3, 3))
    # Object-space points of the kept observations: X = R^T x + S.
    x = cartesian_from_spherical(planes.observations, xp=np)
    s_pt = planes.point_scan
    X = np.einsum("mji,mj->mi", R[s_pt], x) + poses[s_pt, :3]
    N = np.einsum("pji,pj->pi", R[planes.patch_scan], planes.patch_normal)
    D = planes.patch_distance + np.einsum("pi,pi->p", N, poses[planes.patch_scan, :3])
    C = np.zeros((P, 3))
    np.add.at(C, planes.point_patch, X)
    C /= np.maximum(np.bincount(planes.point_patch, minlength=P), 1)[:, None]

    # Candidate pairs by orientation and offset, all pairs at once.
    cos = N @ N.T
    angle_ok = np.abs(cos) >= np.cos(config.max_angle)
    off_ij = np.abs(C @ N.T - D[None, :])  # centroid i from plane j
    close = angle_ok & (np.maximum(off_ij, off_ij.T) <= config.max_offset)
    iu, ju = np.nonzero(np.triu(close, 1))
    if config.overlap_distance is None:
        edges = list(zip(iu, ju))
    else:
        # Overlap on a voxel grid of size h: nearest points closer than h always fall in
        # neighbouring voxels, and neighbouring voxels are never more than 2 sqrt(3) h apart.
        h = config.overlap_distance
        cell = np.floor(X / h).astype(np.int64)
        cell -= cell.min(axis=0) - 1 if len(cell) else 0
        span = cell.max(axis=0) + 2 if len(cell) else np.ones(3, dtype=np.int64)
        key = (cell[:, 0] * span[1] + cell[:, 1]) * span[2] + cell[:, 2]
        offsets = np.array([(a * span[1] + b) * span[2] + c for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1)])
        keys = [np.unique(key[planes.point_patch == p]) for p in range(P)]
        edges = [(a, b) for a, b in zip(iu, ju)
                 if np.isin(keys[b], (keys[a][:, None] + offsets[None, :]).ravel()).any()]
    roots = _union_find(P, edges)
    uniq, group = np.unique(roots, return_inverse=True)
    counts = np.bincount(group[planes.point_patch], minlength=len(uniq))
    order = np.argsort(-counts, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    patch_plane = rank[group]

    params = np.zeros((len(uniq), 4))
    point_plane = patch_plane[planes.point_patch]
    for g in range(len(uniq)):
        n, d, _ = _fit_plane(X[point_plane == g])
        members = np.flatnonzero(patch_plane == g)
        ref = members[np.argmax(planes.patch_inliers[members])]
        if n @ N[ref] < 0:
            n, d = -n, -d
        params[g] = (*n, d)
    return dataclasses.replace(planes, patch_plane=patch_plane, poses=poses, planes=params)


# ---------------------------------------------------------------------------------------------
# Files: the .npz of extracted planes, and a poses CSV.

_NPZ_ARRAYS = ("patch_scan", "patch_normal", "patch_distance", "patch_rms", "patch_inliers", "patch_plane",
               "point_patch", "point_index", "observations", "incidence")
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
        raise ValueError(f"{source}: not a tlsjax planes .npz file (missing format tag {_NPZ_FORMAT!r})")
    missing = [k for k in _NPZ_ARRAYS + ("scans",) if k not in data]
    if missing:
        raise ValueError(f"{source}: missing arrays {', '.join(missing)}")
    return ExtractedPlanes(scans=tuple(str(s) for s in data["scans"]),
                           **{k: data[k] for k in _NPZ_ARRAYS},
                           poses=data.get("poses"), planes=data.get("planes"))


_POSE_NUMERIC = ("x", "y", "z", "omega", "phi", "kappa")


def read_poses(path) -> dict[str, np.ndarray]:
    """Scan poses CSV: columns ``scan, x_<len>, y_<len>, z_<len>, omega_<ang>, phi_<ang>,
    kappa_<ang>`` (units as in SPEC section 11, e.g. ``x_m``, ``omega_deg``), meaning
    ``x = R3(kappa) R2(phi) R1(omega) (X - S)``. Returns scan -> (Xs, Ys, Zs, omega, phi, kappa)."""
    source = os.fspath(path)
    loc = _Located(source)
    header_line, names, data = _read_rows(path, loc)
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
                raise loc.error(f"unknown column '{name}'; accepted: scan, " + ", ".join(q + "_<unit>" for q in _POSE_NUMERIC),
                                header_line, name)
            want = "length" if key in ("x", "y", "z") else "angle"
            if UNITS[unit][0] != want:
                raise loc.error(f"'{key}' is an {want} but '_{unit}' is a unit of {UNITS[unit][0]}", header_line, name)
        if key in columns:
            raise loc.error(f"'{key}' given twice", header_line, name)
        columns[key] = (i, name, factor)
    for q in ("scan",) + _POSE_NUMERIC:
        if q not in columns:
            raise loc.error("missing required column", header_line, q if q == "scan" else q + "_<unit>")
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
        poses[scan] = np.array([_number(fields[columns[q][0]], line, columns[q][1], loc, True) * columns[q][2]
                                for q in _POSE_NUMERIC])
    if not poses:
        raise loc.error("no data rows after the header", header_line + 1)
    return poses


# ---------------------------------------------------------------------------------------------
# Command line: tlsjax extract-planes SCANS... --out planes.npz


def add_extract_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``extract-planes`` sub-command to an argparse ``subparsers`` object."""
    p = subparsers.add_parser(
        "extract-planes", help="extract and match planes from point clouds",
        description="Extract planes from scans (PLY/PCD/XYZ/PTX/E57, coordinates in scanner space), match "
                    "them across scans with the scan poses, write them as .npz and optionally as a plane "
                    "observation CSV.")
    p.add_argument("scans", nargs="+", help="point-cloud files, one scan each (PTX/E57 files may hold several)")
    p.add_argument("--out", required=True, help="output .npz of the extracted planes")
    p.add_argument("--poses", help="scan poses CSV (scan, x_m, y_m, z_m, omega_deg, phi_deg, kappa_deg); "
                                   "default: the poses stored in the files")
    p.add_argument("--architecture", choices=("hybrid", "panoramic"), default="hybrid")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--budget", type=int, default=None, help="most points kept per plane patch")
    p.add_argument("--distance-threshold", type=float, default=ExtractionConfig.distance_threshold,
                   help="RANSAC inlier distance [m]")
    p.add_argument("--min-points", type=int, default=ExtractionConfig.min_points)
    p.add_argument("--csv", help="also write the plane observations CSV (SPEC section 11)")
    p.set_defaults(func=cli_extract)
    return p


def cli_extract(args) -> int:
    """Run ``tlsjax extract-planes``; returns the exit code."""
    import sys

    from ._io import write_observations
    from ._pointclouds import read_point_clouds

    clouds = []
    for path in args.scans:
        clouds.extend(read_point_clouds(path, architecture=args.architecture))
    names = [c.name for c in clouds]
    if len(set(names)) != len(names):
        raise ValueError(f"scan names are not unique: {names}")
    if args.poses:
        table = read_poses(args.poses)
        missing = [n for n in names if n not in table]
        if missing:
            raise ValueError(f"{args.poses}: no pose for scan(s) {', '.join(missing)}")
        poses = np.stack([table[n] for n in names])
    elif all(c.pose is not None for c in clouds):
        poses = np.stack([c.pose for c in clouds])
    elif len(clouds) == 1:
        poses = np.zeros((1, 6))  # one scan: its own frame is object space
    else:
        poses = None
    if poses is None and args.csv:
        raise ValueError("matching planes across scans needs scan poses: give --poses poses.csv")
    config = ExtractionConfig(distance_threshold=args.distance_threshold, min_points=args.min_points,
                              budget=args.budget)
    planes = extract_planes([c.observations for c in clouds], config, names=names, seed=args.seed)
    if poses is not None:
        planes = match_planes(planes, poses)
    save_planes(args.out, planes)
    if args.csv:
        write_observations(args.csv, planes.to_table())
    matched = "not matched (no scan poses: give --poses)" if planes.planes is None else f"{len(planes.planes)} planes"
    print(f"{len(names)} scan(s), {len(planes.patch_scan)} patches, {matched}, "
          f"{len(planes.point_patch)} points -> {args.out}", file=sys.stdout)
    return 0
