"""Rotations, spherical observations and the two scanner architectures (SPEC section 1).

Scanner space of scan j: ``x = R_j (X - S_j)``, ``R_j = R3(kappa) R2(phi) R1(omega)`` with
passive Cardan rotations. Observations of a point: range ``rho = |x|``, horizontal direction
``theta = atan2(y, x)`` and elevation angle ``alpha = atan2(z, hypot(x, y))``.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np

TWO_PI = 2.0 * np.pi


def wrap_angle(a):
    """Wrap an angle difference to (-pi, pi]."""
    return a - TWO_PI * jnp.ceil((a - np.pi) / TWO_PI)


def rotation_matrix(omega, phi, kappa, xp=jnp):
    """``R = R3(kappa) R2(phi) R1(omega)`` (SPEC section 1), for jax or numpy (``xp``)."""
    cw, sw = xp.cos(omega), xp.sin(omega)
    cp, sp = xp.cos(phi), xp.sin(phi)
    ck, sk = xp.cos(kappa), xp.sin(kappa)
    # R2 R1 written out; then R3 mixes its first two rows.
    r0 = xp.stack([cp, sp * sw, -sp * cw])
    r1 = xp.stack([xp.zeros_like(cw), cw, sw])
    r2 = xp.stack([sp, -cp * sw, cp * cw])
    return xp.stack([ck * r0 + sk * r1, -sk * r0 + ck * r1, r2])


def angles_from_matrix(R: np.ndarray) -> np.ndarray:
    """Cardan angles (omega, phi, kappa) of ``R = R3 R2 R1`` (host side, numpy)."""
    phi = np.arcsin(np.clip(R[2, 0], -1.0, 1.0))
    omega = np.arctan2(-R[2, 1], R[2, 2])
    kappa = np.arctan2(-R[1, 0], R[0, 0])
    return np.array([omega, phi, kappa])


def spherical_from_cartesian(x, panoramic_face2=None, xp=jnp):
    """(rho, theta, alpha) of scanner-space points ``x[..., 3]``.

    ``theta`` in [0, 2pi) and ``alpha`` in [-pi/2, pi/2] (hybrid convention). With
    ``panoramic_face2`` true, the direction is expressed in the second face of a panoramic
    scanner: ``theta - pi``, ``pi - alpha`` (SPEC section 1).
    """
    rho = xp.sqrt(xp.sum(x * x, axis=-1))
    theta = xp.mod(xp.arctan2(x[..., 1], x[..., 0]), TWO_PI)
    alpha = xp.arctan2(x[..., 2], xp.hypot(x[..., 0], x[..., 1]))
    if panoramic_face2 is not None:
        theta = xp.where(panoramic_face2, theta - np.pi, theta)
        alpha = xp.where(panoramic_face2, np.pi - alpha, alpha)
    return xp.stack([rho, theta, alpha], axis=-1)


def cartesian_from_spherical(l, xp=jnp):
    """Scanner-space point of observations ``l[..., 3] = (rho, theta, alpha)``.

    Valid for both faces: a panoramic face-2 direction (theta - pi, pi - alpha) maps to the
    same point because cos(pi - a) cos(t - pi) = cos a cos t, etc.
    """
    rho, theta, alpha = l[..., 0], l[..., 1], l[..., 2]
    ca = xp.cos(alpha)
    return xp.stack(
        [rho * ca * xp.cos(theta), rho * ca * xp.sin(theta), rho * xp.sin(alpha)], axis=-1
    )


def is_face2(alpha, xp=jnp):
    """True where an observed elevation angle belongs to the second face of a panoramic scanner."""
    return alpha > np.pi / 2


def rigid_fit(src, dst, xp=jnp):
    """R, t minimising ``sum |R src + t - dst|^2`` over rotations (Horn 1987; SVD of the
    cross-covariance, with the reflection removed), both (n, 3); jax (differentiable) or numpy."""
    cs, cd = src.mean(axis=0), dst.mean(axis=0)
    U, _, Vt = xp.linalg.svd((src - cs).T @ (dst - cd), full_matrices=False)
    dsign = xp.sign(xp.linalg.det(Vt.T @ U.T))
    D = xp.diag(xp.stack([xp.ones_like(dsign), xp.ones_like(dsign), dsign]))
    R = Vt.T @ D @ U.T
    return R, cd - R @ cs


def helmert_fit(src, dst, scale: bool = False, xp=np):
    """s, R, t minimising ``sum |s R src + t - dst|^2`` (s = 1 unless ``scale``): the rigid
    (6-parameter) or similarity (7-parameter Helmert) least-squares fit with equal weights,
    which is the inner-constraint solution on the points (Horn 1987; Umeyama 1991: the rotation
    does not depend on the scale, ``s = sum (R src_c) . dst_c / sum |src_c|^2``)."""
    R, t = rigid_fit(src, dst, xp=xp)
    s = 1.0
    if scale:
        cs, cd = src.mean(axis=0), dst.mean(axis=0)
        a = (src - cs) @ R.T
        s = xp.sum(a * (dst - cd)) / xp.sum(a * a)
        t = cd - s * (R @ cs)
    return s, R, t
