"""Normal equations of the structured adjustment: assembly by segment sums, Schur elimination
of the primitives, factorisation of the reduced system, the update and its size.

With whitened residuals ``e`` (weight matrix = I) and Jacobian blocks ``J_p, J_s, J_a`` of each
observation from ``vmap(jacfwd)``:

    N_pp[i] = sum J_p^T J_p          (segment sum over the observations of primitive i)
    N_pz[i] = [sum J_p^T J_s per scan | sum J_p^T J_a]
    N_zz    = blockdiag_s(sum J_s^T J_s) + [J_s^T J_a], [J_a^T J_a]

The primitives are eliminated by Schur complement, ``K = N_zz - sum_i N_zp N_pp^-1 N_pz``, the
reduced system (r = 6 scans + n APs) is scaled, the rigid-motion datum defect is closed by
``+ Q Q^T`` with Q an orthonormal basis of the null space, and it is factorised by the
rank-revealing Cholesky of :mod:`._linalg`. No Jacobian of the whole network is ever formed.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, Bool, Float

from .._linalg import (
    bmm,
    cholesky_solve,
    constrained_spd_inverse,
    estimable_cholesky_damped,
    matvec_t,
    outer,
)
from .._model._datum import move_eop, null_space_columns, s_transform_vector
from .._pytree import Module
from ._families import (
    Params,
    Problem,
    Spec,
    ap_prior_residual,
    ap_prior_weight,
    levelling_jacobian,
    levelling_residual,
    pseudo_cost,
)


class Blocks(Module):
    """Normal-equation blocks of one linearisation; the right-hand sides are ``-J^T e``."""

    Npp: tuple  # per family (n, p, p)
    Npz: tuple  # per family (n, p, r)
    bp: tuple  # per family (n, p)
    Nzz: Float[Array, "r r"]
    bz: Float[Array, " r"]
    # Diagonal of the observations' part of N_pp (priors left out): the Levenberg-Marquardt
    # scaling, so that a heavy pseudo-observation (a control point) does not freeze the
    # directions it does not constrain.
    Dp: tuple = ()
    # Per family the null-space basis of its hard constraints (``Family.constraint_basis``:
    # (n, p, q) for planes, None for points).
    Ep: tuple = ()


def ap_jacobians(spec: Spec, problem: Problem, params: Params) -> tuple:
    """The constant AP blocks per family (:meth:`Family.ap_block`; None where the block changes
    with the estimate). For points Delta is linear in the AP coefficients with its bases
    evaluated at the observations, and F does not depend on the APs (SPEC section 2): taken
    once, the iterations differentiate only the geometry."""
    return tuple(fam.ap_block(spec, problem, params, fi) for fi, fam in enumerate(problem.families))


class Rows(Module):
    """One family's linearisation per observation: whitened residual rows ``e`` (m, k),
    Jacobian blocks ``Jp`` (m, k, p), ``Js`` (m, k, 6), ``Ja`` (m, k, a), ``raw``, the
    residual the quality pass reports (see :meth:`Family.linear_rows`), and for a
    Gauss-Helmert family ``B = dg/dl`` (m, 3), which sets its weights (None otherwise)."""

    e: Array
    Jp: Array
    Js: Array
    Ja: Array
    raw: Array
    B: Array | None = None


def _slot_rows(J, cells):
    """Slots times rows per grid cell of a block ``J`` (m, k, q) (written out: a reshape with
    -1 cannot infer it when q = 0, a model without APs)."""
    return J.shape[0] * J.shape[1] // cells


#: A grid cell with at most this many rows per scan (slots times rows: 3 for a target) has its
#: sums written out as sums of products of input slices (one fused loop per block); larger
#: cells (plane points) are contracted as einsums.
SMALL_CELL = 8


def _cell_terms(A, B, over_scans: bool):
    """``sum_rows A^T B`` per cell (n, s, ., .), or per primitive over its scans too (n, ., .),
    written out as products of slices of the inputs (A, B (n, s, rows, .)): XLA fuses them into
    one loop without materialising the products."""
    rk = A.shape[2]
    cell = sum(A[:, :, i, :, None] * B[:, :, i, None, :] for i in range(rk))
    # Over the scans one reduction, not written out: the program's size (and its compile time)
    # then does not grow with the number of scans.
    return jnp.sum(cell, axis=1) if over_scans else cell


def _flat_rows(J):
    """``J`` (..., k) as (rows, k); also with k = 0 (no APs), where reshape(-1, 0) is undefined."""
    return J.reshape(int(np.prod(J.shape[:-1])), J.shape[-1])


def _sums_on_grid(shape, Jp, Js, Ja):
    """Normal-matrix sums of a family on its grid (n primitives, s scans, c slots): reshapes
    and sums over axes. Returns (N_pp, N_ps pairs (n, s, p, 6), N_pa, N_ss, N_sa, N_aa)."""
    n, ns, c = shape
    g = lambda J: J.reshape(n, ns, _slot_rows(J, n * ns), J.shape[-1])  # slots, rows: one axis
    Jp, Js, Ja = g(Jp), g(Js), g(Ja)
    if Jp.shape[2] <= SMALL_CELL:
        # Per cell and per primitive the few rows' products written out; over the primitives
        # (many) a reduction. Measured on the Chow room: 175 against 290 us per assembly (the
        # einsums were batched dots on transposed copies of the rows).
        return (
            _cell_terms(Jp, Jp, True),
            _cell_terms(Jp, Js, False),
            _cell_terms(Jp, Ja, True),
            jnp.sum(_cell_terms(Js, Js, False), axis=0),
            jnp.sum(_cell_terms(Js, Ja, False), axis=0),
            # The AP block, a sum over every row: one matrix product.
            _flat_rows(Ja).T @ _flat_rows(Ja),
        )
    # Contractions as einsums (dot_general): measured 2x faster than broadcast-multiply-sum
    # for these shapes on the CPU.
    es = jnp.einsum
    return (
        es("nskp,nskq->npq", Jp, Jp),
        es("nskp,nskq->nspq", Jp, Js),
        es("nskp,nska->npa", Jp, Ja),
        es("nskp,nskq->spq", Js, Js),
        es("nskp,nska->spa", Js, Ja),
        es("nskp,nskq->pq", Ja, Ja),
    )


def _sums_by_segment(fam, ns, Jp, Js, Ja):
    """The same sums for any index plan: segment sums over primitives, pairs and scans."""
    seg = jax.ops.segment_sum
    n, nq = fam.n, fam.pair_prim.shape[0]
    nps_pairs = seg(outer(Jp, Js), fam.pair, nq)  # (q, p, 6)
    nps = jnp.zeros((n, ns, fam.p, 6)).at[fam.pair_prim, fam.pair_scan].set(nps_pairs)
    return (
        seg(outer(Jp, Jp), fam.prim, n),
        nps,
        seg(outer(Jp, Ja), fam.prim, n),
        seg(outer(Js, Js), fam.scan, ns),
        seg(outer(Js, Ja), fam.scan, ns),
        jnp.sum(outer(Ja, Ja), axis=0),
    )


def _gradient_sums(grid, fam, ns, r: Rows):
    """``-J^T e`` of a family's rows: per primitive (n, p), per scan (s, 6) and APs (a,)."""
    if grid:
        n, ns_, c = grid
        g = lambda J: J.reshape(n, ns_, _slot_rows(J, n * ns_), J.shape[-1])
        e = r.e.reshape(n, ns_, -1)[..., None]
        if e.shape[2] <= SMALL_CELL:
            # As :func:`_sums_on_grid`: products of input slices, reductions over primitives.
            Jp, Js, Ja = g(r.Jp), g(r.Js), g(r.Ja)
            per_prim = lambda J: jnp.sum(
                sum(J[:, :, i] * e[:, :, i] for i in range(e.shape[2])), axis=1
            )
            per_cell = sum(Js[:, :, i] * e[:, :, i] for i in range(e.shape[2]))
            return -per_prim(Jp), -jnp.sum(per_cell, axis=0), -jnp.sum(per_prim(Ja), axis=0)
        e = e[..., 0]
        es = jnp.einsum
        return (
            -es("nskp,nsk->np", g(r.Jp), e),
            -es("nskp,nsk->sp", g(r.Js), e),
            -es("nskp,nsk->p", g(r.Ja), e),
        )
    seg = jax.ops.segment_sum
    return (
        -seg(matvec_t(r.Jp, r.e), fam.prim, fam.n),
        -seg(matvec_t(r.Js, r.e), fam.scan, ns),
        -jnp.sum(matvec_t(r.Ja, r.e), axis=0),
    )


def rows_at(
    spec: Spec, problem: Problem, params: Params, ap_jac: tuple | None = None, state=None
) -> tuple:
    """Per family the residual rows and Jacobian blocks at ``params`` (:class:`Rows`), with the
    families' iteration states ``state`` (the Gauss-Helmert residuals v at which a plane family
    is linearised, ``l + v``; None: their initial states)."""
    return tuple(
        Rows(
            *fam.linear_rows(
                spec,
                problem,
                params,
                fi,
                None if ap_jac is None else ap_jac[fi],
                None if state is None else state[fi],
            )
        )
        for fi, fam in enumerate(problem.families)
    )


def _grids(problem: Problem):
    return problem.grids or (None,) * len(problem.families)


def gradient(spec: Spec, problem: Problem, params: Params, rows: tuple, Jl=None):
    """The right-hand sides ``b = -J^T e`` of the normal equations at ``params`` from its rows
    (observations, priors on the primitives, orientation readings, AP priors): (per family (n,
    p), (r,)). ``Jl``: the orientation readings' :func:`levelling_jacobian` at ``params``, if
    already taken."""
    ns = spec.n_scans
    bs = jnp.zeros((ns, 6))
    ba = jnp.zeros((spec.n_aps,))
    bp = []
    for fam, grid, r, P in zip(problem.families, _grids(problem), rows, params.prims):
        gp, gs, ga = _gradient_sums(grid, fam, ns, r)
        bp.append(gp - matvec_t(fam.prior_jacobian(P), fam.prior_residuals(P)))
        bs, ba = bs + gs, ba + ga
    # Orientation pseudo-observations (tilt readings, observed kappa) act on the scan's
    # rotation; AP priors on the APs (linear, weight w).
    Jl = levelling_jacobian(problem, params.eops) if Jl is None else Jl
    bs = bs - matvec_t(Jl, levelling_residual(problem, params.eops))
    ba = ba - ap_prior_weight(problem, spec.n_aps) * ap_prior_residual(problem, params.aps)
    return tuple(bp), jnp.concatenate([bs.reshape(-1), ba])


def assemble(spec: Spec, problem: Problem, params: Params, rows: tuple, Jl=None) -> Blocks:
    """The normal-equation :class:`Blocks` from the rows at ``params``: on each family's grid
    when it has one (:class:`._families.Layout`), by segment sums otherwise; a family's hard
    constraints (:meth:`._families.Family.constraint_basis`) ride along for :func:`reduce`.
    ``Jl``: the orientation readings' :func:`levelling_jacobian` at ``params``, if already
    taken."""
    ns, na = spec.n_scans, spec.n_aps
    Nss = jnp.zeros((ns, 6, 6))
    Nsa = jnp.zeros((ns, 6, na))
    Naa = jnp.zeros((na, na))
    Npp, Npz, Dp, Ep = [], [], [], []
    for fam, grid, r, P in zip(problem.families, _grids(problem), rows, params.prims):
        J = (r.Jp, r.Js, r.Ja)
        sums = _sums_on_grid(grid, *J) if grid else _sums_by_segment(fam, ns, *J)
        npp, nps, npa, nss, nsa, naa = sums
        Ep.append(fam.constraint_basis(P))
        # Priors on primitives (control points, scale-bar lengths).
        Jpr = fam.prior_jacobian(P)
        Dp.append(jnp.diagonal(npp, axis1=-2, axis2=-1))
        Npp.append(npp + outer(Jpr, Jpr))
        nps = jnp.transpose(nps, (0, 2, 1, 3)).reshape(fam.n, fam.p, 6 * ns)
        Npz.append(jnp.concatenate([nps, npa], axis=-1))
        Nss, Nsa, Naa = Nss + nss, Nsa + nsa, Naa + naa
    # Orientation pseudo-observations (tilt readings, observed kappa) act on the scan's
    # rotation; AP priors on the APs (linear, weight w: w^2 on the diagonal).
    Jl = levelling_jacobian(problem, params.eops) if Jl is None else Jl
    Nss = Nss + outer(Jl, Jl)
    Naa = Naa + jnp.diag(ap_prior_weight(problem, na) ** 2)
    diag = np.eye(ns, dtype=bool)[:, None, :, None]
    Nss_full = jnp.where(diag, Nss[:, :, None, :], 0.0).reshape(6 * ns, 6 * ns)
    Nsa_full = Nsa.reshape(6 * ns, na)
    Nzz = jnp.block([[Nss_full, Nsa_full], [Nsa_full.T, Naa]])
    bp, bz = gradient(spec, problem, params, rows, Jl)
    return Blocks(tuple(Npp), tuple(Npz), bp, Nzz, bz, tuple(Dp), tuple(Ep))


def linearise(
    spec: Spec, problem: Problem, params: Params, ap_jac: tuple | None = None, state=None
) -> Blocks:
    """Assemble the normal-equation blocks (never a dense Jacobian); see :func:`linearise_rows`.

    ``ap_jac``: the AP Jacobians of :func:`ap_jacobians`, if already taken.
    """
    return linearise_rows(spec, problem, params, ap_jac, state)[0]


def linearise_rows(
    spec: Spec, problem: Problem, params: Params, ap_jac: tuple | None = None, state=None
):
    """The one linearisation of the engine: per family the residual rows and Jacobian blocks
    (:func:`rows_at`, with the families' states ``state``) and the normal-equation
    :class:`Blocks` summed from them (:func:`assemble`). The solver and the quality pass share
    it. Returns (blocks, rows)."""
    rows = rows_at(spec, problem, params, ap_jac, state)
    return assemble(spec, problem, params, rows), rows


def linearised_cost(problem: Problem, params: Params, rows) -> Array:
    """``v^T P v`` at the linearisation point from its rows (for a family with frozen weights,
    the weights of that point: the reference cost of a step's acceptance)."""
    total = pseudo_cost(problem, params)
    for fam, P, r in zip(problem.families, params.prims, rows):
        total = total + jnp.sum(r.e**2) + jnp.sum(fam.prior_residuals(P) ** 2)
    return total


def null_space(spec: Spec, families, params: Params):
    """Rigid-motion null-space columns H: per family (n, p, d) and the reduced part (r, d)."""
    cols = spec.datum_columns
    Hp = tuple(null_space_columns(fam.motion, P, cols) for fam, P in zip(families, params.prims))
    Hs = null_space_columns(move_eop, params.eops, cols).reshape(6 * spec.n_scans, len(cols))
    Hz = jnp.concatenate([Hs, jnp.zeros((spec.n_aps, len(cols)))], axis=0)
    return Hp, Hz


class Reduced(Module):
    """The Schur-reduced system, scaled and factorised."""

    Npp_inv: tuple
    Y: tuple  # Npp^-1 Npz per family
    scale: Float[Array, " r"]  # 1/sqrt(diag N_zz), the unreduced diagonal
    L: Float[Array, "r r"]
    dependent: Bool[Array, " r"]
    pivots: Float[Array, " r"]
    Ks: Float[Array, "r r"]  # scaled reduced matrix with the datum closed (for diagnostics)
    K: Float[Array, "r r"]  # the reduced matrix itself, N_zz - sum N_zp N_pp^-1 N_pz


def reduce(spec, problem, blocks: Blocks, Hz, damping, rank_tolerance, dependent=None) -> Reduced:
    """Eliminate the primitives and factorise the reduced system (SPEC section 7).

    The reduced matrix K is scaled by the diagonal of the *unreduced* normal matrix,
    ``K_s = D^-1/2 K D^-1/2`` with ``D = diag(N_zz)``, so that the in-order Cholesky pivot of
    parameter j is ``1 - R^2`` of its column regressed on the reduced unknowns before it and
    the eliminated targets and planes, and ``1 / (K_s^-1)_jj`` that on every other unknown (the
    test of the APs, :func:`._linalg.estimable_cholesky_damped`). A parameter whose effect the
    primitives absorb entirely (A0 with every scan at one station) has pivot 0 and is found
    dependent; on the unit-diagonal K its pivot would be rounding noise of any size. The test
    is a ratio, so it does not depend on the scale of the sigmas or the parameters' units. The datum defect is closed by ``+ Q Q^T`` (Q an orthonormal
    basis of the rigid-motion null space in the scaled coordinates).

    ``dependent``: the columns found dependent at the last undamped linearisation, held as
    well when ``damping > 0``: with damped primitive blocks the Schur complement no longer
    shows that the primitives absorb a parameter entirely.
    """
    inv_list, Y_list, K = schur(blocks, damping)
    diag = jnp.diagonal(blocks.Nzz)
    ok = diag > 0
    scale = jnp.where(ok, 1.0 / jnp.sqrt(jnp.where(ok, diag, 1.0)), 0.0)
    Ks = K * scale[:, None] * scale[None, :]
    if Hz.shape[1]:
        Ks = Ks + datum_projector(Hz / jnp.where(ok, scale, 1.0)[:, None])
    Ks = jnp.where(ok[:, None] & ok[None, :], Ks, 0.0)
    # Rank is judged on the undamped system; the damped one is factorised with the same
    # dependent columns held fixed.
    held = problem.fixed | ~ok
    if dependent is not None:
        held = held | ((damping > 0) & dependent)
    # The APs are tested against every other unknown (not only those before them): a term the
    # network cannot determine is held, named later (_diagnose), never left to diverge.
    L, dep, piv, Ld = estimable_cholesky_damped(Ks, damping, held, rank_tolerance, spec.n_aps)
    L = jnp.where(damping > 0, Ld, L)
    return Reduced(inv_list, Y_list, scale, L, dep, piv, Ks, K)


def schur(blocks: Blocks, damping=0.0):
    """The primitives eliminated: per family ``N_pp^-1`` (damped by ``damping`` times its
    diagonal) and ``Y = N_pp^-1 N_pz``, and the reduced matrix ``K = N_zz - sum N_zp Y``
    (what :func:`reduce` then scales and factorises; the score tests need K alone)."""
    K = blocks.Nzz
    inv_list, Y_list = [], []
    Ep = blocks.Ep or (None,) * len(blocks.Npp)
    for Npp, Npz, D, E in zip(blocks.Npp, blocks.Npz, blocks.Dp, Ep):
        # Hard constraints (a plane's unit normal) in null-space form: the block's inverse is
        # the constrained one, and everything below (Schur complement, back substitution,
        # cofactors) is that of the constrained normal equations.
        Ninv = constrained_spd_inverse(Npp + damping * D[..., :, None] * jnp.eye(Npp.shape[-1]), E)
        # Computed once: XLA would otherwise recompute the unrolled inverse inside every
        # consumer's loop, once per column of Npz (measured: 73 against 10 us for Y^T).
        Ninv = lax.optimization_barrier(Ninv)
        Y = bmm(Ninv, Npz)  # (n, p, r)
        # One matrix product over all primitives' rows (the einsum over (n, p) was a dot with
        # transposed operands, 80 us a pass on the Chow room).
        r = Npz.shape[-1]
        Yt = jnp.transpose(Y, (2, 0, 1)).reshape(r, -1)  # written transposed by its own loop
        K = K - Yt @ Npz.reshape(-1, r)
        inv_list.append(Ninv)
        Y_list.append(Y)
    return tuple(inv_list), tuple(Y_list), K


def datum_projector(H):
    """``Q Q^T``, the orthogonal projector onto the columns of H (Q an orthonormal basis of
    them, by QR: two LAPACK calls)."""
    Q, _ = jnp.linalg.qr(H)
    return Q @ Q.T


def reduced_rhs(bp: tuple, bz, Ys: tuple):
    """``b_z - sum Y^T b_p``, the right-hand side of the reduced system (``Ys``: the ``Y =
    N_pp^-1 N_pz`` blocks per family, :func:`schur`)."""
    c = bz
    for Y, b in zip(Ys, bp):
        c = c - jnp.einsum("npr,np->r", Y, b)
    return c


def solve(spec, red: Reduced, bp: tuple, bz, Hp, Hz):
    """``N^- b`` from the factorisation: the reduced solve, the back substitution of the
    primitives and the S-transformation onto the inner constraints. Returns (dps, dz)."""
    c = reduced_rhs(bp, bz, red.Y) * red.scale
    c = jnp.where(red.dependent, 0.0, c)
    dz = cholesky_solve(red.L, c) * red.scale
    dz = jnp.where(red.dependent, 0.0, dz)
    dps = tuple(
        jnp.einsum("npq,nq->np", Ninv, b) - jnp.einsum("npr,r->np", Y, dz)
        for Ninv, Y, b in zip(red.Npp_inv, red.Y, bp)
    )
    if spec.inner and Hz.shape[1]:
        dps, dz = s_transform_vector(Hp, Hz, dps, dz)
    return dps, dz


def norm_squared(dps: tuple, dz, bp: tuple, bz):
    """``dx^T b``: for ``dx = N^- b`` the squared length of the update in the metric of the
    normal matrix, ``dx^T N dx``, in a priori sigmas. It bounds every component, ``|dx_i| <=
    sqrt(Q_ii) sqrt(dx^T N dx)`` (Cauchy-Schwarz), with no inverse formed."""
    return jnp.dot(dz, bz) + sum(jnp.sum(d * b) for d, b in zip(dps, bp))


def apply_update(spec, problem, params: Params, dps: tuple, dz) -> Params:
    """The parameters after an update, the primitives retracted onto their constraints."""
    ns = spec.n_scans
    prims = tuple(fam.retract(P + dp) for fam, P, dp in zip(problem.families, params.prims, dps))
    return Params(prims, params.eops + dz[: 6 * ns].reshape(ns, 6), params.aps + dz[6 * ns :])


def solve_step(spec, problem, params, blocks, red: Reduced, Hp, Hz):
    """Solve for the update, back-substitute the primitives, apply the datum and retract the
    primitives onto their constraints. Returns (new parameters, applied primitive updates, dz)."""
    dps, dz = solve(spec, red, blocks.bp, blocks.bz, Hp, Hz)
    new = apply_update(spec, problem, params, dps, dz)
    # The update as applied (after the retraction onto the constraints).
    dps = tuple(n - P for n, P in zip(new.prims, params.prims))
    return new, dps, dz
