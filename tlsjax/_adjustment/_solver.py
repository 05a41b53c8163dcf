"""Gauss-Newton with Levenberg-Marquardt damping on the block normal equations (SPEC section 7).

Iterations run in one ``lax.while_loop``; each step assembles and reduces the normal equations
(:mod:`._normal`), solves, and accepts the step when it does not increase ``v^T P v``.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, Bool, Float, Int

from .._model._planes import condition_variance, plane_condition
from ._families import (
    Options,
    Params,
    Problem,
    Spec,
    family_args,
    family_residuals,
    levelling_residual,
)
from ._normal import ap_jacobians, linearise, null_space, reduce, solve_step, update_size


def cost(spec, problem, params, frozen: Params | None = None):
    """``v^T P v``: sum of squared whitened residuals, observations and pseudo-observations.

    ``frozen``: evaluate the plane conditions' variances ``m = B Sigma B^T`` there instead of at
    ``params``. A Gauss-Helmert step holds M fixed at its linearisation point, so its
    acceptance must compare costs under that M: with M re-evaluated the step can look like an
    ascent near the solution and Levenberg-Marquardt would stall (seen at 100k points).
    """
    total = jnp.sum(levelling_residual(problem, params.eops) ** 2)
    for fi, fam in enumerate(problem.families):
        e, pr = family_residuals(spec, problem, params, fi)
        if frozen is not None and fam.kind == "plane":
            e = _plane_rows_frozen(spec, problem, params, frozen, fi)
        total = total + jnp.sum(e**2) + jnp.sum(pr**2)
    return total


def _plane_rows_frozen(spec, problem, params, frozen, fi):
    fam = problem.families[fi]
    new, ref = family_args(problem, params, fi), family_args(problem, frozen, fi)
    sigma = jnp.where(fam.weight > 0, 1.0 / jnp.where(fam.weight > 0, fam.weight, 1.0), 0.0)
    sl = (spec.scanners, spec.ap_names, spec.ap_slices)
    m = jax.vmap(lambda P, E, l, s, i: condition_variance(P, E, frozen.aps, l, s, *sl, i)[0])(
        ref[0], ref[1], fam.obs, sigma, ref[6]
    )
    g = jax.vmap(lambda P, E, l, i: plane_condition(P, E, params.aps, l, *sl, i))(
        new[0], new[1], fam.obs, new[6]
    )
    return jnp.where(jnp.any(fam.weight > 0, axis=-1), g / jnp.sqrt(jnp.where(m > 0, m, 1.0)), 0.0)


class SolveState(eqx.Module):
    params: Params
    cost: Float[Array, ""]
    damping: Float[Array, ""]
    iteration: Int[Array, ""]
    converged: Bool[Array, ""]
    finite: Bool[Array, ""]


def adjust(spec: Spec, problem: Problem, params0: Params, options: Options):
    """Gauss-Newton with Levenberg-Marquardt damping as a safeguard, one ``lax.while_loop``.

    A step is accepted when it does not increase ``v^T P v``; otherwise the damping grows
    tenfold and the step is recomputed. Convergence: the largest update in units of the
    parameter's precision (:func:`update_size`) is below ``options.tolerance``. Returns the
    final state (pure, jittable, vmappable).
    """

    ap_jac = ap_jacobians(spec, problem, params0)
    planes = any(fam.kind == "plane" for fam in problem.families)

    def step(state: SolveState):
        blocks = linearise(spec, problem, state.params, ap_jac)
        Hp, Hz = null_space(spec, state.params)
        red = reduce(spec, problem, blocks, Hz, state.damping, options.rank_tolerance)
        new, dps, dz = solve_step(spec, problem, state.params, blocks, red, Hp, Hz)
        if planes:
            ref_cost = cost(spec, problem, state.params)
            new_cost = cost(spec, problem, new, frozen=state.params)
        else:
            ref_cost, new_cost = state.cost, cost(spec, problem, new)
        finite = jnp.isfinite(new_cost)
        accept = finite & (new_cost <= ref_cost * (1.0 + 1e-12) + 1e-12)
        size = update_size(blocks, red, dz, dps)
        # A damped step is short by construction; only an undamped (Gauss-Newton) step may
        # declare convergence, or LM would stop early on its own damping.
        converged = accept & (state.damping == 0) & (size < options.tolerance)
        params = jax.tree.map(lambda a, b: jnp.where(accept, a, b), new, state.params)
        damping = jnp.where(
            accept,
            jnp.where(state.damping < 1e-7, 0.0, state.damping * 0.1),
            jnp.maximum(state.damping * 10.0, 1e-4),
        )
        return SolveState(
            params,
            jnp.where(accept, new_cost, state.cost),
            damping,
            state.iteration + 1,
            converged,
            finite | accept,
        )

    def cond(state: SolveState):
        return (
            (~state.converged) & (state.iteration < options.max_iterations) & (state.damping < 1e8)
        )

    c0 = cost(spec, problem, params0)
    init = SolveState(
        params0, c0, jnp.asarray(0.0), jnp.asarray(0), jnp.asarray(False), jnp.isfinite(c0)
    )
    return lax.while_loop(cond, step, init)
