"""Many adjustments of one design on one shared factorisation: the chord method.

Monte Carlo realisations, compatibility simulations and design studies adjust the same design
with different noise. Its normal matrix ``N0`` at the truth, with the AP corrections applied to
the observations it is linearised at (each realisation's normal matrix differs from it by about
the noise-to-signal ratio, 1e-4), is factorised once; each realisation then iterates

    x <- x + N0^- b(x),     b(x) = -J(x)^T P e(x)

with its own gradient only: a simplified Gauss-Newton (chord) method (Ortega & Rheinboldt 1970,
section 7.1; Kelley 1995, section 5.4). Its fixed point is the realisation's least-squares
estimate ``b(x) = 0``, the same as the full Gauss-Newton loop of :mod:`._solver`; it converges
linearly with the rate ``|N0^-1 (N(x) - N0)|`` (measured: about 2e-3 per iteration on the Chow
room), so from the truth three to four gradients reach 1e-10 sigma. Each iteration is one
evaluation of the residuals and their vector-Jacobian product; the solve is a product with the
explicit inverse of the reduced matrix, which a batch of realisations shares as one matrix
product (a batched triangular solve with a shared factor is slow on the CPU, see
:func:`._linalg.forward_substitution`).

The covariance reported for each realisation is the design's ``s0^2 Q0`` (``Q0 = N0^-``, scaled
by the realisation's own ``s0^2``): what the scatter of the estimates is compared against. It
differs from the realisation's own by the same 1e-4.

Convergence: the step ``c = N0^- b`` is measured in the metric of ``N0``, ``sqrt(c^T b)`` a
priori sigmas (a bound on every component in units of its standard deviation, as in
:mod:`._solver`). The loop stops when the error it predicts after the step, the step times the
contraction measured from the last two steps, is below ``CHORD_ACCURACY`` times the tolerance
(``tolerance`` a posteriori sigmas): the accuracy a full Gauss-Newton loop stops at, whose own
contraction is of that size. A realisation whose contraction does not fall below
``CHORD_MAX_RATE`` has left the neighbourhood where the chord converges; it ends with the result
code of a failed convergence, which the caller answers with the full loop.

Gauss-Helmert families (planes) carry their residuals v as in :mod:`._solver`: the rows are
evaluated at ``l + v``, the next v is the linear Gauss-Helmert prediction of the chord step, and
the loop stops only when v has settled as well (its update from the rows differs from the v they
were evaluated with by less than the tolerance). The design's factorisation is linearised at the
noise-free observations, where v = 0.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, Bool, Float, Int

from .._linalg import cholesky_inverse, small_spd_solve
from .._model._datum import inner_gram, s_transform_vector
from .._pytree import Module
from ._families import (
    Params,
    Problem,
    Spec,
    cost,
    count_observations,
    initial_state,
    predicted_state,
    state_from_rows,
)
from ._normal import (
    ap_jacobians,
    apply_update,
    gradient,
    linearise,
    linearised_cost,
    null_space,
    reduce,
    reduced_rhs,
    rows_at,
)
from ._solver import ROUNDING_FACTOR, rounding_sigma

#: The chord loop stops when its predicted remaining error is below this share of the
#: tolerance (module docstring).
CHORD_ACCURACY = 1e-3
#: A contraction above this rate means the chord does not converge for this realisation.
CHORD_MAX_RATE = 0.5


class DesignFactorisation(Module):
    """The factorisation of one design's normal matrix, shared by its realisations: the Schur
    blocks of the primitives (``Npp^-1``, ``Y = Npp^-1 Npz``), the explicit inverse of the
    scaled reduced matrix, the datum's null space, the AP cofactor block and the dependent
    (non-estimable) columns of the rank test, and the degrees of freedom."""

    Npp_inv: tuple
    Y: tuple
    scale: Float[Array, " r"]
    Kinv: Float[Array, "r r"]
    dependent: Bool[Array, " r"]
    Hp: tuple
    Hz: Array
    Qaa: Float[Array, "a a"]
    dof: Float[Array, ""]
    GtH_inv: Float[Array, "d d"]  # (G^T H)^-1 of the inner constraints (d = 0: none)


def design_factorisation(spec: Spec, problem: Problem, params: Params, rank_tolerance):
    """:class:`DesignFactorisation` of ``problem`` (on its grid) at ``params``: one undamped
    linearisation, reduction and rank-revealing factorisation."""
    blocks = linearise(spec, problem, params, ap_jacobians(spec, problem, params))
    Hp, Hz = null_space(spec, problem.families, params)
    red = reduce(spec, problem, blocks, Hz, jnp.asarray(0.0), rank_tolerance)
    dep = red.dependent
    Kinv = jnp.where(dep[:, None] | dep[None, :], 0.0, cholesky_inverse(red.L))
    a0 = 6 * spec.n_scans
    s = red.scale[a0:]
    Qaa = Kinv[a0:, a0:] * s[:, None] * s[None, :]
    n_unknowns = jnp.sum(~dep) + sum(P.size for P in params.prims)
    dof = count_observations(problem, params) - n_unknowns + Hz.shape[1]
    d = Hz.shape[1] if spec.inner else 0
    GtH = inner_gram(Hp) if d else jnp.zeros((0, 0))
    GtH_inv = small_spd_solve(GtH, jnp.eye(d, dtype=GtH.dtype)) if d else GtH
    return DesignFactorisation(
        red.Npp_inv,
        red.Y,
        red.scale,
        Kinv,
        dep,
        Hp,
        Hz,
        Qaa,
        jnp.asarray(dof, jnp.float64),
        GtH_inv,
    )


def shared_solve(spec: Spec, fact: DesignFactorisation, bp: tuple, bz):
    """``N0^- b`` (primitives per family, reduced unknowns) with the shared factorisation."""
    c = reduced_rhs(bp, bz, fact.Y)
    dz = fact.scale * (fact.Kinv @ (c * fact.scale))
    dps = tuple(
        jnp.einsum("npq,nq->np", Ni, b) - jnp.einsum("npr,r->np", Y, dz)
        for Ni, Y, b in zip(fact.Npp_inv, fact.Y, bp)
    )
    if spec.inner and fact.Hz.shape[1]:
        dps, dz = s_transform_vector(fact.Hp, fact.Hz, dps, dz, fact.GtH_inv)
    return dps, dz


class ChordState(Module):
    params: Params
    cost: Float[Array, ""]  # v^T P v at params (the quadratic model after the last step)
    iteration: Int[Array, ""]
    converged: Bool[Array, ""]
    failed: Bool[Array, ""]
    size: Float[Array, ""]  # last step in units of the tolerance
    state: tuple = ()  # the families' states the next rows are evaluated with (:mod:`._solver`)

    @property
    def finite(self):
        return jnp.isfinite(self.cost)


def _gradient(spec, problem, params, ap_jac, state):
    """(v^T P v, b = -J^T P e) at params as (cost, per-family b_p, b_z), from the engine's rows
    (:func:`._normal.rows_at`, :func:`._normal.gradient`) evaluated with the families' states,
    the primitives' part tangent to their constraints; and the rows (None without states).

    Without Gauss-Helmert states (targets) the rows are not needed: b is the gradient of
    ``-v^T P v / 2`` by reverse mode, one residual evaluation and its vector-Jacobian product,
    instead of the Jacobian blocks of every observation contracted afterwards (measured on the
    Chow room's Monte Carlo: a third of a chord iteration)."""
    if all(st is None for st in state):
        half, g = jax.value_and_grad(lambda p: 0.5 * cost(spec, problem, p, None, ap_jac))(params)
        bp = tuple(-x for x in g.prims)
        bp = tuple(f.tangent_gradient(P, b) for f, P, b in zip(problem.families, params.prims, bp))
        return 2.0 * half, bp, -jnp.concatenate([g.eops.reshape(-1), g.aps]), None
    rows = rows_at(spec, problem, params, ap_jac, state)
    bp, bz = gradient(spec, problem, params, rows)
    bp = tuple(f.tangent_gradient(P, b) for f, P, b in zip(problem.families, params.prims, bp))
    return linearised_cost(problem, params, rows), bp, bz, rows


def chord_adjust(
    spec: Spec, problem: Problem, params0: Params, fact: DesignFactorisation, options
) -> ChordState:
    """The chord iteration of one realisation (``problem`` on its grid) from ``params0`` with
    the design's factorisation (module docstring). Pure; vmapped over realisations."""
    ap_jac = ap_jacobians(spec, problem, params0)
    floor = ROUNDING_FACTOR * rounding_sigma(problem)
    state0 = initial_state(problem)
    has_state = any(st is not None for st in state0)

    def body(state: ChordState):
        value, bp, bz, rows = _gradient(spec, problem, state.params, ap_jac, state.state)
        dps, dz = shared_solve(spec, fact, bp, bz)
        norm2 = jnp.dot(dz, bz) + sum(jnp.sum(d * b) for d, b in zip(dps, bp))
        s0 = jnp.sqrt(jnp.maximum(value, 0.0) / fact.dof)
        threshold = jnp.maximum(options.tolerance * s0, floor)
        size = jnp.sqrt(jnp.maximum(norm2, 0.0)) / threshold
        rate = jnp.where(state.iteration > 0, size / state.size, 1.0)
        ok = jnp.isfinite(size)
        converged = ok & (size < 1.0) & (rate * size < CHORD_ACCURACY)
        fam_state = state.state
        if has_state:
            updated, moved = state_from_rows(problem, rows, state.state)
            converged = converged & (moved < threshold)
            fam_state = predicted_state(problem, rows, updated, dps, dz, spec.n_scans)
        failed = ~ok | ((state.iteration > 0) & (rate > CHORD_MAX_RATE) & ~converged)
        return ChordState(
            apply_update(spec, problem, state.params, dps, dz),
            value - norm2,
            state.iteration + 1,
            converged,
            failed,
            size,
            fam_state,
        )

    def more(state: ChordState):
        return ~state.converged & ~state.failed & (state.iteration < options.max_iterations)

    init = ChordState(
        params0,
        jnp.asarray(jnp.inf),
        jnp.asarray(0),
        jnp.asarray(False),
        jnp.asarray(False),
        jnp.asarray(jnp.inf),
        state0,
    )
    return lax.while_loop(more, body, init)
