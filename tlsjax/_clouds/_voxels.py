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


def _reduce(keys, count, sums, isum):
    """Sum rows with equal keys (sorted unique keys)."""
    uk, inv = np.unique(keys, return_inverse=True)
    c = np.bincount(inv, weights=count, minlength=len(uk))
    s = np.stack([np.bincount(inv, weights=sums[:, i], minlength=len(uk)) for i in range(3)], 1)
    it = np.bincount(inv, weights=isum, minlength=len(uk))
    return uk, c, s, it


@dataclasses.dataclass(frozen=True, eq=False)
class VoxelCloud:
    """The voxel cloud of one scan: per occupied voxel its ``centroid`` (m, 3) [m], ``count``
    (m,) and mean ``intensity`` (m,) (NaN without intensity); ``n_points`` of the scan,
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
        parts.append(_reduce(voxel_keys(pts, size), np.ones(len(pts)), pts, iv))
        held += len(parts[-1][0])
        if len(parts) > 1 and held > chunk:  # merge so that memory follows the voxels
            parts = [_reduce(*(np.concatenate(p) for p in zip(*parts)))]
            held = len(parts[0][0])
    if n == 0:
        raise ValueError(f"{scan.source}: scan {scan.name} has no valid points")
    keys, count, sums, isum = (
        parts[0] if len(parts) == 1 else _reduce(*(np.concatenate(p) for p in zip(*parts)))
    )
    del keys
    sample, rho = sampler.arrays()
    return VoxelCloud(
        size,
        sums / count[:, None],
        count.astype(np.int64),
        isum / count if has_i else np.full(len(count), np.nan),
        n,
        bool(has_i),
        sample,
        rho,
    )


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
