"""Signalised targets: the geometry and intensity patterns that both the simulator renders and
the target extraction fits (one home for each formula).

Planar contrast targets carry an in-plane frame (u, v) centred on the target's centre. The
laser footprint blurs the printed pattern: a point's intensity is the reflectance averaged over
a Gaussian spot of standard deviation ``blur`` [m] on the plane, so a step edge becomes
``Phi(s / blur)`` (s the signed distance from the edge, Phi the normal distribution function).

- 2 x 2 checkerboard, white where ``u v > 0``: the white share of the footprint is
  ``(1 + erf(u / (sqrt2 blur)) erf(v / (sqrt2 blur))) / 2`` (the expectation of
  ``sign(u + e1) sign(v + e2)`` for independent Gaussian e1, e2 is the product of the erfs).
  Its centre is the saddle point of the intensity surface.
- White disc of radius r on a dark ground: ``Phi((r - |(u, v)|) / blur)`` (the straight-edge
  approximation, exact to O(blur / r)). Its centre is the intensity-weighted centroid.

Spheres: a ray ``t D`` from the scanner (unit D) meets a sphere of centre C and radius R at
``t = D.C - sqrt((D.C)^2 - |C|^2 + R^2)`` (the near side), when the root is real.
"""

from __future__ import annotations

import jax.numpy as jnp
import jax.scipy.special as jss
import numpy as np

PATTERNS = ("checkerboard", "circle")


def _erf(xp):
    if xp is jnp:
        return jss.erf
    from scipy.special import erf  # at first use: scipy is slow to import

    return erf


def checkerboard_white(u, v, blur, xp=jnp):
    """White share of the footprint at in-plane coordinates (u, v) [m] of a 2 x 2 checkerboard
    (white where ``u v > 0``), blurred by a Gaussian spot of standard deviation ``blur`` [m]."""
    erf = _erf(xp)
    k = 1.0 / (np.sqrt(2.0) * blur)
    return 0.5 * (1.0 + erf(u * k) * erf(v * k))


def disc_white(u, v, radius, blur, xp=jnp):
    """White share of the footprint at (u, v) [m] of a white disc of ``radius`` [m] centred on
    the origin of a dark ground, blurred by a Gaussian spot of standard deviation ``blur``."""
    erf = _erf(xp)
    r = xp.sqrt(u * u + v * v)
    return 0.5 * (1.0 + erf((radius - r) / (np.sqrt(2.0) * blur)))


def plane_frame(normal, rotation: float = 0.0) -> np.ndarray:
    """Orthonormal in-plane axes (2, 3) of a plane with unit ``normal``: u horizontal (normal x
    Z) where the plane is not horizontal, else X; both turned by ``rotation`` [rad] about the
    normal. ``u x v = normal``."""
    n = np.asarray(normal, dtype=np.float64)
    n = n / np.linalg.norm(n)
    u = np.cross([0.0, 0.0, 1.0], n)
    if np.linalg.norm(u) < 1e-6:
        u = np.array([1.0, 0.0, 0.0]) - n[0] * n
    u /= np.linalg.norm(u)
    v = np.cross(n, u)
    c, s = np.cos(rotation), np.sin(rotation)
    return np.stack([c * u + s * v, -s * u + c * v])


def sphere_ray_distance(directions, centre, radius) -> np.ndarray:
    """Distance along unit rays ``directions`` (m, 3) from the origin to the near side of a
    sphere (centre (3,), radius), inf where a ray misses it or the sphere is behind."""
    b = directions @ np.asarray(centre, dtype=np.float64)
    disc = b * b - float(np.dot(centre, centre)) + radius * radius
    with np.errstate(invalid="ignore"):
        t = b - np.sqrt(disc)
    return np.where((disc >= 0.0) & (t > 1e-9), t, np.inf)
