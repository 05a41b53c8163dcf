"""Gauss-Newton with Levenberg-Marquardt damping on the block normal equations (SPEC section 7).

Iterations run in one ``lax.while_loop``. A pass holds the residual rows and Jacobian blocks at
the current estimate x (:class:`._normal.Rows`); it assembles and reduces the normal equations
from them (:mod:`._normal`), solves for the step, and evaluates the rows at the candidate
``x + dx``: they give the candidate's cost (accept the step when it does not increase ``v^T P
v``), its gradient, and, when accepted, the next pass's linearisation. A rejected step raises
the damping (``damping_increase``), an accepted one lowers it (``damping_decrease``) down to
pure Gauss-Newton below ``damping_min``: a descent method on ``v^T P v`` from any start,
Gauss-Newton near the solution.

**Convergence is decided in the pass that reaches it**, with nothing left to confirm. After an
accepted undamped step the gradient ``b`` at the candidate and the factorisation at hand give
the chord step ``c = N^- b`` (one back-substitution): the next Gauss-Newton step up to the
relative change of the normal matrix over one step (about 1e-4 here). Its length in the metric
of the normal matrix, ``sqrt(c^T N c) = sqrt(c^T b)``, bounds every component in units of the
parameter's standard deviation, ``|c_i| <= sqrt(Q_ii) sqrt(c^T N c)`` (Cauchy-Schwarz), so no
cofactor diagonal is needed. When that bound is below ``tolerance`` a posteriori sigmas (``s0^2 =
v^T P v / r`` at the candidate), the adjustment has converged: ``x + dx + c`` is returned, which
is the next Gauss-Newton iterate to within ``1e-4 |c|``, i.e. the estimate of a loop that took
one more full pass. The quality (cofactors, redundancy) comes from the last factorisation and
the rows at the candidate: they differ from a linearisation at the final estimate by the change
over a step smaller than ``tolerance`` sigmas (relative 1e-12 on the test networks), and ``v^T P
v`` from the candidate's residuals (the chord step lowers it by ``c^T b``, of order
``tolerance^2``). The number of factorisations then equals the number of Gauss-Newton steps a
trust-region solver such as Ceres takes on the same problem.

The tolerance is in a posteriori sigmas; the ratio does not change when all sigmas are scaled
by a common factor. On noise-free data s0 is itself rounding noise, so the test is floored at
the rounding level of the whitened residuals (``ROUNDING_FACTOR`` times their RMS rounding
error): an update that small cannot be resolved in float64, and a step there is accepted or
rejected by rounding alone.
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
    count_observations,
    levelling_residual,
    on_grid,
)
from ._normal import (
    Reduced,
    ap_jacobians,
    apply_update,
    assemble,
    gradient,
    linearised_cost,
    norm_squared,
    null_space,
    reduce,
    rows_at,
    solve,
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
    size: Float[Array, ""]  # last convergence measure over its threshold (below 1: converged)
    # Columns of the reduced system found dependent at the last undamped linearisation: a
    # damped step holds them too (damping the primitives' blocks would hide the dependency of
    # an AP whose effect they absorb, and the step would wander along it).
    dependent: Bool[Array, " r"]


class Linearisation(eqx.Module):
    """What the loop hands to the quality pass: per-family rows (:class:`._normal.Rows`) at
    the final estimate, the datum's null-space columns and the undamped reduced system."""

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
    convergence measure over its threshold (below 1 when converged).
    """
    return adjust_linearised(spec, on_grid(problem), params0, options)[0]


class _Loop(eqx.Module):
    state: SolveState
    rows: tuple  # at state.params (before a final chord correction)
    lin: Linearisation  # the last pass's factorisation (at the point the last step left)
    damped: Bool[Array, ""]  # the last pass's factorisation was damped
    done: Bool[Array, ""]


def _frozen_cost(problem: Problem, params: Params, rows, frozen):
    """``v^T P v`` at ``params`` from its rows, families with ``frozen_cost`` whitened with the
    weights of the linearisation point (``frozen``: its rows): a step's acceptance test."""
    total = jnp.sum(levelling_residual(problem, params.eops) ** 2)
    for fam, P, r, f in zip(problem.families, params.prims, rows, frozen):
        e = fam.frozen_rows(r, f) if fam.frozen_cost else r.e
        total = total + jnp.sum(e**2) + jnp.sum(fam.prior_residuals(P) ** 2)
    return total


def adjust_linearised(
    spec: Spec, problem: Problem, params0: Params, options: Options, final_pass: bool = True
):
    """:func:`adjust` on a problem already on its grid (:func:`._families.on_grid`); also
    returns the :class:`Linearisation` the quality pass needs (see the module docstring).

    ``final_pass``: when the loop ends without convergence (iteration limit, too much damping)
    the last factorisation may be damped; the quality then needs an undamped one at the final
    estimate, made after the loop (a ``lax.cond``). Monte Carlo, which reports failures by
    their result code only, passes False."""
    ap_jac = ap_jacobians(spec, problem, params0)
    dof = jnp.maximum(
        count_observations(problem, params0)
        - _unknowns(spec, problem, params0)
        + len(spec.datum_columns),
        1.0,
    )
    rho = rounding_sigma(problem)
    floor = ROUNDING_FACTOR * rho

    # Nested jits: the initial rows and the candidate's rows share one trace, as do the
    # factorisation in the loop and after it.
    @jax.jit
    def rows_of(params):
        return rows_at(spec, problem, params, ap_jac)

    @jax.jit
    def factorise(params, rows, damping, dependent):
        blocks = assemble(spec, problem, params, rows)
        Hp, Hz = null_space(spec, problem.families, params)
        red = reduce(spec, problem, blocks, Hz, damping, options.rank_tolerance, dependent)
        return blocks, Linearisation(rows, Hp, Hz, red)

    def threshold(cost):
        s0 = jnp.sqrt(jnp.maximum(cost, 0.0) / dof)
        return jnp.maximum(options.tolerance * s0, floor)

    def body(loop: _Loop):
        state, rows = loop.state, loop.rows
        damping = state.damping
        blocks, lin = factorise(state.params, rows, damping, state.dependent)
        red = lin.reduced
        dps, dz = solve(spec, red, blocks.bp, blocks.bz, lin.Hp, lin.Hz)
        new = apply_update(spec, problem, state.params, dps, dz)
        new_rows = rows_of(new)
        new_cost = _frozen_cost(problem, new, new_rows, rows)
        finite = jnp.isfinite(new_cost)
        accept = finite & (new_cost <= state.cost * (1.0 + 1e-12))
        # A step is accepted by comparing costs, and the cost carries rounding noise of about
        # 2 rho sqrt(cost) (rho: rounding of one whitened residual). A step of length u (in a
        # priori sigmas) lowers the cost by about u^2; below COST_RESOLUTION times that noise
        # its rejection says nothing: at the solution an undamped step is rounding noise and
        # may be rejected by rounding alone; it is converged either way.
        update = jnp.sqrt(jnp.maximum(norm_squared(dps, dz, blocks.bp, blocks.bz), 0.0))
        resolvable = jnp.sqrt(COST_RESOLUTION * 2.0 * rho * jnp.sqrt(jnp.maximum(state.cost, 0)))
        unresolved = ~accept & (update < resolvable)
        # The chord step at the candidate with the factorisation at hand (module docstring).
        own_cost = linearised_cost(problem, new, new_rows)
        bp, bz = gradient(spec, problem, new, new_rows)
        bp = tuple(f.tangent_gradient(P, b) for f, P, b in zip(problem.families, new.prims, bp))
        cps, cz = solve(spec, red, bp, bz, lin.Hp, lin.Hz)
        chord = jnp.sqrt(jnp.maximum(norm_squared(cps, cz, bp, bz), 0.0)) / threshold(own_cost)
        undamped = damping == 0
        done_here = undamped & accept & jnp.isfinite(chord) & (chord < 1.0)
        converged = done_here | (undamped & unresolved)
        params = _where(accept, new, state.params)
        params = _where(done_here, apply_update(spec, problem, new, cps, cz), params)
        damping_next = jnp.where(
            accept,
            jnp.where(damping < options.damping_min, 0.0, damping * options.damping_decrease),
            jnp.maximum(damping * options.damping_increase, options.damping_initial),
        )
        size = jnp.where(unresolved, 0.0, chord)
        new_state = SolveState(
            params,
            jnp.where(accept, own_cost, state.cost),
            damping_next,
            state.iteration + 1,
            converged,
            finite | accept,
            jnp.where(undamped, size, state.size),
            jnp.where(undamped, red.dependent, state.dependent),
        )
        rows = _where(accept, new_rows, rows)
        lin = Linearisation(rows, lin.Hp, lin.Hz, red)
        stop = (
            converged
            | (new_state.iteration >= options.max_iterations)
            | (damping_next > options.damping_max)
        )
        return _Loop(new_state, rows, lin, ~undamped, stop)

    rows0 = rows_of(params0)
    cost0 = linearised_cost(problem, params0, rows0)
    init = SolveState(
        params0,
        cost0,
        jnp.asarray(0.0),
        jnp.asarray(0),
        jnp.asarray(False),
        jnp.isfinite(cost0),
        jnp.asarray(jnp.inf),
        jnp.zeros(spec.r, dtype=bool),
    )
    # The loop carries the last factorisation; its first pass fills it.
    _, lin0 = jax.eval_shape(factorise, params0, rows0, jnp.asarray(0.0), init.dependent)
    zeros = jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), lin0)
    zeros = Linearisation(rows0, zeros.Hp, zeros.Hz, zeros.reduced)
    start = _Loop(init, rows0, zeros, jnp.asarray(False), ~init.finite)
    out = lax.while_loop(lambda loop: ~loop.done, body, start)
    state, lin = out.state, out.lin
    state = eqx.tree_at(lambda s: s.finite, state, state.finite & jnp.isfinite(state.cost))
    if final_pass:
        # Without convergence the last factorisation may be damped, or be missing (a start
        # that is not finite): an undamped one at the final estimate for the quality.
        redo = ~state.converged | out.damped | (state.iteration == 0)
        lin = lax.cond(
            redo,
            lambda: factorise(state.params, out.rows, jnp.asarray(0.0), state.dependent)[1],
            lambda: lin,
        )
    return state, lin


def _where(flag, a, b):
    return jax.tree.map(lambda x, y: jnp.where(flag, x, y), a, b)
