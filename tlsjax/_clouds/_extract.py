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

import dataclasses
from collections.abc import Sequence

import numpy as np

from .._io._extracted import ExtractedPlanes
from .._model._geometry import cartesian_from_spherical, fit_plane
from .._optional import require
from .._summary import Settings


@dataclasses.dataclass(frozen=True)
class ExtractionOptions(Settings):
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
                raise ValueError(f"ExtractionOptions.{name} must be positive, got {v}")
        if not 0 < self.max_surface_variation <= 1.0 / 3.0:
            raise ValueError(
                f"ExtractionOptions.max_surface_variation must be in (0, 1/3], got {self.max_surface_variation}"
            )
        for name in (
            "ransac_iterations",
            "max_rounds",
            "min_points",
            "cluster_min_points",
            "planarity_neighbours",
        ):
            if int(getattr(self, name)) < 1:
                raise ValueError(
                    f"ExtractionOptions.{name} must be a positive integer, got {getattr(self, name)}"
                )
        if self.min_points < 3:
            raise ValueError(
                f"ExtractionOptions.min_points must be at least 3, got {self.min_points}"
            )
        if self.budget is not None and int(self.budget) < 3:
            raise ValueError(
                f"ExtractionOptions.budget must be None or at least 3 points, got {self.budget}"
            )


def _require_open3d():
    # A missing system library (libusb, libGL, libgomp) is named with its Debian package.
    return require("open3d", "plane extraction")


def _refine(x, rejection, max_iter=20):
    """Iterated least-squares plane with rejection beyond ``rejection`` x RMS: (mask, n, d, rms, eig)."""
    keep = np.ones(len(x), dtype=bool)
    for _ in range(max_iter):
        n, d, w = fit_plane(x[keep])
        r = x @ n - d
        rms = float(np.sqrt(np.mean(r[keep] ** 2)))
        new = np.abs(r) <= rejection * max(rms, 1e-12)
        if new.sum() < 3 or np.array_equal(new, keep):
            break
        keep = new
    n, d, w = fit_plane(x[keep])
    rms = float(np.sqrt(np.mean((x[keep] @ n - d) ** 2)))
    return keep, n, d, rms, w


def _extract_scan(o3d, obs, config: ExtractionOptions, seed_seq, bar=None):
    """Patches of one scan: list of (indices, n, d, rms); ``bar`` (tqdm) counts the points
    assigned to patches or left over.

    (A little over 60 lines: the RANSAC rounds, clustering and refit of one scan as one loop,
    which reads best in one place.)
    """
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
            if (
                keep.sum() < config.min_points
                or np.sqrt(max(w[1], 0.0)) < config.min_extent
                or rms > config.max_rms
            ):
                continue
            pool[members[keep]] = False
            if bar is not None:
                bar.update(int(keep.sum()))
            if d > 0:  # normal towards the scanner at the origin
                n, d = -n, -d
            patches.append((members[keep], n, d, rms))
    if bar is not None:
        bar.update(int(pool.sum()))  # the rest: clutter, edges, planes too small
    return patches


def extract_planes(
    scans: Sequence,
    options: ExtractionOptions | None = None,
    *,
    names: Sequence[str] | None = None,
    seed: int = 0,
    progress: bool = False,
    on_scan=None,
) -> ExtractedPlanes:
    """Extract plane patches from each scan's observations (see the module docstring).

    ``scans``: one (n_j, 3) array of (rho [m], theta [rad], alpha [rad]) per scan, hybrid or
    panoramic (both faces map to the same scanner-space point). ``names``: scan names (default
    S1, S2, ...). ``seed`` makes RANSAC and the budget sampling repeatable. ``progress``: a
    progress bar over the points of all scans. ``on_scan(name, n_patches, n_on_patches,
    n_points)`` is called after each scan (the CLI's progress lines where stderr is no terminal).

    (Long because of its validation of the inputs and the progress bar; the work is
    :func:`_extract_scan`.)
    """
    from tqdm.auto import tqdm

    o3d = _require_open3d()
    options = options or ExtractionOptions()
    names = tuple(names) if names is not None else tuple(f"S{j + 1}" for j in range(len(scans)))
    if len(names) != len(scans):
        raise ValueError(f"{len(names)} scan names for {len(scans)} scans")
    root = np.random.SeedSequence(seed)
    children = root.spawn(len(scans))
    total = sum(len(o) for o in scans)
    bar = tqdm(total=total, disable=not progress, unit="pt", unit_scale=True)
    p_scan, p_n, p_d, p_rms, p_cnt, pt_patch, pt_index, pt_obs, pt_inc = (
        [],
        [],
        [],
        [],
        [],
        [],
        [],
        [],
        [],
    )
    for j, (obs, ss) in enumerate(zip(scans, children)):
        obs = np.asarray(obs, dtype=np.float64)
        if obs.ndim != 2 or obs.shape[1] != 3 or not np.all(np.isfinite(obs)):
            raise ValueError(
                f"scan {names[j]}: observations must be a finite (n, 3) array of (rho, theta, alpha)"
            )
        ransac_seed, budget_seed = ss.spawn(2)
        rng = np.random.default_rng(budget_seed)
        x = cartesian_from_spherical(obs, xp=np)
        bar.set_description(f"planes of scan {names[j]}")
        found = _extract_scan(o3d, obs, options, ransac_seed, bar)
        if on_scan is not None:
            on_scan(names[j], len(found), sum(len(f[0]) for f in found), len(obs))
        for members, n, d, rms in found:
            sel = members
            if options.budget is not None and len(members) > options.budget:
                sel = np.sort(rng.choice(members, size=int(options.budget), replace=False))
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

    bar.close()

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
