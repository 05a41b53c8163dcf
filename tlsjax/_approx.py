"""Approximate values from the observations alone (host side, numpy).

Each scan's observations are turned into scanner-space points; scans are registered one after
another to the targets already placed, by the closed-form least-squares rotation (Horn 1987 /
Kabsch, SVD), starting from the first scan, which defines the frame. When scans are levelled,
the frame is then turned so that the levelled scans' vertical axes point up (mean direction).
"""

from __future__ import annotations

import numpy as np

from ._geometry import angles_from_matrix, cartesian_from_spherical
from ._network import Network


def rigid_fit(src: np.ndarray, dst: np.ndarray):
    """R, t minimising ``sum |R src + t - dst|^2`` (Horn 1987), both (n, 3)."""
    cs, cd = src.mean(axis=0), dst.mean(axis=0)
    U, _, Vt = np.linalg.svd((src - cs).T @ (dst - cd))
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return R, cd - R @ cs


def approximate_values(net: Network):
    """Targets (t, 3) and scan poses (s, 6) = (Xs, Ys, Zs, omega, phi, kappa)."""
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
        R, t = rigid_fit(local[mk], acc[net.target_index[mk]] / cnt[net.target_index[mk], None])
        A[best], S[best] = R, t
        current = best

    targets = acc / cnt[:, None]
    levelled = net.is_levelled
    if levelled.any():
        # Scanner z axis in object space is A_j e_z; rotate their mean onto +Z.
        up = np.mean([A[j][:, 2] for j in np.flatnonzero(levelled)], axis=0)
        up /= np.linalg.norm(up)
        Rl = _rotation_between(up, np.array([0.0, 0.0, 1.0]))
        targets = targets @ Rl.T
        A = [Rl @ a for a in A]
        S = [Rl @ s for s in S]
    eops = np.array([np.concatenate([S[j], angles_from_matrix(A[j].T)]) for j in range(n_s)])
    return targets, eops


def _rotation_between(a, b):
    v = np.cross(a, b)
    c = float(np.dot(a, b))
    if np.linalg.norm(v) < 1e-15:
        return np.eye(3) if c > 0 else np.diag([1.0, -1.0, -1.0])
    vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)
