"""The approximate values of a network of targets only, vectorised over its observations.

The same steps as the general path (:mod:`._approximate`) with points alone, where each needs
only sums over observations: a scan is placed by one robust fit (:func:`._rigid.robust_fit`)
against the mean points of the placed scans' targets, and the refinement re-registers every
scan at once (one weighted Kabsch per scan from sums over its observations, all scans' SVDs in
one call) against the mean of the other scans' points of each target. A few hundred array
operations in all, so a room of a hundred targets takes about a millisecond. Any failure (a
scan that the targets it shares do not fix) falls back to the general path, which names it.
"""

from __future__ import annotations

import numpy as np

from ._config import ApproxConfig
from ._local import Data, target_sigma
from ._rigid import robust_fit, rotations_from_cross


def _per_scan(data: Data, values, weights=None):
    """Sums of per-row ``values`` (m, ...) over each scan's rows, (s, ...)."""
    flat = values.reshape(len(values), -1)
    w = np.ones(len(values)) if weights is None else weights
    out = np.stack(
        [np.bincount(data.t_scan, flat[:, i] * w, data.n_scans) for i in range(flat.shape[1])],
        axis=-1,
    )
    return out.reshape((data.n_scans,) + values.shape[1:])


def _per_target(data: Data, values, keep):
    flat = values.reshape(len(values), -1) * keep[:, None]
    return np.stack(
        [np.bincount(data.t_index, flat[:, i], data.n_targets) for i in range(flat.shape[1])],
        axis=-1,
    )


def place_scans(data: Data, cfg: ApproxConfig, order, rng):
    """Poses (A, S) chained over ``order`` (the first scan's frame is the object frame), each
    scan fitted robustly to the mean points of the scans placed before it, and the inlier mask
    of the rows (False: an outlier of its scan's fit). None when a scan is not fixed."""
    n_s = data.n_scans
    A = np.tile(np.eye(3), (n_s, 1, 1))
    S = np.zeros((n_s, 3))
    rng_rows = np.linalg.norm(data.x_t, axis=1)
    sx = target_sigma(rng_rows, cfg)
    inlier = np.ones(len(data.t_scan), dtype=bool)
    first = data.t_scan == order[0]
    t_sum = _per_target(data, data.x_t, first)
    t_cnt = np.bincount(data.t_index[first], minlength=data.n_targets).astype(np.float64)
    t_var = np.bincount(data.t_index[first], sx[first] ** 2, data.n_targets)
    regs = []
    for j in order[1:]:
        rows = np.flatnonzero((data.t_scan == j) & (t_cnt[data.t_index] > 0))
        t = data.t_index[rows]
        xa = t_sum[t] / t_cnt[t, None]
        s2 = sx[rows] ** 2 + t_var[t] / t_cnt[t] ** 2
        tol = np.maximum(cfg.distance_tol, 4 * np.sqrt(s2))
        out = robust_fit(data.x_t[rows], xa, tol, s2, rng, cfg.hypotheses)
        if out is None or out[3] < 0.05 or out[2].sum() < 3:
            return None
        A[j], S[j], ok, _ = out
        inlier[rows] = ok
        mine = np.flatnonzero(data.t_scan == j)
        keep = np.ones(len(mine), dtype=bool)
        keep[np.searchsorted(mine, rows)] = ok
        mine = mine[keep]
        X = data.x_t[mine] @ A[j].T + S[j]
        for i in range(3):
            t_sum[:, i] += np.bincount(data.t_index[mine], X[:, i], data.n_targets)
        t_cnt += np.bincount(data.t_index[mine], minlength=data.n_targets)
        t_var += np.bincount(data.t_index[mine], sx[mine] ** 2, data.n_targets)
        regs.append((int(j), int(ok.sum()), len(rows)))
    return A, S, inlier, regs


def refine_scans(data: Data, A, S, use, cfg: ApproxConfig):
    """Every scan re-registered at once against the other scans' mean point of each target
    (rows ``use``), by weighted Kabsch from sums over its rows (A, S updated in place)."""
    X = np.einsum("mij,mj->mi", A[data.t_scan], data.x_t) + S[data.t_scan]
    t_sum = _per_target(data, X, use)
    t_cnt = np.bincount(data.t_index, use.astype(np.float64), data.n_targets)
    own = use.astype(np.float64)
    cnt = t_cnt[data.t_index] - own
    ok = use & (cnt > 0)
    xa = (t_sum[data.t_index] - X * own[:, None]) / np.where(cnt > 0, cnt, 1.0)[:, None]
    sx2 = target_sigma(np.linalg.norm(data.x_t, axis=1), cfg, data.target_noise(slice(None))) ** 2
    w = np.where(ok, 1.0 / sx2, 0.0)
    sw = np.maximum(np.bincount(data.t_scan, w, data.n_scans), 1e-300)
    mb = _per_scan(data, data.x_t, w) / sw[:, None]
    ma = _per_scan(data, xa, w) / sw[:, None]
    u = data.x_t - mb[data.t_scan]
    v = xa - ma[data.t_scan]
    H = _per_scan(data, u[:, :, None] * v[:, None, :], w)
    R = rotations_from_cross(H)
    A[:] = R
    S[:] = ma - np.einsum("sij,sj->si", R, mb)


def all_determined(data: Data, A, S, use) -> bool:
    """Whether every scan's consistent rows that share their target with another scan fix its
    pose: at least three of them, spanning two directions (the second singular value of their
    centred points at least 0.05 of the largest point's distance, as :func:`._register.
    determined`)."""
    seen = np.bincount(data.t_index, use.astype(np.float64), data.n_targets)
    ok = use & (seen[data.t_index] > 1)
    n = np.bincount(data.t_scan, ok.astype(np.float64), data.n_scans)
    if (n < 3).any():
        return False
    X = np.einsum("mij,mj->mi", A[data.t_scan], data.x_t) + S[data.t_scan]
    w = ok.astype(np.float64)
    m = _per_scan(data, X, w) / n[:, None]
    d = X - m[data.t_scan]
    C = _per_scan(data, d[:, :, None] * d[:, None, :], w)
    scale2 = np.zeros(data.n_scans)
    np.maximum.at(scale2, data.t_scan[ok], np.sum(d[ok] ** 2, axis=1))
    lam = np.linalg.eigvalsh(C)
    return bool(np.all(lam[:, 1] >= 0.05**2 * scale2))
