"""Planar contrast targets from intensity: 2 x 2 checkerboards and white discs on a dark ground.

**Candidates** (voxel cloud): a voxel is dark when its mean intensity, normalised per scan and
range band (``_voxels.intensity_normaliser``), is below ``dark_threshold``. Dark voxels and
the other voxels each form connected components (neighbours within two voxel edges). The
target's size decides which components are candidates: the two black squares of a
checkerboard (touching at its centre), the dark plate around a disc, the white disc inside it,
the two white squares of a checkerboard on a dark ground: each has an RMS radius between 0.12
and 0.75 of the pattern's size and its centroid at (or, for one square alone, near) the
target's centre. Walls, floors and ceilings are far larger; clutter is rarely planar and of
the right size, and what is left is judged by the fit. The midpoint of two square-sized
components closer than 0.9 of the size is a candidate too (the two squares of one
checkerboard, 0.71 of the size apart, that touch only at the centre).

**Fit** (the points near a candidate, second pass): the plane of the plate and its surround
by iteratively trimmed least squares (``_extract._refine``), the points' in-plane coordinates
(u, v) (each point moved onto the plane along its own noise, ``_in_plane``: nearly along its
line of sight on black print) and then the centre by the pattern:

- checkerboard: the saddle point of the intensity, by a least-squares fit of the blurred
  pattern of ``_model/_targets.py``, ``I = dark + (bright - dark) W(u', v'; blur)`` in the
  pattern's turned and shifted frame, 6 unknowns (centre, angle, two levels, blur), to the
  points within 0.4 of the size of the centre (inside the four squares), started from the
  saddle of a quadric fit of the intensity at three angles (``_lsq``, batched);
- circle: the intensity-weighted centroid ``c = sum w_i a_i x_i / sum w_i a_i`` of the points
  within 0.45 of the size, with ``w_i`` the intensity scaled from the dark to the bright level
  (two-class split, Otsu 1979) and clipped to [0, 1], and ``a_i ~ rho_i^2 cos(alpha_i) /
  cos(beta_i)`` the surface each point of an angular grid stands for (without it the denser
  near half of an obliquely seen disc pulls the centroid towards the scanner), iterated on a
  window centred on the estimate.

The centre lies on the plane. **Range bias against the plane**: ``plane_offset`` is the
intensity-weighted centroid of the raw points (as contrast centroiding computes it, Lichti &
Licht 2006, section 5.3: -0.24 mm for iQscene) from the plane, along the line of sight
(positive: farther); ``contrast_bias`` the mean range offset of the dark points from the plane
minus that of the bright ones (the scanner's intensity-dependent range error, which moves the
first and is what the second measures).
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

from .._model._targets import checkerboard_white
from .._stats import MAD_TO_SIGMA
from ._lsq import FIT_POINTS, covariance, fit_batch
from ._spheres import disc_coverage
from ._voxels import crop

#: Levenberg-Marquardt steps of a checkerboard fit (from a quadric saddle start it converges
#: in about 6-10).
_STEPS = 16


def _components(vox, label, link):
    """Connected components of voxel centroids that share ``label`` and lie within ``link``
    of one of their 12 nearest neighbours. The graph is built in CSR form straight from the
    neighbour table (int32 columns, int8 data): a million voxels, not a million times 12 pairs
    of int64 rows and columns."""
    d, idx = vox.neighbours
    m = len(idx)
    ok = (d <= link) & (label[idx] == label[:, None])
    ok[:, 0] = False  # the voxel itself
    indptr = np.concatenate([[0], np.cumsum(ok.sum(axis=1))])
    cols = idx[ok]
    from scipy.sparse import csr_matrix  # at first use: it is slow to import
    from scipy.sparse.csgraph import connected_components

    graph = csr_matrix((np.ones(len(cols), dtype=np.int8), cols, indptr), shape=(m, m))
    return connected_components(graph, directed=False)[1]


#: A candidate's robust thickness may reach this many times the noise of its points (3 sigma:
#: a flat target's voxel centroids, each a mean of many points, scatter far less).
FLATNESS_SIGMAS = 3.0
#: Largest ratio of a candidate's in-plane variances (two squares on a diagonal: 4-10; a
#: line of dark voxels along an edge: hundreds).
MAX_ELONGATION = 25.0
#: Rejected candidates reported per scan (the largest first): the rest are specks.
REPORTED_CANDIDATES = 20


def _robust_plane(P, w, noise, draws: int = 96):
    """Weighted plane of points P (m, 3) with weights w: least median of squares from ``draws``
    triplets (seeded; up to half the points may lie off the target: a stand, a wall behind
    its edge), then weighted least squares of the points within 3 robust scales (at least 3
    times ``noise``), twice. Returns (inlier mask, normal, signed distances, robust scale =
    1.4826 x weighted median |r| of the inliers)."""
    rng = np.random.default_rng(len(P))
    tri = rng.integers(0, len(P), (draws, 3))
    nrm = np.cross(P[tri[:, 1]] - P[tri[:, 0]], P[tri[:, 2]] - P[tri[:, 0]])
    ok = np.linalg.norm(nrm, axis=1) > 0
    sub = rng.choice(len(P), min(len(P), 2000), replace=False)
    best, n, c = np.inf, None, P.mean(axis=0)
    for t, m in zip(tri[ok], nrm[ok] / np.linalg.norm(nrm[ok], axis=1)[:, None]):
        med = _weighted_median(np.abs((P[sub] - P[t[0]]) @ m), w[sub])
        if med < best:
            best, n, c = med, m, P[t[0]]
    if n is None:
        n = np.linalg.eigh((P - c).T @ (P - c))[1][:, 0]
    floor = 3.0 * noise if np.isfinite(noise) else 0.0
    keep = np.abs((P - c) @ n) <= max(3.0 * MAD_TO_SIGMA * best, floor, 1e-9)
    for _ in range(2):
        if keep.sum() < 4:
            keep = np.ones(len(P), dtype=bool)
        ww = w * keep
        c = (ww @ P) / ww.sum()
        Q = P - c
        n = np.linalg.eigh((ww[:, None] * Q).T @ Q)[1][:, 0]
        r = Q @ n
        scale = MAD_TO_SIGMA * _weighted_median(np.abs(r[keep]), w[keep])
        keep = np.abs(r) <= max(3.0 * scale, floor, 1e-9)
    return keep, n, r, scale


def _weighted_median(x, w):
    order = np.argsort(x)
    cw = np.cumsum(w[order])
    return float(x[order][np.searchsorted(cw, 0.5 * cw[-1])]) if len(x) else 0.0


def size_band(options):
    """(lo, hi) [m]: RMS radius of a dark or bright component that may belong to a target of
    the given pattern size. A square of a 2 x 2 checkerboard has 0.20 of the size, the two dark
    squares together 0.41, a disc of radius 0.1-0.45 of the size 0.07-0.32; the band spans
    0.15-0.6 of the size widened by the size tolerance (the size is a prior, not a gate)."""
    s, tol = options.pattern_size, options.size_tolerance
    return 0.15 * s * (1.0 - tol), 0.6 * s * (1.0 + tol)


def planar_candidates(vox, normalise, options):
    """Candidate centres (c, 3) of planar targets on the voxel cloud (module docstring), and the
    components of about a target's size that failed a test: list of (centre (3,), reason)."""
    P = vox.centroid
    if len(P) < 4:
        return np.zeros((0, 3)), []
    dark = normalise(vox.intensity, np.linalg.norm(P, axis=1)) < options.dark_threshold
    comp = _components(vox, dark, 2.0 * vox.size)
    n = np.bincount(comp)
    lo, hi = size_band(options)
    scan_noise = None
    good, rejected = [], []
    order = np.argsort(comp, kind="stable")
    bounds = np.concatenate([[0], np.cumsum(n)])
    for k in np.flatnonzero(n >= 4):
        idx = order[bounds[k] : bounds[k + 1]]
        Q = P[idx]
        c = Q.mean(axis=0)
        rms = float(np.sqrt(np.mean(np.sum((Q - c) ** 2, axis=1))))
        if not 0.5 * lo <= rms <= 2.0 * hi:  # a speck, a wall: not worth a line
            continue
        keep, normal, r, thick = _robust_plane(Q, vox.count[idx].astype(float), np.nan)
        noise = vox.noise(idx, normal)
        if not np.isfinite(noise):  # single-point voxels only: the scan's noise at large
            if scan_noise is None:
                scan_noise = vox.noise(np.arange(len(P)))
            noise = scan_noise
        keep, normal, r, thick = _robust_plane(Q, vox.count[idx].astype(float), noise)
        Qk = Q[keep] - Q[keep].mean(axis=0)
        lam = np.linalg.eigvalsh(Qk.T @ Qk / len(Qk))
        c = Q[keep].mean(axis=0)
        rms = float(np.sqrt(lam.sum()))
        what = "dark" if dark[idx[0]] else "bright"
        where = f"{what} patch of {len(idx)} voxels"
        if not lo <= rms <= hi:
            reason = (
                f"candidate: {where} of RMS radius {rms * 1e3:.0f} mm, outside "
                f"{lo * 1e3:.0f}..{hi * 1e3:.0f} mm for a {options.pattern_size * 1e3:.0f} mm "
                f"pattern (+-{options.size_tolerance:.0%})"
            )
        elif thick > FLATNESS_SIGMAS * max(noise, 1e-4):
            reason = (
                f"candidate: {where} not flat: thickness {thick * 1e3:.1f} mm > "
                f"{FLATNESS_SIGMAS:.0f} x the points' noise {noise * 1e3:.1f} mm"
            )
        elif lam[2] > MAX_ELONGATION * max(lam[1], 1e-30):
            reason = (
                f"candidate: {where} elongated (variances {lam[2] / max(lam[1], 1e-30):.0f}:1 "
                f"> {MAX_ELONGATION:.0f}:1, a line, not a pattern)"
            )
        else:
            good.append((len(idx), c, rms))
            continue
        rejected.append((len(idx), c, reason))
    good.sort(key=lambda g: -g[0])
    cands = [g[1] for g in good]
    # A checkerboard's two squares may be two components (touching only at the centre): their
    # midpoint is a candidate too. The fits decide; duplicates are dropped after them.
    square = 0.3 * options.pattern_size * (1 + options.size_tolerance)
    single = [g[1] for g in good if g[2] < square]
    for a in range(len(single)):
        for b in range(a + 1, len(single)):
            if np.linalg.norm(single[a] - single[b]) < 0.9 * options.pattern_size * (
                1 + options.size_tolerance
            ):
                cands.append(0.5 * (single[a] + single[b]))
    rejected.sort(key=lambda g: -g[0])
    return np.array(cands).reshape(-1, 3), [
        (c, why) for _, c, why in rejected[:REPORTED_CANDIDATES]
    ]


def _plane_frame(P, c0, size):
    """Robust plane of the points within 0.45 size of c0 (on the target itself: a plate stands
    off its wall), all points within 0.72 size taken to it: (mask over P of those within 3
    robust scales of the plane, n towards the scanner, d, robust scale, origin p0 on the plane
    nearest c0, in-plane axes (2, 3), bend). The scale is 1.4826 x the median absolute
    distance (the dark squares' range noise may be several times the white ones'; an RMS
    would be ruled by their outliers); ``bend`` is the RMS departure from the plane of the
    quadric surface fitted to the distances (a sphere or a curved object bends by far more
    than its points' noise; a flat target by a fraction of it)."""
    near = np.linalg.norm(P - c0, axis=1) <= 0.45 * size
    if near.sum() < 6:
        return None
    keep_n, n, _, scale = _robust_plane(P[near], np.ones(int(near.sum())), np.nan)
    c = P[near][keep_n].mean(axis=0)
    d = float(n @ c)
    if d > 0:  # normal towards the scanner at the origin
        n, d = -n, -d
    dist = P @ n - d
    keep = (np.linalg.norm(P - c0, axis=1) <= 0.72 * size) & (np.abs(dist) <= 4.0 * scale)
    p0 = c0 - (n @ c0 - d) * n
    e1 = np.cross([0.0, 0.0, 1.0], n)
    if np.linalg.norm(e1) < 1e-6:
        e1 = np.cross([1.0, 0.0, 0.0], n)
    e1 /= np.linalg.norm(e1)
    E = np.stack([e1, np.cross(n, e1)])
    inner = keep & near
    uv = (P[inner] - p0) @ E.T
    A = np.stack([np.ones(len(uv)), uv[:, 0], uv[:, 1], uv[:, 0] ** 2, uv[:, 0] * uv[:, 1],
                  uv[:, 1] ** 2], 1)  # fmt: skip
    coef = np.linalg.lstsq(A, dist[inner], rcond=None)[0] if len(uv) >= 6 else np.zeros(6)
    bend = A[:, 3:] @ coef[3:]
    bend = float(np.sqrt(np.mean((bend - bend.mean()) ** 2))) if len(uv) else 0.0
    return keep, n, d, float(scale), p0, E, bend


def _target_intensity(normalise, intensity, centre):
    """A target's intensities scaled by one factor, the scan's normaliser at the target's range:
    the normaliser varies with range, and a slope of it across an oblique target would bias
    the centre (by 2 mm at 67 deg incidence in a test room, against 0.3 mm with one factor)."""
    return normalise(intensity, np.full(len(intensity), np.linalg.norm(centre)))


def _checker_model(y, uv, xp=jnp):
    """Intensity of the blurred 2 x 2 checkerboard y = (u0, v0, angle, dark, bright, log
    blur) at in-plane points uv (m, 2)."""
    c, s = xp.cos(y[2]), xp.sin(y[2])
    du, dv = uv[:, 0] - y[0], uv[:, 1] - y[1]
    blur = xp.exp(xp.clip(y[5], -12.0, 0.0))  # 6 um .. 1 m: a diverging start stays finite
    white = checkerboard_white(c * du + s * dv, -s * du + c * dv, blur, xp=xp)
    return y[3] + (y[4] - y[3]) * white


def _checker_residual(y, args):
    UV, intensity, sw = args
    return sw * (intensity - _checker_model(y, UV))


def _effective_weights(y, uv, inten, sigma_pos):
    """Weights ``1 / sqrt(s_I^2 + |grad I|^2 s_pos^2)``: a point's position error moves its
    intensity by the pattern's gradient there (errors in variables), which near an edge
    outweighs the intensity noise ``s_I`` (robust scale of the residuals)."""
    h = 1e-4
    g = [
        (_checker_model(y, uv + dx, np) - _checker_model(y, uv - dx, np)) / (2 * h)
        for dx in (np.array([h, 0.0]), np.array([0.0, h]))
    ]
    res = inten - _checker_model(y, uv, np)
    s_i = max(MAD_TO_SIGMA * np.median(np.abs(res)), 1e-6 * abs(y[4] - y[3]))
    return 1.0 / np.sqrt(s_i**2 + (g[0] ** 2 + g[1] ** 2) * sigma_pos**2), res


def _quadric_start(uv, inten, size):
    """Saddle point and pattern angle of a quadric fit ``I = a + b u + c v + d u^2 + e u v +
    f v^2`` (the axes of a checkerboard are at 45 deg to the Hessian's eigenvectors)."""
    u, v = uv[:, 0], uv[:, 1]
    A = np.stack([np.ones_like(u), u, v, u * u, u * v, v * v], 1)
    coef = np.linalg.lstsq(A, inten, rcond=None)[0]
    H = np.array([[2 * coef[3], coef[4]], [coef[4], 2 * coef[5]]])
    w, V = np.linalg.eigh(H)
    centre = np.zeros(2)
    if w[0] * w[1] < 0:
        centre = np.linalg.solve(H, -coef[1:3])
        if np.linalg.norm(centre) > 0.25 * size:
            centre = np.zeros(2)
    return centre, float(np.arctan2(V[1, 0], V[0, 0]) - np.pi / 4)


def _window(uv, centre, radius):
    with np.errstate(over="ignore", invalid="ignore"):  # a diverged start: an empty window
        return np.sum((uv - centre) ** 2, axis=1) <= radius**2


def _levels(inten):
    """Dark and bright levels of a two-class split of the intensities (Otsu 1979)."""
    x = np.sort(inten)
    n = len(x)
    if n < 4:
        return float(x.min()), float(x.max())
    cs = np.cumsum(x)
    k = np.arange(1, n)
    m0, m1 = cs[:-1] / k, (cs[-1] - cs[:-1]) / (n - k)
    best = int(np.argmax(k * (n - k) * (m1 - m0) ** 2))
    return float(m0[best]), float(m1[best])


def fit_checkerboards(items, options):
    """Saddle points of candidate checkerboards. ``items``: per candidate (uv (m, 2) in-plane
    coordinates, normalised intensity (m,), sigma of the in-plane position (m,)). Returns per
    candidate (centre (2,), covariance (2, 2), levels (dark, bright), pattern rms over
    contrast, blur, converged, points used), or None.

    Three starts per candidate at angles 30 deg apart, fitted with equal weights; the best is
    fitted again on a window centred on its estimate, then with the weights of
    :func:`_effective_weights`, whose covariance is the one reported."""
    s = options.pattern_size
    starts, owner = [], []
    for q, (uv, inten, _) in enumerate(items):
        win = _window(uv, 0.0, 0.4 * s)
        if win.sum() < 8:
            continue
        lo, hi = _levels(inten[win])
        c0, phi0 = _quadric_start(uv[win], inten[win], s)
        for dphi in (0.0, np.pi / 6, np.pi / 3):
            starts.append([c0[0], c0[1], phi0 + dphi, lo, hi, np.log(0.02 * s)])
            owner.append(q)
    out = [None] * len(items)
    if not starts:
        return out
    y = np.asarray(starts)
    UV, inten, sw, _, used = _pack(items, owner, y[:, :2], 0.4 * s)
    y, r, _, ok = fit_batch(_checker_residual, y, (UV, inten, sw), _STEPS, used.max())
    cost = np.where(ok, np.sum(r**2, axis=1) / np.maximum(used, 1), np.inf)
    best = {}
    for i, q in enumerate(owner):
        if q not in best or cost[i] < cost[best[q]]:
            best[q] = i
    qs = sorted(best)
    y = y[[best[q] for q in qs]]
    # The best start again on a window centred on its estimate, then with the weights of
    # _effective_weights (the covariance reported).
    UV, inten, sw, sig, used = _pack(items, qs, y[:, :2], 0.4 * s)
    y, r, _, ok = fit_batch(_checker_residual, y, (UV, inten, sw), _STEPS, used.max())
    for k in range(len(qs)):
        m = used[k]
        if m:  # an estimate that wandered off has an empty window: no weights, no fit
            sw[k, :m], _ = _effective_weights(y[k], UV[k, :m], inten[k, :m], sig[k, :m])
    y2, r2, N2, ok2 = fit_batch(_checker_residual, y, (UV, inten, sw), _STEPS, used.max())
    cov, _ = covariance(r2, N2, used, 6)
    for k, q in enumerate(qs):
        m = used[k]
        dark, bright = sorted(y2[k, 3:5])
        contrast = bright - dark
        res = inten[k, :m] - _checker_model(y2[k], UV[k, :m], np)
        rms = float(np.sqrt(np.mean(res**2))) if m else np.inf
        out[q] = (
            y2[k, :2],
            cov[k, :2, :2],
            (dark, bright),
            rms / contrast if contrast > 0 else np.inf,
            float(np.exp(np.clip(y2[k, 5], -12.0, 0.0))),
            bool(ok2[k]) and bool(ok[k]),
            int(m),
        )
    return out


def _pack(items, owner, centres, radius):
    """Padded arrays of each start's window for :func:`fit_batch`: in-plane points,
    intensities, weights (1 on real rows), position sigmas, rows used."""
    k = len(owner)
    UV = np.zeros((k, FIT_POINTS, 2))
    inten, sw, sig = np.zeros((k, FIT_POINTS)), np.zeros((k, FIT_POINTS)), np.ones((k, FIT_POINTS))
    used = np.zeros(k, dtype=np.int64)
    for i, q in enumerate(owner):
        uv, val, sp = items[q]
        sel = np.flatnonzero(_window(uv, centres[i], radius))
        if len(sel) > FIT_POINTS:
            sel = sel[np.linspace(0, len(sel) - 1, FIT_POINTS).astype(np.int64)]
        m = len(sel)
        UV[i, :m], inten[i, :m], sw[i, :m], sig[i, :m] = uv[sel], val[sel], 1.0, sp[sel]
        used[i] = m
    return UV, inten, sw, sig, used


def fit_circle(uv, inten, area, options, sigma_pos):
    """Intensity-weighted centroid of a white disc (module docstring): (centre (2,), covariance
    (2, 2), (dark, bright), pattern misfit, effective radius, weights (m,), window mask)."""
    s = options.pattern_size
    r_w = 0.45 * s
    c = np.zeros(2)
    win = _window(uv, c, r_w)
    if win.sum() < 8:
        return None
    dark, bright = _levels(inten[win])
    if bright <= dark:
        return None
    w = np.clip((inten - dark) / (bright - dark), 0.0, 1.0)
    for _ in range(4):
        win = _window(uv, c, r_w)
        wa = w[win] * area[win]
        c = (wa @ uv[win]) / max(wa.sum(), 1e-300)
    win = _window(uv, c, r_w)
    wa = w[win] * area[win]
    W = wa.sum()
    scale = np.pi * r_w**2 / area[win].sum()  # the window's area over the points' share
    r_eff = float(np.sqrt(W * scale / np.pi))
    d = uv[win] - c
    rr = np.linalg.norm(d, axis=1)
    misfit = _disc_misfit(d, w[win], wa, r_eff, r_w, s)
    # Noise: intensity noise on the unclipped weights, point positions on all of them.
    res = np.concatenate(
        [inten[win][rr < 0.7 * r_eff] - bright, inten[win][rr > 1.3 * r_eff] - dark]
    )
    sig_i = MAD_TO_SIGMA * np.median(np.abs(res)) / (bright - dark) if len(res) else 0.0
    live = (w[win] > 0) & (w[win] < 1)
    g = (area[win] * live)[:, None] * d / W
    C = sig_i**2 * g.T @ g + np.eye(2) * np.sum((wa / W) ** 2 * sigma_pos[win] ** 2)
    return c, C, (dark, bright), float(misfit), r_eff, w, win


def _disc_misfit(d, w, wa, r_eff, r_w, size):
    """How far the bright blob around the centroid is from a white disc on a dark ground, as a
    share of the contrast: the larger of the dark share inside 0.7 r, the bright share of the
    ring from 1.3 r to the window's edge, and the 4-fold harmonic ``|sum w r^4 exp(4 i phi)| /
    sum w r^4`` of the bright mass (0 for a disc, 0.43 for a square: a checkerboard's white
    square has a disc's area and isotropic second moments); 1 when the ring is not seen all
    round (a blob at a plate's edge) or the second moments are not a disc's (r^2 / 4)."""
    rr = np.linalg.norm(d, axis=1)
    inner = w[rr < 0.7 * r_eff]
    in_ring = (rr > 1.3 * r_eff + 0.01 * size) & (rr < r_w)
    phi = np.arctan2(d[:, 1], d[:, 0])
    sectors = np.unique(((phi[in_ring] + np.pi) / (2 * np.pi) * 8).astype(np.int64) % 8)
    r4 = wa * rr**4
    m4 = abs(np.sum(r4 * np.exp(4j * phi))) / max(r4.sum(), 1e-300)
    lam = np.linalg.eigvalsh((wa[:, None, None] * d[:, :, None] * d[:, None, :]).sum(0) / wa.sum())
    disc = lam[1] > 0 and lam[0] / lam[1] >= 0.6 and abs(np.sqrt(lam.sum() * 2) / r_eff - 1) <= 0.35
    if len(sectors) < 8 or not disc or not len(inner):
        return 1.0
    ring = w[in_ring].mean() if in_ring.any() else 1.0
    return float(max(1.0 - inner.mean(), ring, m4))


def _in_plane(P, inten, frame, sigma_angle):
    """In-plane coordinates (m, 2) of a plate's points and their position sigmas (m,) [m].

    Each point is moved onto the plate's plane ``n.X = d`` as a condition adjustment of the
    point alone would move it (best linear unbiased; one condition on three coordinates): with
    its covariance ``S = s_r^2 u u^T + (rho s_a)^2 (I - u u^T)`` (u the line of sight, s_r the
    range sigma, s_a the angle sigma), ``x = P - S n (n^T S n)^-1 (n.P - d)``. Where the range
    noise outweighs the angle noise (the dark print of a phase scanner: 3-5 times the white's)
    this is nearly along the line of sight and the range noise drops out of the in-plane
    position, which a projection along the normal keeps as ``dr sin(beta)`` (at 57 deg and 4
    mm on black, 3.4 mm a point, the largest checkerboard errors of
    benchmarks/bench_target_rooms.py); where the angle noise dominates it tends to the
    normal. s_r: robust scale (1.4826 MAD) of the points' range residuals from the plane, of
    the dark and the bright points apart (the Otsu split of their intensities); the in-plane
    sigma: ``sqrt(trace(S - S n n^T S / n^T S n) / 2)``."""
    _, n, d, _, p0, E, _ = frame
    rho = np.linalg.norm(P, axis=1)
    u = P / np.maximum(rho, 1e-12)[:, None]
    c = u @ n
    c = np.where(np.abs(c) < 0.05, np.copysign(0.05, c), c)  # grazing: bounded
    dist = P @ n - d
    r = dist / c  # the range error that would put the point on the plane
    dark_level, bright_level = _levels(inten) if len(inten) >= 4 else (0.0, 1.0)
    bright = inten > 0.5 * (dark_level + bright_level)
    pooled = MAD_TO_SIGMA * np.median(np.abs(r)) if len(r) else 0.0
    s_r = np.empty(len(P))
    for cls in (bright, ~bright):
        s_r[cls] = MAD_TO_SIGMA * np.median(np.abs(r[cls])) if cls.sum() >= 5 else pooled
    s_r = np.maximum(s_r, 1e-6)
    s_p = np.maximum(rho * sigma_angle, 1e-7)
    Sn = (s_r**2 * c)[:, None] * u + (s_p**2)[:, None] * (n[None, :] - c[:, None] * u)
    q = s_r**2 * c**2 + s_p**2 * (1.0 - c**2)
    X = P - Sn * (dist / q)[:, None]
    var = np.maximum(s_r**2 + 2 * s_p**2 - np.sum(Sn**2, axis=1) / q, 0.0)
    return (X - p0) @ E.T, np.sqrt(var / 2.0)


def _offsets(P, n, d, los_cos, weights, white):
    """Range offsets (along the line of sight, positive farther) from the plane: of the
    weighted centroid, and of the dark points minus the bright ones."""
    dist = -(P @ n - d) / los_cos
    W = weights.sum()
    centroid = float(weights @ dist / W) if W > 0 else np.nan
    dk, br = white < 0.1, white > 0.9
    bias = float(dist[dk].mean() - dist[br].mean()) if dk.any() and br.any() else np.nan
    return centroid, bias


def _fit_candidate(P, I_raw, normalise, c0, frame, options, kinds, checker_fit):
    """The pattern fits (checkerboard, circle or both) of one candidate, as record dicts."""
    s = options.pattern_size
    keep, n, d, rms, p0, E, _ = frame
    Pk = P[keep]
    rho = np.linalg.norm(Pk, axis=1)
    inten = _target_intensity(normalise, I_raw[keep], p0)
    uv, sigma_pos = _in_plane(Pk, inten, frame, options.sigma_angle)
    cosb = abs(float(n @ p0) / np.linalg.norm(p0))
    cos_alpha = np.hypot(Pk[:, 0], Pk[:, 1]) / rho
    # Each point's own incidence: across a disc seen at 50 deg it varies enough (+-2.5 % at
    # 2.3 m) to move an unweighted centroid by 0.2-0.3 mm.
    area = rho**2 * cos_alpha / np.maximum(np.abs(Pk @ n) / rho, 1e-3)
    recs = {}
    if "checkerboard" in kinds and checker_fit is not None:
        c, C, (dark, bright), prms, blur, ok, used = checker_fit
        win = _window(uv, c, 0.4 * s)
        white = np.clip((inten - dark) / max(bright - dark, 1e-12), 0, 1)
        recs["checkerboard"] = dict(
            centre2=c, cov2=C, levels=(dark, bright), pattern_rms=prms, converged=ok,
            n_points=int(win.sum()), weights=white[win] * area[win], white=white[win], win=win,
        )  # fmt: skip
    if "circle" in kinds:
        fit = fit_circle(uv, inten, area, options, sigma_pos)
        if fit is not None:
            c, C, (dark, bright), misfit, r_eff, w, win = fit
            recs["circle"] = dict(
                centre2=c, cov2=C, levels=(dark, bright), pattern_rms=misfit, converged=True,
                n_points=int(win.sum()), weights=w[win] * area[win], white=w[win], win=win,
                radius=r_eff,
            )  # fmt: skip
    out = []
    for kind, f in recs.items():
        centre = p0 + f["centre2"] @ E
        sd2 = rms**2 / max(len(Pk), 1)
        cov = E.T @ f["cov2"] @ E + np.outer(n, n) * sd2
        offset, bias = _offsets(Pk[f["win"]], n, d, cosb, f["weights"], f["white"])
        uvw = (uv[f["win"]] - f["centre2"]) / (0.45 * s)
        rec = {
            "kind": kind,
            "size": s,
            "centre": centre,
            "covariance": cov,
            "n_points": f["n_points"],
            "rms": rms,
            "incidence": float(np.arccos(min(cosb, 1.0))),
            "coverage": disc_coverage(uvw[:, 0], uvw[:, 1]),
            "plane_offset": offset,
            "contrast_bias": bias,
            "pattern_rms": f["pattern_rms"],
            "contrast": f["levels"][1] - f["levels"][0],
            "converged": f["converged"],
            "shift": float(np.linalg.norm(centre - c0)),
            "points": Pk[f["win"]],
        }
        if kind == "circle":
            rec["radius_fit"] = f["radius"]
        rec["reason"] = _judge(rec, options)
        out.append(rec)
    return out


def _judge(rec, options):
    """The first failed check of a planar target fit, or "". A fit that wandered out of the
    candidate's window says so first (its window then holds no points, which is not the
    cause)."""
    s = options.pattern_size
    if not rec["shift"] <= 0.5 * s:
        return (
            f"the fit wandered {rec['shift'] * 1e3:.0f} mm from the candidate, out of its "
            f"{0.5 * s * 1e3:.0f} mm window (not a {rec['kind']} of this size)"
        )
    if rec["n_points"] < options.min_points:
        return f"too few points ({rec['n_points']} < {options.min_points})"
    if not rec["converged"] or not np.all(np.isfinite(rec["covariance"])):
        return "the pattern fit did not converge"
    if rec["incidence"] > options.max_incidence:
        return (
            f"incidence {np.degrees(rec['incidence']):.0f} deg > "
            f"{np.degrees(options.max_incidence):.0f} deg"
        )
    if options.max_rms is not None and rec["rms"] > options.max_rms:
        return f"plane scale {rec['rms'] * 1e3:.2f} mm > max_rms {options.max_rms * 1e3:.2f} mm"
    if rec["contrast"] < options.min_contrast:
        return f"contrast {rec['contrast']:.2f} < {options.min_contrast:.2f} (not a {rec['kind']})"
    if not rec["pattern_rms"] <= options.max_pattern_rms:
        return (
            f"pattern misfit {rec['pattern_rms']:.2f} of the contrast > "
            f"{options.max_pattern_rms:.2f} (not a {rec['kind']})"
        )
    if rec["kind"] == "circle":
        r = rec.get("radius_fit", np.nan)
        lo, hi = (
            (0.1 * s, 0.45 * s)
            if options.circle_radius is None
            else (0.75 * options.circle_radius, 1.25 * options.circle_radius)
        )
        if not lo <= r <= hi:
            return f"disc radius {r * 1e3:.1f} mm outside {lo * 1e3:.1f}..{hi * 1e3:.1f} mm"
    if rec["coverage"] < options.min_coverage:
        return f"coverage {rec['coverage']:.2f} of the target < {options.min_coverage:.2f}"
    return ""


def _best(recs):
    """Of a candidate's fits (checkerboard and circle), the accepted one with the smaller
    pattern misfit, else the one that got furthest."""
    good = [r for r in recs if r["reason"] == ""]
    if good:
        return min(good, key=lambda r: r["pattern_rms"])
    return min(recs, key=lambda r: np.nan_to_num(r["pattern_rms"], nan=np.inf))


def _unfitted(kind, c0, frame, options, reason):
    """The record of a candidate rejected before any fit."""
    return {
        "kind": kind,
        "size": options.pattern_size,
        "centre": np.asarray(c0, dtype=np.float64),
        "covariance": np.full((3, 3), np.nan),
        "n_points": 0 if frame is None else int(frame[0].sum()),
        "rms": np.nan if frame is None else frame[3],
        "incidence": np.nan,
        "coverage": np.nan,
        "reason": reason,
    }


def scan_planar_targets(scan, vox, normalise, options, rng, bar):
    """Planar target records of one scan (accepted or not), with the candidates of about a
    target's size rejected on the voxel cloud."""
    starts, dropped = planar_candidates(vox, normalise, options)
    kinds = [
        k for k, on in (("checkerboard", options.checkerboards), ("circle", options.circles)) if on
    ]
    out = [_unfitted(kinds[0], c, None, options, why) for c, why in dropped]
    if not len(starts):
        return out
    crops = crop(
        scan, starts, 0.75 * options.pattern_size + 0.02, chunk=options.chunk_points, bar=bar
    )
    frames = []
    for (P, _), c0 in zip(crops, starts):
        fr = _plane_frame(P, c0, options.pattern_size) if len(P) >= 3 else None
        inside = (
            0
            if fr is None
            else int(np.sum(np.linalg.norm(P[fr[0]] - c0, axis=1) < 0.4 * options.pattern_size))
        )
        if inside < options.min_points:  # a speck, or a target too far for this scan's grid
            out.append(
                _unfitted(
                    kinds[0], c0, fr, options, f"too few points ({inside} < {options.min_points})"
                )
            )
            fr = None
        elif fr[6] > max(fr[3], 1e-4):  # not planar (a sphere, clutter)
            reason = (
                f"not planar: bends {fr[6] * 1e3:.2f} mm (RMS) from its plane, more than the "
                f"points' noise {fr[3] * 1e3:.2f} mm"
            )
            out.append(_unfitted(kinds[0], c0, fr, options, reason))
            fr = None
        elif options.max_rms is not None and fr[3] > options.max_rms:
            reason = f"plane scale {fr[3] * 1e3:.2f} mm > max_rms {options.max_rms * 1e3:.2f} mm"
            out.append(_unfitted(kinds[0], c0, fr, options, reason))
            fr = None
        frames.append(fr)
    checker = [None] * len(starts)
    if "checkerboard" in kinds:
        items, where = [], []
        for q, ((P, I_raw), fr) in enumerate(zip(crops, frames)):
            if fr is None or I_raw is None:
                continue
            keep, p0 = fr[0], fr[4]
            inten = _target_intensity(normalise, I_raw[keep], p0)
            uv, sigma_pos = _in_plane(P[keep], inten, fr, options.sigma_angle)
            items.append((uv, inten, sigma_pos))
            where.append(q)
        for q, fit in zip(where, fit_checkerboards(items, options)):
            checker[q] = fit
    for q, ((P, I_raw), c0) in enumerate(zip(crops, starts)):
        if frames[q] is None or I_raw is None:
            continue
        recs = _fit_candidate(P, I_raw, normalise, c0, frames[q], options, kinds, checker[q])
        if recs:
            out.append(_best(recs))
    return out
