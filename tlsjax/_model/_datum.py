"""Datum: the rigid-motion null space of the free network and the S-transformation.

The constraint matrix is the derivative of the parameters with respect to a small rigid motion
of object space (translation t, rotation vector w), evaluated at the current estimate (SPEC
section 6). Each primitive supplies only its rigid-motion action; autodiff gives the columns,
so points, scale bars and planes share this code. Free network with inner constraints on the
primitives: ``G^T dx = 0`` where ``G`` is the primitive part of the null space ``H``; the
inner-constraint solution is ``S dx`` with ``S = I - H (G^T H)^-1 G^T`` (Koch 1999; Lichti & Chow
2013 for planes).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .._linalg import bmm, mm, small_spd_solve
from ._geometry import rotation_matrix


def free_motions(levelled: bool, headed: bool = False) -> tuple:
    """Rigid motions (columns of tx, ty, tz, rx, ry, rz) that leave the observations of a free
    network invariant: all six, or with levelling (compensator) observations the translations
    and the rotation about Z (SPEC section 6), or with levelling and an observed kappa (a
    heading) the translations alone. They are also the pose parameters (Xs, Ys, Zs, omega, phi,
    kappa) that a fixed scan must hold to define the datum."""
    if levelled:
        return (0, 1, 2) if headed else (0, 1, 2, 5)
    return (0, 1, 2, 3, 4, 5)


def small_rotation(w):
    # First-order rotation; only its derivative at w = 0 is used.
    return jnp.array([[1.0, -w[2], w[1]], [w[2], 1.0, -w[0]], [-w[1], w[0], 1.0]])


def move_point(X, motion):
    """Rigid-motion action on a point: ``X -> R(w) X + t``."""
    return small_rotation(motion[3:]) @ X + motion[:3]


def move_points(P, motion):
    """Action on a primitive made of several points stacked as (3k,) (e.g. a scale bar)."""
    return jax.vmap(lambda X: move_point(X, motion))(P.reshape(-1, 3)).reshape(-1)


def move_plane(plane, motion):
    """Rigid-motion action on a plane (Lichti & Chow 2013): ``n -> R n``, ``d -> d + (R n) . t``."""
    n = small_rotation(motion[3:]) @ plane[:3]
    return jnp.concatenate([n, (plane[3] + jnp.dot(n, motion[:3]))[None]])


def _angles(R):
    phi = jnp.arcsin(jnp.clip(R[2, 0], -1.0, 1.0))
    omega = jnp.arctan2(-R[2, 1], R[2, 2])
    kappa = jnp.arctan2(-R[1, 0], R[0, 0])
    return jnp.stack([omega, phi, kappa])


def move_eop(eop, motion):
    """Rigid-motion action on a scan pose: ``S -> R S + t``, ``R_j -> R_j R^T``."""
    Rd = small_rotation(motion[3:])
    S = Rd @ eop[:3] + motion[:3]
    Rj = rotation_matrix(eop[3], eop[4], eop[5]) @ Rd.T
    return jnp.concatenate([S, _angles(Rj)])


def null_space_columns(action, params, columns):
    """``d action(params, motion) / d motion`` at motion = 0, for the chosen motion columns.

    Returns (n, p, d) for params of shape (n, p).
    """
    J = jax.vmap(lambda x: jax.jacfwd(lambda m: action(x, m))(jnp.zeros(6)))(params)
    return J[..., jnp.asarray(columns, dtype=jnp.int32)]


def inner_gram(Hp):
    """``G^T H`` (d x d) of the inner constraints, G the primitive rows of H."""
    return sum(jnp.einsum("npd,npe->de", H, H) for H in Hp)


def s_transform_vector(Hp, Hz, dps, dz, GtH_inv=None):
    """``dx - H (G^T H)^-1 G^T dx`` with G the primitive rows of H (inner constraints);
    ``GtH_inv``: ``(G^T H)^-1`` when it is at hand (many vectors with one H)."""
    Gtx = sum(jnp.einsum("npd,np->d", H, dp) for H, dp in zip(Hp, dps))
    if GtH_inv is None:
        coef = small_spd_solve(inner_gram(Hp), Gtx)
    else:
        coef = GtH_inv @ Gtx
    dps = tuple(dp - jnp.einsum("npd,d->np", H, coef) for H, dp in zip(Hp, dps))
    return dps, dz - Hz @ coef


def inner_constraint_cofactor(Hp, Hz, Ninv, Y, Qzz):
    """Blocks of the inner-constraint cofactor matrix ``S Q S^T`` from the Schur blocks of any
    generalised inverse ``Q`` of the normal matrix, never forming a matrix of size u^2.

    ``Q_ii = N_ii^-1 + Y_i Q_zz Y_i^T``, ``Q_iz = -Y_i Q_zz`` (per primitive i, ``Y = N_pp^-1
    N_pz``), ``S = I - H M G^T``, ``M = (G^T H)^-1``, ``G = [H_p; 0]`` (Koch 1999, eq. 3.298;
    inner constraints on the primitives). With ``W = G^T Q`` (d x u) and ``Z = M (W G) M^T``:
    ``(S Q S^T)_ab = Q_ab - H_a M W_b - W_a^T M^T H_b^T + H_a Z H_b^T``.

    ``Hp``, ``Ninv``, ``Y``: per family (n, p, d), (n, p, p), (n, p, r); ``Hz`` (r, d); ``Qzz``
    (r, r). Returns (per family diagonal blocks (n, p, p), per family (n, p, r) blocks with the
    reduced unknowns, the (r, r) block). Linear in the number of primitives.
    """
    # The products over all primitives as matrix products (``mm``), those per primitive over
    # its few components written out (``bmm``): no batched dots (:mod:`tlsjax._linalg`).
    T = lambda a: jnp.swapaxes(a, -1, -2)
    flat = lambda a: a.reshape(-1, a.shape[-1])
    C = sum(flat(H).T @ flat(y) for H, y in zip(Hp, Y))  # Hp^T Y (d, r)
    GtH = inner_gram(Hp)
    M = small_spd_solve(GtH, jnp.eye(GtH.shape[0], dtype=GtH.dtype))
    CQ = C @ Qzz
    Wz = -CQ  # (d, r)
    Wp = tuple(
        bmm(T(H), Ni) + T(mm(y, CQ.T)) for H, Ni, y in zip(Hp, Ninv, Y)
    )  # per family (n, d, p): columns of W for the primitives
    WG = sum(flat(H).T @ flat(bmm(Ni, H)) for H, Ni in zip(Hp, Ninv)) + CQ @ C.T
    Z = M @ WG @ M.T
    HzM = Hz @ M
    Qzz_s = Qzz - HzM @ Wz - Wz.T @ HzM.T + Hz @ Z @ Hz.T
    diag, cross = [], []
    for H, Ni, y, W in zip(Hp, Ninv, Y, Wp):
        HM = mm(H, M)
        YQ = mm(y, Qzz)
        Qii = Ni + bmm(YQ, T(y))
        HMW = bmm(HM, W)
        HZH = bmm(mm(H, Z), T(H))
        diag.append(Qii - HMW - T(HMW) + HZH)
        cross.append(-YQ - mm(HM, Wz) - mm(T(W), HzM.T) + mm(mm(H, Z), Hz.T))
    return tuple(diag), tuple(cross), Qzz_s
