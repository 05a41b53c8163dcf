"""Plane-based functional model (Gauss-Helmert): one condition per point on a plane.

Chow et al. 2013, sec. 2.2 (after Lichti 2007); SPEC section 4. Plane k has the unit normal
``n = (a, b, c)`` and the distance ``d`` (object space, ``n . X = d``). A point observed in
scan j on plane k gives the condition

    g = n . (R_j^T x + S_j) - d = 0,
    x = (rho - Drho) (cos(alpha - Dalpha) cos(theta - Dtheta),
                      cos(alpha - Dalpha) sin(theta - Dtheta),
                      sin(alpha - Dalpha)),

with the AP corrections ``Delta(l)`` evaluated at the observations. Linearised,
``A dx + B v + w = 0`` with ``A = dg/dx`` and ``B = dg/dl`` from autodiff; the condition's
variance is ``m = B Sigma_l B^T`` (one scalar per point, so ``M`` is diagonal). Dividing the
condition by ``sqrt(m)`` (held fixed in the linearisation) turns each point into one row of
a whitened Gauss-Markov system, so the structured solver (segment sums, Schur elimination of
the planes) applies unchanged; the observation residuals follow as
``v = -Sigma_l B^T m^-1 g`` and the three redundancy numbers of a point split the condition's
redundancy in the ratio ``sigma_l^2 b_l^2 / m`` (so they sum to at most 1).

The unit length of n is a constraint, ``c = n . n - 1 = 0``, and the rigid-motion action on a
plane, ``n -> R n``, ``d -> d + (R n) . t``, gives its inner-constraint columns by autodiff
(Lichti & Chow 2013), as for points in :mod:`._datum`.

This module holds the pure model; the plane family of the structured solver is built on it.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from ._aps import corrected_observations
from ._geometry import cartesian_from_spherical, rotation_matrix


def plane_condition(
    plane, eop, coeffs, l, scanners: tuple, ap_names: tuple, ap_slices: tuple, instrument
):
    """``g = n . (R^T x(l - Delta(l)) + S) - d`` [m] for one point (SPEC section 4).

    ``plane`` (4,) = (a, b, c, d); ``eop`` (6,) = (Xs, Ys, Zs, omega, phi, kappa); ``coeffs``
    the AP vector of all instruments, ``ap_slices[i]`` the block of instrument i (as
    :func:`tlsjax._models.point_misclosure`); ``l`` (3,) = (rho, theta, alpha).
    """
    out = jnp.zeros(())
    for i, (scanner, names, (a, b)) in enumerate(zip(scanners, ap_names, ap_slices)):
        x = cartesian_from_spherical(corrected_observations(coeffs[a:b], names, l, scanner))
        R = rotation_matrix(eop[3], eop[4], eop[5])
        g = jnp.dot(plane[:3], R.T @ x + eop[:3]) - plane[3]
        out = jnp.where(instrument == i, g, out)
    return out


def condition_variance(plane, eop, coeffs, l, sigma, scanners, ap_names, ap_slices, instrument):
    """``m = B Sigma_l B^T`` with ``B = dg/dl`` (autodiff) and ``Sigma_l = diag(sigma^2)``;
    also returns B."""
    B = jax.grad(plane_condition, argnums=3)(
        plane, eop, coeffs, l, scanners, ap_names, ap_slices, instrument
    )
    return jnp.sum((B * sigma) ** 2), B


def whitened_condition(plane, eop, coeffs, l, weight, scanners, ap_names, ap_slices, instrument):
    """``g / sqrt(m)`` as a (1,) row, m held fixed (the Gauss-Helmert weight ``M^-1``).

    ``weight`` = 1/sigma of the three observations; a zero weight removes the observation
    from ``m`` (an all-zero weight removes the point, see the solver's masking).
    """
    sigma = jnp.where(weight > 0, 1.0 / jnp.where(weight > 0, weight, 1.0), 0.0)
    m, _ = condition_variance(
        plane, eop, coeffs, l, sigma, scanners, ap_names, ap_slices, instrument
    )
    m = jax.lax.stop_gradient(m)
    active = jnp.any(weight > 0)
    g = plane_condition(plane, eop, coeffs, l, scanners, ap_names, ap_slices, instrument)
    return jnp.where(active, g / jnp.sqrt(jnp.where(m > 0, m, 1.0)), 0.0)[None]


def observation_residuals(plane, eop, coeffs, l, weight, scanners, ap_names, ap_slices, instrument):
    """Gauss-Helmert residuals of the three observations, ``v = -Sigma_l B^T g / m`` [m, rad, rad]."""
    sigma = jnp.where(weight > 0, 1.0 / jnp.where(weight > 0, weight, 1.0), 0.0)
    m, B = condition_variance(
        plane, eop, coeffs, l, sigma, scanners, ap_names, ap_slices, instrument
    )
    g = plane_condition(plane, eop, coeffs, l, scanners, ap_names, ap_slices, instrument)
    return -(sigma**2) * B * g / jnp.where(m > 0, m, 1.0)


def unit_normal_constraint(plane):
    """``n . n - 1``: the constraint that keeps n a unit vector."""
    return jnp.dot(plane[:3], plane[:3]) - 1.0
