"""The public entry point: ``calibrate(network, model, options) -> CalibrationResult``.

Host side: validate the configuration, build the index plan and the approximate values, call
the compiled adjustment (:mod:`._solver`) and quality (:mod:`._quality`) once, and turn the
arrays into a result with names, units and result codes (:mod:`._result`).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from ._config import CalibrationModel, SolverOptions
from ._network import Network, check_calibration_arguments
from ._plan import build_plan, initial_params
from ._quality import quality
from ._result import CalibrationResult, assemble
from ._solver import adjust


@functools.partial(jax.jit, static_argnums=(0, 5))
def _run(spec, problem, params0, options, rank_tolerance, full_covariance):
    state = adjust(spec, problem, params0, options)
    q = quality(spec, problem, state.params, rank_tolerance, full_covariance)
    return state, q


def calibrate(
    network: Network,
    model: CalibrationModel | None = None,
    options: SolverOptions | None = None,
    *,
    throw: bool = False,
    initial=None,
) -> CalibrationResult:
    """Self-calibrate a TLS network: one free-network adjustment of targets and/or planes, scan
    poses and APs.

    Targets: Gauss-Markov model of Chow et al. 2013 (eqs. 1-6). Planes: one Gauss-Helmert
    condition per point, ``n . (R^T x(l - Delta) + S) - d = 0`` (eq. 3; SPEC section 4), with
    the unit-normal constraint. Structured Gauss-Newton with LM damping (targets and planes
    eliminated by Schur complement), datum by inner constraints on the object-space primitives
    (or a fixed scan, or control points), quality from the compiled normal matrix. With
    ``throw=True`` a failed result raises ``RuntimeError``. ``initial`` optionally gives
    (targets (t, 3), eops (s, 6)[, planes (k, 4)]) instead of the computed approximate values.
    """
    check_calibration_arguments(network, model, options, "calibrate")
    model = model or CalibrationModel()
    options = options or SolverOptions()
    plan = build_plan(network, model)
    p0 = initial_params(network, plan, *(initial or (None, None)))
    state, q = _run(
        plan.spec,
        plan.problem,
        p0,
        options.arrays(),
        jnp.asarray(options.rank_tolerance),
        options.full_covariance,
    )
    res = assemble(network, model, plan, state, q)
    if throw and not res.ok:
        raise RuntimeError(res.message)
    return res
