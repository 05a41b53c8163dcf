"""The object frame of the approximate values and the orientation of the plane normals.

With three or more control points the frame is theirs (a rigid fit of the approximate targets
onto the control coordinates), so that the adjustment starts where its datum is. Otherwise the
first scan's station is the origin and the frame is turned so that the levelled scans' vertical
axes point up (their compensator readings start near zero), or, when no scan is levelled, kept
as the first scan's frame unless a scan's Cardan angle phi would come near the gimbal lock at
+-90 deg. Object-space normals get one orientation per plane: towards the side where most of its
points were observed from.
"""

from __future__ import annotations

import numpy as np

from ..._model._geometry import angles_from_matrix
from ..._units import DEG
from ._local import Data, Prims
from ._rigid import weighted_fit


def orient(obj: Prims, data: Data, A, S, keep_p):
    """One orientation per object-space normal: towards the side most of its points were
    observed from (weighted by points), which for a room's faces is into the room."""
    n = obj.n.copy()
    side = np.zeros(data.n_planes)
    q = np.flatnonzero(keep_p & np.isin(data.pair_plane, obj.plane))
    if len(q):
        pos = np.full(data.n_planes, -1)
        pos[obj.plane] = np.arange(len(obj.plane))
        js, k = data.pair_scan[q], data.pair_plane[q]
        centre = data.s1[q] / data.cnt[q, None]
        X = np.einsum("qij,qj->qi", A[js], centre) + S[js]
        # The station is on the positive side when n . (S - X) > 0.
        s = np.sign(np.einsum("qi,qi->q", n[pos[k]], S[js] - X))
        side += np.bincount(k, data.cnt[q] * s, data.n_planes)
    n[side[obj.plane] < 0] *= -1
    return n


def to_frame(A, S, targets, planes, levelled, control=None):
    """The poses (s, 6), targets and planes in the object frame (module docstring).
    ``control``: (target indices, coordinates) of the control points, or None."""
    if control is not None and len(control[0]) >= 3:
        idx, xyz = control
        R, t, q = weighted_fit(targets[idx], xyz, np.ones(len(idx)))
        if q > 1e-3:
            return _moved(A, S, targets, planes, R, -R.T @ t)
    Q = _frame_rotation(A, levelled)
    return _moved(A, S, targets, planes, Q, S[0].copy())


def _moved(A, S, targets, planes, Q, origin):
    """Everything in the frame ``X' = Q (X - origin)``, poses as (Xs, Ys, Zs, omega, phi,
    kappa) with ``x = R (X - S)``."""
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
