"""Robust closed-form registration of frame b onto frame a, ``x_a = R x_b + t``, over their
shared planes and targets.

Targets alone: :func:`._rigid.robust_fit` (minimal triples screened by the invariant distances,
scored on all targets, refitted on the inliers). With planes: rotation hypotheses from minimal
sets (two non-parallel planes with the four sign combinations of their normals, or the targets'
robust fit), screened all at once by the normals they make agree, then each scored on all
shared primitives: the angle between normals (their signs follow from the hypothesis), the
position by iteratively reweighted least squares from the condition that each plane's centroid
in one scan lies on the plane in the other (``n_a . (R c_b + t) = d_a``, free of the normal's
sign) and from the targets (``R x_b + t = x_a``). The best hypothesis (most consistent
primitives; on a tie, the one that keeps most planes on the same side of both stations) is
refined on its inliers by weighted Kabsch (Horn 1987) of the signed normals and centred targets
(Khoshelham 2016, plane-to-plane registration in closed form).
"""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np

from ..._units import DEG
from ._config import ApproxConfig
from ._local import Prims
from ._rigid import kabsch, robust_fit


@dataclasses.dataclass(eq=False)
class Shared:
    """The correspondences of two frames, aligned: planes (normals, whether both have one,
    their variance sum, centroids, centroid variance sum, ids) and targets (points, variance
    sum, ids)."""

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


def shared(a: Prims, b: Prims) -> Shared:
    k, ia, ib = np.intersect1d(a.plane, b.plane, assume_unique=True, return_indices=True)
    t, ta, tb = np.intersect1d(a.target, b.target, assume_unique=True, return_indices=True)
    both = a.has_n[ia] & b.has_n[ib]
    return Shared(
        a.n[ia],
        b.n[ib],
        both,
        np.where(both, a.sn[ia] ** 2 + b.sn[ib] ** 2, np.inf),
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
class Fit:
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
    shared: Shared | None = None

    @property
    def determined(self) -> bool:
        return self.rotation_ok and self.position_ok

    @property
    def n_inliers(self) -> int:
        return int(self.plane_in.sum() + self.target_in.sum())


def target_tolerance(sh: Shared, cfg: ApproxConfig):
    """Largest distance [m] of a consistent target correspondence."""
    return np.maximum(cfg.distance_tol, 4.0 * np.sqrt(sh.sx2))


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


def _plane_hypotheses(sh: Shared, cfg: ApproxConfig):
    """Rotations of pairs of non-parallel shared planes with the sign combinations their angle
    allows, from the best-determined ``cfg.minimal_planes`` planes."""
    out = []
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


def _screen(hyps, sh: Shared, cfg: ApproxConfig, keep: int = 8):
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


def position_rows(R, sh: Shared):
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


def _translation(rows, rhs, wp, tol_d, tr, tol_t):
    """IRLS (Cauchy weights) for the translation from plane rows and target differences."""
    base_p, wt = wp.copy(), np.ones(len(tr))
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
    return t


def evaluate(R, sh: Shared, cfg: ApproxConfig, t=None) -> Fit:
    """Score a rotation on all correspondences: signs and angles of the normals, the
    translation (IRLS with Cauchy weights, unless ``t`` is given) and the inliers."""
    c = np.einsum("ki,ki->k", sh.na, sh.nb @ R.T)
    sign = np.where(c < 0, -1.0, 1.0)
    angle = np.where(sh.both_n, np.arccos(np.clip(np.abs(c), 0.0, 1.0)), np.nan)
    tol_ang = np.maximum(cfg.angle_tol, 4.0 * np.sqrt(sh.sn2))
    ang_ok = ~sh.both_n | (angle < tol_ang)
    rows, rhs, valid, tr = position_rows(R, sh)
    # A plane's centroids are far apart when a plane is seen in different places: the normal's
    # uncertainty times that lever adds to the distance's.
    lever2 = np.sum((sh.ca - sh.cb @ R.T) ** 2, axis=1)
    tol_d = np.maximum(
        cfg.distance_tol, 4.0 * np.sqrt(sh.sc2 + np.where(sh.both_n, sh.sn2, 0) * lever2)
    )
    tol_t = target_tolerance(sh, cfg)
    if t is None:
        t = _translation(rows, rhs, (valid & ang_ok).astype(np.float64), tol_d, tr, tol_t)
    dist = np.abs(rows @ t - rhs)
    tdist = np.linalg.norm(tr - t, axis=1)
    plane_in = valid & ang_ok & (dist < tol_d)
    target_in = tdist < tol_t
    rot_ok, pos_ok = determined(R, sh, plane_in, target_in)
    same_side = int(np.sum(plane_in & sh.both_n & (sign > 0)))
    misfit = float(np.sum((dist / tol_d)[plane_in] ** 2) + np.sum((tdist / tol_t)[target_in] ** 2))
    score = (rot_ok and pos_ok, int(plane_in.sum() + target_in.sum()), same_side, -misfit)
    return Fit(R, t, sign, angle, dist, plane_in, tdist, target_in, rot_ok, pos_ok, score)


def determined(R, sh: Shared, plane_in, target_in) -> tuple[bool, bool]:
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
    pos_ok = bool(target_in.any())
    if not pos_ok:
        M = position_rows(R, sh)[0][plane_in]
        pos_ok = len(M) >= 3 and np.linalg.svd(M, compute_uv=False)[2] >= 0.05
    return bool(rot_ok), bool(pos_ok)


def _refine(fit: Fit, sh: Shared, cfg: ApproxConfig) -> Fit:
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
        R, q = kabsch(u, v, w)
        if q < 1e-6:
            return fit
        new = evaluate(R, sh, cfg)
        if new.score < fit.score:
            return fit
        same = np.array_equal(new.plane_in, fit.plane_in) and np.array_equal(
            new.target_in, fit.target_in
        )
        fit = new
        if same:
            break
    return fit


def _target_fit(sh: Shared, cfg: ApproxConfig, rng):
    """The robust fit to the shared targets as a :class:`Fit` (None when none agree)."""
    out = robust_fit(sh.xb, sh.xa, target_tolerance(sh, cfg), sh.sx2, rng, cfg.hypotheses)
    if out is None:
        return None
    R, t, inlier, _ = out
    fit = evaluate(R, sh, cfg, t=t)
    fit.target_in &= inlier | (fit.tdist < target_tolerance(sh, cfg))
    return fit


def register(a: Prims, b: Prims, cfg: ApproxConfig, rng, current=None) -> Fit | None:
    """Robust registration of frame b onto frame a over all their shared primitives; None when
    they share nothing. ``current`` (R, t) is kept when it explains (nearly) everything."""
    sh = shared(a, b)
    if sh.size == 0:
        return None
    best = None
    if current is not None:
        best = _refine(evaluate(current[0], sh, cfg), sh, cfg)
        if best.determined and best.n_inliers >= 0.9 * sh.size:
            return _with_shared(best, sh)
    if len(sh.target) >= 3:
        fit = _target_fit(sh, cfg, rng)
        if fit is not None and not len(sh.plane):
            # Targets alone: the robust fit is the registration.
            return _with_shared(fit if best is None or fit.score > best.score else best, sh)
        if fit is not None:
            fit = _refine(fit, sh, cfg)
            best = fit if best is None or fit.score > best.score else best
            if best.determined and best.n_inliers >= 0.9 * sh.size:
                return _with_shared(best, sh)
    for R in _screen(_plane_hypotheses(sh, cfg), sh, cfg):
        fit = evaluate(R, sh, cfg)
        if best is None or fit.score > best.score:
            best = fit
    if best is None:
        # No minimal set at all (e.g. only parallel planes): a fit that says so.
        return _with_shared(evaluate(np.eye(3), sh, cfg), sh)
    return _with_shared(_refine(best, sh, cfg), sh)


def _with_shared(fit: Fit, sh: Shared) -> Fit:
    fit.shared = sh
    return fit
