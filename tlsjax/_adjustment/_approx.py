"""Approximate values from the observations alone (host side, numpy).

The adjustment linearises about these values, so they must be right to centimetres and tenths
of a degree for any plausible network: targets, planes of any orientation (oblique, nearly
parallel, crossing the room and so seen from both sides), stations close to a plane, scans that
see different subsets of the primitives, levelled or tilted scans, hybrid or panoramic scanners.

1. *Local primitives* per scan, in scanner space: the target points ``x = x(l)`` and, per
   (scan, plane) pair, the moments of its points with the PCA plane fit (unit normal ``n_l``,
   centroid ``c_l``) and the precision of both (normal ``sigma_n^2 = lambda_1 / ((m - 3)
   lambda_2)`` from the eigenvalues of the scatter, plus a floor for what the uncorrected APs
   and unflat surfaces leave). A local normal is an *axis*: its sign says nothing, because a
   plane between two stations is seen from opposite sides.
2. *Pairwise relative orientation* of every scan pair, in closed form and robust: rotation
   hypotheses from minimal sets (two non-parallel planes with the four sign combinations of their
   normals, or three targets), each scored on all shared primitives: the angle between normals
   (their signs follow from the hypothesis), then the position by iteratively reweighted least
   squares from the condition that each plane's centroid in one scan lies on the plane in the
   other (``n_a . (R c_b + t) = d_a``, free of the normal's sign) and from the targets
   (``R x_b + t = x_a``). The best hypothesis (most consistent primitives; on a tie, the one that
   keeps most planes on the same side of both stations) is refined on its inliers by weighted
   Kabsch (Horn 1987) of the signed normals and centred targets (Khoshelham 2016, plane-to-plane
   registration in closed form).
3. A *maximum spanning tree* over the scans (edge weight: number of consistent shared
   primitives) chains the poses from the best-connected scan outwards; a scan without a usable
   edge is registered against the object-space primitives of all scans placed so far.
4. *Consensus and re-registration*: per primitive, the largest group of its (scan, primitive)
   correspondences that agree in object space (normals, centroids on each other's planes,
   target positions) is kept; the rest are inconsistent (a wrong match in real data), reported
   (:attr:`Approximation.inconsistent`, and logged) and left out of the object-space primitives,
   so they do not spoil the other scans. Then each scan in turn is registered against the
   object-space primitives of all the other scans (planes fitted to the moments of all their
   points), every correspondence at once; two rounds. A scan whose consistent correspondences
   do not fix its rotation or position raises a one-line ``ValueError`` naming the scan and its
   primitives.
5. *Frame*: the first scan's station is the origin; the object frame is turned so that the
   levelled scans' vertical axes point up (their compensator readings start near zero), or, when
   no scan is levelled, kept as the first scan's frame unless a scan's Cardan angle phi would come
   near the gimbal lock at +-90 deg. Object-space normals get one orientation per plane: towards
   the side where most of its points were observed from.

Why not a library: registration libraries (open3d ICP, teaser++) register point clouds given a
close start or feature matches; here the correspondences are known by name and what is needed is
the closed-form solution over all of them with the sign ambiguity of plane normals, which is a
few dozen lines of linear algebra.
"""

from __future__ import annotations

import dataclasses
import heapq
import itertools
import logging

import numpy as np

from .._model._geometry import (
    angles_from_matrix,
    cartesian_from_spherical,
    kabsch,
    plane_from_moments,
)
from .._units import DEG
from ._network import Network

_LOG = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class ApproxConfig:
    """Tolerances of the approximate values.

    A (scan, primitive) correspondence is consistent when its normals agree within
    ``max(angle_tol, 4 sigma)`` and its centroid or target lies within
    ``max(distance_tol, 4 sigma)`` of the other scans' primitive, sigma propagated from the local
    fits. ``normal_sigma_floor`` [rad] and ``point_sigma_floor`` [m] are the model error of a local
    normal and point (uncorrected APs, unflat walls). A local normal needs at least
    ``min_spread`` [m] RMS extent of its points along their second principal axis.
    ``rounds`` of re-registration follow the spanning tree.
    """

    angle_tol: float = 3.0 * DEG
    distance_tol: float = 0.10
    normal_sigma_floor: float = 0.2 * DEG
    point_sigma_floor: float = 0.005
    min_spread: float = 0.02
    rounds: int = 2
    minimal_planes: int = 6

    def __post_init__(self):
        for name in ("angle_tol", "distance_tol", "normal_sigma_floor", "point_sigma_floor"):
            if not getattr(self, name) > 0:
                raise ValueError(f"ApproxConfig.{name} must be positive, got {getattr(self, name)}")


@dataclasses.dataclass(frozen=True)
class Inconsistency:
    """A (scan, primitive) correspondence that disagrees with the other scans: the angle [rad]
    between its normal and theirs (NaN for targets and planes without a local normal) and the
    RMS distance [m] of its points from their plane, or of its target from theirs."""

    scan: str
    kind: str
    name: str
    angle: float
    distance: float

    def __str__(self) -> str:
        ang = "" if np.isnan(self.angle) else f"normal {self.angle / DEG:.2f} deg off, "
        return (
            f"scan {self.scan}, {self.kind} {self.name}: {ang}{self.distance * 1e3:.0f} mm "
            "from the other scans"
        )


@dataclasses.dataclass(frozen=True, eq=False)
class Approximation:
    """Approximate values of a network: targets (t, 3), scan poses (s, 6) = (Xs, Ys, Zs, omega,
    phi, kappa), planes (k, 4) = (n, d) with ``n . X = d``; the inconsistent (scan, primitive)
    pairs; the spanning tree as (scan, parent scan or None) in the order the scans were placed."""

    targets: np.ndarray
    eops: np.ndarray
    planes: np.ndarray
    inconsistent: tuple = ()
    tree: tuple = ()


def approximate_values(net: Network, config: ApproxConfig | None = None):
    """Targets (t, 3) and scan poses (s, 6) = (Xs, Ys, Zs, omega, phi, kappa)."""
    a = approximate(net, config)
    return a.targets, a.eops


def approximate_network(net: Network, config: ApproxConfig | None = None):
    """Targets (t, 3), scan poses (s, 6) and planes (k, 4) = (n, d) of any network."""
    a = approximate(net, config)
    return a.targets, a.eops, a.planes


# ---------------------------------------------------------------------------------------------
# Local primitives


@dataclasses.dataclass(eq=False)
class _Prims:
    """Primitives of one frame (a scan, or object space): planes by id with normal ``n`` (not
    to be used where ``has_n`` is False), its sigma ``sn`` [rad], centroid ``c``, the sigma ``sc`` [m] of the
    centroid across the plane; targets by id with points ``x`` and sigmas ``sx`` [m]."""

    plane: np.ndarray
    n: np.ndarray
    has_n: np.ndarray
    sn: np.ndarray
    c: np.ndarray
    sc: np.ndarray
    target: np.ndarray
    x: np.ndarray
    sx: np.ndarray


def _moments(x, group, n_groups):
    """Count, sum (g, 3) and second moments (g, 3, 3) of the rows of x per group."""
    cnt = np.bincount(group, minlength=n_groups).astype(np.float64)
    s1 = np.stack([np.bincount(group, x[:, i], n_groups) for i in range(3)], axis=1)
    s2 = np.einsum("mi,mj->mij", x, x)
    s2 = np.stack([np.bincount(group, s2[:, i, j], n_groups) for i in range(3) for j in range(3)])
    return cnt, s1, s2.T.reshape(n_groups, 3, 3)


def _transform_moments(cnt, s1, s2, A, S):
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


def _plane_fit(cnt, s1, s2, cfg: ApproxConfig):
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
class _Data:
    """The network's local primitives: per (scan, plane) pair its scan, plane and moments; per
    target observation its scanner-space point."""

    n_scans: int
    n_targets: int
    n_planes: int
    pair_scan: np.ndarray
    pair_plane: np.ndarray
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


def _local_data(net: Network) -> _Data:
    n_k = len(net.planes)
    if n_k:
        x_p = cartesian_from_spherical(net.plane_observations, xp=np)
        key = net.plane_scan_index.astype(np.int64) * n_k + net.plane_index
        pair_key, pair_of = np.unique(key, return_inverse=True)
        cnt, s1, s2 = _moments(x_p, pair_of.reshape(-1), len(pair_key))
        pair_scan, pair_plane = pair_key // n_k, pair_key % n_k
    else:
        cnt, s1, s2 = np.zeros(0), np.zeros((0, 3)), np.zeros((0, 3, 3))
        pair_scan = pair_plane = np.zeros(0, dtype=np.int64)
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
    return _Data(
        len(net.scans),
        len(net.targets),
        n_k,
        pair_scan,
        pair_plane,
        cnt,
        s1,
        s2,
        x_t,
        np.asarray(net.scan_index, dtype=np.int64),
        np.asarray(net.target_index, dtype=np.int64),
        weight,
    )


def _scan_prims(data: _Data, j: int, cfg: ApproxConfig) -> _Prims:
    q = np.flatnonzero(data.pair_scan == j)
    n, has_n, sn, c, sc = _plane_fit(data.cnt[q], data.s1[q], data.s2[q], cfg)
    m = data.t_scan == j
    return _Prims(
        data.pair_plane[q],
        n,
        has_n,
        sn,
        c,
        sc,
        data.t_index[m],
        data.x_t[m],
        _target_sigma(np.linalg.norm(data.x_t[m], axis=1), cfg, data.target_noise(m)),
    )


def _object_prims(data: _Data, A, S, use_p, use_t, scans, cfg: ApproxConfig) -> _Prims:
    """Object-space primitives from the consistent correspondences of ``scans`` (bool (s,)),
    at poses X = A_j x + S_j: planes fitted to the moments of all their points, targets
    averaged."""
    q = np.flatnonzero(use_p & scans[data.pair_scan])
    k_cnt = np.zeros(data.n_planes)
    k_s1, k_s2 = np.zeros((data.n_planes, 3)), np.zeros((data.n_planes, 3, 3))
    if len(q):
        js = data.pair_scan[q]
        o1, o2 = _transform_moments(data.cnt[q], data.s1[q], data.s2[q], A[js], S[js])
        np.add.at(k_cnt, data.pair_plane[q], data.cnt[q])
        np.add.at(k_s1, data.pair_plane[q], o1)
        np.add.at(k_s2, data.pair_plane[q], o2)
    seen = np.flatnonzero(k_cnt > 0)
    n, has_n, sn, c, sc = _plane_fit(k_cnt[seen], k_s1[seen], k_s2[seen], cfg)
    m = use_t & scans[data.t_scan]
    js = data.t_scan[m]
    X = np.einsum("mij,mj->mi", A[js], data.x_t[m]) + S[js]
    t_sum = np.zeros((data.n_targets, 3))
    t_cnt = np.zeros(data.n_targets)
    t_rng = np.zeros(data.n_targets)
    t_var = np.zeros(data.n_targets)
    np.add.at(t_sum, data.t_index[m], X)
    np.add.at(t_cnt, data.t_index[m], 1.0)
    np.add.at(t_rng, data.t_index[m], np.linalg.norm(data.x_t[m], axis=1))
    np.add.at(t_var, data.t_index[m], data.target_noise(m) ** 2)
    tv = np.flatnonzero(t_cnt > 0)
    return _Prims(
        seen,
        n,
        has_n,
        sn,
        c,
        sc,
        tv,
        t_sum[tv] / t_cnt[tv, None],
        _target_sigma(t_rng[tv] / t_cnt[tv], cfg, np.sqrt(t_var[tv] / t_cnt[tv]))
        / np.sqrt(t_cnt[tv]),
    )


def _target_sigma(rho, cfg: ApproxConfig, noise: float = 0.0):
    """Sigma [m] of a target point at range rho in approximate values: the point floor, the
    angular model error (uncorrected APs) over the range and the network's noise."""
    return np.sqrt(cfg.point_sigma_floor**2 + (cfg.normal_sigma_floor * rho) ** 2 + noise**2)


def _target_noise(data: _Data, A, S) -> float:
    """Robust per-axis sigma [m] of the target points about their targets at poses (A, S):
    the median distance of a point from its target's median point, scaled for a Gaussian
    (chi with 3 degrees of freedom: median 1.54 sigma) and for the median's own share
    (sqrt(n / (n - 1)) for a target seen n times). Noisy data widen the tolerances with it
    rather than flag good targets as inconsistent."""
    if not len(data.t_scan):
        return 0.0
    X = np.einsum("mij,mj->mi", A[data.t_scan], data.x_t) + S[data.t_scan]
    dist = []
    for q in _groups_by_size(data.t_index):
        k = q.shape[1]
        if k > 1:
            d = np.linalg.norm(X[q] - np.median(X[q], axis=1, keepdims=True), axis=-1)
            dist.append((d / data.t_weight[q]).ravel() * np.sqrt(k / (k - 1)))
    return float(np.median(np.concatenate(dist)) / 1.54) if dist else 0.0


def _groups_by_size(index):
    """The rows of each group of ``index`` (e.g. a target's observations), one (G, k) array of
    row numbers per group size k, ascending within a group: per-group work is then vectorised
    over the groups of one size (a loop over groups would cost O(groups x rows))."""
    order = np.argsort(index, kind="stable")
    _, start, count = np.unique(index[order], return_index=True, return_counts=True)
    for k in np.unique(count):
        yield order[start[count == k][:, None] + np.arange(k)]


# ---------------------------------------------------------------------------------------------
# Robust closed-form registration of frame b onto frame a: x_a = R x_b + t


@dataclasses.dataclass(eq=False)
class _Shared:
    """The correspondences of two frames, aligned: planes (ia, ib into a's and b's arrays) and
    targets."""

    na: np.ndarray
    nb: np.ndarray
    both_n: np.ndarray
    sn2: np.ndarray
    ca: np.ndarray
    cb: np.ndarray
    has_a: np.ndarray
    has_b: np.ndarray
    sc2: np.ndarray
    plane: np.ndarray
    xa: np.ndarray
    xb: np.ndarray
    sx2: np.ndarray
    target: np.ndarray

    @property
    def size(self) -> int:
        return len(self.plane) + len(self.target)


def _shared(a: _Prims, b: _Prims) -> _Shared:
    k, ia, ib = np.intersect1d(a.plane, b.plane, assume_unique=True, return_indices=True)
    t, ta, tb = np.intersect1d(a.target, b.target, assume_unique=True, return_indices=True)
    return _Shared(
        a.n[ia],
        b.n[ib],
        a.has_n[ia] & b.has_n[ib],
        np.where(a.has_n[ia] & b.has_n[ib], a.sn[ia] ** 2 + b.sn[ib] ** 2, np.inf),
        a.c[ia],
        b.c[ib],
        a.has_n[ia],
        b.has_n[ib],
        a.sc[ia] ** 2 + b.sc[ib] ** 2,
        k,
        a.x[ta],
        b.x[tb],
        a.sx[ta] ** 2 + b.sx[tb] ** 2,
        t,
    )


@dataclasses.dataclass(eq=False)
class _Fit:
    """A registration: rotation, translation, per shared plane the sign of b's normal in a, the
    normal angle [rad] and centroid distance [m], inlier masks, whether rotation and position
    are determined by the inliers, and the score it was chosen by."""

    R: np.ndarray
    t: np.ndarray
    sign: np.ndarray
    angle: np.ndarray
    dist: np.ndarray
    plane_in: np.ndarray
    tdist: np.ndarray
    target_in: np.ndarray
    rotation_ok: bool
    position_ok: bool
    score: tuple
    shared: _Shared | None = None

    @property
    def determined(self) -> bool:
        return self.rotation_ok and self.position_ok

    @property
    def n_inliers(self) -> int:
        return int(self.plane_in.sum() + self.target_in.sum())


def _kabsch(u, v, w):
    """Rotation R minimising ``sum w |R u - v|^2`` (rows u, v; Horn 1987), and the ratio of
    the second to the first singular value of the cross-covariance (0: rotation undetermined)."""
    R, sv = kabsch(u, v, w, xp=np)
    return R, sv[1] / max(sv[0], 1e-300)


def _cross(a, b):
    # np.cross costs more than the arithmetic for one pair of 3-vectors.
    return np.array(
        [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]
    )


def _triad(u1, u2, v1, v2):
    """The rotation taking u1 onto v1 and u2 into the plane of (v1, v2)."""

    def frame(a, b):
        e2 = b - (a @ b) * a
        e2 = e2 / np.sqrt(e2 @ e2)
        return np.column_stack([a, e2, _cross(a, e2)])

    return frame(v1, v2) @ frame(u1, u2).T


def _all_targets(sh: _Shared):
    """The rotation of the weighted Kabsch fit to all shared targets, as a list of at most one."""
    if len(sh.target) < 3:
        return []
    R, q = _kabsch(sh.xb - sh.xb.mean(0), sh.xa - sh.xa.mean(0), 1.0 / sh.sx2)
    return [R] if q > 1e-3 else []


def _hypotheses(sh: _Shared, cfg: ApproxConfig):
    """Rotation hypotheses of minimal sets: a few target triples (against a wrong target label)
    and pairs of non-parallel shared planes with the sign combinations their angle allows."""
    out = []
    if len(sh.target) >= 5:
        rng = np.random.default_rng(len(sh.target))
        for tri in (rng.choice(len(sh.target), 3, replace=False) for _ in range(6)):
            xb, xa = sh.xb[tri], sh.xa[tri]
            R, q = _kabsch(xb - xb.mean(0), xa - xa.mean(0), np.ones(3))
            if q > 1e-2:
                out.append(R)
    idx = np.flatnonzero(sh.both_n)
    idx = idx[np.argsort(sh.sn2[idx], kind="stable")][: cfg.minimal_planes]
    pairs = []
    for p, q in itertools.combinations(idx, 2):
        sin_a = np.sqrt(max(1.0 - (sh.na[p] @ sh.na[q]) ** 2, 0.0))
        sin_b = np.sqrt(max(1.0 - (sh.nb[p] @ sh.nb[q]) ** 2, 0.0))
        pairs.append((min(sin_a, sin_b), p, q))
    good = [pq for pq in pairs if pq[0] > np.sin(20 * DEG)] or [
        pq for pq in pairs if pq[0] > np.sin(5 * DEG)
    ]
    for _, p, q in good:
        tol = max(cfg.angle_tol, 4.0 * np.sqrt(sh.sn2[p] + sh.sn2[q]))
        for sp, sq in itertools.product((1.0, -1.0), repeat=2):
            if abs(sh.na[p] @ sh.na[q] - sp * sq * (sh.nb[p] @ sh.nb[q])) > 2 * np.sin(tol):
                continue
            out.append(_triad(sp * sh.nb[p], sq * sh.nb[q], sh.na[p], sh.na[q]))
    return out


def _screen(hyps, sh: _Shared, cfg: ApproxConfig, keep: int = 8):
    """The distinct hypotheses whose normals agree best (all at once, before the costlier
    position solve): those within one plane of the largest number of agreeing normals, at most
    ``keep`` of them."""
    if len(hyps) <= 1:
        return hyps
    Rs = np.stack(hyps)
    c = np.abs(np.einsum("ki,hij,kj->hk", sh.na, Rs, sh.nb))
    tol = np.maximum(cfg.angle_tol, 4.0 * np.sqrt(sh.sn2))
    agree = np.sum(sh.both_n & (np.arccos(np.clip(c, 0.0, 1.0)) < tol), axis=1)
    order = np.argsort(-agree, kind="stable")
    out = []
    for h in order:
        if agree[h] < agree[order[0]] - 1 or len(out) == keep:
            break
        if all(np.abs(Rs[h] - R).max() > 1e-3 for R in out):
            out.append(Rs[h])
    return out


def _position_rows(R, sh: _Shared):
    """Linear equations ``M t = r`` for the translation: plane rows (centroid of one frame on
    the other frame's plane) and target rows (three each)."""
    Rcb = sh.cb @ R.T
    Rnb = sh.nb @ R.T
    use_a = sh.has_a
    rows = np.where(use_a[:, None], sh.na, Rnb)
    rhs = np.where(
        use_a,
        np.einsum("ki,ki->k", sh.na, sh.ca - Rcb),
        np.einsum("ki,ki->k", Rnb, sh.ca - Rcb),
    )
    valid = sh.has_a | sh.has_b
    return rows, rhs, valid, sh.xa - sh.xb @ R.T


def _evaluate(R, sh: _Shared, cfg: ApproxConfig, t=None) -> _Fit:
    """Score a rotation on all correspondences: signs and angles of the normals, the
    translation (IRLS with Cauchy weights, unless ``t`` is given) and the inliers."""
    c = np.einsum("ki,ki->k", sh.na, sh.nb @ R.T)
    sign = np.where(c < 0, -1.0, 1.0)
    angle = np.where(sh.both_n, np.arccos(np.clip(np.abs(c), 0.0, 1.0)), np.nan)
    tol_ang = np.maximum(cfg.angle_tol, 4.0 * np.sqrt(sh.sn2))
    ang_ok = ~sh.both_n | (angle < tol_ang)
    rows, rhs, valid, tr = _position_rows(R, sh)
    # A plane's centroids are far apart when a plane is seen in different places: the normal's
    # uncertainty times that lever adds to the distance's.
    lever2 = np.sum((sh.ca - sh.cb @ R.T) ** 2, axis=1)
    tol_d = np.maximum(
        cfg.distance_tol, 4.0 * np.sqrt(sh.sc2 + np.where(sh.both_n, sh.sn2, 0) * lever2)
    )
    tol_t = np.maximum(cfg.distance_tol, 4.0 * np.sqrt(sh.sx2))
    base_p = (valid & ang_ok).astype(np.float64)
    wp, wt = base_p.copy(), np.ones(len(tr))
    if t is None:
        t = np.zeros(3)
        for _ in range(6):
            N = (rows * (wp / tol_d**2)[:, None]).T @ rows + np.eye(3) * np.sum(wt / tol_t**2)
            b = (rows * (wp / tol_d**2)[:, None]).T @ rhs + (tr * (wt / tol_t**2)[:, None]).sum(0)
            t_old, t = t, np.linalg.lstsq(N, b, rcond=1e-12)[0]
            if np.abs(t - t_old).max() < 1e-4:
                break
            rp = (rows @ t - rhs) / tol_d
            rt = np.linalg.norm(tr - t, axis=1) / tol_t
            wp, wt = base_p / (1.0 + rp**2), 1.0 / (1.0 + rt**2)
    dist = np.abs(rows @ t - rhs)
    tdist = np.linalg.norm(tr - t, axis=1)
    plane_in = valid & ang_ok & (dist < tol_d)
    target_in = tdist < tol_t
    rot_ok, pos_ok = _determined(R, sh, plane_in, target_in)
    same_side = int(np.sum(plane_in & sh.both_n & (sign > 0)))
    misfit = float(np.sum((dist / tol_d)[plane_in] ** 2) + np.sum((tdist / tol_t)[target_in] ** 2))
    score = (rot_ok and pos_ok, int(plane_in.sum() + target_in.sum()), same_side, -misfit)
    return _Fit(R, t, sign, angle, dist, plane_in, tdist, target_in, rot_ok, pos_ok, score)


def _determined(R, sh: _Shared, plane_in, target_in) -> tuple[bool, bool]:
    """Rotation and position fixed by the inliers: two independent directions among the inlier
    normals and centred targets, and rows of the position equations spanning three dimensions
    (smallest singular value of the unit rows above 0.05)."""
    pn = sh.na[plane_in & sh.both_n]
    xt = sh.xa[target_in]
    dirs = [pn]
    if len(xt) >= 2:
        d = xt - xt.mean(0)
        scale = np.sqrt(np.max(np.sum(d * d, axis=1)))
        dirs.append(d / max(scale, 1e-300))
    D = np.concatenate(dirs)
    rot_ok = len(D) >= 2 and np.linalg.svd(D, compute_uv=False)[1] >= 0.05
    rows, _, _, _ = _position_rows(R, sh)
    M = rows[plane_in]
    if target_in.any():
        M = np.vstack([M, np.tile(np.eye(3), (int(target_in.sum()), 1))])
    pos_ok = len(M) >= 3 and np.linalg.svd(M, compute_uv=False)[2] >= 0.05
    return bool(rot_ok), bool(pos_ok)


def _refine(fit: _Fit, sh: _Shared, cfg: ApproxConfig) -> _Fit:
    """Weighted Kabsch of the inlier normals (signed) and centred inlier targets, then the
    translation, until the inliers no longer change."""
    for _ in range(4):
        pi = fit.plane_in & sh.both_n
        ti = fit.target_in
        u = [sh.nb[pi] * fit.sign[pi, None]]
        v = [sh.na[pi]]
        w = [1.0 / sh.sn2[pi]]
        if ti.sum() >= 2:
            wt = 1.0 / sh.sx2[ti]
            mb = np.average(sh.xb[ti], axis=0, weights=wt)
            ma = np.average(sh.xa[ti], axis=0, weights=wt)
            u.append(sh.xb[ti] - mb)
            v.append(sh.xa[ti] - ma)
            w.append(wt)
        u, v, w = np.concatenate(u), np.concatenate(v), np.concatenate(w)
        if len(u) < 2:
            return fit
        R, q = _kabsch(u, v, w)
        if q < 1e-6:
            return fit
        new = _evaluate(R, sh, cfg)
        if new.score < fit.score:
            return fit
        same = np.array_equal(new.plane_in, fit.plane_in) and np.array_equal(
            new.target_in, fit.target_in
        )
        fit = new
        if same:
            break
    return fit


def _register(a: _Prims, b: _Prims, cfg: ApproxConfig, current=None) -> _Fit | None:
    """Robust registration of frame b onto frame a over all their shared primitives; None when
    they share nothing usable. ``current`` (R, t) is kept unless a hypothesis is better."""
    sh = _shared(a, b)
    if sh.size == 0:
        return None
    best = None
    for R in ([current[0]] if current is not None else []) + _all_targets(sh):
        fit = _refine(_evaluate(R, sh, cfg), sh, cfg)
        best = fit if best is None or fit.score > best.score else best
        # The start, or the fit to all targets, explains (nearly) everything: no search.
        if best.determined and best.n_inliers >= 0.9 * sh.size:
            return _with_shared(best, sh)
    for R in _screen(_hypotheses(sh, cfg), sh, cfg):
        fit = _evaluate(R, sh, cfg)
        if best is None or fit.score > best.score:
            best = fit
    if best is None:
        # No minimal set at all (e.g. only parallel planes): a fit that says so.
        return _with_shared(_evaluate(np.eye(3), sh, cfg), sh)
    return _with_shared(_refine(best, sh, cfg), sh)


def _with_shared(fit: _Fit, sh: _Shared) -> _Fit:
    fit.shared = sh
    return fit


# ---------------------------------------------------------------------------------------------
# The network: spanning tree, re-registration, consistency


def approximate(net: Network, config: ApproxConfig | None = None) -> Approximation:
    """Approximate values of any network (targets, planes or both), with the inconsistent
    (scan, primitive) pairs and the spanning tree (see the module docstring)."""
    cfg = config or ApproxConfig()
    data = _local_data(net)
    n_s = data.n_scans
    local = [_scan_prims(data, j, cfg) for j in range(n_s)]
    A, S, tree = _spanning_tree(net, data, local, cfg)
    data.t_noise = _target_noise(data, A, S)
    local = [_scan_prims(data, j, cfg) for j in range(n_s)]
    order = [j for j, _ in tree]
    for _ in range(cfg.rounds):
        use_p, use_t = _consensus(data, A, S, cfg)
        for j in order:
            _reregister(data, local, A, S, use_p, use_t, j, cfg)
    use_p, use_t = _consensus(data, A, S, cfg)
    for j in order:
        _check_determined(net, data, local, A, S, use_p, use_t, j, cfg)
    inconsistent = _inconsistencies(net, data, A, S, use_p, use_t, cfg)
    for item in inconsistent:
        _LOG.warning("%s: inconsistent correspondence: %s", net.source, item)

    # Object-space primitives from the consistent correspondences.
    obj = _object_prims(data, A, S, use_p, use_t, np.ones(n_s, dtype=bool), cfg)
    targets = np.zeros((data.n_targets, 3))
    targets[obj.target] = obj.x
    planes = np.zeros((data.n_planes, 4))
    planes[obj.plane, :3] = _orient(obj, data, A, S, use_p)
    planes[:, 3] = np.einsum("ki,ki->k", planes[:, :3], _centroids(obj, data.n_planes))
    targets, eops, planes = _to_frame(A, S, targets, planes, net.is_levelled)
    names = tuple((net.scans[j], None if p is None else net.scans[p]) for j, p in tree)
    return Approximation(targets, eops, planes, inconsistent, names)


def _centroids(obj: _Prims, n_planes):
    c = np.zeros((n_planes, 3))
    c[obj.plane] = obj.c
    return c


def _orient(obj: _Prims, data: _Data, A, S, keep_p):
    """One orientation per object-space normal: towards the side most of its points were
    observed from (weighted by points), which for a room's faces is into the room."""
    n = obj.n.copy()
    side = np.zeros(data.n_planes)
    q = np.flatnonzero(keep_p)
    pos = {k: i for i, k in enumerate(obj.plane)}
    for p in q:
        i = pos.get(int(data.pair_plane[p]))
        if i is None:
            continue
        centre = data.s1[p] / data.cnt[p]
        X = A[data.pair_scan[p]] @ centre + S[data.pair_scan[p]]
        # The station is on the positive side when n . (S - X) > 0.
        side[obj.plane[i]] += data.cnt[p] * np.sign(n[i] @ (S[data.pair_scan[p]] - X))
    flip = side[obj.plane] < 0
    n[flip] *= -1
    return n


def _spanning_tree(net, data, local, cfg):
    """Poses chained along a maximum spanning tree of the pairwise registrations (Prim), from
    the best-connected scan; a scan without a usable edge is registered against everything
    placed so far."""
    n_s = data.n_scans
    edges = {}
    weight = np.zeros(n_s)
    for i, j in itertools.combinations(range(n_s), 2):
        fit = _register(local[i], local[j], cfg)
        if fit is not None and fit.determined:
            edges[(i, j)] = fit
            weight[i] += fit.n_inliers
            weight[j] += fit.n_inliers
    A = np.tile(np.eye(3), (n_s, 1, 1))
    S = np.zeros((n_s, 3))
    root = int(np.argmax(weight))
    placed = np.zeros(n_s, dtype=bool)
    placed[root] = True
    tree = [(root, None)]
    heap = []

    def push(i):
        for (a, b), fit in edges.items():
            if i in (a, b):
                other = b if a == i else a
                if not placed[other]:
                    heapq.heappush(heap, (-fit.n_inliers, a, b, i, other))

    push(root)
    while not placed.all():
        while heap and placed[heap[0][4]]:
            heapq.heappop(heap)
        if heap:
            _, a, b, i, j = heapq.heappop(heap)
            fit = edges[(a, b)]
            # fit: x_a = R x_b + t. Relative pose of j in i's scanner frame: x_i = R_ij x_j + t_ij.
            R, t = (fit.R, fit.t) if i == a else (fit.R.T, -fit.R.T @ fit.t)
            A[j], S[j] = A[i] @ R, A[i] @ t + S[i]
            parent = i
        else:
            j, parent = _attach_to_placed(net, data, local, A, S, placed, cfg)
        placed[j] = True
        tree.append((j, parent))
        push(j)
    return A, S, tree


def _attach_to_placed(net, data, local, A, S, placed, cfg):
    """Register the unplaced scan that fits best against the object-space primitives of all
    placed scans; a one-line ValueError when none can be oriented."""
    ones_p = np.ones(len(data.pair_scan), dtype=bool)
    ones_t = np.ones(len(data.t_scan), dtype=bool)
    obj = _object_prims(data, A, S, ones_p, ones_t, placed, cfg)
    best, best_j, fits = None, None, {}
    for j in np.flatnonzero(~placed):
        fit = _register(obj, local[j], cfg)
        fits[int(j)] = fit
        if fit is not None and fit.determined and (best is None or fit.score > best.score):
            best, best_j = fit, int(j)
    if best is None:
        # Name the unplaced scan that shares the most with the placed ones, and why.
        j = max(fits, key=lambda k: -1 if fits[k] is None else fits[k].shared.size)
        _raise_undetermined(net, j, fits[j])
    A[best_j], S[best_j] = best.R, best.t
    return best_j, None


def _reregister(data, local, A, S, use_p, use_t, j, cfg):
    """Register scan j, from its current pose, against the object-space primitives of all the
    other scans (their consistent correspondences), over all its correspondences at once."""
    others = np.ones(data.n_scans, dtype=bool)
    others[j] = False
    obj = _object_prims(data, A, S, use_p, use_t, others, cfg)
    fit = _register(obj, local[j], cfg, current=(A[j], S[j]))
    if fit is not None and fit.determined:
        A[j], S[j] = fit.R, fit.t


def _check_determined(net, data, local, A, S, use_p, use_t, j, cfg):
    """Scan j's pose must be fixed by those of its correspondences that agree with the other
    scans; a one-line ValueError otherwise."""
    others = np.ones(data.n_scans, dtype=bool)
    others[j] = False
    mine = np.zeros(data.n_scans, dtype=bool)
    mine[j] = True
    obj = _object_prims(data, A, S, use_p, use_t, others, cfg)
    own = _object_prims(
        data,
        np.tile(np.eye(3), (data.n_scans, 1, 1)),
        np.zeros((data.n_scans, 3)),
        use_p,
        use_t,
        mine,
        cfg,
    )
    sh = _shared(obj, local[j])
    if sh.size == 0:
        if data.n_scans > 1:
            _raise_undetermined(net, j, None)
        return
    fit = _evaluate(A[j], sh, cfg, t=S[j])
    fit.shared = sh
    # Only the correspondences the consensus kept count.
    fit.plane_in &= np.isin(sh.plane, own.plane)
    fit.target_in &= np.isin(sh.target, own.target)
    fit.rotation_ok, fit.position_ok = _determined(A[j], sh, fit.plane_in, fit.target_in)
    if not fit.determined:
        _raise_undetermined(net, j, fit)


def _consensus(data: _Data, A, S, cfg: ApproxConfig):
    """Which (scan, primitive) correspondences agree with the others at poses (A, S): per
    primitive, the largest group that agrees with one of its members (normals within the angle
    tolerance, centroids on each other's planes, targets within the distance tolerance),
    weighted by points. The rest are inconsistent (e.g. a wrong match)."""
    use_p = np.ones(len(data.pair_scan), dtype=bool)
    if len(data.pair_scan):
        js = data.pair_scan
        o1, o2 = _transform_moments(data.cnt, data.s1, data.s2, A[js], S[js])
        n, has_n, sn, c, sc = _plane_fit(data.cnt, o1, o2, cfg)
        for q in _groups_by_size(data.pair_plane):
            if q.shape[1] > 1:
                agree = _planes_agree(n[q], has_n[q], sn[q], c[q], sc[q], cfg)
                best = np.argmax(np.einsum("gpq,gq->gp", agree, data.cnt[q]), axis=1)
                use_p[q] = agree[np.arange(len(q)), best]
    use_t = np.ones(len(data.t_scan), dtype=bool)
    if len(data.t_scan):
        X = np.einsum("mij,mj->mi", A[data.t_scan], data.x_t) + S[data.t_scan]
        rows = np.arange(len(data.t_scan))
        sx2 = _target_sigma(np.linalg.norm(data.x_t, axis=1), cfg, data.target_noise(rows)) ** 2
        for q in _groups_by_size(data.t_index):
            if q.shape[1] > 1:
                s2 = sx2[q]
                tol = np.maximum(cfg.distance_tol, 4.0 * np.sqrt(s2[:, :, None] + s2[:, None, :]))
                agree = np.linalg.norm(X[q][:, :, None] - X[q][:, None, :], axis=-1) < tol
                use_t[q] = agree[np.arange(len(q)), np.argmax(agree.sum(axis=2), axis=1)]
    return use_p, use_t


def _planes_agree(n, has_n, sn, c, sc, cfg: ApproxConfig):
    """(..., m, m) agreement of m object-space fits of one plane (batched over leading axes):
    normals within ``max(angle_tol, 4 sigma)`` (either sign) and each centroid within
    ``max(distance_tol, 4 sigma)`` of the other's plane, sigma including the normal's error
    over the lever."""
    col, row = (lambda x: x[..., :, None]), (lambda x: x[..., None, :])
    both = col(has_n) & row(has_n)
    sn2 = np.where(has_n, sn, 0.0) ** 2
    s2 = col(sn2) + row(sn2)
    cos = np.abs(np.einsum("...pi,...qi->...pq", n, n))
    ang_ok = ~both | (cos > np.cos(np.maximum(cfg.angle_tol, 4.0 * np.sqrt(s2))))
    diff = c[..., None, :, :] - c[..., :, None, :]  # c_q - c_p
    lever2 = np.sum(diff * diff, axis=-1)
    tol = np.maximum(cfg.distance_tol, 4.0 * np.sqrt(col(sc) ** 2 + row(sc) ** 2 + s2 * lever2))
    off = np.abs(np.einsum("...pi,...pqi->...pq", n, diff))  # |n_p . (c_q - c_p)|
    dist_ok = (~col(has_n) | (off < tol)) & (~row(has_n) | (np.swapaxes(off, -1, -2) < tol))
    return ang_ok & dist_ok | np.eye(n.shape[-2], dtype=bool)


def _raise_undetermined(net, j, fit):
    """A one-line ValueError: which of rotation and position of scan j its consistent
    correspondences leave undetermined, naming them and the inconsistent ones."""
    if fit is None:
        raise ValueError(
            f"{net.source}: scan {net.scans[j]}: its pose is not determined: it shares no "
            "primitive with the scans it is connected to"
        )
    sh = fit.shared
    ok = [f"plane {net.planes[k]}" for k in sh.plane[fit.plane_in]]
    ok += [f"target {net.targets[t]}" for t in sh.target[fit.target_in]]
    bad = [f"plane {net.planes[k]}" for k in sh.plane[~fit.plane_in]]
    bad += [f"target {net.targets[t]}" for t in sh.target[~fit.target_in]]
    what = "rotation" if not fit.rotation_ok else "position"

    def listed(names, most=8):
        # A scan with a scale error contradicts every primitive: name a few and count them all.
        if not names:
            return "none"
        more = f" and {len(names) - most} more" if len(names) > most else ""
        return ", ".join(names[:most]) + more

    need = (
        "two non-parallel planes or three targets that agree"
        if what == "rotation"
        else "plane normals and targets that span three directions"
    )
    raise ValueError(
        f"{net.source}: scan {net.scans[j]}: its {what} is not determined by the primitives it "
        f"shares with the other scans (consistent: {listed(ok)}; inconsistent: "
        f"{listed(bad)}); it needs {need}"
    )


def _inconsistencies(net, data, A, S, use_p, use_t, cfg):
    """The (scan, primitive) correspondences left out as inconsistent, with their misfit
    against the object-space primitive of all other scans: normal angle and RMS distance of
    the scan's points from that plane, or the target's distance."""
    out = []
    for p in np.flatnonzero(~use_p):
        j, k = int(data.pair_scan[p]), int(data.pair_plane[p])
        others = (data.pair_plane == k) & (data.pair_scan != j)
        q = np.flatnonzero(others & use_p) if (others & use_p).any() else np.flatnonzero(others)
        o1, o2 = _transform_moments(
            data.cnt[q], data.s1[q], data.s2[q], A[data.pair_scan[q]], S[data.pair_scan[q]]
        )
        n, _, _, c, _ = _plane_fit(*(v.sum(0, keepdims=True) for v in (data.cnt[q], o1, o2)), cfg)
        m1, m2 = _transform_moments(data.cnt[[p]], data.s1[[p]], data.s2[[p]], A[[j]], S[[j]])
        cnt = data.cnt[p]
        d = n[0] @ c[0]
        msd = n[0] @ (m2[0] / cnt) @ n[0] - 2 * d * (n[0] @ m1[0]) / cnt + d * d
        ln, has, _, _, _ = _plane_fit(data.cnt[[p]], data.s1[[p]], data.s2[[p]], cfg)
        ang = np.arccos(min(1.0, abs(n[0] @ (A[j] @ ln[0])))) if has[0] else np.nan
        out.append(
            Inconsistency(
                net.scans[j], "plane", net.planes[k], float(ang), float(np.sqrt(max(msd, 0.0)))
            )
        )
    for r in np.flatnonzero(~use_t):
        j, t = int(data.t_scan[r]), int(data.t_index[r])
        others = (data.t_index == t) & (data.t_scan != j)
        q = np.flatnonzero(others & use_t) if (others & use_t).any() else np.flatnonzero(others)
        X = np.einsum("mij,mj->mi", A[data.t_scan[q]], data.x_t[q]) + S[data.t_scan[q]]
        mine = A[j] @ data.x_t[r] + S[j]
        out.append(
            Inconsistency(
                net.scans[j],
                "target",
                net.targets[t],
                np.nan,
                float(np.linalg.norm(mine - X.mean(0))),
            )
        )
    return tuple(out)


# ---------------------------------------------------------------------------------------------
# Frame


def _to_frame(A, S, targets, planes, levelled):
    """Origin at the first scan's station; the object frame turned by :func:`_frame_rotation`.
    Returns targets, scan poses (s, 6) and planes in that frame."""
    origin = S[0].copy()
    Q = _frame_rotation(A, levelled)
    S2 = (S - origin) @ Q.T
    A2 = np.einsum("ij,sjk->sik", Q, A)
    t2 = (targets - origin) @ Q.T
    p2 = planes.copy()
    p2[:, :3] = planes[:, :3] @ Q.T
    p2[:, 3] = planes[:, 3] - planes[:, :3] @ origin
    eops = np.array([np.concatenate([s, angles_from_matrix(a.T)]) for a, s in zip(A2, S2)])
    return t2, eops, p2


def _frame_rotation(A, levelled):
    """Rotation Q of the object frame (X' = Q X): the levelled scans' mean vertical axis onto +Z
    (then the free rotation about Z), or the first scan's frame; among candidates, the first
    that keeps every scan's phi at least 30 deg from the gimbal lock at +-90 deg (R[2, 0] =
    sin phi, the object X component of the scanner's z axis)."""
    base = A[0].T
    if levelled.any():
        up = np.mean([A[j][:, 2] for j in np.flatnonzero(levelled)], axis=0)
        base = _rotation_between(up / np.linalg.norm(up), np.array([0.0, 0.0, 1.0]))
    worst = lambda Q: np.max(np.abs((np.einsum("ij,sjk->sik", Q, A))[:, 0, 2]))
    if worst(base) <= np.sin(60 * DEG):
        return base
    cands = [_rz(a) @ base for a in np.arange(1, 12) * 15 * DEG]
    if not levelled.any():
        rng = np.random.default_rng(0)
        for _ in range(64):
            q = rng.standard_normal(4)
            cands.append(_quat(q / np.linalg.norm(q)))
    return min(cands, key=worst) if min(map(worst, cands)) < worst(base) else base


def _rz(a):
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _quat(q):
    w, x, y, z = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def _rotation_between(a, b):
    v = np.cross(a, b)
    c = float(np.dot(a, b))
    if np.linalg.norm(v) < 1e-15:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)
