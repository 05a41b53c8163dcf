"""One streamed pass over a scan into a voxel cloud, and a second one that crops the points
around candidates (host side, numpy + scipy).

Target candidates are found on the voxel cloud: the centroid, point count and mean intensity
of every occupied voxel of edge ``size``. Its size grows with the surface area scanned, not with
the points (a 10-million-point room scan at 2 cm is about a million voxels), and its sampling is
metric: a target has about as many voxels at 20 m as at 2 m once the scan's spacing there is
finer than the voxel. The precise fits then use every point near a candidate, collected in a
second pass (:func:`crop`); no more of the scan is ever held.

Intensity is normalised per scan and per range band (:func:`intensity_normaliser`): a voxel's
mean intensity divided by the median of the voxels in its range band, so that "dark" means dark
against what the scanner sees at that range (raw intensity falls with range by a factor of
several over a room) and a white target and a white wall both sit near 1.

**Noise from the data.** Each voxel also keeps the covariance of its points about their
centroid. Along the surface's normal this is the points' noise (range noise times the cosine
of the incidence, plus the angular noise times its sine), whatever the centroids of
neighbouring voxels do; pooled over a group of voxels (:meth:`VoxelCloud.noise`) it estimates
the scan's noise there, at that range and on that material (a phase scanner's range noise on
black paper is 3-5 times that on white: 6-12 mm against 1-3 mm at 20-22 m for a Z+F 5016,
against which no fixed millimetre limit serves). The candidate tests of ``_contrast`` and
``_spheres`` compare shapes with this figure instead of fixed constants.
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

#: Nearest neighbours of a voxel centroid used for its local surface and connectivity.
NEIGHBOURS = 12
_BITS = 21
_OFFSET = 1 << (_BITS - 1)
_MASK = (1 << _BITS) - 1


def voxel_keys(points, size: float) -> np.ndarray:
    """One int64 key per point of its voxel ``floor(x / size)`` (21 bits per axis: +-1,048,576
    voxels, i.e. +-21 km at 2 cm, from the scanner)."""
    ijk = np.floor(np.asarray(points) / size).astype(np.int64) + _OFFSET
    if len(ijk) and (ijk.min() < 0 or ijk.max() > _MASK):
        raise ValueError(
            f"points lie beyond {_OFFSET * size:.4g} m of the scanner: not a scan in its own frame"
        )
    return (ijk[:, 0] << (2 * _BITS)) | (ijk[:, 1] << _BITS) | ijk[:, 2]


#: Columns summed per voxel: count, x, y, z, intensity, xx, xy, xz, yy, yz, zz.
_SUMS = 11


def _columns(pts, inten):
    """Per point the :data:`_SUMS` columns that voxels sum (coordinates relative to the
    voxel's corner)."""
    x = pts
    cols = [np.ones(len(x)), x[:, 0], x[:, 1], x[:, 2], inten]
    cols += [x[:, i] * x[:, j] for i in range(3) for j in range(i, 3)]
    return np.stack(cols, 1)


def _reduce(keys, sums):
    """Sum rows with equal keys (sorted unique keys)."""
    uk, inv = np.unique(keys, return_inverse=True)
    return uk, np.stack(
        [np.bincount(inv, weights=sums[:, i], minlength=len(uk)) for i in range(sums.shape[1])], 1
    )


def _covariances(sums):
    """Each voxel's point covariance about its centroid, (m, 3, 3), float32 (memory)."""
    n = sums[:, 0]
    mean = sums[:, 1:4] / n[:, None]
    M = np.zeros((len(n), 3, 3), dtype=np.float32)
    k = 5
    for i in range(3):
        for j in range(i, 3):
            M[:, i, j] = M[:, j, i] = sums[:, k] / n - mean[:, i] * mean[:, j]
            k += 1
    return M


@dataclasses.dataclass(frozen=True, eq=False)
class VoxelCloud:
    """The voxel cloud of one scan: per occupied voxel its ``centroid`` (m, 3) [m], ``count``
    (m,), mean ``intensity`` (m,) (NaN without intensity) and the ``covariance`` (m, 3, 3)
    [m^2] of its points about the centroid (module docstring); ``n_points`` of the scan,
    ``size`` [m]; ``intensity_sample``/``range_sample``: a thinned sample of the points'
    intensities and ranges (at most about 200,000) for the normalisation."""

    size: float
    centroid: np.ndarray
    count: np.ndarray
    intensity: np.ndarray
    n_points: int
    has_intensity: bool
    intensity_sample: np.ndarray
    range_sample: np.ndarray
    covariance: np.ndarray = None

    def noise(self, index, normals=None) -> float:
        """Noise [m] of the points of voxels ``index`` along ``normals`` ((3,) or one per
        voxel; None: each voxel's direction of least spread): the pooled within-voxel variance ``sum (n_v - 1) s_v^2 / sum (n_v - 1)``, with
        ``s_v^2 = n_v / (n_v - 1) u^T C_v u``, of the voxels of at least 2 points whose
        ``s_v`` is at most 3 times the median (a voxel holding a stray point behind the
        surface is left out). NaN when no voxel has 2 points."""
        index = np.asarray(index, dtype=np.int64).reshape(-1)
        n = self.count[index].astype(np.float64)
        C = self.covariance[index].astype(np.float64)
        if normals is None:
            var = np.linalg.eigvalsh(C)[:, 0]
        else:
            u = np.broadcast_to(np.asarray(normals, dtype=np.float64), (len(index), 3))
            var = np.einsum("ki,kij,kj->k", u, C, u)
        ok = n >= 2
        if not ok.any():
            return np.nan
        s2 = np.maximum(var[ok], 0.0) * n[ok] / (n[ok] - 1.0)
        dof = n[ok] - 1.0
        keep = s2 <= 9.0 * np.median(s2)
        return float(np.sqrt(np.sum(dof[keep] * s2[keep]) / np.sum(dof[keep])))

    @functools.cached_property
    def neighbours(self):
        """Distances (m, k) and indices (m, k) of each centroid's k = 12 nearest centroids
        (itself first), computed once for the sphere and the planar target candidates."""
        k = min(NEIGHBOURS, len(self.centroid))
        from scipy.spatial import cKDTree  # at first use: it is slow to import

        tree = cKDTree(self.centroid)
        d = np.empty((len(self.centroid), k), dtype=np.float32)
        i = np.empty((len(self.centroid), k), dtype=np.int32 if len(d) < 2**31 else np.int64)
        for a in range(0, len(d), 200_000):
            d[a : a + 200_000], i[a : a + 200_000] = tree.query(
                self.centroid[a : a + 200_000], k=k, workers=-1
            )
        return d, i


class _Sampler:
    """Every k-th point's (intensity, range), k doubling whenever more than ``cap`` are held."""

    def __init__(self, cap=200_000):
        self.cap, self.stride, self.phase = cap, 1, 0
        self.values, self.ranges = [], []

    def add(self, inten, rho):
        take = np.arange((-self.phase) % self.stride, len(rho), self.stride)
        self.phase = (self.phase + len(rho)) % self.stride
        self.values.append(inten[take])
        self.ranges.append(rho[take])
        if sum(len(v) for v in self.values) > 2 * self.cap:
            self.values = [np.concatenate(self.values)[::2]]
            self.ranges = [np.concatenate(self.ranges)[::2]]
            self.stride *= 2

    def arrays(self):
        if not self.values:
            return np.zeros(0), np.zeros(0)
        return np.concatenate(self.values), np.concatenate(self.ranges)


def voxelise(scan, size: float, *, chunk: int, bar=None) -> VoxelCloud:
    """One pass over a :class:`~tlsjax._io._scan_chunks.ScanChunks` into a :class:`VoxelCloud`."""
    parts, held, n, has_i = [], 0, 0, None
    sampler = _Sampler()
    for pts, inten, _ in scan.chunks(chunk):
        has_i = inten is not None if has_i is None else has_i
        n += len(pts)
        if bar is not None:
            bar.update(len(pts))
        if not len(pts):
            continue
        iv = inten if inten is not None else np.zeros(len(pts))
        if inten is not None:
            sampler.add(inten, np.linalg.norm(pts, axis=1))
        # Second moments about the voxel's corner, not the scanner: at 1 km x^2 would leave
        # no digits for millimetre noise.
        origin = np.floor(pts / size) * size
        keys = voxel_keys(pts, size)
        parts.append(_reduce(keys, np.concatenate([_columns(pts - origin, iv), origin], 1)))
        held += len(parts[-1][0])
        if len(parts) > 1 and held > chunk:  # merge so that memory follows the voxels
            parts = [_merge(parts)]
            held = len(parts[0][0])
    if n == 0:
        raise ValueError(f"{scan.source}: scan {scan.name} has no valid points")
    keys, sums = parts[0] if len(parts) == 1 else _merge(parts)
    del keys
    count = sums[:, 0]
    origin = sums[:, _SUMS:] / count[:, None]
    sample, rho = sampler.arrays()
    return VoxelCloud(
        size,
        sums[:, 1:4] / count[:, None] + origin,
        count.astype(np.int64),
        sums[:, 4] / count if has_i else np.full(len(count), np.nan),
        n,
        bool(has_i),
        sample,
        rho,
        _covariances(sums[:, :_SUMS]),
    )


def _merge(parts):
    return _reduce(*(np.concatenate(p) for p in zip(*parts)))


def intensity_normaliser(sample, ranges, bands: int = 24):
    """A function ``f(intensity, range)`` that divides by the median intensity of the scan at
    that range: medians of the sampled points in ``bands`` quantile bands of range,
    interpolated in log range. Returns None when there is no intensity."""
    if len(sample) < 10:
        return None
    order = np.argsort(ranges)
    groups = np.array_split(order, min(bands, max(1, len(order) // 500)))
    mid = np.array([np.median(np.log(np.maximum(ranges[g], 1e-3))) for g in groups])
    med = np.array([np.median(sample[g]) for g in groups])
    floor = max(np.percentile(np.abs(sample), 50) * 1e-3, 1e-12)
    med = np.maximum(med, floor)

    def normalise(intensity, rho):
        lr = np.log(np.maximum(np.asarray(rho, dtype=np.float64), 1e-3))
        return np.asarray(intensity, dtype=np.float64) / np.interp(lr, mid, med)

    return normalise


def crop(scan, centres, radii, *, chunk: int, bar=None):
    """Second pass: for each candidate q the points within ``radii[q]`` of ``centres[q]``.

    Returns a list of (points (m_q, 3), intensity (m_q,) or None). A point near several
    candidates goes to each. Points are first screened by a hash of coarse cells (of the
    largest radius) around the candidates, then tested exactly with a k-d tree."""
    centres = np.asarray(centres, dtype=np.float64).reshape(-1, 3)
    radii = np.asarray(radii, dtype=np.float64).reshape(-1)
    if len(centres) == 0:
        return []
    cell = float(radii.max())
    ijk = np.floor(centres / cell).astype(np.int64)
    shifts = np.stack(np.meshgrid(*[np.arange(-1, 2)] * 3, indexing="ij"), -1).reshape(-1, 3)
    near = np.unique(voxel_keys((ijk[:, None, :] + shifts).reshape(-1, 3) * cell + cell / 2, cell))
    out_p = [[] for _ in centres]
    out_i = [[] for _ in centres]
    for pts, inten, _ in scan.chunks(chunk):
        if bar is not None:
            bar.update(len(pts))
        sel = np.flatnonzero(np.isin(voxel_keys(pts, cell), near, assume_unique=False))
        if not len(sel):
            continue
        sub = pts[sel]
        from scipy.spatial import cKDTree

        for q, idx in enumerate(cKDTree(sub).query_ball_point(centres, radii)):
            if idx:
                out_p[q].append(sub[idx])
                out_i[q].append(None if inten is None else inten[sel][idx])
    return [
        (
            np.concatenate(p) if p else np.zeros((0, 3)),
            np.concatenate(i) if i and i[0] is not None else None,
        )
        for p, i in zip(out_p, out_i)
    ]
