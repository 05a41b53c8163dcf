"""Gauss-Newton with Levenberg-Marquardt damping on the block normal equations (SPEC section 7).

Iterations run in one ``lax.while_loop``; each step assembles and reduces the normal equations
(:mod:`._normal`), solves, and accepts the step when it does not increase ``v^T P v``. After
the last step one more pass linearises and reduces (undamped) at the final estimate and stops:
the quality pass takes that linearisation from the loop, so the linearisation is traced and
compiled once for both (and a batch of Monte Carlo realisations runs the same code). A
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

Gauss-Helmert families (planes) carry their residuals v through the loop (``SolveState.state``,
the families' ``state_init``/``cost_state`` hooks): each linearisation is taken at ``l + v``
(the rigorous iteration of Lenzmann & Lenzmann 2004), the cost of a trial step is ``v^T P v``
after one Gauss-Helmert update of v at the trial unknowns, and the loop has converged when the
update of the unknowns and the change of v are both below the threshold.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, Bool, Float, Int

from ._families import (
    Options,
    Params,
    Problem,
    Spec,
    cost_and_state,
    count_observations,
    initial_state,
    on_grid,
    state_from_rows,
)
from ._normal import (
    Blocks,
    Reduced,
    ap_jacobians,
    linearise_rows,
    linearised_cost,
    null_space,
    reduce,
    solve_step,
    update_size,
)

#: An update below this many RMS rounding errors of the whitened residuals cannot be resolved.
ROUNDING_FACTOR = 1e4
#: A cost decrease below this many times the cost's rounding noise cannot be resolved.
COST_RESOLUTION = 10.0


class SolveState(eqx.Module):
    params: Params
    cost: Float[Array, ""]
    damping: Float[Array, ""]
    iteration: Int[Array, ""]
    converged: Bool[Array, ""]
    finite: Bool[Array, ""]
    size: Float[Array, ""]  # last Gauss-Newton update over the convergence threshold
    # Columns of the reduced system found dependent at the last undamped linearisation: a
    # damped step holds them too (damping the primitives' blocks would hide the dependency of
    # an AP whose effect they absorb, and the step would wander along it).
    dependent: Bool[Array, " r"]
    # Per family its iteration state (the Gauss-Helmert residuals v of a plane family).
    state: tuple = ()


class Linearisation(eqx.Module):
    """The linearisation at the final estimate that the loop hands to the quality pass:
    normal-equation blocks, per-family rows (:class:`._normal.Rows`), the datum's null-space
    columns and the undamped reduced system."""

    blocks: Blocks
    rows: tuple
    Hp: tuple
    Hz: Array
    reduced: Reduced


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
    return adjust_linearised(spec, on_grid(problem), params0, options)[0]


class _Loop(eqx.Module):
    state: SolveState
    lin: Linearisation
    done: Bool[Array, ""]


def adjust_linearised(
    spec: Spec, problem: Problem, params0: Params, options: Options, final_pass: bool = True
):
    """:func:`adjust` on a problem already on its grid (:func:`._families.on_grid`); also
    returns the :class:`Linearisation` at the final estimate. One trace of the linearisation:
    the loop's last pass (after convergence, the iteration limit or too much damping) only
    linearises and reduces, undamped, at the final estimate.

    ``final_pass=False`` (Monte Carlo, which needs only the estimable summary) skips that pass
    and returns the linearisation of the last step instead: converged means that step was an
    undamped Gauss-Newton step shorter than ``tolerance`` a posteriori sigmas, so its reduced
    system differs from the one at the final estimate at second order (the AP cofactors by
    about 1e-10 relatively, tested against calibrate), and ``state.cost`` is the cost of the
    accepted step (at the final estimate)."""
    ap_jac = ap_jacobians(spec, problem, params0)
    dof = jnp.maximum(
        count_observations(problem, params0)
        - _unknowns(spec, problem, params0)
        + len(spec.datum_columns),
        1.0,
    )
    rho = rounding_sigma(problem)
    floor = ROUNDING_FACTOR * rho

    # A nested jit: the loop's carry needs the linearisation's shapes before the loop body is
    # traced, and jit's trace cache lets the body reuse that one trace (eval_shape of a plain
    # function would trace it a second time, a third of the lowering time).
    @jax.jit
    def linearisation(params, fam_state, damping, dependent):
        blocks, rows = linearise_rows(spec, problem, params, ap_jac, fam_state)
        Hp, Hz = null_space(spec, problem.families, params)
        red = reduce(spec, problem, blocks, Hz, damping, options.rank_tolerance, dependent)
        return Linearisation(blocks, rows, Hp, Hz, red)

    def body(loop: _Loop):
        state = loop.state
        last = (
            state.converged
            | (state.iteration >= options.max_iterations)
            | (state.damping > options.damping_max)
        )
        if not final_pass:
            lin = linearisation(state.params, state.state, state.damping, state.dependent)
            ref_cost = linearised_cost(problem, state.params, lin.rows)
            new_state = _step(state, lin, ref_cost, state.damping)
            return _Loop(new_state, lin, _stop(new_state))
        damping = jnp.where(last, 0.0, state.damping)
        lin = linearisation(state.params, state.state, damping, state.dependent)
        ref_cost = linearised_cost(problem, state.params, lin.rows)
        new_state = lax.cond(last, lambda: state, lambda: _step(state, lin, ref_cost, damping))
        return _Loop(new_state, lin, last)

    def _stop(state):
        return (
            state.converged
            | (state.iteration >= options.max_iterations)
            | (state.damping > options.damping_max)
        )

    def _step(state, lin, ref_cost, damping):
        red = lin.reduced
        new, dps, dz = solve_step(spec, problem, state.params, lin.blocks, red, lin.Hp, lin.Hz)
        new_cost, new_fam, moved = cost_and_state(spec, problem, new, state.state, ap_jac)
        # A rejected step keeps the unknowns; the Gauss-Helmert residuals still take their
        # update at them (from the linearisation's own rows).
        kept_fam, moved_kept = state_from_rows(problem, lin.rows, state.state)
        finite = jnp.isfinite(new_cost)
        accept = finite & (new_cost <= ref_cost * (1.0 + 1e-12))
        s0 = jnp.sqrt(jnp.maximum(ref_cost, 0.0) / dof)
        threshold = jnp.maximum(options.tolerance * s0, floor)
        update = update_size(lin.blocks, red, dz, dps)
        size = update / threshold
        # A step is accepted by comparing costs, and the cost carries rounding noise of about
        # 2 rho sqrt(cost) (rho: rounding of one whitened residual). A step of size u (in a
        # priori sigmas) lowers the cost by about u^2; below COST_RESOLUTION times that noise
        # its rejection says nothing (warm starts at small noise otherwise alternate rejected
        # and damped steps at the solution). Accepted steps keep the plain threshold, so the
        # estimate does not depend on the path (Monte Carlo equals calibrate to 1e-9 sigma).
        resolvable = jnp.sqrt(COST_RESOLUTION * 2.0 * rho * jnp.sqrt(jnp.maximum(ref_cost, 0.0)))
        unresolved = ~accept & (update < resolvable)
        # Only an undamped step measures the distance to the solution: a damped one is short
        # by construction. At the solution an undamped step is rounding noise and may be
        # rejected by rounding alone; it is converged either way.
        # ... and the residuals of Gauss-Helmert families have settled as well.
        settled = jnp.where(accept, moved, moved_kept) < threshold
        converged = (damping == 0) & jnp.isfinite(size) & ((size < 1.0) | unresolved) & settled
        params = _where(accept, new, state.params)
        damping_next = jnp.where(
            accept,
            jnp.where(damping < options.damping_min, 0.0, damping * options.damping_decrease),
            jnp.maximum(damping * options.damping_increase, options.damping_initial),
        )
        return SolveState(
            params,
            jnp.where(accept, new_cost, ref_cost),
            damping_next,
            state.iteration + 1,
            converged,
            finite | accept,
            jnp.where(damping == 0, size, state.size),
            jnp.where(damping == 0, red.dependent, state.dependent),
            _where(accept, new_fam, kept_fam),
        )

    init = SolveState(
        params0,
        jnp.asarray(jnp.inf),
        jnp.asarray(0.0),
        jnp.asarray(0),
        jnp.asarray(False),
        jnp.asarray(True),
        jnp.asarray(jnp.inf),
        jnp.zeros(spec.r, dtype=bool),
        initial_state(problem),
    )
    # The loop carries the last linearisation; its first pass fills it.
    lin0 = jax.eval_shape(linearisation, params0, init.state, jnp.asarray(0.0), init.dependent)
    zeros = jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), lin0)
    out = lax.while_loop(lambda loop: ~loop.done, body, _Loop(init, zeros, jnp.asarray(False)))
    state = out.state
    if not final_pass:
        return state, out.lin
    # v^T P v at the final estimate (with its own weights), from the last linearisation.
    final_cost = linearised_cost(problem, state.params, out.lin.rows)
    finite = state.finite & jnp.isfinite(final_cost)
    state = eqx.tree_at(lambda s: (s.cost, s.finite), state, (final_cost, finite))
    return state, out.lin


def _where(flag, a, b):
    return jax.tree.map(lambda x, y: jnp.where(flag, x, y), a, b)
