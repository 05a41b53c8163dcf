"""Rotations, spherical observations, the two scanner architectures (SPEC section 1), and the
two closed-form fits every part of tlsjax uses: the rotation between two point sets (Kabsch)
and the least-squares plane of points (PCA).

Scanner space of scan j: ``x = R_j (X - S_j)``, ``R_j = R3(kappa) R2(phi) R1(omega)`` with
passive Cardan rotations. Observations of a point: range ``rho = |x|``, horizontal direction
``theta = atan2(y, x)`` and elevation angle ``alpha = atan2(z, hypot(x, y))``. A panoramic
scanner observes a direction whose hybrid horizontal direction ``theta'`` is at least pi in its
second face, as ``(theta' - pi, pi - alpha')`` (:func:`second_face`, :func:`fold_second_face`).
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


def rotation_matrix_column_z(omega, phi, kappa, xp=jnp):
    """``R e3``, the third column of :func:`rotation_matrix` (the object-space vertical seen in
    scanner space), written out alone: what a compensator reads, at a fraction of the
    arithmetic of the whole matrix (and of its derivative)."""
    cw, sw = xp.cos(omega), xp.sin(omega)
    sp_cw = xp.sin(phi) * cw
    ck, sk = xp.cos(kappa), xp.sin(kappa)
    return xp.stack([sk * sw - ck * sp_cw, ck * sw + sk * sp_cw, xp.cos(phi) * cw])


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
    # The sum of three squares written out: a reduction over the last axis is a kernel of its
    # own in XLA (and under jacfwd a second one), the written-out sum fuses with the rest.
    h2 = x[..., 0] * x[..., 0] + x[..., 1] * x[..., 1]
    rho = xp.sqrt(h2 + x[..., 2] * x[..., 2])
    theta = xp.mod(xp.arctan2(x[..., 1], x[..., 0]), TWO_PI)
    # sqrt, not hypot: coordinates in metres neither overflow nor underflow their squares, and
    # XLA's CPU backend at optimisation level 0 (the docs build's) with the older emitters
    # (tlsjax._jit) generated wrong code for hypot's derivative fused with the rotation
    # written out before it: 57 of 144 elevation rows of the point Jacobian 40 % off, and the
    # adjustment did not converge (tests/test_jit.py; jaxlib 0.10.2).
    alpha = xp.arctan2(x[..., 2], xp.sqrt(h2))
    l = xp.stack([rho, theta, alpha], axis=-1)
    return l if panoramic_face2 is None else fold_second_face(l, panoramic_face2, xp)


def second_face(theta_hybrid, architecture: str = "panoramic"):
    """The panoramic face rule (SPEC section 1): True where a direction whose hybrid horizontal
    direction ``theta'`` (in [0, 2 pi)) is at least pi, which a panoramic scanner observes in
    its second face; False everywhere for a hybrid scanner (one face)."""
    if architecture != "panoramic":
        return np.zeros(np.shape(theta_hybrid), dtype=bool)
    return theta_hybrid >= np.pi


def fold_second_face(l, face2, xp=jnp):
    """Hybrid observations ``l[..., 3]`` as a panoramic scanner's: ``(rho, theta - pi, pi -
    alpha)`` where ``face2`` (:func:`second_face`), unchanged elsewhere."""
    theta = xp.where(face2, l[..., 1] - np.pi, l[..., 1])
    alpha = xp.where(face2, np.pi - l[..., 2], l[..., 2])
    return xp.stack([l[..., 0], theta, alpha], axis=-1)


def scanner_observations(x, architecture: str, xp=jnp):
    """(rho, theta, alpha) of scanner-space points ``x[..., 3]`` as a scanner of
    ``architecture`` reports them: theta in [0, 2 pi) for a hybrid scanner, the two faces of
    SPEC section 1 for a panoramic one."""
    l = spherical_from_cartesian(x, xp=xp)
    theta = xp.where(l[..., 1] >= TWO_PI, 0.0, l[..., 1])  # the mod can round up to 2 pi
    l = xp.stack([l[..., 0], theta, l[..., 2]], axis=-1)
    if architecture == "panoramic":
        l = fold_second_face(l, second_face(theta), xp)
    return l


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


def kabsch(u, v, weights=None, xp=jnp):
    """Rotation R minimising ``sum w_i |R u_i - v_i|^2`` over rotations, for centred point sets
    (or directions) ``u``, ``v`` (n, 3) (Kabsch 1976; Horn 1987): ``R = V D U^T`` from the SVD
    ``U S V^T`` of the cross-covariance ``H = sum w_i u_i v_i^T``, with ``D = diag(1, 1,
    det(V U^T))`` removing a reflection (1 where H is too degenerate to tell). Returns R and
    the singular values of H (descending; ``s_2 / s_1`` near 0: the rotation is undetermined).
    jax (differentiable) or numpy (``xp``)."""
    H = (u if weights is None else u * weights[:, None]).T @ v
    U, sv, Vt = xp.linalg.svd(H, full_matrices=False)
    dsign = xp.where(xp.linalg.det(Vt.T @ U.T) < 0, -1.0, 1.0)
    D = xp.diag(xp.stack([xp.ones_like(dsign), xp.ones_like(dsign), dsign]))
    return Vt.T @ D @ U.T, sv


def rigid_fit(src, dst, xp=jnp):
    """R, t minimising ``sum |R src + t - dst|^2`` over rotations: :func:`kabsch` of the
    centred sets, both (n, 3); jax (differentiable) or numpy."""
    cs, cd = src.mean(axis=0), dst.mean(axis=0)
    R, _ = kabsch(src - cs, dst - cd, xp=xp)
    return R, cd - R @ cs


def plane_from_moments(count, first, second):
    """Least-squares planes of point sets from their moments (host side, numpy; batched over
    leading axes): ``count`` n, ``first`` = sum x (..., 3), ``second`` = sum x x^T (..., 3, 3),
    about any origin. The covariance ``C = second / n - c c^T`` about the centroid ``c = first
    / n``; the unit normal is the eigenvector of its smallest eigenvalue (principal component
    analysis; the orthogonal-distance least-squares plane). Returns (normal (..., 3), centroid
    (..., 3), eigenvalues of C (..., 3), ascending)."""
    n = np.asarray(count, dtype=np.float64)
    c = first / n[..., None]
    C = second / n[..., None, None] - c[..., :, None] * c[..., None, :]
    w, V = np.linalg.eigh(C)
    return V[..., :, 0], c, w


def fit_plane(x):
    """Least-squares plane of points x (n, 3): unit normal, d (``n . X = d``), eigenvalues of
    the points' covariance (ascending); :func:`plane_from_moments` about the centroid."""
    c = x.mean(axis=0)
    y = x - c
    n, cy, w = plane_from_moments(len(x), y.sum(axis=0), y.T @ y)
    return n, float(n @ (c + cy)), w


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
