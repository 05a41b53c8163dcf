"""Closed-form rigid registration of corresponding points, robust to gross errors.

``x_a = R x_b + t`` from corresponding points (targets seen in a scan and already placed in
object space). Least squares (one SVD, Horn 1987) spreads a target that is metres off over the
whole fit, so the correspondences are first screened with what a rigid motion cannot change:
the distance between two targets is the same in both frames. Minimal triples of mutually
consistent correspondences give rotation hypotheses (RANSAC, Fischler & Bolles 1981), each
scored on all correspondences at once; the best is refitted on its inliers.

Written by hand: the registration libraries (open3d's RANSAC and ICP, teaser++) search for
correspondences in clouds; here they are known by name and what is needed is the closed form
over them, with the inlier mask as a result (the robust start relies on it).
"""

from __future__ import annotations

import numpy as np

from ..._model._geometry import kabsch as geometry_kabsch

#: Correspondences the distance screen compares pairwise (its cost is quadratic in them; the
#: scoring of hypotheses on all correspondences is linear).
SCREEN_SIZE = 64


def kabsch(u, v, w):
    """Rotation R minimising ``sum w |R u - v|^2`` (rows u, v; Horn 1987), and the ratio of
    the second to the first singular value of the cross-covariance (0: rotation undetermined)."""
    R, sv = geometry_kabsch(u, v, w, xp=np)
    return R, sv[1] / max(sv[0], 1e-300)


def kabsch_many(u, v):
    """:func:`kabsch` of h sets of points at once, unit weights: u, v (h, k, 3), centred."""
    return rotations_from_cross(np.einsum("hki,hkj->hij", u, v))


def rotations_from_cross(H):
    """The rotations ``R = V D U^T`` of cross-covariances ``H = U S V^T`` (h, 3, 3), the
    reflection removed (Horn 1987); all SVDs in one call (the batched form of
    :func:`tlsjax._model._geometry.kabsch`, which takes one set)."""
    U, _, Vt = np.linalg.svd(H)
    V = np.swapaxes(Vt, -1, -2)
    d = np.sign(np.linalg.det(V @ np.swapaxes(U, -1, -2)))
    V[:, :, 2] *= np.where(d == 0, 1.0, d)[:, None]
    return V @ np.swapaxes(U, -1, -2)


def weighted_fit(xb, xa, w):
    """Weighted Kabsch with translation: (R, t, singular-value ratio)."""
    mb = np.average(xb, axis=0, weights=w)
    ma = np.average(xa, axis=0, weights=w)
    R, q = kabsch(xb - mb, xa - ma, w)
    return R, ma - R @ mb, q


def _triples(C, spread, rng, n):
    """Up to n triples (i, j, k) of the screened correspondences whose three distances agree
    (``C``) and which span a triangle (area above ``spread``), largest first, from the
    correspondences that agree with the most others."""
    support = C.sum(axis=1)
    cand = np.flatnonzero(support >= max(3, 0.5 * support.max()))
    if len(cand) < 3:
        return np.zeros((0, 3), dtype=np.int64)
    draw = rng.choice(cand, size=(8 * n, 3))
    i, j, k = draw.T
    ok = (i != j) & (j != k) & (i != k) & C[i, j] & C[j, k] & C[i, k]
    draw = draw[ok]
    if not len(draw):
        return np.zeros((0, 3), dtype=np.int64)
    return draw[np.argsort(-spread(draw), kind="stable")[:n]]


def robust_fit(xb, xa, tol, sigma2, rng, hypotheses: int):
    """``x_a = R x_b + t`` from corresponding points (m, 3) with gross errors among them.

    ``tol`` (m,): the largest residual of a good correspondence [m]; ``sigma2`` (m,) the
    variances that weight the final fit. Returns (R, t, inlier (m,), singular-value ratio of the
    inliers' fit) or None when no three correspondences agree.
    """
    m = len(xb)
    if m < 3:
        return None
    # Without gross errors the least-squares fit on all correspondences is the answer the
    # search below ends with (its final fit on an inlier set that is then all of them): when
    # every residual of it is within tolerance it is returned at once. A gross error beyond
    # ``tol`` shows in its residual (the fit spreads it over m points) and takes the search.
    if m >= 3:
        R1, t1, q = weighted_fit(xb, xa, 1.0 / sigma2)
        if np.all(np.linalg.norm(xb @ R1.T + t1 - xa, axis=-1) < tol):
            return R1, t1, np.ones(m, dtype=bool), q
    sub = np.sort(rng.choice(m, SCREEN_SIZE, replace=False)) if m > SCREEN_SIZE else np.arange(m)
    pb, pa, ts = xb[sub], xa[sub], tol[sub]
    db = np.linalg.norm(pb[:, None] - pb[None], axis=-1)
    da = np.linalg.norm(pa[:, None] - pa[None], axis=-1)
    C = np.abs(db - da) < ts[:, None] + ts[None, :]

    def spread(t):
        a, b, c = pb[t[:, 0]], pb[t[:, 1]], pb[t[:, 2]]
        return np.linalg.norm(np.cross(b - a, c - a), axis=-1)

    tri = _triples(C, spread, rng, hypotheses)
    tri = tri[spread(tri) > 0.01 * np.max(db) ** 2] if len(tri) else tri
    if not len(tri):
        return None
    ub, ua = pb[tri], pa[tri]  # (h, 3, 3)
    cb, ca = ub.mean(axis=1), ua.mean(axis=1)
    R = kabsch_many(ub - cb[:, None], ua - ca[:, None])
    t = ca - np.einsum("hij,hj->hi", R, cb)
    res = np.linalg.norm(np.einsum("hij,mj->hmi", R, xb) + t[:, None] - xa, axis=-1)
    inl = res < tol
    # Most inliers; among equals the smallest truncated residual (MSAC, Torr & Zisserman 2000).
    score = inl.sum(axis=1) - np.minimum(res / tol, 1.0).sum(axis=1) / (m + 1)
    inlier = inl[int(np.argmax(score))]
    q = 0.0
    for _ in range(3):
        if inlier.sum() < 3:
            return None
        R1, t1, q = weighted_fit(xb[inlier], xa[inlier], 1.0 / sigma2[inlier])
        new = np.linalg.norm(xb @ R1.T + t1 - xa, axis=-1) < tol
        if np.array_equal(new, inlier):
            break
        inlier = new
    return R1, t1, inlier, q
