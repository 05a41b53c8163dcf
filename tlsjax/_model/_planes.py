"""Plane-based functional model (Gauss-Helmert): one condition per point on a plane.

Chow et al. 2013, sec. 2.2 (after Lichti 2007); SPEC section 4. Plane k has the unit normal
``n = (a, b, c)`` and the distance ``d`` (object space, ``n . X = d``). A point observed in
scan j on plane k gives the condition

    g = n . (R_j^T x + S_j) - d = 0,
    x = (rho - Drho) (cos(alpha - Dalpha) cos(theta - Dtheta),
                      cos(alpha - Dalpha) sin(theta - Dtheta),
                      sin(alpha - Dalpha)),

with the AP corrections ``Delta(l)`` evaluated at the observations. The rigorous Gauss-Helmert linearisation (Lenzmann & Lenzmann 2004; Neitzel 2010; SPEC section
4) is taken at the current estimates of both the unknowns x0 and the observations ``l + v0``:

    A dx + B v + w = 0,    w = g(x0, l + v0) - B v0,    A = dg/dx, B = dg/dl at (x0, l + v0),

with ``A`` and ``B`` from autodiff. The condition's variance is ``m = B Sigma_l B^T`` (one
scalar per point, so ``M`` is diagonal); dividing by ``sqrt(m)`` turns each point into one row
``e = w / sqrt(m)`` of a whitened Gauss-Markov system, so the structured solver (segment sums,
Schur elimination of the planes) applies unchanged. The residuals follow as
``v = -Sigma_l B^T m^-1 (A dx + w)`` and the three redundancy numbers of a point split the
condition's redundancy in the ratio ``sigma_l^2 b_l^2 / m`` (so they sum to at most 1).

For fixed x, ``v(x)`` is the Sigma-orthogonal projection of l onto the condition surface
``g(x, l + v) = 0``, the fixed point of :func:`projection_step` (``dx = 0`` in the update above);
``sum_i v_i^T P v_i = sum_i w_i^2 / m_i = Phi(x)`` is then the objective that the adjustment
minimises, and ``J^T e`` with ``J = A / sqrt(m)`` is exactly ``grad Phi / 2`` (the envelope
theorem): the iteration's fixed point is the least-squares solution of the Gauss-Helmert model,
not the one of ``sum g(x, l)^2 / m`` (which linearising at l would give).

The unit length of n is a hard constraint, ``c = n . n - 1 = 0``: a step moves the normal in
its tangent plane (:func:`tangent_basis`, three unknowns per plane: two for n and d) and the
plane is renormalised after the step. The rigid-motion action on a plane, ``n -> R n``,
``d -> d + (R n) . t``, gives its inner-constraint columns by autodiff (Lichti & Chow 2013), as
for points in :mod:`._datum`.

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


def _sigma(weight):
    return jnp.where(weight > 0, 1.0 / jnp.where(weight > 0, weight, 1.0), 0.0)


def gauss_helmert_terms(plane, eop, coeffs, l, v, sigma, scanners, ap_names, ap_slices, instrument):
    """At ``(x0, l + v)``: ``w = g - B v``, ``B = dg/dl`` and ``m = B Sigma_l B^T`` of one point
    (Lenzmann & Lenzmann 2004); ``sigma`` the three observations' sigmas (0 = removed)."""
    args = (scanners, ap_names, ap_slices, instrument)
    g, B = jax.value_and_grad(plane_condition, argnums=3)(plane, eop, coeffs, l + v, *args)
    return g - jnp.dot(B, v), B, jnp.sum((B * sigma) ** 2)


def whitened_condition(plane, eop, coeffs, l, v, weight, scanners, ap_names, ap_slices, instrument):
    """``w / sqrt(m)`` as a (1,) row, the Gauss-Helmert row linearised at ``l + v`` with ``B v``
    and ``m`` held fixed (so its Jacobian w.r.t. the unknowns is ``A / sqrt(m)``).

    ``weight`` = 1/sigma of the three observations; a zero weight removes the observation
    from ``m`` (an all-zero weight removes the point, see the solver's masking).
    """
    sl = (scanners, ap_names, ap_slices, instrument)
    held = jax.lax.stop_gradient(gauss_helmert_terms(plane, eop, coeffs, l, v, _sigma(weight), *sl))
    _, B, m = held
    active = jnp.any(weight > 0)
    g = plane_condition(plane, eop, coeffs, l + v, *sl)
    w = g - jnp.dot(B, v)
    return jnp.where(active, w / jnp.sqrt(jnp.where(m > 0, m, 1.0)), 0.0)[None]


def projection_step(plane, eop, coeffs, l, v, weight, scanners, ap_names, ap_slices, instrument):
    """One Gauss-Helmert update of the residuals at fixed unknowns,
    ``v_new = -Sigma_l B^T w / m`` with ``w``, B and m at ``l + v`` [m, rad, rad]; from v = 0 it
    is the first-order residual ``-Sigma_l B^T g(l) / m``, and its fixed point is the
    Sigma-orthogonal projection of l onto ``g(x, l + v) = 0``."""
    sigma = _sigma(weight)
    w, B, m = gauss_helmert_terms(
        plane, eop, coeffs, l, v, sigma, scanners, ap_names, ap_slices, instrument
    )
    return -(sigma**2) * B * w / jnp.where(m > 0, m, 1.0)


def observation_residuals(plane, eop, coeffs, l, weight, scanners, ap_names, ap_slices, instrument):
    """Gauss-Helmert residuals of the three observations at fixed unknowns [m, rad, rad]: the
    projection of l onto the condition surface (:func:`projection_step` iterated to its fixed
    point; the first step is ``v = -Sigma_l B^T g / m``)."""
    sl = (scanners, ap_names, ap_slices, instrument)
    v = jnp.zeros_like(l)
    for _ in range(PROJECTION_STEPS):
        v = projection_step(plane, eop, coeffs, l, v, weight, *sl)
    return v


#: Projection steps that take the residuals from 0 to their fixed point at fixed unknowns: each
#: step contracts the error by about the angular residual (in rad) and ``v_rho / rho``, 1e-4 or
#: less, so four steps reach float64 resolution.
PROJECTION_STEPS = 4


def tangent_basis(n):
    """An orthonormal basis (3, 2) of the plane orthogonal to the unit vector n: the directions
    in which a step may move n without breaking ``|n| = 1`` to first order."""
    axis = jax.nn.one_hot(jnp.argmin(jnp.abs(n)), 3, dtype=n.dtype)
    t1 = axis - jnp.dot(axis, n) * n
    t1 = t1 / jnp.linalg.norm(t1)
    return jnp.stack([t1, jnp.cross(n, t1)], axis=1)


def plane_step_basis(plane):
    """``E`` (4, 3): a step of the plane ``(n, d)`` is ``E delta`` (n in its tangent plane, d
    free), the hard unit-normal constraint in its null-space form."""
    T = tangent_basis(plane[:3] / jnp.linalg.norm(plane[:3]))
    E = jnp.zeros((4, 3), dtype=plane.dtype)
    return E.at[:3, :2].set(T).at[3, 2].set(1.0)


def unit_normal_constraint(plane):
    """``n . n - 1``: the constraint that keeps n a unit vector."""
    return jnp.dot(plane[:3], plane[:3]) - 1.0
