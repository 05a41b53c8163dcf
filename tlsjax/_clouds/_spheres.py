"""Sphere targets of known radii: detection on the voxel cloud, then a least-squares fit.

**Detection: a Hough vote on curvature-filtered normals.** Every voxel centroid gets a local
frame from its nearest neighbours (PCA; the normal turned towards the scanner) and a quadric
height fit ``z = a x^2 + b x y + c y^2 + d x + e y + f`` in that frame, whose principal
curvatures are the eigenvalues of ``-[[2a, b], [b, 2c]]``. Where both lie near ``1 / R`` (an
umbilic, convex patch: a sphere of radius R seen from outside; planes, edges, cylinders and
room corners do not pass) the voxel votes for the centre ``x + (f - R) n``. Votes are counted
in cells of R / 3 (each with its 26 neighbours); local maxima with enough votes are
candidates. Why a vote and not RANSAC: one linear pass over the voxels finds every sphere of
every radius at once, whatever their number, with no sampling schedule per sphere, and a
sphere's votes do not depend on how much else the scan holds; RANSAC on local neighbourhoods
would need seeds everywhere (cost ~ points x iterations) for the same answer.

**Fit.** The points near a candidate (second pass) within ``max(0.3 R, 1 cm)`` of its shell
and on the scanner's side of the centre enter an iteratively trimmed, weighted least-squares
fit of the centre (Levenberg-Marquardt of ``_lsq``, batched over the scan's candidates) of the
radial residuals ``r_i = |x_i - c| - R``, with the radius known (3 unknowns) and again free
(4 unknowns: the radius misfit). A scanner sees at most the near hemisphere, and its range noise
lies along the line of sight: with the range sigma ``sigma_rho sec(beta)`` of SPEC section 5
(beta the incidence on the sphere) and the angular sigma ``rho sigma_a`` across, the radial
residual has variance ``sigma_rho^2 + (rho sigma_a sin beta)^2``, its weight. The centre's
covariance is ``s0^2 (J^T W J)^-1`` with the a posteriori variance factor.

**Coverage** of the visible hemisphere: the unit vectors ``(x_i - c) / R`` projected onto the
plane across the line of sight fill a disc (sampled uniformly by an angular grid); coverage is
the share of 32 equal-area cells of that disc (4 rings, 8 sectors) holding a point, divided by
the share expected for that many uniformly spread points, ``1 - exp(-n / 32)``. A sphere
half hidden behind something covers about 0.5.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .._stats import MAD_TO_SIGMA
from ._lsq import FIT_POINTS, covariance, fit_batch
from ._voxels import NEIGHBOURS as _NEIGHBOURS
from ._voxels import voxel_keys

_BLOCK = 100_000


def local_surfaces(vox):
    """Per voxel centroid of a :class:`~tlsjax._clouds._voxels.VoxelCloud`: unit normal towards
    the scanner (m, 3), principal curvatures (m, 2) (ascending; positive = convex towards the
    scanner; NaN where not computed) and the height offset f (m,). The quadric is fitted only
    where the neighbourhood is not flat to 1e-3 (surface variation ``lambda_0 / sum lambda``,
    Pauly et al. 2002): a sphere's neighbourhood of half its radius has about 0.01, a plane
    scanned at a few millimetres of noise less than 0.006."""
    P = vox.centroid
    m = len(P)
    normal = np.zeros((m, 3))
    kappa = np.full((m, 2), np.nan)
    offset = np.zeros(m)
    if m < _NEIGHBOURS:
        return normal, kappa, offset
    _, idx = vox.neighbours
    for a in range(0, m, _BLOCK):
        b = min(m, a + _BLOCK)
        Q = P[idx[a:b]] - P[a:b, None, :]
        Qc = Q - Q.mean(axis=1, keepdims=True)
        lam, V = np.linalg.eigh(np.einsum("bki,bkj->bij", Qc, Qc))
        n = V[:, :, 0]
        n *= -np.sign(np.einsum("bi,bi->b", n, P[a:b]) + 1e-300)[:, None]
        normal[a:b] = n
        curved = np.flatnonzero(lam[:, 0] > 1e-3 * lam.sum(axis=1))
        n, Q, V = n[curved], Q[curved], V[curved]
        e1, e2 = V[:, :, 2], np.cross(n, V[:, :, 2])
        x, y, z = (np.einsum("bki,bi->bk", Q, e) for e in (e1, e2, n))
        A = np.stack([x * x, x * y, y * y, x, y, np.ones_like(x)], axis=2)
        N = np.einsum("bki,bkj->bij", A, A)
        N += np.eye(6) * 1e-12 * np.trace(N, axis1=1, axis2=2)[:, None, None]
        coef = np.linalg.solve(N, np.einsum("bki,bk->bi", A, z)[..., None])[..., 0]
        H = np.stack([2 * coef[:, 0], coef[:, 1], coef[:, 1], 2 * coef[:, 2]], 1).reshape(-1, 2, 2)
        kappa[a + curved] = np.linalg.eigvalsh(-H)
        offset[a + curved] = coef[:, 5]
    return normal, kappa, offset


def _peaks(votes, cell, min_votes):
    """Centres of vote clusters: local maxima of the 27-cell box counts (>= min_votes), each
    the mean of the votes in its box, strongest first."""
    if len(votes) < min_votes:
        return np.zeros((0, 3)), np.zeros(0)
    keys = voxel_keys(votes, cell)
    uk, cnt = np.unique(keys, return_counts=True)
    d = np.arange(-1, 2)
    shifts = np.stack(np.meshgrid(d, d, d, indexing="ij"), -1).reshape(-1, 3)
    codes = (shifts[:, 0] << 42) + (shifts[:, 1] << 21) + shifts[:, 2]
    box = np.zeros(len(uk))
    nb = uk[:, None] + codes[None, :]
    pos = np.clip(np.searchsorted(uk, nb), 0, len(uk) - 1)
    hit = uk[pos] == nb
    nbc = np.where(hit, cnt[pos], 0)
    box = nbc.sum(axis=1)
    nb_box = np.where(hit, box[pos], -1)
    peak = (box >= min_votes) & (box >= nb_box.max(axis=1))
    # Ties between neighbouring cells: keep the smaller key.
    tie = hit & (box[pos] == box[:, None]) & (nb < uk[:, None])
    peak &= ~tie.any(axis=1)
    order = np.flatnonzero(peak)[np.argsort(-box[peak], kind="stable")]
    vpos = np.searchsorted(uk, keys)
    centres = []
    for p in order:
        members = np.isin(uk[vpos], nb[p][hit[p]])
        centres.append(votes[members].mean(axis=0))
    return np.asarray(centres).reshape(-1, 3), box[order].astype(np.float64)


def sphere_candidates(normal, kappa, offset, centroids, radii, min_votes: int):
    """Candidate centres (c, 3), their radius index (c,) and votes (c,), strongest first per
    radius; candidates of one radius closer than that radius to a stronger one are dropped."""
    out_c, out_r, out_v = [], [], []
    for k, R in enumerate(radii):
        ok = (kappa[:, 0] > 0.45 / R) & (kappa[:, 1] < 2.2 / R)
        votes = centroids[ok] + (offset[ok] - R)[:, None] * normal[ok]
        centres, box = _peaks(votes, R / 3.0, min_votes)
        kept = []
        for c in centres:
            if all(np.linalg.norm(c - q) > R for q in kept):
                kept.append(c)
        out_c += kept
        out_r += [k] * len(kept)
        out_v += list(box[: len(kept)])
    return np.asarray(out_c).reshape(-1, 3), np.asarray(out_r, dtype=np.int64), np.asarray(out_v)


def _sphere_residual(y, args):
    """Weighted radial residuals of the three sphere models in one function (one compiled
    program): y = (centre - start (3), t). ``mode`` = (free, offset):

    - (0, 0) "known": ``|x_i - c| - R``; t is pinned to 0 by an extra row;
    - (1, 0) "free": ``|x_i - c| - (R + t)``, t the radius misfit;
    - (0, 1) "offset": ``|x_i - t (u_i - u_c) - c| - R``: t a range offset common to the
      sphere's points, each moved back along its own ray u_i, the centre along its ray u_c;
      c is then the apparent centre, the one the scanner's observation model describes (a
      rangefinder offset A0 moves every point by A0 along its ray, which magnifies the sphere
      by A0 / D; a fit with the radius known takes that for a shift of the centre).
    """
    P, sw, R, U, c0, mode = args
    X = c0 + y[:3]
    uc = X / jnp.sqrt(jnp.sum(X * X))
    d = P - y[:3] - mode[1] * y[3] * (U - uc)
    r = sw * (jnp.sqrt(jnp.sum(d * d, axis=1)) - R - mode[0] * y[3])
    pin = (1.0 - mode[0] - mode[1]) * y[3] * jnp.max(sw)
    return jnp.concatenate([r, pin[None]])


#: Sphere models: (free, offset) switches of :func:`_sphere_residual`.
SPHERE_MODELS = {"known": (0.0, 0.0), "free": (1.0, 0.0), "offset": (0.0, 1.0)}


def radial_sigma(P, c, sigma_range, sigma_angle):
    """Standard deviation of the radial residual of points P (scanner space) of a sphere
    centred at c: ``sqrt(sigma_rho^2 + (rho sigma_a sin beta)^2)`` (module docstring)."""
    rho = np.linalg.norm(P, axis=1)
    n = P - c
    n /= np.maximum(np.linalg.norm(n, axis=1), 1e-12)[:, None]
    cosb = np.abs(np.einsum("ij,ij->i", n, P)) / np.maximum(rho, 1e-12)
    return np.sqrt(sigma_range**2 + (rho * sigma_angle) ** 2 * np.clip(1 - cosb**2, 0, 1))


def _disc_coordinates(P, c, R):
    """The unit vectors ``(x_i - c) / R`` projected onto the plane across the line of sight
    to c: (a, b) on the unit disc."""
    los = c / np.linalg.norm(c)
    u = (P - c) / R
    u -= np.outer(u @ los, los)
    e1 = np.cross(los, [0.0, 0.0, 1.0])
    if np.linalg.norm(e1) < 1e-6:
        e1 = np.cross(los, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(los, e1)
    return u @ e1, u @ e2


def residual_trend(P, c, R, res) -> float:
    """RMS [m] of the quadratic trend ``1, a, b, a^2, a b, b^2`` over the visible disc
    (:func:`_disc_coordinates`) fitted to the radial residuals ``res``: a sphere leaves noise
    (a trend of about ``sigma sqrt(6 / n)``), a cylinder or a bump that voted for a centre
    leaves its shape (residuals of one sign along its axis, the other across)."""
    if len(P) < 12:
        return np.nan
    a, b = _disc_coordinates(P, c, R)
    A = np.stack([np.ones_like(a), a, b, a * a, a * b, b * b], 1)
    fit = A @ np.linalg.lstsq(A, res, rcond=None)[0]
    return float(np.sqrt(np.mean(fit**2)))


def coverage(P, c, R):
    """Share of the visible hemisphere covered (module docstring), in [0, 1]."""
    if len(P) == 0:
        return 0.0
    return disc_coverage(*_disc_coordinates(P, c, R))


def disc_coverage(a, b) -> float:
    """Share of the unit disc covered by points (a, b): filled cells of 32 equal-area cells (4
    rings, 8 sectors) over the share that as many uniformly spread points fill on average,
    ``1 - exp(-n / 32)``; in [0, 1]."""
    if len(a) == 0:
        return 0.0
    ring = np.minimum((4 * (a * a + b * b)).astype(np.int64), 3)
    sector = np.minimum(((np.arctan2(b, a) + np.pi) / (2 * np.pi) * 8).astype(np.int64), 7)
    filled = len(np.unique(ring * 8 + sector)) / 32.0
    return float(min(1.0, filled / (1.0 - np.exp(-len(a) / 32.0))))


def _shell(P, c, R, tol):
    """Points within ``tol`` of the shell and on the scanner's side of the centre."""
    d = P - c
    r = np.linalg.norm(d, axis=1) - R
    front = d @ (-c / np.linalg.norm(c)) > -0.1 * R
    return (np.abs(r) < tol) & front


def fit_spheres(crops, starts, radii, options, rng):
    """Fit every candidate: ``crops`` (points (m, 3)) per candidate, ``starts`` (c, 3),
    ``radii`` (c,) nominal. Returns one dict per candidate (see :func:`_record`)."""
    k = len(starts)
    if k == 0:
        return []
    centres = np.asarray(starts, dtype=np.float64).copy()
    radii = np.asarray(radii, dtype=np.float64)
    tol = np.maximum(0.3 * radii, 0.01)
    pts = []
    for q in range(k):
        P = crops[q]
        sel = np.flatnonzero(_shell(P, centres[q], radii[q], tol[q])) if len(P) else []
        pts.append(P[np.sort(rng.permutation(sel)[:FIT_POINTS])] if len(sel) else P[:0])
    inl = [np.ones(len(p), dtype=bool) for p in pts]
    for _ in range(4):
        y, r, _, ok = _fit("known", centres, radii, pts, inl, options)
        changed = False
        for q in range(k):
            if not len(pts[q]):
                continue
            centres[q] = y[q, :3]
            res = np.linalg.norm(pts[q] - centres[q], axis=1) - radii[q]
            sig = radial_sigma(pts[q], centres[q], options.sigma_range, options.sigma_angle)
            scale = MAD_TO_SIGMA * np.median(np.abs(res[inl[q]])) if inl[q].any() else 0.0
            lim = np.maximum(3.0 * max(scale, 1e-12), 3.0 * sig)
            new = (np.abs(res) <= lim) & _shell(pts[q], centres[q], radii[q], tol[q])
            changed |= not np.array_equal(new, inl[q])
            inl[q] = new
        if not changed:
            break
    fits = {m: _fit(m, centres, radii, pts, inl, options) for m in ("free", options.sphere_model)}
    return [_record(q, pts[q][inl[q]], radii[q], fits, options) for q in range(k)]


def _fit(model, centres, radii, pts, inl, options):
    """One batched fit of ``model`` (:data:`SPHERE_MODELS`) from ``centres`` (k, 3): values
    (k, 4) with the absolute centre, residuals, normal matrices, converged."""
    k = len(centres)
    P = np.ones((k, FIT_POINTS, 3))  # padding away from the centre (|x - c| > 0)
    U = np.zeros((k, FIT_POINTS, 3))
    sw = np.zeros((k, FIT_POINTS))
    for q in range(k):
        m = len(pts[q])
        if not m:
            continue
        P[q, :m] = pts[q] - centres[q]
        U[q, :m] = pts[q] / np.linalg.norm(pts[q], axis=1)[:, None]
        sig = radial_sigma(pts[q], centres[q], options.sigma_range, options.sigma_angle)
        sw[q, :m] = np.where(inl[q], 1.0 / sig, 0.0)
    mode = np.tile(SPHERE_MODELS[model], (k, 1))
    used = max(len(p) for p in pts)
    args = (P, sw, radii, U, centres, mode)
    y, r, N, ok = fit_batch(_sphere_residual, np.zeros((k, 4)), args, rows=used)
    y = y.copy()
    y[:, :3] += centres
    return y, r[:, :-1], N, ok


def _record(q, P, R, fits, options):
    """The fit of candidate q as a dict: centre and covariance of ``options.sphere_model``,
    the free radius and its sigma, statistics."""
    n = len(P)
    y, r, N, ok = (a[q : q + 1] for a in fits[options.sphere_model])
    cov, s02 = covariance(r, N, [n], 3 if options.sphere_model == "known" else 4)
    yf, rf, Nf, okf = (a[q : q + 1] for a in fits["free"])
    covf, _ = covariance(rf, Nf, [n], 4)
    c = y[0, :3].copy()
    radius = R + yf[0, 3] if options.sphere_model == "free" else R
    res = np.linalg.norm(P - c, axis=1) - radius
    if options.sphere_model == "offset":
        uc = c / np.linalg.norm(c)
        U = P / np.linalg.norm(P, axis=1)[:, None]
        res = np.linalg.norm(P - y[0, 3] * (U - uc) - c, axis=1) - R
    return {
        "trend": residual_trend(P, c, R, res),
        "kind": "sphere",
        "size": float(R),
        "centre": c,
        "covariance": cov[0, :3, :3],
        "n_points": n,
        "rms": float(np.sqrt(np.mean(res**2))) if n else np.nan,
        "incidence": 0.0,
        "coverage": coverage(P, c, R),
        "radius_fit": float(R + yf[0, 3]),
        "radius_sigma": float(np.sqrt(covf[0, 3, 3])) if np.isfinite(covf[0, 3, 3]) else np.nan,
        "converged": bool(ok[0] and okf[0]),
        "s0": float(np.sqrt(s02[0])) if np.isfinite(s02[0]) else np.nan,
        "points": P,
    }
