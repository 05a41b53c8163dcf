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

**Gauss-Helmert families** (planes, SPEC section 4) carry their residuals v through the loop,
with the rows (``SolveState.state``; the families' ``state_init``, ``state_from_rows`` and
``state_predict`` hooks): the rows at a point are evaluated at the observations ``l + v`` of the
state they are given, the rigorous iteration of Lenzmann & Lenzmann (2004). The candidate's
state is the linear Gauss-Helmert prediction ``v = -Sigma_l B^T M^-1 (A dx + w)`` of the step
from the rows at x; the candidate's cost ``v^T P v`` is that of one Gauss-Helmert update of v at
the candidate unknowns (its rows, ``e = w / sqrt(m)``), and an accepted step sets the state to
that update. A rejected step keeps the unknowns and their state (already the update from x's
rows). The pass converges only when, besides the chord step, the state has settled: the update
differs from the state the rows were evaluated with by less than the threshold (a priori
sigmas of the observations), i.e. the rows were taken at the right ``l + v``; otherwise one more
pass. At convergence the candidate's rows are moved to the final estimate ``x + dx + c`` to
first order (``e + J c``: the residuals v and ``v^T P v`` the quality reports) and factorised
once more, so that cofactors and redundancy numbers are those of the final rows (the normal
matrix, linearised at ``l + v``, changes more over a step than a point network's: the redundancy
numbers would otherwise sum to the degrees of freedom only to 1e-9 relatively on strongly
nonlinear networks). A network without such families (targets only) has no state and runs
exactly the loop above, with the same number of factorisations.

The tolerance is in a posteriori sigmas; the ratio does not change when all sigmas are scaled
by a common factor. On noise-free data s0 is itself rounding noise, so the test is floored at
the rounding level of the whitened residuals (``ROUNDING_FACTOR`` times their RMS rounding
error): an update that small cannot be resolved in float64, and a step there is accepted or
rejected by rounding alone.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, Bool, Float, Int

from .._pytree import Module
from ._families import (
    Options,
    Params,
    Problem,
    Spec,
    count_observations,
    initial_state,
    levelling_jacobian,
    on_grid,
    predicted_state,
    rows_after,
    settled_state,
    state_from_rows,
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


class SolveState(Module):
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
    # Per family its iteration state (the Gauss-Helmert residuals v of a plane family; None
    # for a family without one).
    state: tuple = ()


class Linearisation(Module):
    """What the loop hands to the quality pass: per-family rows (:class:`._normal.Rows`) with
    the residuals at the final estimate and the Jacobians of the last factorisation, the datum's
    null-space columns and that undamped reduced system."""

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


class _Loop(Module):
    state: SolveState  # at the current estimate x (with the state update from its rows)
    Jl: Float[Array, "s 3 6"]  # the orientation readings' Jacobian at x
    lin: Linearisation  # the factorisation at x that made the candidate
    candidate: Params  # the point the next pass evaluates (the start, then x + dx)
    candidate_state: tuple  # the families' states the candidate's rows are evaluated with
    step: Float[Array, ""]  # length of the step to the candidate, sqrt(dx^T b)
    moved: Float[Array, ""]  # how far the state moved at x (its update from x's rows)
    first: Bool[Array, ""]  # the candidate is the start
    done: Bool[Array, ""]


def adjust_linearised(spec: Spec, problem: Problem, params0: Params, options: Options):
    """:func:`adjust` on a problem already on its grid (:func:`._families.on_grid`); also
    returns the :class:`Linearisation` the quality pass needs (see the module docstring).

    One pass evaluates the rows at the candidate (the start, then the last step's end point),
    accepts or rejects it, tests convergence with the chord step of the factorisation at hand,
    and, unless converged, factorises at the accepted estimate and steps. A loop that ends
    without convergence (iteration limit, too much damping) factorises its final estimate
    undamped, for the quality. Every piece of the pass is traced and compiled once."""
    ap_jac = ap_jacobians(spec, problem, params0)
    dof = jnp.maximum(
        count_observations(problem, params0)
        - _unknowns(spec, problem, params0)
        + len(spec.datum_columns),
        1.0,
    )
    rho = rounding_sigma(problem)
    floor = ROUNDING_FACTOR * rho
    state0 = initial_state(problem)
    # Gauss-Helmert families carry a state; without one the loop is the plain Gauss-Newton one.
    has_state = any(st is not None for st in state0)

    @jax.jit  # a nested jit, so that eval_shape below reuses the loop body's trace
    def factorise(params, rows, damping, dependent, Jl):
        blocks = assemble(spec, problem, params, rows, Jl)
        Hp, Hz = null_space(spec, problem.families, params)
        red = reduce(spec, problem, blocks, Hz, damping, options.rank_tolerance, dependent)
        return Linearisation(rows, Hp, Hz, red), blocks.bp, blocks.bz

    def body(loop: _Loop):
        state, y, first = loop.state, loop.candidate, loop.first
        rows_y = rows_at(spec, problem, y, ap_jac, loop.candidate_state)
        # v^T P v at the candidate: of a Gauss-Helmert family, after one update of its state
        # at the candidate unknowns (the squares of its rows); that update and how far it moved.
        new_cost = linearised_cost(problem, y, rows_y)
        state_y, moved_y = state_from_rows(problem, rows_y, loop.candidate_state)
        accept = first | (jnp.isfinite(new_cost) & (new_cost <= state.cost * (1.0 + 1e-12)))
        # A step is accepted by comparing costs, and the cost carries rounding noise of about
        # 2 rho sqrt(cost) (rho: rounding of one whitened residual). A step of length u (in a
        # priori sigmas) lowers the cost by about u^2; below COST_RESOLUTION times that noise
        # its rejection says nothing: at the solution an undamped step is rounding noise and
        # may be rejected by rounding alone; it is converged either way.
        resolvable = jnp.sqrt(COST_RESOLUTION * 2.0 * rho * jnp.sqrt(jnp.maximum(state.cost, 0)))
        undamped = ~first & (state.damping == 0)
        unresolved = undamped & ~accept & (loop.step < resolvable)
        # The chord step at the candidate with the factorisation at hand (module docstring).
        # The orientation readings' Jacobian at the candidate: for its gradient here and, when
        # the step is accepted, for the factorisation at it (one copy of it in the program).
        Jl_y = levelling_jacobian(problem, y.eops)
        bp, bz = gradient(spec, problem, y, rows_y, Jl_y)
        bp = tuple(f.tangent_gradient(P, b) for f, P, b in zip(problem.families, y.prims, bp))
        cps, cz = solve(spec, loop.lin.reduced, bp, bz, loop.lin.Hp, loop.lin.Hz)
        s0 = jnp.sqrt(jnp.maximum(new_cost, 0.0) / dof)
        threshold = jnp.maximum(options.tolerance * s0, floor)
        chord = jnp.sqrt(jnp.maximum(norm_squared(cps, cz, bp, bz), 0.0)) / threshold
        done_here = undamped & accept & jnp.isfinite(chord) & (chord < 1.0)
        if has_state:
            # The state has settled at the candidate (done_here) or at x (a rejected step).
            # A rejection that says nothing (a step below the resolution) of a candidate that
            # has converged (chord) with its state settled, from an x whose state has not: the
            # candidate is taken, the two being equal within the cost's rounding (else the loop
            # would go on damped, never undamped again, to the iteration limit; seen on a
            # plane network at XLA's optimisation level 0).
            settled_y = jnp.isfinite(chord) & (chord < 1.0) & (moved_y < threshold)
            tie = unresolved & jnp.isfinite(new_cost) & settled_y & (loop.moved >= threshold)
            accept = accept | tie
            done_here = (done_here | tie) & (moved_y < threshold)
            unresolved = unresolved & ~tie & (loop.moved < threshold)
            chord = jnp.maximum(chord, moved_y / threshold)
        converged = done_here | unresolved

        params = _where(accept, y, state.params)
        # The rows at x are those of the factorisation at x (the loop goes on only after one).
        rows = _where(accept, rows_y, loop.lin.rows)
        Jl = jnp.where(accept, Jl_y, loop.Jl)
        fam_state = _where(accept, state_y, state.state)
        moved = jnp.where(accept, moved_y, loop.moved)
        cost_x = jnp.where(accept, new_cost, state.cost)
        damping = jnp.where(
            first,
            state.damping,
            jnp.where(
                accept,
                jnp.where(
                    state.damping < options.damping_min,
                    0.0,
                    state.damping * options.damping_decrease,
                ),
                jnp.maximum(state.damping * options.damping_increase, options.damping_initial),
            ),
        )
        iteration = state.iteration + jnp.where(first, 0, 1)
        finite = jnp.isfinite(cost_x) & (first | jnp.isfinite(new_cost) | accept)
        stop = (
            converged
            | (iteration >= options.max_iterations)
            | (damping > options.damping_max)
            | ~jnp.isfinite(cost_x)
        )
        # Unless converged, factorise at the estimate: for the next step, or, at a stop
        # without convergence, undamped for the quality.
        used = jnp.where(stop, 0.0, damping)
        final = _where(done_here, apply_update(spec, problem, y, cps, cz), params)
        rows_out, cost_out, state_out, keep = rows, cost_x, fam_state, converged
        if has_state:
            # Converged here: the rows handed to the quality moved to the final estimate
            # x + dx + c to first order, ``e + J c`` (a Gauss-Helmert family's residuals and
            # v^T P v come from them), and the state with them. They are factorised once more
            # (undamped: a stop), so that the cofactors and redundancy numbers are those of the
            # final rows (the normal matrix of a Gauss-Helmert network, linearised at l + v,
            # changes more over the last step).
            keep = converged & ~done_here
            at_final = rows_after(problem, rows, cps, cz, spec.n_scans)
            rows_out = _where(done_here, at_final, rows)
            cost_out = jnp.where(done_here, linearised_cost(problem, final, rows_out), cost_x)
            state_out = _where(
                done_here, state_from_rows(problem, at_final, fam_state)[0], fam_state
            )
        lin, b_p, b_z = lax.cond(
            keep,
            lambda: (
                Linearisation(
                    _residuals_into(rows_out, loop.lin.rows),
                    loop.lin.Hp,
                    loop.lin.Hz,
                    loop.lin.reduced,
                ),
                bp,
                bz,
            ),
            lambda: factorise(params, rows_out, used, state.dependent, Jl),
        )
        dps, dz = solve(spec, lin.reduced, b_p, b_z, lin.Hp, lin.Hz)
        step = jnp.sqrt(jnp.maximum(norm_squared(dps, dz, b_p, b_z), 0.0))
        new_state = SolveState(
            final,
            cost_out,
            damping,
            iteration,
            converged,
            finite,
            jnp.where(undamped, jnp.where(unresolved, 0.0, chord), state.size),
            jnp.where(~converged & (used == 0), lin.reduced.dependent, state.dependent),
            state_out,
        )
        candidate = apply_update(spec, problem, params, dps, dz)
        # The candidate's state: the linear Gauss-Helmert prediction of the step.
        cand_state = predicted_state(problem, rows, fam_state, dps, dz, spec.n_scans)
        return _Loop(
            new_state, Jl, lin, candidate, cand_state, step, moved, jnp.asarray(False), stop
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
        state0,
    )
    rows0 = jax.eval_shape(lambda p: rows_at(spec, problem, p, ap_jac, state0), params0)
    Jl0 = _zeros(jax.eval_shape(lambda e: levelling_jacobian(problem, e), params0.eops))
    strong_zero = jnp.zeros((), jnp.float64)  # as the loop's damping: one trace of factorise
    shapes = jax.eval_shape(factorise, params0, rows0, strong_zero, init.dependent, Jl0)[0]
    zeros = _zeros(shapes)
    start = _Loop(
        init,
        Jl0,
        zeros,
        params0,
        # The start is evaluated with its state settled at fixed unknowns: a step's cost is
        # compared with the start's, and the start's state must be as settled as the
        # candidate's, which is predicted (with v = 0 a start at the solution, a warm start,
        # would have a lower cost than every step, the linearisation at l).
        settled_state(spec, problem, params0) if has_state else state0,
        jnp.asarray(jnp.inf),
        jnp.asarray(0.0),
        jnp.asarray(True),
        jnp.asarray(False),
    )
    out = lax.while_loop(lambda loop: ~loop.done, body, start)
    return out.state, out.lin


def _residuals_into(at, factorised):
    """The factorised rows' Jacobians with the residuals of the rows ``at`` the estimate: the
    quality's cofactors, redundancy numbers and reliability then come from one linearisation
    (so that their identities, e.g. sum r_i = dof, hold to rounding), its residuals from the
    estimate."""
    return tuple(dataclasses.replace(f, e=a.e, raw=a.raw) for a, f in zip(at, factorised))


def _zeros(shapes):
    return jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype), shapes)


def _where(flag, a, b):
    return jax.tree.map(lambda x, y: jnp.where(flag, x, y), a, b)
