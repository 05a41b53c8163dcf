"""Matching plane patches across scans into global planes (host side, numpy).

Matching turns every patch into object space with the scan poses, ``n = R^T n_s``,
``d = d_s + n . S`` (from ``x = R (X - S)``), and joins patches (union-find) whose normals agree
within ``max_angle``, whose centroids lie within ``max_offset`` of each other's plane and whose
points come within ``overlap_distance`` of each other. Each joined set is one global plane.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .._model._geometry import cartesian_from_spherical, rotation_matrix
from .._units import DEG
from ._extract import ExtractedPlanes, fit_plane


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
            raise ValueError(
                f"MatchingConfig.max_angle must be in (0, 90 deg), got {self.max_angle / DEG:g} deg"
            )
        if not self.max_offset > 0:
            raise ValueError(f"MatchingConfig.max_offset must be positive, got {self.max_offset}")
        if self.overlap_distance is not None and not self.overlap_distance > 0:
            raise ValueError(
                f"MatchingConfig.overlap_distance must be positive or None, got {self.overlap_distance}"
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


def match_planes(
    planes: ExtractedPlanes, poses, config: MatchingConfig | None = None
) -> ExtractedPlanes:
    """Join the patches of all scans into global planes, given scan poses (s, 6) =
    (Xs, Ys, Zs, omega, phi, kappa) with ``x = R (X - S)`` (SPEC section 1).

    Returns a copy with ``patch_plane``, ``poses`` and ``planes`` (object space, fitted to all
    points of each plane; normals oriented like the largest patch) set. Planes are numbered by
    decreasing number of kept points.
    """
    config = config or MatchingConfig()
    poses = np.asarray(poses, dtype=np.float64)
    if poses.shape != (len(planes.scans), 6) or not np.all(np.isfinite(poses)):
        raise ValueError(
            f"poses must be a finite ({len(planes.scans)}, 6) array "
            f"(Xs, Ys, Zs, omega, phi, kappa), got shape {poses.shape}"
        )
    P = len(planes.patch_scan)
    R = (
        np.stack([rotation_matrix(*p[3:], xp=np) for p in poses])
        if len(poses)
        else np.zeros((0, 3, 3))
    )
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
        offsets = np.array(
            [
                (a * span[1] + b) * span[2] + c
                for a in (-1, 0, 1)
                for b in (-1, 0, 1)
                for c in (-1, 0, 1)
            ]
        )
        keys = [np.unique(key[planes.point_patch == p]) for p in range(P)]
        edges = [
            (a, b)
            for a, b in zip(iu, ju)
            if np.isin(keys[b], (keys[a][:, None] + offsets[None, :]).ravel()).any()
        ]
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
        n, d, _ = fit_plane(X[point_plane == g])
        members = np.flatnonzero(patch_plane == g)
        ref = members[np.argmax(planes.patch_inliers[members])]
        if n @ N[ref] < 0:
            n, d = -n, -d
        params[g] = (*n, d)
    return dataclasses.replace(planes, patch_plane=patch_plane, poses=poses, planes=params)
