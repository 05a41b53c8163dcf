"""Matching plane patches across scans into global planes (host side, numpy).

Matching turns every patch into object space with the scan poses, ``n = R^T n_s``,
``d = d_s + n . S`` (from ``x = R (X - S)``). Two patches are candidates when their normals agree
within ``max_angle``, their centroids lie within ``max_offset`` of each other's plane, and their
points come within ``overlap_distance`` of each other (patches of one scan that are coplanar need
no overlap: an occluded floor is one plane). Candidates are joined greedily, closest in angle
first, and a join is made only if *every* patch of the joined set is within the limits of every
other patch and of the set's least-squares plane (complete linkage): a chain of matches, each
within 3 deg of its neighbour, cannot gather patches 5 deg apart. Each joined set is one global
plane.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .._io._extracted import ExtractedPlanes
from .._model._geometry import (
    cartesian_from_spherical,
    fit_plane,
    plane_from_moments,
    rotation_matrix,
)
from .._summary import Settings
from .._units import DEG


@dataclasses.dataclass(frozen=True)
class MatchingOptions(Settings):
    """Thresholds for joining patches into global planes: ``max_angle`` [rad] between normals,
    ``max_offset`` [m] of a centroid from the other plane, ``overlap_distance`` h [m] between
    the nearest points of two patches, tested on a voxel grid of size h (patches closer than h
    pass, patches farther apart than 2 sqrt(3) h never; ``None`` skips the test).
    ``merge_coplanar_in_scan``: patches of one scan within the angle and offset limits need no
    overlap (an occluded floor is one plane). The limits hold between every two patches of a
    plane and between each patch and the plane's fit, not only between neighbours."""

    max_angle: float = 3.0 * DEG
    max_offset: float = 0.05
    overlap_distance: float | None = 0.5
    merge_coplanar_in_scan: bool = True

    def __post_init__(self):
        if not (0 < self.max_angle < np.pi / 2):
            raise ValueError(
                f"MatchingOptions.max_angle must be in (0, 90 deg), got {self.max_angle / DEG:g} deg"
            )
        if not self.max_offset > 0:
            raise ValueError(f"MatchingOptions.max_offset must be positive, got {self.max_offset}")
        if self.overlap_distance is not None and not self.overlap_distance > 0:
            raise ValueError(
                f"MatchingOptions.overlap_distance must be positive or None, got {self.overlap_distance}"
            )


class _Moments:
    """Point counts, sums and second moments per patch, so that the least-squares plane of any
    union of patches costs one 3 x 3 eigenproblem."""

    def __init__(self, X, patch, P):
        self.origin = X.mean(axis=0) if len(X) else np.zeros(3)  # no cancellation in map frames
        Y = X - self.origin
        self.n = np.bincount(patch, minlength=P).astype(np.float64)
        self.s = np.zeros((P, 3))
        np.add.at(self.s, patch, Y)
        self.ss = np.zeros((P, 3, 3))
        np.add.at(self.ss, patch, Y[:, :, None] * Y[:, None, :])

    def plane(self, members):
        nrm, c, _ = plane_from_moments(
            self.n[members].sum(), self.s[members].sum(axis=0), self.ss[members].sum(axis=0)
        )
        return nrm, float(nrm @ (c + self.origin))


def _compatible(members, N, D, C, moments, config) -> bool:
    """Every pair of patches within the angle and offset limits, and every patch within them
    of the joined set's least-squares plane."""
    m = np.asarray(members)
    cos_min = np.cos(config.max_angle)
    if (np.abs(N[m] @ N[m].T) < cos_min - 1e-12).any():
        return False
    off = np.abs(C[m] @ N[m].T - D[m][None, :])
    if (np.maximum(off, off.T) > config.max_offset).any():
        return False
    n, d = moments.plane(m)
    return bool(
        (np.abs(N[m] @ n) >= cos_min - 1e-12).all()
        and (np.abs(C[m] @ n - d) <= config.max_offset).all()
    )


def _join(P, edges, N, D, C, moments, config):
    """Greedy complete-linkage joining of candidate pairs (closest in angle first)."""
    group = np.arange(P)
    members = {p: [p] for p in range(P)}
    for a, b in edges:
        ga, gb = group[a], group[b]
        if ga == gb:
            continue
        joined = members[ga] + members[gb]
        if not _compatible(joined, N, D, C, moments, config):
            continue
        members[ga] = joined
        for p in members.pop(gb):
            group[p] = ga
    return group


def _overlapping(X, point_patch, P, iu, ju, h):
    """Pairs whose points come within h of each other, tested on a voxel grid of size h: nearest
    points closer than h always fall in neighbouring voxels, and neighbouring voxels are never
    more than 2 sqrt(3) h apart."""
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
    keys = [np.unique(key[point_patch == p]) for p in range(P)]
    return np.array(
        [
            np.isin(keys[b], (keys[a][:, None] + offsets[None, :]).ravel()).any()
            for a, b in zip(iu, ju)
        ],
        dtype=bool,
    )


def match_planes(
    planes: ExtractedPlanes, poses, options: MatchingOptions | None = None
) -> ExtractedPlanes:
    """Join the patches of all scans into global planes, given scan poses (s, 6) =
    (Xs, Ys, Zs, omega, phi, kappa) with ``x = R (X - S)`` (SPEC section 1).

    Returns a copy with ``patch_plane``, ``poses`` and ``planes`` (object space, fitted to all
    points of each plane; normals oriented like the largest patch) set. Planes are numbered by
    decreasing number of kept points.

    (A little over 60 lines: candidate pairs, joining, the object-space fit and the numbering,
    one sequence.)
    """
    options = options or MatchingOptions()
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
    angle_ok = np.abs(cos) >= np.cos(options.max_angle)
    off_ij = np.abs(C @ N.T - D[None, :])  # centroid i from plane j
    close = angle_ok & (np.maximum(off_ij, off_ij.T) <= options.max_offset)
    iu, ju = np.nonzero(np.triu(close, 1))
    keep = np.ones(len(iu), dtype=bool)
    if options.overlap_distance is not None:
        keep = _overlapping(X, planes.point_patch, P, iu, ju, options.overlap_distance)
        if options.merge_coplanar_in_scan:
            keep |= planes.patch_scan[iu] == planes.patch_scan[ju]
    iu, ju = iu[keep], ju[keep]
    order = np.lexsort((off_ij[iu, ju] + off_ij[ju, iu], -np.abs(cos[iu, ju])))
    moments = _Moments(X, planes.point_patch, P)
    group = _join(P, zip(iu[order], ju[order]), N, D, C, moments, options)
    uniq, group = np.unique(group, return_inverse=True)
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
