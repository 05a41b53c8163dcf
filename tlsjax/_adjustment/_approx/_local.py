"""Primitives of one frame (a scan, or object space) for the approximate values.

Per scan, in scanner space: the target points ``x = x(l)`` and, per (scan, plane) pair, the
moments of its points with the PCA plane fit (unit normal, centroid) and the precision of both
(normal ``sigma_n^2 = lambda_1 / ((m - 3) lambda_2)`` from the eigenvalues of the scatter, plus a
floor for what the uncorrected APs and unflat surfaces leave). A local normal is an *axis*: its
sign says nothing, because a plane between two stations is seen from opposite sides. Object-space
primitives are the same, from the moments and points of several scans at their poses.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..._model._geometry import cartesian_from_spherical, plane_from_moments
from .._network import Network
from ._config import ApproxConfig


@dataclasses.dataclass(eq=False)
class Prims:
    """Primitives of one frame: planes by id with normal ``n`` (not to be used where ``has_n``
    is False), its sigma ``sn`` [rad], centroid ``c``, the sigma ``sc`` [m] of the centroid
    across the plane; targets by id with points ``x`` and sigmas ``sx`` [m]."""

    plane: np.ndarray
    n: np.ndarray
    has_n: np.ndarray
    sn: np.ndarray
    c: np.ndarray
    sc: np.ndarray
    target: np.ndarray
    x: np.ndarray
    sx: np.ndarray


def moments(x, group, n_groups):
    """Count, sum (g, 3) and second moments (g, 3, 3) of the rows of x per group."""
    cnt = np.bincount(group, minlength=n_groups).astype(np.float64)
    s1 = np.stack([np.bincount(group, x[:, i], n_groups) for i in range(3)], axis=1)
    s2 = np.einsum("mi,mj->mij", x, x)
    s2 = np.stack([np.bincount(group, s2[:, i, j], n_groups) for i in range(3) for j in range(3)])
    return cnt, s1, s2.T.reshape(n_groups, 3, 3)


def transform_moments(cnt, s1, s2, A, S):
    """Moments of ``X = A x + S`` from those of x (per group; A (g, 3, 3), S (g, 3))."""
    t1 = np.einsum("gij,gj->gi", A, s1)
    t2 = np.einsum("gij,gjk,glk->gil", A, s2, A)
    o2 = (
        t2
        + t1[:, :, None] * S[:, None, :]
        + S[:, :, None] * t1[:, None, :]
        + cnt[:, None, None] * S[:, :, None] * S[:, None, :]
    )
    return t1 + cnt[:, None] * S, o2


def plane_fit(cnt, s1, s2, cfg: ApproxConfig):
    """PCA plane fits from moments: normal (g, 3), has_n, sigma of the normal [rad], centroid,
    sigma of the centroid across the plane [m]."""
    m = np.maximum(cnt, 1.0)
    n, c, w = plane_from_moments(m, s1, s2)
    w = np.clip(w, 0.0, None)
    has_n = (cnt >= 3) & (w[:, 1] >= cfg.min_spread**2)
    # Tilt of a PCA normal: residual variance over the points' spread along the weaker axis.
    resid = w[:, 0] * m / np.maximum(m - 3.0, 1.0)
    sn = np.sqrt(resid / (m * np.maximum(w[:, 1], 1e-300)) + cfg.normal_sigma_floor**2)
    sc = np.sqrt(resid / m + cfg.point_sigma_floor**2)
    # Without has_n the normal is still the PCA axis (a unit vector), only not to be trusted.
    return n, has_n, np.where(has_n, sn, np.inf), c, sc


@dataclasses.dataclass(eq=False)
class Data:
    """The network's local primitives: per (scan, plane) pair its scan, plane and moments; per
    target observation its scanner-space point and relative a priori sigma; ``t_noise`` the
    robust noise scale of the target points [m] once the poses are known."""

    n_scans: int
    n_targets: int
    n_planes: int
    pair_scan: np.ndarray
    pair_plane: np.ndarray
    pair_of_row: np.ndarray  # the (scan, plane) pair of every plane observation row
    cnt: np.ndarray
    s1: np.ndarray
    s2: np.ndarray
    x_t: np.ndarray
    t_scan: np.ndarray
    t_index: np.ndarray
    t_weight: np.ndarray
    t_noise: float = 0.0

    def target_noise(self, rows):
        """Noise sigma [m] of target observations ``rows``: the network's robust scale times
        each observation's a priori point sigma relative to the median one."""
        return self.t_noise * self.t_weight[rows]


def local_data(net: Network) -> Data:
    n_k = len(net.planes)
    if n_k:
        x_p = cartesian_from_spherical(net.plane_observations, xp=np)
        key = net.plane_scan_index.astype(np.int64) * n_k + net.plane_index
        pair_key, pair_of = np.unique(key, return_inverse=True)
        pair_of = pair_of.reshape(-1)
        cnt, s1, s2 = moments(x_p, pair_of, len(pair_key))
        pair_scan, pair_plane = pair_key // n_k, pair_key % n_k
    else:
        cnt, s1, s2 = np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3, 3))
        pair_scan = pair_plane = pair_of = np.zeros(0, dtype=np.int64)
    x_t = (
        cartesian_from_spherical(net.observations, xp=np) if len(net.targets) else np.zeros((0, 3))
    )
    # Relative a priori sigma of each target point (range and both angles over the range;
    # incidence included): only ratios, so the approximate values never depend on the sigmas'
    # scale.
    sig = net.sigmas
    rho = net.observations[:, 0]
    point = np.sqrt(sig[:, 0] ** 2 + (rho * sig[:, 1] * np.cos(net.observations[:, 2])) ** 2)
    point = np.sqrt(point**2 + (rho * sig[:, 2]) ** 2)
    weight = point / np.median(point) if len(point) else point
    return Data(
        len(net.scans),
        len(net.targets),
        n_k,
        pair_scan,
        pair_plane,
        pair_of,
        cnt,
        s1,
        s2,
        x_t,
        np.asarray(net.scan_index, dtype=np.int64),
        np.asarray(net.target_index, dtype=np.int64),
        weight,
    )


def scan_prims(data: Data, j: int, cfg: ApproxConfig) -> Prims:
    """The primitives of scan j in its own scanner frame."""
    q = np.flatnonzero(data.pair_scan == j)
    n, has_n, sn, c, sc = plane_fit(data.cnt[q], data.s1[q], data.s2[q], cfg)
    m = data.t_scan == j
    return Prims(
        data.pair_plane[q],
        n,
        has_n,
        sn,
        c,
        sc,
        data.t_index[m],
        data.x_t[m],
        target_sigma(np.linalg.norm(data.x_t[m], axis=1), cfg, data.target_noise(m)),
    )


@dataclasses.dataclass(eq=False)
class Sums:
    """Object-space sums per primitive over a set of (scan, primitive) correspondences at some
    poses: plane moments; target point sums, counts, ranges and noise variances. The sums of
    every scan but one are the totals minus that scan's own (:meth:`without`), so the
    primitives "of all other scans" cost one pass over the observations per round."""

    k_cnt: np.ndarray
    k_s1: np.ndarray
    k_s2: np.ndarray
    t_sum: np.ndarray
    t_cnt: np.ndarray
    t_rng: np.ndarray
    t_var: np.ndarray

    @classmethod
    def of(cls, data: Data, A, S, use_p, use_t, scans) -> Sums:
        """Sums over the correspondences ``use_p``/``use_t`` of the scans ``scans`` (bool
        (s,)) at poses ``X = A_j x + S_j``."""
        q = np.flatnonzero(use_p & scans[data.pair_scan])
        k = data.pair_plane[q]
        o1, o2 = transform_moments(
            data.cnt[q], data.s1[q], data.s2[q], A[data.pair_scan[q]], S[data.pair_scan[q]]
        )
        nk = data.n_planes
        k_cnt = np.bincount(k, data.cnt[q], nk)
        k_s1 = np.stack([np.bincount(k, o1[:, i], nk) for i in range(3)], axis=1)
        k_s2 = np.stack([np.bincount(k, o2[:, i // 3, i % 3], nk) for i in range(9)], axis=1)
        m = np.flatnonzero(use_t & scans[data.t_scan])
        js, t, nt = data.t_scan[m], data.t_index[m], data.n_targets
        X = np.einsum("mij,mj->mi", A[js], data.x_t[m]) + S[js]
        return cls(
            k_cnt,
            k_s1,
            k_s2.reshape(nk, 3, 3),
            np.stack([np.bincount(t, X[:, i], nt) for i in range(3)], axis=1),
            np.bincount(t, minlength=nt).astype(np.float64),
            np.bincount(t, np.linalg.norm(data.x_t[m], axis=1), nt),
            np.bincount(t, data.target_noise(m) ** 2, nt),
        )

    def without(self, other: Sums) -> Sums:
        return Sums(*(a - b for a, b in zip(dataclasses.astuple(self), dataclasses.astuple(other))))

    def prims(self, cfg: ApproxConfig) -> Prims:
        """Object-space primitives: planes fitted to the moments of all their points, targets
        averaged (their sigma shrinks with the number of scans)."""
        seen = np.flatnonzero(self.k_cnt > 0.5)
        n, has_n, sn, c, sc = plane_fit(self.k_cnt[seen], self.k_s1[seen], self.k_s2[seen], cfg)
        tv = np.flatnonzero(self.t_cnt > 0.5)
        cnt = self.t_cnt[tv]
        return Prims(
            seen,
            n,
            has_n,
            sn,
            c,
            sc,
            tv,
            self.t_sum[tv] / cnt[:, None],
            target_sigma(self.t_rng[tv] / cnt, cfg, np.sqrt(np.maximum(self.t_var[tv], 0) / cnt))
            / np.sqrt(cnt),
        )


def object_prims(data: Data, A, S, use_p, use_t, scans, cfg: ApproxConfig) -> Prims:
    """Object-space primitives from the correspondences ``use_p``/``use_t`` of ``scans``."""
    return Sums.of(data, A, S, use_p, use_t, scans).prims(cfg)


def target_sigma(rho, cfg: ApproxConfig, noise=0.0):
    """Sigma [m] of a target point at range rho in approximate values: the point floor, the
    angular model error (uncorrected APs) over the range and the network's noise."""
    return np.sqrt(cfg.point_sigma_floor**2 + (cfg.normal_sigma_floor * rho) ** 2 + noise**2)


def target_noise(data: Data, A, S) -> float:
    """Robust per-axis sigma [m] of the target points about their targets at poses (A, S):
    the median distance of a point from its target's median point, scaled for a Gaussian
    (chi with 3 degrees of freedom: median 1.54 sigma) and for the median's own share
    (sqrt(n / (n - 1)) for a target seen n times). Noisy data widen the tolerances with it
    rather than flag good targets as inconsistent."""
    if not len(data.t_scan):
        return 0.0
    X = np.einsum("mij,mj->mi", A[data.t_scan], data.x_t) + S[data.t_scan]
    dist = []
    for q in groups_by_size(data.t_index):
        k = q.shape[1]
        if k > 1:
            d = np.linalg.norm(X[q] - np.median(X[q], axis=1, keepdims=True), axis=-1)
            dist.append((d / data.t_weight[q]).ravel() * np.sqrt(k / (k - 1)))
    return float(np.median(np.concatenate(dist)) / 1.54) if dist else 0.0


def groups_by_size(index):
    """The rows of each group of ``index`` (e.g. a target's observations), one (G, k) array of
    row numbers per group size k, ascending within a group: per-group work is then vectorised
    over the groups of one size (a loop over groups would cost O(groups x rows))."""
    order = np.argsort(index, kind="stable")
    _, start, count = np.unique(index[order], return_index=True, return_counts=True)
    for k in np.unique(count):
        yield order[start[count == k][:, None] + np.arange(k)]
