"""Implicit differentiation of the converged adjustment (SPEC section 12).

The adjustment runs Levenberg-Marquardt in a ``lax.while_loop`` (:mod:`._solver`), which JAX
cannot differentiate in reverse mode, and whose iterations should not be differentiated anyway:
the estimate depends on the inputs theta (observations, sigmas, levelling, and for simulated
networks the design), not on the path to it. At convergence the whitened normal equations hold,

    F(x, theta) = J^T e(x, theta) = 0,     G^T (x - x_ref) = 0   (inner constraints),

and by the implicit function theorem the tangent ``dx`` of the solution solves the bordered system
``[[H, G], [G^T, 0]] [dx; dk] = -[F_theta dtheta; 0]`` with ``H = dF/dx``. ``H`` is the
Gauss-Newton matrix ``J^T J`` plus the second-order term ``sum_i e_i d2 e_i / dx2``, so:

* the structured, Schur-reduced Gauss-Newton factorisation of the forward solve
  (:func:`._normal.linearise`, :func:`._normal.reduce`: segment sums, 3 x 3 / 4 x 4 blocks,
  rank-revealing Cholesky of the reduced system, the S-transformation onto the inner constraints)
  is the preconditioner, and
* a few steps of iterative refinement with the exact ``H`` (Hessian-vector products, ``jax.jvp``
  of F) remove the Gauss-Newton approximation: ``dx <- dx + N^- (b - H dx)``. The error contracts
  by ``|N^- (H - N)|``, i.e. by the size of the whitened residuals times the curvature of the
  model, about 1e-3 per step on the calibration networks of the tests.

No Jacobian of the whole network is formed. The rule is a ``jax.custom_jvp`` around the compiled
adjustment, so forward mode is the rule itself and reverse mode is its transpose (JAX transposes
the linear tangent computation: the adjoint solves the transposed bordered system with the same
factorisation). Both work under ``jit`` and ``vmap``.

Which objective is differentiated (plane networks). The rigorous Gauss-Helmert iteration
converges to the fixed point ``F(x, theta) = sum_i (w_i / m_i) A_i^T + priors = 0`` with ``w =
g(x, l + v) - B v``, A, B and ``m = B Sigma_l B^T`` at ``(x, l + v)`` and ``v = v(x, theta)``
the residuals settled at x (the projection of l onto the conditions,
:func:`._families.settled_state`); F is the gradient of the Gauss-Helmert objective
``Phi = v^T P v`` (envelope theorem). :func:`normal_equations` evaluates it with v, ``B v`` and
m computed differentiably from (x, theta). The unit normal of a plane is a hard constraint, so F
vanishes only in its tangent space: the tangent solves the bordered system of the Lagrangian,
whose Hessian adds ``-(n . F_n) I`` on each plane's normal (:func:`_constraint_curvature`), and
the structured inverse works in the tangent space of the constraint.

The datum: tangents satisfy ``G^T dx = 0`` with ``G`` the inner-constraint matrix at the solution
(S-transformation); parameters held fixed (a fixed scan, fixed APs) and parameters the network
does not determine (non-estimable APs) have zero tangent. Derivatives w.r.t. the start values
and the solver options are zero by definition.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._jit import jit
from .._linalg import cholesky_solve
from .._model._datum import s_transform_vector
from .._model._planes import plane_condition
from .._pytree import Module
from ._families import Family, Params, PlaneFamily, Problem, Spec, cost, settled_state
from ._normal import linearise, null_space, reduce
from ._quality import minimal_detectable_bias, quality
from ._solver import adjust

#: Iterative-refinement steps with the exact Hessian after the Gauss-Newton solve. Each step
#: costs one Hessian-vector product; the error contracts by ~1e-3 per step on calibration
#: networks (small residuals), so 3 steps reach float64 rounding with a wide margin.
REFINEMENT_STEPS = 3


class FrozenPlaneFamily(PlaneFamily):
    """A plane family whose Gauss-Helmert residuals v, ``B v`` and condition variances ``m`` (one
    per point) are data, evaluated at a given solution: the whitened row ``(g(y, l + v) - B v) /
    sqrt(m)`` has the Gauss-Helmert Jacobian ``A / sqrt(m)`` in y, and stays differentiable in v,
    ``B v`` and m (the engine's family holds them inside a step, which is right there and wrong
    for derivatives w.r.t. theta). ``point`` holds each row's index into them."""

    v: Float[Array, "m 3"]
    Bv: Float[Array, " m"]
    variance: Float[Array, " m"]

    def residual_state(self, state):
        return self.v[self.point]

    def residual(self, spec, P, eop, aps, lv, w, point, inst):
        sl = (spec.scanners, spec.ap_names, spec.ap_slices)
        g = plane_condition(P, eop, aps, lv[0] + lv[1], *sl, inst)
        m = self.variance[point]
        active = jnp.any(w > 0)
        return jnp.where(active, (g - self.Bv[point]) / jnp.sqrt(jnp.where(m > 0, m, 1.0)), 0.0)[
            None
        ]

    def cost_state(self, spec, problem, params, fi, state, ap_jac=None):
        return Family.cost_state(self, spec, problem, params, fi, state, ap_jac)


def frozen_problem(spec: Spec, problem: Problem, params: Params) -> Problem:
    """``problem`` with every plane family's Gauss-Helmert residuals, ``B v`` and condition
    variances evaluated at ``params`` (differentiably, the residuals settled at ``params``);
    point families are returned as they are."""
    settled = settled_state(spec, problem, params)
    fams = []
    for fi, fam in enumerate(problem.families):
        if isinstance(fam, PlaneFamily) and not isinstance(fam, FrozenPlaneFamily):
            t = fam._gauss_helmert(spec, problem, params, fi, settled[fi], jacobian=False)
            fields = {f.name: getattr(fam, f.name) for f in dataclasses.fields(fam)}
            fields["point"] = jnp.arange(t["m"].shape[0], dtype=jnp.int32)
            fam = FrozenPlaneFamily(**fields, v=settled[fi], Bv=t["g"] - t["w"], variance=t["m"])
        fams.append(fam)
    return dataclasses.replace(problem, families=tuple(fams))


def _constraint_curvature(problem: Problem, params: Params, F: Params, dx: Params) -> Params:
    """The constraints' part of the Lagrangian's Hessian times ``dx``: for the unit normal of
    each plane, ``c = n . n - 1`` with multiplier ``lambda = -(n . F_n) / 2`` (from ``F_n + 2
    lambda n = 0`` at the solution), ``2 lambda dn = -(n . F_n) dn``."""
    out = []
    for fam, P, Fp, dp in zip(problem.families, params.prims, F.prims, dx.prims):
        if isinstance(fam, PlaneFamily):
            lam2 = -jnp.sum(P[:, :3] * Fp[:, :3], axis=1, keepdims=True)
            out.append(jnp.concatenate([lam2 * dp[:, :3], jnp.zeros_like(dp[:, 3:])], axis=1))
        else:
            out.append(jnp.zeros_like(dp))
    return Params(tuple(out), jnp.zeros_like(dx.eops), jnp.zeros_like(dx.aps))


def normal_equations(spec: Spec, problem: Problem, params: Params) -> Params:
    """``F(x, theta) = J^T e``: the gradient of ``v^T P v / 2`` with the plane variances held at
    ``x`` (the fixed point of the adjustment, see the module docstring), as a ``Params`` tree."""
    fixed = frozen_problem(spec, problem, params)
    return jax.grad(lambda y: 0.5 * cost(spec, fixed, y))(params)


@dataclasses.dataclass(frozen=True)
class GaussNewtonInverse:
    """``N^-`` applied to a right-hand side, from the engine's structured factorisation at x:
    Schur reduction, rank-revealing Cholesky of the reduced system, back substitution and the
    S-transformation onto the inner constraints (exactly the forward solve's step)."""

    spec: Spec
    red: object
    Hp: tuple
    Hz: Array

    @classmethod
    def at(cls, spec: Spec, problem: Problem, params: Params, rank_tolerance):
        params = jax.lax.stop_gradient(params)
        blocks = linearise(spec, problem, params, state=settled_state(spec, problem, params))
        Hp, Hz = null_space(spec, problem.families, params)
        red = reduce(spec, problem, blocks, Hz, jnp.asarray(0.0), rank_tolerance)
        return cls(spec, red, Hp, Hz)

    def __call__(self, r: Params) -> Params:
        spec, red = self.spec, self.red
        ns = spec.n_scans
        c = jnp.concatenate([r.eops.reshape(-1), r.aps])
        for Y, rp in zip(red.Y, r.prims):
            c = c - jnp.einsum("npr,np->r", Y, rp)
        c = jnp.where(red.dependent, 0.0, c * red.scale)
        dz = jnp.where(red.dependent, 0.0, cholesky_solve(red.L, c) * red.scale)
        dps = tuple(
            jnp.einsum("npq,nq->np", Ni, rp) - jnp.einsum("npr,r->np", Y, dz)
            for Ni, Y, rp in zip(red.Npp_inv, red.Y, r.prims)
        )
        if spec.inner and self.Hz.shape[1]:
            dps, dz = s_transform_vector(self.Hp, self.Hz, dps, dz)
        return Params(dps, dz[: 6 * ns].reshape(ns, 6), dz[6 * ns :])


def _tree_add(a, b, scale=1.0):
    return jax.tree.map(lambda x, y: x + scale * y, a, b)


def solution_tangent(spec, problem, params, problem_dot, rank_tolerance, steps=REFINEMENT_STEPS):
    """``dx = -H^-1 F_theta dtheta`` at the solution ``params`` (module docstring): the
    Gauss-Newton solve as preconditioner and ``steps`` refinement steps with the exact H."""
    x = jax.lax.stop_gradient(params)
    _, F_dot = jax.jvp(lambda pb: normal_equations(spec, pb, x), (problem,), (problem_dot,))
    b = jax.tree.map(jnp.negative, F_dot)
    inverse = GaussNewtonInverse.at(spec, problem, x, rank_tolerance)
    F = normal_equations(spec, problem, x)
    hvp = lambda v: _tree_add(
        jax.jvp(lambda y: normal_equations(spec, problem, y), (x,), (v,))[1],
        _constraint_curvature(problem, x, F, v),
    )
    # A rolled loop (a linear scan, so reverse mode transposes it): one copy of the
    # Hessian-vector product in the compiled code, whatever ``steps`` is.
    refine = lambda _, dx: _tree_add(dx, inverse(_tree_add(b, hvp(dx), -1.0)))
    return jax.lax.fori_loop(0, steps, refine, inverse(b))


def _zero_tangent(x):
    x = jnp.asarray(x)
    if jnp.issubdtype(x.dtype, jnp.inexact):
        return jnp.zeros_like(x)
    return np.zeros(x.shape, dtype=jax.dtypes.float0)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 4))
def solve_implicit(spec: Spec, problem: Problem, params0: Params, options, steps=REFINEMENT_STEPS):
    """The engine's adjustment (:func:`._solver.adjust`) with derivatives by the implicit
    function theorem: the returned state's ``params`` has the tangent of the module docstring
    w.r.t. every float array of ``problem`` (observations, weights, levelling, control); every
    other field of the state has zero tangent. Pure, jittable, vmappable; forward and reverse
    mode."""
    return adjust(spec, problem, params0, options)


@solve_implicit.defjvp
def _solve_implicit_jvp(spec, steps, primals, tangents):
    problem, params0, options = primals
    problem_dot = tangents[0]
    state = adjust(spec, problem, params0, options)
    dx = solution_tangent(spec, problem, state.params, problem_dot, options.rank_tolerance, steps)
    state_dot = jax.tree.map(_zero_tangent, state)
    return state, dataclasses.replace(state_dot, params=dx)


# --- The differentiable calibration: inputs theta in network row order -> estimates -----------


class NetworkInputs(Module):
    """The float inputs theta of one analysed network, in the network's row order (SI units).

    ``observations``/``sigmas`` (n, 3) of the target rows (range [m], hz, el [rad]; sigmas with
    the incidence applied, ``inf`` = removed), ``plane_observations``/``plane_sigmas`` (m, 3) of
    the plane rows, ``levelling``/``levelling_sigmas`` (s, 2) [rad] (``inf`` = not levelled).
    """

    observations: Float[Array, "n 3"]
    sigmas: Float[Array, "n 3"]
    plane_observations: Float[Array, "m 3"]
    plane_sigmas: Float[Array, "m 3"]
    levelling: Float[Array, "s 2"]
    levelling_sigmas: Float[Array, "s 2"]


def network_inputs(adjustment) -> NetworkInputs:
    """The inputs of an analysed adjustment's network (:func:`tlsjax.analyze`)."""
    net = adjustment.network
    f = lambda a: jnp.asarray(np.asarray(a, dtype=np.float64))
    return NetworkInputs(
        f(net.observations),
        f(net.sigmas),
        f(net.plane_observations),
        f(net.plane_sigmas),
        f(net.levelling),
        f(net.levelling_sigma),
    )


def _weight(sigma):
    # 1/sigma, 0 for a removed observation (sigma inf or 0), with a finite derivative there.
    ok = jnp.isfinite(sigma) & (sigma > 0)
    return jnp.where(ok, 1.0 / jnp.where(ok, sigma, 1.0), 0.0)


def problem_from_inputs(problem: Problem, rows: tuple, plane_family, inputs: NetworkInputs):
    """The plan's problem with the observations, weights and levelling of ``inputs``
    (``rows``: per family, the network rows it holds, as the plan's ``family_rows``)."""
    fams = []
    for fi, (fam, r) in enumerate(zip(problem.families, rows)):
        obs, sig = (
            (inputs.plane_observations, inputs.plane_sigmas)
            if fi == plane_family
            else (inputs.observations, inputs.sigmas)
        )
        fams.append(dataclasses.replace(fam, obs=obs[r], weight=_weight(sig[r])))
    return dataclasses.replace(
        problem,
        families=tuple(fams),
        levelling=inputs.levelling,
        levelling_weight=_weight(inputs.levelling_sigmas),
    )


class Estimates(Module):
    """What the differentiable adjustment returns; every float field is differentiable w.r.t.
    the :class:`NetworkInputs` (SPEC section 12). SI units; a posteriori where it says so.

    ``params``: the solution (per family primitives, ``eops`` (s, 6), ``aps``) in the datum;
    ``aps`` (a,); ``sigma0``; ``dof``; ``ap_covariance`` (a, a) and ``ap_sigmas`` (a,) a
    posteriori; ``ap_correlation`` (a, a); ``covariance`` (6s + a, 6s + a): a posteriori
    covariance of the scan poses and APs in the datum (inner constraints on the primitives);
    ``residuals``, ``redundancy``, ``mdb`` (n, 3) of the target rows and ``plane_residuals``,
    ``plane_redundancy``, ``plane_mdb`` (m, 3) of the plane rows, in network row order (MDB:
    ``delta0 sigma_i / sqrt(r_i)`` with the a priori sigma and delta0 = 4.13,
    :func:`._quality.minimal_detectable_bias`; inf where an observation is not controlled,
    e.g. removed); ``ap_influence``
    (n, 3, a): external reliability, the change of each AP caused by a one-sigma error of each
    observation, in a priori AP sigmas (:mod:`._quality`); ``estimable`` (a,): False for APs held
    fixed or not determined (their value, sigma and derivatives are 0).
    """

    params: Params
    aps: Float[Array, " a"]
    sigma0: Float[Array, ""]
    dof: Float[Array, ""]
    ap_covariance: Float[Array, "a a"]
    ap_sigmas: Float[Array, " a"]
    ap_correlation: Float[Array, "a a"]
    covariance: Float[Array, "r r"]
    residuals: Float[Array, "n 3"]
    redundancy: Float[Array, "n 3"]
    mdb: Float[Array, "n 3"]
    ap_influence: Float[Array, "n 3 a"]
    plane_residuals: Float[Array, "m 3"]
    plane_redundancy: Float[Array, "m 3"]
    plane_mdb: Float[Array, "m 3"]
    estimable: Array
    converged: Array
    iterations: Array


def safe_sqrt(x):
    """``sqrt(max(x, 0))`` with a zero (not infinite) derivative at 0."""
    ok = x > 0
    return jnp.where(ok, jnp.sqrt(jnp.where(ok, x, 1.0)), 0.0)


def _scatter_rows(n, rows, parts, shape_tail):
    out = jnp.zeros((n,) + shape_tail)
    for r, v in zip(rows, parts):
        out = out.at[r].set(v)
    return out


def estimates_from_solution(spec, problem, state, rank_tolerance, rows, plane_family, sizes):
    """Quality at the solution (:func:`._quality.quality` on the problem with the plane
    variances as functions of the solution) and the :class:`Estimates`."""
    x = state.params
    q = quality(spec, frozen_problem(spec, problem, x), x, rank_tolerance)
    ns, na = spec.n_scans, spec.n_aps
    s0sq = q.vtpv / q.dof
    ap = slice(6 * ns, 6 * ns + na)
    estimable = ~q.dependent[ap]
    cov = q.Qzz * s0sq
    Caa = cov[ap, ap]
    sig = safe_sqrt(jnp.diagonal(Caa))
    corr = Caa / jnp.where(sig[:, None] * sig[None, :] > 0, sig[:, None] * sig[None, :], 1.0)
    point_fams = [fi for fi in range(len(problem.families)) if fi != plane_family]
    n, m = sizes

    def mdb(fi):
        w = problem.families[fi].weight
        sigma = jnp.where(w > 0, 1.0 / jnp.where(w > 0, w, 1.0), 0.0)
        return minimal_detectable_bias(sigma, q.redundancy[fi])

    pr = [rows[fi] for fi in point_fams]
    plane = [plane_family] if plane_family is not None else []
    pl_rows = [rows[fi] for fi in plane]
    return Estimates(
        params=x,
        aps=jnp.where(estimable, x.aps, 0.0),
        sigma0=safe_sqrt(s0sq),
        dof=q.dof,
        ap_covariance=Caa,
        ap_sigmas=sig,
        ap_correlation=corr,
        covariance=cov,
        residuals=_scatter_rows(n, pr, [q.residuals[fi] for fi in point_fams], (3,)),
        redundancy=_scatter_rows(n, pr, [q.redundancy[fi] for fi in point_fams], (3,)),
        mdb=_scatter_rows(n, pr, [mdb(fi) for fi in point_fams], (3,)),
        ap_influence=_scatter_rows(n, pr, [q.ap_influence[fi] for fi in point_fams], (3, na)),
        plane_residuals=_scatter_rows(m, pl_rows, [q.residuals[fi] for fi in plane], (3,)),
        plane_redundancy=_scatter_rows(m, pl_rows, [q.redundancy[fi] for fi in plane], (3,)),
        plane_mdb=_scatter_rows(m, pl_rows, [mdb(fi) for fi in plane], (3,)),
        estimable=estimable,
        converged=state.converged,
        iterations=state.iteration,
    )


@functools.partial(jit, static_argnums=(0, 1, 2, 3))
def _estimates(spec, plane_family, sizes, steps, problem, rows, inputs, params0, options):
    problem = problem_from_inputs(problem, rows, plane_family, inputs)
    state = solve_implicit(spec, problem, params0, options, steps)
    return estimates_from_solution(
        spec, problem, state, options.rank_tolerance, rows, plane_family, sizes
    )


def differentiable_adjustment(adjustment, *, refinement_steps: int = REFINEMENT_STEPS):
    """The adjustment of an analysed network as a pure function ``f(inputs[, params0]) ->
    Estimates`` of its :class:`NetworkInputs` (SPEC section 12): jit-compiled once per network
    shape and model, differentiable in forward (``jax.jvp``, ``jax.jacfwd``) and reverse
    (``jax.grad``, ``jax.vjp``) mode by the implicit function theorem, vmappable.

    ``params0``: the start values (default: the adjustment's approximate values).

    Example::

        adj = tj.analyze(network, model)
        f = tj.differentiable_adjustment(adj)
        theta = tj.network_inputs(adj)
        d_sigma_b6 = jax.grad(lambda t: f(t).ap_sigmas[1])(theta)  # a NetworkInputs of derivatives
    """
    plan = adjustment.plan
    rows = tuple(jnp.asarray(r, dtype=jnp.int32) for r in plan.family_rows)
    net = adjustment.network
    sizes = (net.observations.shape[0], net.plane_observations.shape[0])
    options = adjustment.options.arrays()
    # Approximate values now, on the host: computed lazily inside a trace they would be cached
    # as tracers.
    initial = adjustment.initial

    def f(inputs: NetworkInputs, params0: Params | None = None) -> Estimates:
        p0 = initial if params0 is None else params0
        return _estimates(
            plan.spec,
            plan.plane_family,
            sizes,
            refinement_steps,
            plan.problem,
            rows,
            inputs,
            p0,
            options,
        )

    return f
