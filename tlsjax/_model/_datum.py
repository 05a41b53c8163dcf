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

from ._geometry import rotation_matrix

#: Columns of the 6-parameter rigid motion: translations, then rotations about X, Y, Z.
MOTIONS = ("tx", "ty", "tz", "rx", "ry", "rz")


def small_rotation(w):
    # First-order rotation; only its derivative at w = 0 is used.
    return jnp.array([[1.0, -w[2], w[1]], [w[2], 1.0, -w[0]], [-w[1], w[0], 1.0]])


def move_point(X, motion):
    """Rigid-motion action on a point: ``X -> R(w) X + t``."""
    return small_rotation(motion[3:]) @ X + motion[:3]


def move_points(P, motion):
    """Action on a primitive made of several points stacked as (3k,) (e.g. a scale bar)."""
    return jax.vmap(lambda X: move_point(X, motion))(P.reshape(-1, 3)).reshape(-1)


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


def s_transform_vector(Hp, Hz, dps, dz):
    """``dx - H (G^T H)^-1 G^T dx`` with G the primitive rows of H (inner constraints)."""
    GtH = sum(jnp.einsum("npd,npe->de", H, H) for H in Hp)
    Gtx = sum(jnp.einsum("npd,np->d", H, dp) for H, dp in zip(Hp, dps))
    coef = jnp.linalg.solve(GtH, Gtx)
    dps = tuple(dp - jnp.einsum("npd,d->np", H, coef) for H, dp in zip(Hp, dps))
    return dps, dz - Hz @ coef
