"""Gauss-Newton with Levenberg-Marquardt damping on the block normal equations (SPEC section 7).

Iterations run in one ``lax.while_loop``; each step assembles and reduces the normal equations
(:mod:`._normal`), solves, and accepts the step when it does not increase ``v^T P v``. A
rejected step raises the damping (``damping_increase``), an accepted one lowers it
(``damping_decrease``) down to pure Gauss-Newton below ``damping_min``: a descent method on
``v^T P v`` from any start, Gauss-Newton near the solution.

Convergence is tested on the undamped (Gauss-Newton) update, in units of each parameter's a
posteriori standard deviation: ``max_i |dx_i| / (s0 sqrt(Q_ii)) < tolerance`` with ``s0^2 = v^T P
v / r`` at the current estimate. The ratio does not change when all sigmas are scaled by a
common factor (dx does not, ``sqrt(Q_ii)`` and ``1/s0`` scale alike). On noise-free data s0 is
itself rounding noise, so the test is floored at the rounding level of the whitened residuals
(``ROUNDING_FACTOR`` times their RMS rounding error): an update that small cannot be resolved
in float64, and a step there is accepted or rejected by rounding alone.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, Bool, Float, Int

from ._families import Options, Params, Problem, Spec, cost, count_observations
from ._normal import ap_jacobians, linearise, null_space, reduce, solve_step, update_size

#: An update below this many RMS rounding errors of the whitened residuals cannot be resolved.
ROUNDING_FACTOR = 1e4


class SolveState(eqx.Module):
    params: Params
    cost: Float[Array, ""]
    damping: Float[Array, ""]
    iteration: Int[Array, ""]
    converged: Bool[Array, ""]
    finite: Bool[Array, ""]
    size: Float[Array, ""]  # last Gauss-Newton update over the convergence threshold


def rounding_sigma(problem: Problem):
    """RMS rounding error of the whitened residual rows (float64 resolution of the data)."""
    num, den = 0.0, 0.0
    for fam in problem.families:
        r = jnp.where(fam.active_rows(), fam.rounding(), 0.0)
        num = num + jnp.sum(r**2)
        den = den + jnp.sum(fam.active_rows())
    return jnp.sqrt(num / jnp.maximum(den, 1))


def _unknowns(spec: Spec, problem: Problem, params: Params):
    return sum(P.size for P in params.prims) + spec.r - jnp.sum(problem.fixed)


def adjust(spec: Spec, problem: Problem, params0: Params, options: Options) -> SolveState:
    """Gauss-Newton with Levenberg-Marquardt damping as a safeguard, one ``lax.while_loop``.

    Returns the final state (pure, jittable, vmappable). ``state.size`` is the last
    Gauss-Newton update over its convergence threshold (below 1 when converged).
    """
    ap_jac = ap_jacobians(spec, problem, params0)
    frozen_cost = any(fam.frozen_cost for fam in problem.families)
    dof = jnp.maximum(
        count_observations(problem, params0)
        - _unknowns(spec, problem, params0)
        + len(spec.datum_columns),
        1.0,
    )
    floor = ROUNDING_FACTOR * rounding_sigma(problem)

    def step(state: SolveState):
        blocks = linearise(spec, problem, state.params, ap_jac)
        Hp, Hz = null_space(spec, problem.families, state.params)
        red = reduce(spec, problem, blocks, Hz, state.damping, options.rank_tolerance)
        new, dps, dz = solve_step(spec, problem, state.params, blocks, red, Hp, Hz)
        if frozen_cost:
            ref_cost = cost(spec, problem, state.params, frozen=state.params)
            new_cost = cost(spec, problem, new, frozen=state.params)
        else:
            ref_cost, new_cost = state.cost, cost(spec, problem, new)
        finite = jnp.isfinite(new_cost)
        accept = finite & (new_cost <= ref_cost * (1.0 + 1e-12))
        s0 = jnp.sqrt(jnp.maximum(ref_cost, 0.0) / dof)
        threshold = jnp.maximum(options.tolerance * s0, floor)
        size = update_size(blocks, red, dz, dps) / threshold
        # Only an undamped step measures the distance to the solution: a damped one is short
        # by construction. At the solution an undamped step is rounding noise and may be
        # rejected by rounding alone; it is converged either way.
        converged = (state.damping == 0) & jnp.isfinite(size) & (size < 1.0)
        params = _where(accept, new, state.params)
        damping = jnp.where(
            accept,
            jnp.where(
                state.damping < options.damping_min, 0.0, state.damping * options.damping_decrease
            ),
            jnp.maximum(state.damping * options.damping_increase, options.damping_initial),
        )
        return SolveState(
            params,
            jnp.where(accept, new_cost, state.cost),
            damping,
            state.iteration + 1,
            converged,
            finite | accept,
            jnp.where(state.damping == 0, size, state.size),
        )

    def cond(state: SolveState):
        return (
            (~state.converged)
            & (state.iteration < options.max_iterations)
            & (state.damping <= options.damping_max)
        )

    c0 = cost(spec, problem, params0)
    init = SolveState(
        params0,
        c0,
        jnp.asarray(0.0),
        jnp.asarray(0),
        jnp.asarray(False),
        jnp.isfinite(c0),
        jnp.asarray(jnp.inf),
    )
    return lax.while_loop(cond, step, init)


def _where(flag, a, b):
    return jax.tree.map(lambda x, y: jnp.where(flag, x, y), a, b)
