"""Approximate values from the observations alone (host side, numpy).

Each scan's observations are turned into scanner-space points; scans are registered one after
another to the targets already placed, by the closed-form least-squares rotation (Horn 1987 /
Kabsch, SVD), starting from the first scan, which defines the frame. When scans are levelled,
the frame is then turned so that the levelled scans' vertical axes point up (mean direction).

Planes take part in the same registration (Khoshelham's plane-to-plane registration in closed
form): every (scan, plane) pair is fitted in scanner space from its point moments (PCA; the
normal oriented towards the scanner), its normal joins the Kabsch cross-covariance, ``A n_l =
n``, and its distance gives one linear equation for the position, ``n . S = d - d_l`` (from
``n . (A x + S) = d`` and ``n_l . x = d_l``). Object-space planes are fitted to the moments of
all their points once the poses are known. A scan whose placed primitives do not fix its
rotation (fewer than two independent normals and three targets) or position (normals and
targets of rank < 3) is reported by name.
"""

from __future__ import annotations

import numpy as np

from .._model._geometry import angles_from_matrix, cartesian_from_spherical, rigid_fit
from ._network import Network


def approximate_values(net: Network):
    """Targets (t, 3) and scan poses (s, 6) = (Xs, Ys, Zs, omega, phi, kappa)."""
    if net.has_planes:
        targets, eops, _ = approximate_network(net)
        return targets, eops
    n_s, n_t = len(net.scans), len(net.targets)
    local = cartesian_from_spherical(net.observations, xp=np)
    placed = np.zeros(n_t, dtype=bool)
    acc = np.zeros((n_t, 3))
    cnt = np.zeros(n_t)
    # Object-from-scanner transforms: X = A_j x + S_j (A_j = R_j^T).
    A = [None] * n_s
    S = [None] * n_s
    todo = set(range(n_s))
    current = 0
    A[0], S[0] = np.eye(3), np.zeros(3)
    while True:
        j = current
        todo.discard(j)
        m = net.scan_index == j
        X = local[m] @ A[j].T + S[j]
        np.add.at(acc, net.target_index[m], X)
        np.add.at(cnt, net.target_index[m], 1)
        placed[net.target_index[m]] = True
        if not todo:
            break
        # Next: the scan with most targets in common with what is placed.
        best, best_n = None, -1
        for k in todo:
            n_common = int(placed[net.target_index[net.scan_index == k]].sum())
            if n_common > best_n:
                best, best_n = k, n_common
        mk = (net.scan_index == best) & placed[net.target_index]
        R, t = rigid_fit(
            local[mk], acc[net.target_index[mk]] / cnt[net.target_index[mk], None], xp=np
        )
        A[best], S[best] = R, t
        current = best

    targets = acc / cnt[:, None]
    Rl = _levelling_rotation(A, net.is_levelled)
    targets = targets @ Rl.T
    return targets, _eops(A, S, Rl)


def _levelling_rotation(A, levelled):
    """The rotation of the object frame that takes the mean scanner z axis of the levelled scans
    (A_j e_z in object space) onto +Z, so that their compensator readings start near zero."""
    if not levelled.any():
        return np.eye(3)
    up = np.mean([A[j][:, 2] for j in np.flatnonzero(levelled)], axis=0)
    return _rotation_between(up / np.linalg.norm(up), np.array([0.0, 0.0, 1.0]))


def _eops(A, S, Rl):
    """Scan poses (s, 6) from object-from-scanner rotations A_j and positions S_j, after the
    object-frame rotation Rl."""
    return np.array(
        [np.concatenate([Rl @ s, angles_from_matrix((Rl @ a).T)]) for a, s in zip(A, S)]
    )


def _rotation_between(a, b):
    v = np.cross(a, b)
    c = float(np.dot(a, b))
    if np.linalg.norm(v) < 1e-15:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


# ---------------------------------------------------------------------------------------------
# Networks with planes (and combined networks)

#: Weight [m^2] of a normal pair in the Kabsch cross-covariance, against centred target points.
_NORMAL_WEIGHT = 10.0
#: A (scan, plane) pair is used for registration when its points span at least this much
#: in the plane (RMS along the second principal axis) [m] and at least this many points.
_MIN_SPREAD = 0.05
_MIN_PAIR_POINTS = 10


def _moments(x, group, n_groups):
    """Count, sum (g, 3) and second moments (g, 3, 3) of the rows of x per group."""
    cnt = np.bincount(group, minlength=n_groups).astype(np.float64)
    s1 = np.stack([np.bincount(group, x[:, i], n_groups) for i in range(3)], axis=1)
    s2 = np.stack(
        [
            np.stack([np.bincount(group, x[:, i] * x[:, j], n_groups) for j in range(3)], axis=1)
            for i in range(3)
        ],
        axis=1,
    )
    return cnt, s1, s2


def _fit_moments(cnt, s1, s2):
    """Plane fit (PCA) from moments: unit normals (g, 3), d (g,), eigenvalues (g, 3) ascending."""
    c = s1 / cnt[:, None]
    C = s2 / cnt[:, None, None] - c[:, :, None] * c[:, None, :]
    w, V = np.linalg.eigh(C)
    n = V[:, :, 0]
    return n, np.einsum("gi,gi->g", n, c), w


def _transform_moments(cnt, s1, s2, A, S):
    """Moments of ``X = A x + S`` from those of x (per group, A (g, 3, 3), S (g, 3))."""
    t1 = np.einsum("gij,gj->gi", A, s1)
    o1 = t1 + cnt[:, None] * S
    t2 = np.einsum("gij,gjk,glk->gil", A, s2, A)
    o2 = (
        t2
        + t1[:, :, None] * S[:, None, :]
        + S[:, :, None] * t1[:, None, :]
        + cnt[:, None, None] * S[:, :, None] * S[:, None, :]
    )
    return o1, o2


def approximate_network(net: Network):
    """Targets (t, 3), scan poses (s, 6) and planes (k, 4) = (n, d) of any network."""
    n_s, n_t, n_k = len(net.scans), len(net.targets), len(net.planes)
    local_t = cartesian_from_spherical(net.observations, xp=np) if n_t else np.zeros((0, 3))
    # Per (scan, plane) pair: moments of the scanner-space points and the local plane fit.
    x_p = cartesian_from_spherical(net.plane_observations, xp=np)
    key = net.plane_scan_index.astype(np.int64) * max(n_k, 1) + net.plane_index
    pair_key, pair_of = np.unique(key, return_inverse=True)
    pair_scan, pair_plane = pair_key // max(n_k, 1), pair_key % max(n_k, 1)
    cnt, s1, s2 = _moments(x_p, pair_of.reshape(-1), len(pair_key))
    n_l, d_l, ev = _fit_moments(cnt, s1, s2)
    flip = d_l > 0  # normal towards the scanner: the scanner sits on the positive side
    n_l[flip] *= -1
    d_l[flip] *= -1
    good = (cnt >= _MIN_PAIR_POINTS) & (ev[:, 1] >= _MIN_SPREAD**2)

    A = [None] * n_s
    S = [None] * n_s
    placed_t = np.zeros(n_t, dtype=bool)
    acc = np.zeros((n_t, 3))
    cnt_t = np.zeros(n_t)
    placed_k = np.zeros(n_k, dtype=bool)
    obj_n = np.zeros((n_k, 3))
    obj_d = np.zeros(n_k)
    o_cnt, o_s1, o_s2 = np.zeros(n_k), np.zeros((n_k, 3)), np.zeros((n_k, 3, 3))
    votes = np.zeros((n_k, 3))

    def place(j):
        m = net.scan_index == j
        if m.any():
            X = local_t[m] @ A[j].T + S[j]
            np.add.at(acc, net.target_index[m], X)
            np.add.at(cnt_t, net.target_index[m], 1)
            placed_t[net.target_index[m]] = True
        q = np.flatnonzero(pair_scan == j)
        if len(q):
            g = len(q)
            o1, o2 = _transform_moments(
                cnt[q],
                s1[q],
                s2[q],
                np.broadcast_to(A[j], (g, 3, 3)),
                np.broadcast_to(S[j], (g, 3)),
            )
            k = pair_plane[q]
            np.add.at(o_cnt, k, cnt[q])
            np.add.at(o_s1, k, o1)
            np.add.at(o_s2, k, o2)
            np.add.at(votes, k, (n_l[q] @ A[j].T) * cnt[q, None])
            placed_k[k[good[q]]] = True
            seen = o_cnt > 0
            nn, dd, _ = _fit_moments(o_cnt[seen], o_s1[seen], o_s2[seen])
            sign = np.where(np.einsum("gi,gi->g", nn, votes[seen]) < 0, -1.0, 1.0)
            obj_n[seen], obj_d[seen] = nn * sign[:, None], dd * sign

    def shared(j):
        mt = (net.scan_index == j) & placed_t[net.target_index] if n_t else np.zeros(0, dtype=bool)
        q = np.flatnonzero((pair_scan == j) & good)
        q = q[placed_k[pair_plane[q]]]
        return mt, q

    A[0], S[0] = np.eye(3), np.zeros(3)
    place(0)
    todo = set(range(1, n_s))
    while todo:
        # The scan sharing the most placed primitives goes next.
        candidates = {k: shared(k) for k in sorted(todo)}
        best = max(candidates, key=lambda k: int(candidates[k][0].sum()) + len(candidates[k][1]))
        mt, q = candidates[best]
        A[best], S[best] = _register(
            net.scans[best],
            local_t[mt],
            acc[net.target_index[mt]] / cnt_t[net.target_index[mt], None],
            n_l[q],
            d_l[q],
            obj_n[pair_plane[q]],
            obj_d[pair_plane[q]],
        )
        place(best)
        todo.discard(best)

    targets = acc / np.maximum(cnt_t, 1)[:, None]
    planes = np.concatenate([obj_n, obj_d[:, None]], axis=1)
    Rl = _levelling_rotation(A, net.is_levelled)
    targets = targets @ Rl.T
    planes[:, :3] = planes[:, :3] @ Rl.T
    eops = _eops(A, S, Rl)
    return targets, eops, planes


def _register(scan, x, X, n_loc, d_loc, n_obj, d_obj):
    """Object-from-scanner rotation A and position S from target points (x -> X) and planes
    ((n_loc, d_loc) -> (n_obj, d_obj)), in closed form."""
    H = np.zeros((3, 3))
    if len(x) >= 2:
        H += (x - x.mean(axis=0)).T @ (X - X.mean(axis=0))
    H += _NORMAL_WEIGHT * n_loc.T @ n_obj
    U, sv, Vt = np.linalg.svd(H)
    if sv[1] <= 1e-3 * max(sv[0], 1e-300):
        raise ValueError(
            f"scan {scan}: its rotation is not determined by the primitives it shares with the scans "
            f"placed before it ({len(x)} target(s), {len(n_loc)} plane(s) with fewer than two independent normals)"
        )
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    A = Vt.T @ D @ U.T
    # Position: S = X - A x for targets, n . S = d - d_l for planes.
    rows = [np.tile(np.eye(3), (len(x), 1)), n_obj]
    rhs = [(X - x @ A.T).reshape(-1), d_obj - d_loc]
    M, b = np.vstack(rows), np.concatenate(rhs)
    if M.shape[0] < 3 or np.linalg.svd(M, compute_uv=False)[-1] < 0.05:
        raise ValueError(
            f"scan {scan}: its position is not determined by the primitives it shares with the scans "
            f"placed before it ({len(x)} target(s), {len(n_loc)} plane(s) whose normals span fewer than three directions)"
        )
    S, *_ = np.linalg.lstsq(M, b, rcond=None)
    return A, S
