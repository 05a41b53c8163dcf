"""Orientation pseudo-observations of a scan (SPEC section 6; Chow et al. 2013, eq. 7): the
readings of a dual-axis compensator or tilt sensor, and an observed kappa (a known heading)."""

from __future__ import annotations

import jax.numpy as jnp

from ._geometry import rotation_matrix_column_z


def compensator_reading(eop, xp=jnp):
    """Tilt readings (omega_c, phi_c) of a dual-axis compensator in the scanner frame [rad];
    ``eop`` (..., 6), jax or numpy (``xp``: the host computes it in numpy, every scan at once).

    The compensator senses the object-space vertical in scanner space, ``g = R_j e3``:
    ``omega_c = asin(g_y)``, ``phi_c = asin(-g_x / sqrt(1 - g_y^2))``. For kappa = 0 these are
    exactly the Cardan omega and phi of SPEC section 6, so the levelling pseudo-observations
    ``omega_c = 0 +- s``, ``phi_c = 0 +- s`` are SPEC's to first order. Unlike omega and phi
    themselves, g is invariant under a rotation of object space about Z (``R_j -> R_j Rz^T``),
    so rotation about Z stays an exact null vector of the normal equations and the free-network
    solution does not depend on the datum.
    """
    g = rotation_matrix_column_z(eop[..., 3], eop[..., 4], eop[..., 5], xp)
    gy = xp.clip(g[1], -1.0, 1.0)
    omega = xp.arcsin(gy)
    phi = xp.arcsin(xp.clip(-g[0] / xp.sqrt(1.0 - gy * gy), -1.0, 1.0))
    return xp.stack([omega, phi], axis=-1)


def orientation_reading(eop):
    """What the orientation pseudo-observations of one scan observe (3,): the tilt readings
    ``(omega_c, phi_c)`` of :func:`compensator_reading` (the Cardan omega and phi when kappa = 0)
    and the Cardan kappa itself (eq. 7: ``kappa_j = kappa_obs +- s``, linear in the unknown).

    A heading is not invariant under a rotation of object space about Z: a network with an
    observed kappa has no such datum defect (:func:`tlsjax._model._datum.free_motions`)."""
    return jnp.concatenate([compensator_reading(eop), eop[5:]])
