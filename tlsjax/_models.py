"""Observation models as pure functions of (parameters, observations).

Point-based Gauss-Markov model (Chow et al. 2013, eqs. 1-3; SPEC section 2):
``l + v = F(X, EOP) + Delta(l; AP)`` for l = (rho, theta, alpha). The adjustment works with
whitened residuals ``e = wrap(F + Delta - l) / sigma`` so that the weight matrix is the identity;
Jacobian blocks come from ``jax.vmap(jax.jacfwd(...))`` over observations.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from ._aps import ap_corrections, resolve_aps
from ._geometry import rotation_matrix, spherical_from_cartesian, wrap_angle, is_face2

ARCHITECTURES = ("hybrid", "panoramic")


@dataclasses.dataclass(frozen=True)
class Scanner:
    """Settings of one instrument: architecture, active APs and unit lengths.

    ``architecture``: "hybrid" (one face, theta in [0, 2pi), alpha in [-pi/2, pi/2]) or
    "panoramic" (two faces, theta in [0, pi), alpha in [-pi/2, 3pi/2)). ``aps``: names or
    presets, e.g. ``"A0 B6 B7 C0"`` or ``"chow2013"``. ``unit_length`` U [m] of the cyclic
    terms A3/A4, ``unit_length_2`` of A5/A6.
    """

    architecture: str = "hybrid"
    aps: tuple = ("A0", "B6", "B7", "C0")
    unit_length: float = 1.2
    unit_length_2: float = 0.6

    def __post_init__(self):
        if self.architecture not in ARCHITECTURES:
            raise ValueError(f"scanner architecture {self.architecture!r} is not one of {ARCHITECTURES}")
        object.__setattr__(self, "aps", resolve_aps(self.aps))
        for name, u in (("unit_length", self.unit_length), ("unit_length_2", self.unit_length_2)):
            if not (np.isfinite(u) and u > 0):
                raise ValueError(f"scanner {name} must be a positive length in metres, got {u}")


def point_geometry(X, eop):
    """Scanner-space coordinates ``x = R(omega, phi, kappa) (X - S)`` (SPEC section 1)."""
    R = rotation_matrix(eop[3], eop[4], eop[5])
    return R @ (X - eop[:3])


def predict_point(X, eop, l_obs, architecture: str):
    """F(X, EOP): error-free (rho, theta, alpha) in the face of the observation ``l_obs``.

    A panoramic scanner sees a direction in the face the observation was taken in; choosing
    the face from the observation keeps F smooth near the face boundary.
    """
    x = point_geometry(X, eop)
    face2 = is_face2(l_obs[2]) if architecture == "panoramic" else None
    return spherical_from_cartesian(x, face2)


def point_misclosure(X, eop, coeffs, l_obs, scanners: tuple, ap_names: tuple, ap_slices: tuple, instrument):
    """``F(X, EOP) + Delta(l; AP) - l`` with the angles wrapped to (-pi, pi].

    ``coeffs`` is the AP vector of all instruments; ``ap_slices[i]`` is the block of instrument
    i. The instrument code selects the block, so autodiff gives zeros for the other blocks.
    """
    out = jnp.zeros(3)
    for i, (scanner, names, (a, b)) in enumerate(zip(scanners, ap_names, ap_slices)):
        F = predict_point(X, eop, l_obs, scanner.architecture)
        d = ap_corrections(coeffs[a:b], names, l_obs, scanner) if names else 0.0
        f = F + d - l_obs
        f = f.at[1:].set(wrap_angle(f[1:]))
        out = jnp.where(instrument == i, f, out)
    return out


def simulate_point_observations(X, eop, coeffs, scanners, ap_names, ap_slices, instrument, noise, face2=None, iterations=30):
    """Observations ``l`` that satisfy ``l = F + Delta(l; AP) + noise`` exactly (fixed point).

    Delta is evaluated at the observations (SPEC section 2), so simulated data are made
    consistent with the model by a few fixed-point iterations; the AP terms are small, so the
    iteration contracts quickly. A rolled loop, so it compiles once and quickly.
    """
    x = point_geometry(X, eop)
    l0 = spherical_from_cartesian(x, face2) + noise

    def step(_, l):
        # f = F + Delta(l) - l (angles wrapped), so l + f is the next iterate.
        return l + point_misclosure(X, eop, coeffs, l, scanners, ap_names, ap_slices, instrument) + noise

    return jax.lax.fori_loop(0, iterations, step, l0)


@functools.partial(jax.jit, static_argnames=("scanner", "names"))
def observe_points(X, eops, noise, face2, coeffs, scanner: Scanner, names: tuple):
    """:func:`simulate_point_observations` for many points of one instrument: ``X``, ``eops``,
    ``noise`` (m, 3)/(m, 6)/(m, 3), ``face2`` (m,). Compiled once per (scanner, AP names, m)."""
    one = lambda Xi, ei, ni, f2: simulate_point_observations(Xi, ei, coeffs, (scanner,), (names,), ((0, len(names)),), 0, ni, f2)
    return jax.vmap(one)(X, eops, noise, face2)
