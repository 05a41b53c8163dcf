"""Which (scan, primitive) correspondences agree with the other scans at the registered poses,
and whether each scan's pose is fixed by those that do (else a one-line ``ValueError``)."""

from __future__ import annotations

import numpy as np

from ._config import ApproxConfig, Inconsistency
from ._local import Data, Sums, groups_by_size, plane_fit, target_sigma, transform_moments
from ._register import determined, evaluate, shared


def consensus(data: Data, A, S, cfg: ApproxConfig):
    """Which (scan, primitive) correspondences agree with the others at poses (A, S): per
    primitive, the largest group that agrees with one of its members (normals within the angle
    tolerance, centroids on each other's planes, targets within the distance tolerance),
    weighted by points. The rest are inconsistent (e.g. a wrong match)."""
    use_p = np.ones(len(data.pair_scan), dtype=bool)
    if len(data.pair_scan):
        js = data.pair_scan
        o1, o2 = transform_moments(data.cnt, data.s1, data.s2, A[js], S[js])
        n, has_n, sn, c, sc = plane_fit(data.cnt, o1, o2, cfg)
        for q in groups_by_size(data.pair_plane):
            if q.shape[1] > 1:
                agree = planes_agree(n[q], has_n[q], sn[q], c[q], sc[q], cfg)
                best = np.argmax(np.einsum("gpq,gq->gp", agree, data.cnt[q]), axis=1)
                use_p[q] = agree[np.arange(len(q)), best]
    use_t = np.ones(len(data.t_scan), dtype=bool)
    if len(data.t_scan):
        X = np.einsum("mij,mj->mi", A[data.t_scan], data.x_t) + S[data.t_scan]
        rows = np.arange(len(data.t_scan))
        sx2 = target_sigma(np.linalg.norm(data.x_t, axis=1), cfg, data.target_noise(rows)) ** 2
        for q in groups_by_size(data.t_index):
            if q.shape[1] > 1:
                s2 = sx2[q]
                tol = np.maximum(cfg.distance_tol, 4.0 * np.sqrt(s2[:, :, None] + s2[:, None, :]))
                agree = np.linalg.norm(X[q][:, :, None] - X[q][:, None, :], axis=-1) < tol
                use_t[q] = agree[np.arange(len(q)), np.argmax(agree.sum(axis=2), axis=1)]
    return use_p, use_t


def planes_agree(n, has_n, sn, c, sc, cfg: ApproxConfig):
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


def check_determined(net, data: Data, local, A, S, use_p, use_t, cfg: ApproxConfig):
    """Every scan's pose must be fixed by those of its correspondences that agree with the
    other scans; a one-line ValueError naming the scan otherwise."""
    ones = np.ones(data.n_scans, dtype=bool)
    total = Sums.of(data, A, S, use_p, use_t, ones)
    for j in range(data.n_scans):
        mine = ones & (np.arange(data.n_scans) == j)
        obj = total.without(Sums.of(data, A, S, use_p, use_t, mine)).prims(cfg)
        sh = shared(obj, local[j])
        if sh.size == 0:
            if data.n_scans > 1:
                raise_undetermined(net, j, None)
            continue
        fit = evaluate(A[j], sh, cfg, t=S[j])
        fit.shared = sh
        # Only the correspondences the consensus kept count.
        fit.plane_in &= np.isin(sh.plane, data.pair_plane[use_p & (data.pair_scan == j)])
        fit.target_in &= np.isin(sh.target, data.t_index[use_t & (data.t_scan == j)])
        fit.rotation_ok, fit.position_ok = determined(A[j], sh, fit.plane_in, fit.target_in)
        if not fit.determined:
            raise_undetermined(net, j, fit)


def raise_undetermined(net, j, fit):
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


def inconsistencies(net, data: Data, A, S, use_p, use_t, cfg: ApproxConfig):
    """The (scan, primitive) correspondences left out as inconsistent, with their misfit
    against the object-space primitive of all other scans: normal angle and RMS distance of
    the scan's points from that plane, or the target's distance."""
    out = []
    for p in np.flatnonzero(~use_p):
        j, k = int(data.pair_scan[p]), int(data.pair_plane[p])
        others = (data.pair_plane == k) & (data.pair_scan != j)
        q = np.flatnonzero(others & use_p) if (others & use_p).any() else np.flatnonzero(others)
        o1, o2 = transform_moments(
            data.cnt[q], data.s1[q], data.s2[q], A[data.pair_scan[q]], S[data.pair_scan[q]]
        )
        n, _, _, c, _ = plane_fit(*(v.sum(0, keepdims=True) for v in (data.cnt[q], o1, o2)), cfg)
        m1, m2 = transform_moments(data.cnt[[p]], data.s1[[p]], data.s2[[p]], A[[j]], S[[j]])
        cnt = data.cnt[p]
        d = n[0] @ c[0]
        msd = n[0] @ (m2[0] / cnt) @ n[0] - 2 * d * (n[0] @ m1[0]) / cnt + d * d
        ln, has, _, _, _ = plane_fit(data.cnt[[p]], data.s1[[p]], data.s2[[p]], cfg)
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
