"""Observation models as pure functions of (parameters, observations).

Point-based Gauss-Markov model (Chow et al. 2013, eqs. 1-3; SPEC section 2):
``l + v = F(X, EOP) + Delta(l; AP)`` for l = (rho, theta, alpha). The adjustment works with
whitened residuals ``e = wrap(F + Delta - l) / sigma`` so that the weight matrix is the identity;
Jacobian blocks come from ``jax.vmap(jax.jacfwd(...))`` over observations.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from .._jit import jit
from ._aps import ap_corrections
from ._geometry import TWO_PI, is_face2, rotation_matrix, spherical_from_cartesian, wrap_angle
from ._scanner import Scanner


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


def point_misclosure(
    X, eop, coeffs, l_obs, scanners: tuple, ap_names: tuple, ap_slices: tuple, instrument
):
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


#: Fixed-point iterations of :func:`distorted_observations`. The iteration contracts by
#: |dDelta/dl|: about 1e-3 for most terms, but up to 0.2 for the cyclic range terms (a 10 mm
#: amplitude at a 0.6 m unit length has the slope 4 pi A / U), so 30 reach float64 rounding.
FIXED_POINT_ITERATIONS = 30
#: An iteration that moves no observation by more than this many units in the last place has
#: settled (:func:`distorted_observations`): with a contraction below 1/3 the fixed point is
#: then within one unit.
SETTLED_ULPS = 2.0


def distorted_observations(
    base, correction, iterations: int = FIXED_POINT_ITERATIONS, until_settled: bool = False
):
    """Observations ``l`` with ``l = base + correction(l)``, by fixed-point iteration.

    This is how every simulation in tlsjax makes data consistent with the model of SPEC
    section 2, ``l = F + Delta(l; AP) + e``: ``base = F + e`` and ``correction = Delta``,
    evaluated at the observations themselves. The horizontal direction is kept in [0, 2 pi)
    at every step, as a scanner reports it, so that bases of theta see the reported value (a
    panoramic direction pushed below zero is the same direction at 2 pi, not at pi). A rolled
    loop: it compiles once, and quickly.

    ``iterations`` is a bound that reaches float64 rounding at the contraction a design's APs
    can have. ``until_settled``: stop as soon as an iteration moves no observation by more than
    its rounding (:data:`SETTLED_ULPS` units in the last place of ``max(|l|, 1)``), at most
    ``iterations``: the same observations to rounding, in a fraction of the iterations where the
    bound is pessimistic (the Monte Carlo's draws of the Chow room: 3 of its 20). A
    ``while_loop``, so not reverse-differentiable: for draws, not for designs one
    differentiates.
    """

    def step(l):
        l = base + correction(l)
        return l.at[..., 1].set(jnp.mod(l[..., 1], TWO_PI))

    if not until_settled:
        return jax.lax.fori_loop(0, iterations, lambda _, l: step(l), base)

    def body(carry):
        k, l, _ = carry
        new = step(l)
        tol = SETTLED_ULPS * jnp.finfo(new.dtype).eps * jnp.maximum(jnp.abs(new), 1.0)
        return k + 1, new, jnp.any(jnp.abs(new - l) > tol)

    return jax.lax.while_loop(
        lambda carry: carry[2] & (carry[0] < iterations), body, (0, base, jnp.asarray(True))
    )[1]


def simulate_point_observations(
    X, eop, coeffs, scanners, ap_names, ap_slices, instrument, noise, face2=None
):
    """Observations of point ``X`` from pose ``eop`` that satisfy ``l = F + Delta(l; AP) + noise``
    (:func:`distorted_observations`); ``face2`` picks the face of a panoramic scanner."""
    base = spherical_from_cartesian(point_geometry(X, eop), face2) + noise

    def correction(l):
        out = jnp.zeros(3)
        for i, (scanner, names, (a, b)) in enumerate(zip(scanners, ap_names, ap_slices)):
            d = ap_corrections(coeffs[a:b], names, l, scanner) if names else jnp.zeros(3)
            out = jnp.where(instrument == i, d, out)
        return out

    return distorted_observations(base, correction)


def observe_points(X, eops, noise, face2, coeffs, scanner: Scanner, names: tuple):
    """:func:`simulate_point_observations` for many points of one instrument: ``X``, ``eops``,
    ``noise`` (m, 3)/(m, 6)/(m, 3), ``face2`` (m,). Compiled once per (scanner as registered
    now, :meth:`Scanner.current`; AP names; m)."""
    return _observe_points(X, eops, noise, face2, coeffs, scanner.current(), names)


@functools.partial(jit, static_argnames=("scanner", "names"))
def _observe_points(X, eops, noise, face2, coeffs, scanner: Scanner, names: tuple):

    def one(Xi, ei, ni, f2):
        return simulate_point_observations(
            Xi, ei, coeffs, (scanner,), (names,), ((0, len(names)),), 0, ni, f2
        )

    return jax.vmap(one)(X, eops, noise, face2)
