"""Structured Gauss-Newton / Levenberg-Marquardt on the block normal equations.

Unknowns: primitives (targets, scale bars, later planes) in families of fixed block size p,
scan poses (6 per scan) and APs. With whitened residuals ``e`` (weight matrix = I) and
Jacobian blocks ``J_p, J_s, J_a`` of each observation from ``vmap(jacfwd)``:

    N_pp[i] = sum J_p^T J_p          (segment sum over the observations of primitive i)
    N_pz[i] = [sum J_p^T J_s per scan | sum J_p^T J_a]
    N_zz    = blockdiag_s(sum J_s^T J_s) + [J_s^T J_a], [J_a^T J_a]

The primitives are eliminated by Schur complement, ``K = N_zz - sum_i N_zp N_pp^-1 N_pz``, the
reduced system (r = 6 scans + n APs) is scaled to unit diagonal, the rigid-motion datum defect
is closed by ``+ Q Q^T`` with Q an orthonormal basis of the null space, and it is factorised
by the rank-revealing Cholesky of :mod:`._linalg`. No Jacobian of the whole network is ever
formed. Iterations run in one ``lax.while_loop``.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, Bool, Float, Int

from ._geometry import rotation_matrix
from ._datum import move_eop, move_points, null_space_columns
from ._linalg import cholesky_solve, forward_substitution, rank_revealing_cholesky, spd_inverse
from ._models import point_misclosure
from ._planes import condition_variance, move_plane, plane_condition, unit_normal_constraint, whitened_condition

# Result codes (SPEC section 7). Value-dependent failures come back as codes, never as NaN.
SUCCESS = 0
MAX_ITERATIONS = 1
NOT_ESTIMABLE = 2
RANK_DEFICIENT = 3
NONFINITE = 4
RESULT_MESSAGES = {
    SUCCESS: "converged",
    MAX_ITERATIONS: "did not converge within the maximum number of iterations",
    NOT_ESTIMABLE: "converged; some APs are not estimable and were held at zero",
    RANK_DEFICIENT: "the network does not determine all scan poses (rank defect beyond the datum)",
    NONFINITE: "non-finite values in the adjustment (bad approximate values or observations)",
}


class Family(eqx.Module):
    """One family of eliminated primitives made of ``k`` points each (k=1 targets, k=2 scale bars).

    Observations of the family's points: ``obs`` (m, 3), ``weight`` = 1/sigma (m, 3), and the
    index plan ``prim``, ``point``, ``scan``, ``pair`` (m,), ``pair_prim``/``pair_scan`` of the
    (primitive, scan) pairs. Per-primitive pseudo-observations: control coordinates with
    weights (0 = none) and, for scale bars, the bar length with its weight.
    """

    obs: Float[Array, "m 3"]
    weight: Float[Array, "m 3"]
    prim: Int[Array, " m"]
    point: Int[Array, " m"]
    scan: Int[Array, " m"]
    pair: Int[Array, " m"]
    pair_prim: Int[Array, " q"]
    pair_scan: Int[Array, " q"]
    ctrl_xyz: Float[Array, "n k 3"]
    ctrl_weight: Float[Array, "n k 3"]
    bar_length: Float[Array, " n"]
    bar_weight: Float[Array, " n"]
    k: int = eqx.field(static=True)
    kind: str = eqx.field(static=True, default="point")

    @property
    def n(self) -> int:
        return self.ctrl_xyz.shape[0]

    @property
    def p(self) -> int:
        # A plane is (n_x, n_y, n_z, d) with |n| = 1 (SPEC section 4).
        return 4 if self.kind == "plane" else 3 * self.k


class Problem(eqx.Module):
    """Everything the compiled adjustment needs: families, scans, levelling, fixed parameters."""

    families: tuple
    scan_instrument: Int[Array, " s"]
    levelling: Float[Array, "s 2"]
    levelling_weight: Float[Array, "s 2"]
    fixed: Bool[Array, " r"]


@dataclasses.dataclass(frozen=True)
class Spec:
    """Static description of the model: instruments, AP blocks, datum defect columns."""

    scanners: tuple
    ap_names: tuple
    ap_slices: tuple
    n_scans: int
    datum_columns: tuple  # rigid motions that leave the observations invariant
    inner: bool  # S-transform updates to the inner-constraint datum on the primitives
    family_kinds: tuple = ()  # "point" or "plane" per family (default: all point families)

    def kind(self, fi: int) -> str:
        return self.family_kinds[fi] if self.family_kinds else "point"

    @property
    def n_aps(self) -> int:
        return self.ap_slices[-1][1] if self.ap_slices else 0

    @property
    def r(self) -> int:
        return 6 * self.n_scans + self.n_aps


class Params(eqx.Module):
    prims: tuple  # per family (n, 3k)
    eops: Float[Array, "s 6"]
    aps: Float[Array, " a"]


class Options(eqx.Module):
    """Numerical settings as traced arrays, so changing them never recompiles."""

    max_iterations: Int[Array, ""]
    tolerance: Float[Array, ""]
    rank_tolerance: Float[Array, ""]


# ----------------------------------------------------------------------------------------
# Residuals and their Jacobian blocks


def _obs_residual(spec: Spec, fam: Family):
    if fam.kind == "plane":
        # One Gauss-Helmert condition per point, whitened by sqrt(B Sigma B^T) (_planes.py).
        def g(P, eop, aps, l, w, point, inst):
            return whitened_condition(P, eop, aps, l, w, spec.scanners, spec.ap_names, spec.ap_slices, inst)

        return g

    def f(P, eop, aps, l, w, point, inst):
        X = P.reshape(fam.k, 3)[point]
        return point_misclosure(X, eop, aps, l, spec.scanners, spec.ap_names, spec.ap_slices, inst) * w

    return f


def _prior_residual(fam: Family):
    if fam.kind == "plane":
        # The unit-normal constraint as a pseudo-observation of weight ``lw`` (the family's
        # bar_weight slot): heavy enough that |n| = 1 holds to rounding, counted in the dof.
        def c(P, cx, cw, L, lw):
            return (unit_normal_constraint(P) * lw)[None]

        return c

    def f(P, cx, cw, L, lw):
        pts = P.reshape(fam.k, 3)
        out = ((pts - cx) * cw).reshape(-1)
        if fam.k == 2:
            d = jnp.sqrt(jnp.sum((pts[0] - pts[1]) ** 2))
            out = jnp.concatenate([out, ((d - L) * lw)[None]])
        return out

    return f


def _family_residuals(spec, problem, params, fi):
    fam = problem.families[fi]
    P = params.prims[fi]
    inst = problem.scan_instrument[fam.scan]
    e = jax.vmap(_obs_residual(spec, fam), in_axes=(0, 0, None, 0, 0, 0, 0))(
        P[fam.prim], params.eops[fam.scan], params.aps, fam.obs, fam.weight, fam.point, inst
    )
    pr = jax.vmap(_prior_residual(fam))(P, fam.ctrl_xyz, fam.ctrl_weight, fam.bar_length, fam.bar_weight)
    return e, pr


def compensator_reading(eop):
    """Tilt readings (omega_c, phi_c) of a dual-axis compensator in the scanner frame [rad].

    The compensator senses the object-space vertical in scanner space, ``g = R_j e3``:
    ``omega_c = asin(g_y)``, ``phi_c = asin(-g_x / sqrt(1 - g_y^2))``. For kappa = 0 these are
    exactly the Cardan omega and phi of SPEC section 6, so the levelling pseudo-observations
    ``omega_c = 0 +- s``, ``phi_c = 0 +- s`` are SPEC's to first order. Unlike omega and phi
    themselves, g is invariant under a rotation of object space about Z (``R_j -> R_j Rz^T``),
    so rotation about Z stays an exact null vector of the normal equations and the free-network
    solution does not depend on the datum.
    """
    g = rotation_matrix(eop[3], eop[4], eop[5])[:, 2]
    gy = jnp.clip(g[1], -1.0, 1.0)
    omega = jnp.arcsin(gy)
    phi = jnp.arcsin(jnp.clip(-g[0] / jnp.sqrt(1.0 - gy * gy), -1.0, 1.0))
    return jnp.stack([omega, phi])


def _levelling_residual(problem, eops):
    return (jax.vmap(compensator_reading)(eops) - problem.levelling) * problem.levelling_weight


def _levelling_jacobian(problem, eops):
    # (s, 2, 6): whitened compensator residuals w.r.t. the scan's pose.
    return jax.vmap(jax.jacfwd(compensator_reading))(eops) * problem.levelling_weight[:, :, None]


def cost(spec, problem, params, frozen: Params | None = None):
    """``v^T P v``: sum of squared whitened residuals, observations and pseudo-observations.

    ``frozen``: evaluate the plane conditions' variances ``m = B Sigma B^T`` there instead of at
    ``params``. A Gauss-Helmert step holds M fixed at its linearisation point, so its
    acceptance must compare costs under that M: with M re-evaluated the step can look like an
    ascent near the solution and Levenberg-Marquardt would stall (seen at 100k points).
    """
    total = jnp.sum(_levelling_residual(problem, params.eops) ** 2)
    for fi, fam in enumerate(problem.families):
        e, pr = _family_residuals(spec, problem, params, fi)
        if frozen is not None and fam.kind == "plane":
            e = _plane_rows_frozen(spec, problem, params, frozen, fi)
        total = total + jnp.sum(e**2) + jnp.sum(pr**2)
    return total


def _plane_rows_frozen(spec, problem, params, frozen, fi):
    fam = problem.families[fi]
    new, ref = _family_args(problem, params, fi), _family_args(problem, frozen, fi)
    sigma = jnp.where(fam.weight > 0, 1.0 / jnp.where(fam.weight > 0, fam.weight, 1.0), 0.0)
    sl = (spec.scanners, spec.ap_names, spec.ap_slices)
    m = jax.vmap(lambda P, E, l, s, i: condition_variance(P, E, frozen.aps, l, s, *sl, i)[0])(ref[0], ref[1], fam.obs, sigma, ref[6])
    g = jax.vmap(lambda P, E, l, i: plane_condition(P, E, params.aps, l, *sl, i))(new[0], new[1], fam.obs, new[6])
    return jnp.where(jnp.any(fam.weight > 0, axis=-1), g / jnp.sqrt(jnp.where(m > 0, m, 1.0)), 0.0)


def _outer(a, b):
    # (..., k, i) x (..., k, j) -> (..., i, j); broadcast-multiply-sum beats tiny einsums.
    return jnp.sum(a[..., :, :, None] * b[..., :, None, :], axis=-3)


def _matvec_t(a, e):
    # (..., k, i), (..., k) -> (..., i)
    return jnp.sum(a * e[..., :, None], axis=-2)


class Blocks(eqx.Module):
    """Normal-equation blocks of one linearisation; the right-hand sides are ``-J^T e``."""

    Npp: tuple  # per family (n, p, p)
    Npz: tuple  # per family (n, p, r)
    bp: tuple  # per family (n, p)
    Nzz: Float[Array, "r r"]
    bz: Float[Array, " r"]


_OBS_AXES = (0, 0, None, 0, 0, 0, 0)


def _family_args(problem, params, fi):
    fam = problem.families[fi]
    P = params.prims[fi]
    return (P[fam.prim], params.eops[fam.scan], params.aps, fam.obs, fam.weight, fam.point, problem.scan_instrument[fam.scan])


def ap_jacobians(spec: Spec, problem: Problem, params: Params) -> tuple:
    """``d e / d AP`` per family, (m, 3, a).

    Constant during an adjustment of points: Delta is linear in the AP coefficients with its
    bases evaluated at the observations, and F does not depend on the APs (SPEC section 2). Taking it
    once leaves 3 + 6 tangents per observation for the iterations instead of 9 + a.
    """
    # Not for planes: their condition mixes the corrected observation with the plane and the
    # pose, so d g / d AP changes with them.
    return tuple(
        None if fam.kind == "plane" else
        jax.vmap(jax.jacfwd(_obs_residual(spec, fam), argnums=2), in_axes=_OBS_AXES)(*_family_args(problem, params, fi))
        for fi, fam in enumerate(problem.families)
    )


def linearise(spec: Spec, problem: Problem, params: Params, ap_jac: tuple | None = None) -> Blocks:
    """Assemble the normal-equation blocks with segment sums (never a dense Jacobian).

    ``ap_jac``: the AP Jacobians of :func:`ap_jacobians`, if already taken.
    """
    ns, na = spec.n_scans, spec.n_aps
    Nss = jnp.zeros((ns, 6, 6))
    Nsa = jnp.zeros((ns, 6, na))
    Naa = jnp.zeros((na, na))
    bs = jnp.zeros((ns, 6))
    ba = jnp.zeros((na,))
    Npp, Npz, bp = [], [], []
    for fi, fam in enumerate(problem.families):
        P = params.prims[fi]
        f = _obs_residual(spec, fam)
        args = _family_args(problem, params, fi)
        e = jax.vmap(f, in_axes=_OBS_AXES)(*args)
        if ap_jac is None or ap_jac[fi] is None:
            Jp, Js, Ja = jax.vmap(jax.jacfwd(f, argnums=(0, 1, 2)), in_axes=_OBS_AXES)(*args)
        else:
            Jp, Js = jax.vmap(jax.jacfwd(f, argnums=(0, 1)), in_axes=_OBS_AXES)(*args)
            Ja = ap_jac[fi]
        n, nq = fam.n, fam.pair_prim.shape[0]
        seg = jax.ops.segment_sum
        npp = seg(_outer(Jp, Jp), fam.prim, n)
        bpp = -seg(_matvec_t(Jp, e), fam.prim, n)
        # Priors on primitives (control points, scale-bar lengths).
        g = _prior_residual(fam)
        pr = jax.vmap(g)(P, fam.ctrl_xyz, fam.ctrl_weight, fam.bar_length, fam.bar_weight)
        Jpr = jax.vmap(jax.jacfwd(g))(P, fam.ctrl_xyz, fam.ctrl_weight, fam.bar_length, fam.bar_weight)
        npp = npp + _outer(Jpr, Jpr)
        bpp = bpp - _matvec_t(Jpr, pr)
        nps_pairs = seg(_outer(Jp, Js), fam.pair, nq)  # (q, p, 6)
        nps = jnp.zeros((n, ns, fam.p, 6)).at[fam.pair_prim, fam.pair_scan].set(nps_pairs)
        nps = jnp.transpose(nps, (0, 2, 1, 3)).reshape(n, fam.p, 6 * ns)
        npa = seg(_outer(Jp, Ja), fam.prim, n)
        Npp.append(npp)
        Npz.append(jnp.concatenate([nps, npa], axis=-1))
        bp.append(bpp)
        Nss = Nss + seg(_outer(Js, Js), fam.scan, ns)
        Nsa = Nsa + seg(_outer(Js, Ja), fam.scan, ns)
        Naa = Naa + jnp.sum(_outer(Ja, Ja), axis=0)
        bs = bs - seg(_matvec_t(Js, e), fam.scan, ns)
        ba = ba - jnp.sum(_matvec_t(Ja, e), axis=0)
    # Levelling pseudo-observations (compensator readings) act on the scan's rotation.
    Jl = _levelling_jacobian(problem, params.eops)
    lr = _levelling_residual(problem, params.eops)
    Nss = Nss + _outer(Jl, Jl)
    bs = bs - _matvec_t(Jl, lr)
    eye = jnp.eye(ns)
    Nss_full = (Nss[:, None, :, :] * eye[:, :, None, None]).transpose(0, 2, 1, 3).reshape(6 * ns, 6 * ns)
    Nsa_full = Nsa.reshape(6 * ns, na)
    Nzz = jnp.block([[Nss_full, Nsa_full], [Nsa_full.T, Naa]])
    bz = jnp.concatenate([bs.reshape(-1), ba])
    return Blocks(tuple(Npp), tuple(Npz), tuple(bp), Nzz, bz)


def null_space(spec: Spec, params: Params):
    """Rigid-motion null-space columns H: per family (n, p, d) and the reduced part (r, d)."""
    cols = spec.datum_columns
    Hp = tuple(null_space_columns(move_plane if spec.kind(fi) == "plane" else move_points, P, cols)
               for fi, P in enumerate(params.prims))
    Hs = null_space_columns(move_eop, params.eops, cols).reshape(6 * spec.n_scans, len(cols))
    Hz = jnp.concatenate([Hs, jnp.zeros((spec.n_aps, len(cols)))], axis=0)
    return Hp, Hz


class Reduced(eqx.Module):
    """The Schur-reduced system, scaled and factorised."""

    Npp_inv: tuple
    Y: tuple  # Npp^-1 Npz per family
    scale: Float[Array, " r"]  # 1/sqrt(diag K)
    L: Float[Array, "r r"]
    dependent: Bool[Array, " r"]
    pivots: Float[Array, " r"]
    Ks: Float[Array, "r r"]  # scaled reduced matrix with the datum closed (for diagnostics)


def reduce(spec, problem, blocks: Blocks, Hz, damping, rank_tolerance) -> Reduced:
    """Eliminate the primitives and factorise the reduced system (SPEC section 7)."""
    K = blocks.Nzz
    inv_list, Y_list = [], []
    for Npp, Npz in zip(blocks.Npp, blocks.Npz):
        D = jnp.diagonal(Npp, axis1=-2, axis2=-1)
        Ninv = spd_inverse(Npp + damping * D[..., :, None] * jnp.eye(Npp.shape[-1]))
        Y = jnp.sum(Ninv[..., :, :, None] * Npz[..., None, :, :], axis=-2)  # (n, p, r)
        K = K - jnp.einsum("npr,npq->rq", Npz, Y)
        inv_list.append(Ninv)
        Y_list.append(Y)
    diag = jnp.diagonal(K)
    ok = diag > 0
    scale = jnp.where(ok, 1.0 / jnp.sqrt(jnp.where(ok, diag, 1.0)), 0.0)
    Ks = K * scale[:, None] * scale[None, :]
    if Hz.shape[1]:
        Q, _ = jnp.linalg.qr(Hz / jnp.where(ok, scale, 1.0)[:, None])
        Ks = Ks + Q @ Q.T
    Ks = jnp.where(ok[:, None] & ok[None, :], Ks, 0.0)
    # Rank is judged on the undamped system; the damped one is factorised with the same
    # dependent columns held fixed.
    L, dep, piv = rank_revealing_cholesky(Ks, problem.fixed | ~ok, rank_tolerance)
    # Undamped Gauss-Newton steps (the common case) skip the second factorisation.
    L = lax.cond(damping > 0, lambda: rank_revealing_cholesky(Ks + damping * jnp.eye(Ks.shape[0]), dep, -1.0)[0], lambda: L)
    return Reduced(tuple(inv_list), tuple(Y_list), scale, L, dep, piv, Ks)


def reduced_rhs(blocks: Blocks, red: Reduced):
    c = blocks.bz
    for Y, bp in zip(red.Y, blocks.bp):
        c = c - jnp.einsum("npr,np->r", Y, bp)
    return c


def solve_step(spec, problem, params, blocks, red: Reduced, Hp, Hz):
    """Solve for the update, back-substitute the primitives, apply the datum."""
    c = reduced_rhs(blocks, red) * red.scale
    c = jnp.where(red.dependent, 0.0, c)
    dz = cholesky_solve(red.L, c) * red.scale
    dz = jnp.where(red.dependent, 0.0, dz)
    dps = tuple(
        jnp.einsum("npq,nq->np", Ninv, bp) - jnp.einsum("npr,r->np", Y, dz)
        for Ninv, Y, bp in zip(red.Npp_inv, red.Y, blocks.bp)
    )
    if spec.inner and Hz.shape[1]:
        dps, dz = s_transform_vector(Hp, Hz, dps, dz)
    ns = spec.n_scans
    return Params(
        tuple(P + dp for P, dp in zip(params.prims, dps)),
        params.eops + dz[: 6 * ns].reshape(ns, 6),
        params.aps + dz[6 * ns :],
    ), dps, dz


def s_transform_vector(Hp, Hz, dps, dz):
    """``dx - H (G^T H)^-1 G^T dx`` with G the primitive rows of H (inner constraints)."""
    GtH = sum(jnp.einsum("npd,npe->de", H, H) for H in Hp)
    Gtx = sum(jnp.einsum("npd,np->d", H, dp) for H, dp in zip(Hp, dps))
    coef = jnp.linalg.solve(GtH, Gtx)
    dps = tuple(dp - jnp.einsum("npd,d->np", H, coef) for H, dp in zip(Hp, dps))
    return dps, dz - Hz @ coef


def update_size(blocks, red: Reduced, dz, dps):
    """Largest update in units of the parameter's precision: ``|dx_i| / sqrt(Q_ii)``.

    For the scan poses and APs, Q_ii is the diagonal of the inverse of the Schur-reduced matrix
    (from its Cholesky factor, r^3/3 flops), i.e. the parameter's actual cofactor; the
    stand-alone ``1/N_ii`` would be far smaller than that for strongly correlated APs, and the
    test would then chase rounding noise along their nearly singular directions. For the
    eliminated primitives the stand-alone ``(N_pp^-1)_ii`` is used: it is a lower bound of their
    cofactor, so the test is, if anything, stricter there.
    """
    Li = forward_substitution(red.L, jnp.eye(red.L.shape[0], dtype=red.L.dtype))
    q = jnp.sum(Li * Li, axis=0) * red.scale**2
    size = jnp.max(jnp.where(red.dependent | (q <= 0), 0.0, jnp.abs(dz) / jnp.sqrt(jnp.where(q > 0, q, 1.0))), initial=0.0)
    for dp, Ninv in zip(dps, red.Npp_inv):
        qp = jnp.diagonal(Ninv, axis1=-2, axis2=-1)
        size = jnp.maximum(size, jnp.max(jnp.abs(dp) / jnp.sqrt(jnp.abs(qp)), initial=0.0))
    return size


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
        damping = jnp.where(accept, jnp.where(state.damping < 1e-7, 0.0, state.damping * 0.1), jnp.maximum(state.damping * 10.0, 1e-4))
        return SolveState(params, jnp.where(accept, new_cost, state.cost), damping, state.iteration + 1, converged, finite | accept)

    def cond(state: SolveState):
        return (~state.converged) & (state.iteration < options.max_iterations) & (state.damping < 1e8)

    c0 = cost(spec, problem, params0)
    init = SolveState(params0, c0, jnp.asarray(0.0), jnp.asarray(0), jnp.asarray(False), jnp.isfinite(c0))
    return lax.while_loop(cond, step, init)
