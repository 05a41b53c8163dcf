"""Thinning of dense plane observations to a spacing at which their noise is independent.

The plane-based adjustment weights every point as an independent observation (Chow et al.
2013, section 3.2, Equation (8)): its AP sigmas then shrink as ``1 / sqrt(n)`` with the number
of points. The noise of neighbouring points of a dense scan is not independent: the laser
footprints of neighbours overlap, and the surface texture and the rangefinder's short-term
drift are shared by points closer than their correlation length. Chow et al. (2013, section
3.2) name the problem for plane-based calibration and its remedy, *"Correlations between
observations can exist, especially if the observations are within close proximity of each
other ... For plane-based calibration this is more of a concern, but can also be reduced by
downsampling the point cloud"*. Once the points are closer than the correlation length, more
points add no information but still shrink the reported sigmas; a calibration then claims a
precision its Monte Carlo scatter does not have.

tlsjax's default is that downsampling, chosen over a correlation-aware weighting because it
needs no estimate of the correlation function (which the residuals of a calibration in
progress cannot give apart from the unmodelled systematic errors the calibration is looking
for), keeps the stochastic model of the paper unchanged, and makes the adjustment's time and
memory independent of the scan density. Each scan's points of each plane are binned into
cubic voxels of side ``spacing`` in scanner space and the point nearest each voxel's centre is
kept (deterministic, independent of the points' order). Binning and choice use the point where
each line of sight meets the group's least-squares plane, ``u d / (n . u)``, not the observed
point: that depends on the direction alone, so the choice does not select range noise (on a
wall parallel to a voxel face, the point nearest the centre by its observed coordinates is the
one whose range error moves it towards the centre, the same sign over the whole wall: a bias of
14 AP sigmas in A0 at a million points). Kept points are then about
``spacing`` apart; with a Gaussian correlation function of length ``L`` the correlation of two
neighbours is ``exp(-spacing^2 / (2 L^2))``, 0.011 at ``spacing = 3 L``, which inflates an AP
variance by less than 5 % (about four such neighbours in a surface), so the reported sigmas
hold to within about 2 %. The default :data:`DEFAULT_PLANE_SPACING` of 0.1 m thus covers
correlation lengths up to about 3 cm (footprint overlap and surface texture of
indoor surfaces are millimetres to a few centimetres); give a larger spacing where the
residuals of neighbouring kept points are still correlated (``spacing=0`` keeps all points).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .._adjustment._network import ObservationTable
from .._model._geometry import cartesian_from_spherical

#: Default voxel side [m] of :func:`thin_planes` (module docstring: correlation lengths up to
#: about a third of it leave the reported sigmas honest).
DEFAULT_PLANE_SPACING = 0.1


def _codes(labels, n: int) -> np.ndarray:
    """Integer codes of ``n`` labels ((scan, plane) pairs), by a dictionary: linear,
    without an array of strings (a sort of ten million strings takes longer than the rest)."""
    index: dict = {}
    return np.fromiter((index.setdefault(k, len(index)) for k in labels), dtype=np.int64, count=n)


def _on_group_planes(x, groups):
    """Each point's line of sight met with its group's least-squares plane, ``u d / (n . u)``
    (module docstring); a point whose line of sight grazes the plane (``|n . u| < 0.02``) and
    groups of fewer than three points are kept as observed. Moments by ``bincount``: linear."""
    g = int(groups.max()) + 1
    cnt = np.bincount(groups, minlength=g).astype(np.float64)
    mean = np.stack([np.bincount(groups, x[:, i], g) for i in range(3)], 1) / cnt[:, None]
    y = x - mean[groups]
    cov = np.empty((g, 3, 3))
    for i in range(3):
        for j in range(i, 3):
            cov[:, i, j] = cov[:, j, i] = np.bincount(groups, y[:, i] * y[:, j], g)
    normal = np.linalg.eigh(cov)[1][:, :, 0]  # the smallest eigenvalue's eigenvector
    d = np.sum(normal * mean, axis=1)
    u = x / np.maximum(np.linalg.norm(x, axis=1), 1e-300)[:, None]
    nu = np.sum(normal[groups] * u, axis=1)
    ok = (np.abs(nu) >= 0.02) & (cnt[groups] >= 3)
    scale = np.where(ok, d[groups] / np.where(ok, nu, 1.0), 0.0)
    return np.where(ok[:, None], u * scale[:, None], x)


def thin_indices(table: ObservationTable, spacing: float = DEFAULT_PLANE_SPACING) -> np.ndarray:
    """Rows of a plane ``table`` kept by :func:`thin_planes` (sorted; all rows for spacing 0).

    One row per occupied voxel of side ``spacing`` [m] per scan and plane: the point whose line
    of sight meets the plane nearest the voxel's centre (ties: the first row; module
    docstring). Memory and time are linear in the rows (one lexicographic sort)."""
    spacing = float(spacing)
    if not (np.isfinite(spacing) and spacing >= 0.0):
        raise ValueError(f"plane thinning spacing must be >= 0 [m], got {spacing}")
    n = len(table)
    if spacing == 0.0 or n == 0:
        return np.arange(n, dtype=np.int64)
    if table.kind != "plane":
        raise ValueError(f"{table.source}: thinning is for plane observations, not {table.kind}s")
    obs = np.asarray(table.observations, dtype=np.float64)
    if obs.shape != (n, 3) or not np.isfinite(obs).all():
        return np.arange(n, dtype=np.int64)  # all rows: make_network names the bad one
    x = cartesian_from_spherical(obs, xp=np)
    groups = _codes(zip(table.scans, table.primitives), n)
    x = _on_group_planes(x, groups)
    cell = np.floor(x / spacing)
    dist = np.sum((x - (cell + 0.5) * spacing) ** 2, axis=1)
    cell = cell.astype(np.int64)
    keys = (cell[:, 2], cell[:, 1], cell[:, 0], groups)
    order = np.lexsort((np.arange(n), dist) + keys)  # last key is the primary one
    first = np.zeros(n, dtype=bool)
    first[0] = True
    for a in keys:  # one key at a time: no (n, 5) copy
        a = a[order]
        first[1:] |= a[1:] != a[:-1]
    return np.sort(order[first])


def take_rows(table: ObservationTable, rows) -> ObservationTable:
    """The ``rows`` (indices) of an observation ``table``, with everything that is per row."""
    rows = np.asarray(rows, dtype=np.int64)
    pick = lambda a: None if a is None else np.asarray(a)[rows]
    names = lambda t: None if t is None else tuple(t[i] for i in rows)
    return dataclasses.replace(
        table,
        scans=names(table.scans),
        primitives=names(table.primitives),
        observations=pick(table.observations),
        sigmas=pick(table.sigmas),
        incidence=pick(table.incidence),
        instruments=names(table.instruments),
        rows=pick(table.rows),
    )


def thin_planes(
    table: ObservationTable, spacing: float = DEFAULT_PLANE_SPACING
) -> ObservationTable:
    """Plane observations thinned to one point per voxel of side ``spacing`` [m] per scan and
    plane (module docstring: why, and why 0.1 m by default); ``spacing=0`` keeps all. The
    returned table notes how many points were kept; rows keep their file line numbers."""
    keep = thin_indices(table, spacing)
    if len(keep) == len(table):
        return table
    note = (
        f"plane points thinned to one per {spacing:g} m voxel per scan and plane: "
        f"{len(keep)} of {len(table)} kept"
    )
    return dataclasses.replace(take_rows(table, keep), notes=tuple(table.notes) + (note,))
