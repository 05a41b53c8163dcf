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

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, Bool, Float

from .._model._datum import move_eop, null_space_columns, s_transform_vector
from ._families import OBS_AXES, Params, Problem, Spec, levelling_jacobian, levelling_residual
from ._linalg import cholesky_solve, forward_substitution, rank_revealing_cholesky, spd_inverse


def outer(a, b):
    # (..., k, i) x (..., k, j) -> (..., i, j); broadcast-multiply-sum beats tiny einsums.
    return jnp.sum(a[..., :, :, None] * b[..., :, None, :], axis=-3)


def matvec_t(a, e):
    # (..., k, i), (..., k) -> (..., i)
    return jnp.sum(a * e[..., :, None], axis=-2)


class Blocks(eqx.Module):
    """Normal-equation blocks of one linearisation; the right-hand sides are ``-J^T e``."""

    Npp: tuple  # per family (n, p, p)
    Npz: tuple  # per family (n, p, r)
    bp: tuple  # per family (n, p)
    Nzz: Float[Array, "r r"]
    bz: Float[Array, " r"]
    # Diagonal of the observations' part of N_pp (priors left out): the Levenberg-Marquardt
    # scaling, so that a heavy pseudo-observation (a plane's unit-normal constraint) does not
    # freeze the directions it does not constrain.
    Dp: tuple = ()


def ap_jacobians(spec: Spec, problem: Problem, params: Params) -> tuple:
    """``d e / d AP`` per family, (m, rows, a), for the families where it is constant.

    For points Delta is linear in the AP coefficients with its bases evaluated at the
    observations, and F does not depend on the APs (SPEC section 2): taking it once leaves
    3 + 6 tangents per observation for the iterations instead of 9 + a.
    """
    out = []
    for fi, fam in enumerate(problem.families):
        if not fam.constant_ap_jacobian:
            out.append(None)
            continue
        jac = jax.jacfwd(lambda *a, fam=fam: fam.residual(spec, *a), argnums=2)
        out.append(jax.vmap(jac, in_axes=OBS_AXES)(*fam.observation_args(problem, params, fi)))
    return tuple(out)


def _family_jacobians(spec, problem, params, fi, ap_jac):
    """Residual rows e (m, rows) and Jacobian blocks w.r.t. the primitive, pose and APs."""
    fam = problem.families[fi]
    args = fam.observation_args(problem, params, fi)
    f = lambda *a: fam.residual(spec, *a)
    e = jax.vmap(f, in_axes=OBS_AXES)(*args)
    if ap_jac is None or ap_jac[fi] is None:
        Jp, Js, Ja = jax.vmap(jax.jacfwd(f, argnums=(0, 1, 2)), in_axes=OBS_AXES)(*args)
    else:
        Jp, Js = jax.vmap(jax.jacfwd(f, argnums=(0, 1)), in_axes=OBS_AXES)(*args)
        Ja = ap_jac[fi]
    return e, Jp, Js, Ja


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
    Npp, Npz, bp, Dp = [], [], [], []
    for fi, fam in enumerate(problem.families):
        P = params.prims[fi]
        e, Jp, Js, Ja = _family_jacobians(spec, problem, params, fi, ap_jac)
        n, nq = fam.n, fam.pair_prim.shape[0]
        seg = jax.ops.segment_sum
        npp = seg(outer(Jp, Jp), fam.prim, n)
        bpp = -seg(matvec_t(Jp, e), fam.prim, n)
        # Priors on primitives (control points, scale-bar lengths, unit normals).
        pr, Jpr = fam.prior_residuals(P), fam.prior_jacobian(P)
        Dp.append(jnp.diagonal(npp, axis1=-2, axis2=-1))
        npp = npp + outer(Jpr, Jpr)
        bpp = bpp - matvec_t(Jpr, pr)
        nps_pairs = seg(outer(Jp, Js), fam.pair, nq)  # (q, p, 6)
        nps = jnp.zeros((n, ns, fam.p, 6)).at[fam.pair_prim, fam.pair_scan].set(nps_pairs)
        nps = jnp.transpose(nps, (0, 2, 1, 3)).reshape(n, fam.p, 6 * ns)
        npa = seg(outer(Jp, Ja), fam.prim, n)
        Npp.append(npp)
        Npz.append(jnp.concatenate([nps, npa], axis=-1))
        bp.append(bpp)
        Nss = Nss + seg(outer(Js, Js), fam.scan, ns)
        Nsa = Nsa + seg(outer(Js, Ja), fam.scan, ns)
        Naa = Naa + jnp.sum(outer(Ja, Ja), axis=0)
        bs = bs - seg(matvec_t(Js, e), fam.scan, ns)
        ba = ba - jnp.sum(matvec_t(Ja, e), axis=0)
    # Levelling pseudo-observations (compensator readings) act on the scan's rotation.
    Jl = levelling_jacobian(problem, params.eops)
    lr = levelling_residual(problem, params.eops)
    Nss = Nss + outer(Jl, Jl)
    bs = bs - matvec_t(Jl, lr)
    eye = jnp.eye(ns)
    Nss_full = (
        (Nss[:, None, :, :] * eye[:, :, None, None]).transpose(0, 2, 1, 3).reshape(6 * ns, 6 * ns)
    )
    Nsa_full = Nsa.reshape(6 * ns, na)
    Nzz = jnp.block([[Nss_full, Nsa_full], [Nsa_full.T, Naa]])
    bz = jnp.concatenate([bs.reshape(-1), ba])
    return Blocks(tuple(Npp), tuple(Npz), tuple(bp), Nzz, bz, tuple(Dp))


def null_space(spec: Spec, families, params: Params):
    """Rigid-motion null-space columns H: per family (n, p, d) and the reduced part (r, d)."""
    cols = spec.datum_columns
    Hp = tuple(null_space_columns(fam.motion, P, cols) for fam, P in zip(families, params.prims))
    Hs = null_space_columns(move_eop, params.eops, cols).reshape(6 * spec.n_scans, len(cols))
    Hz = jnp.concatenate([Hs, jnp.zeros((spec.n_aps, len(cols)))], axis=0)
    return Hp, Hz


class Reduced(eqx.Module):
    """The Schur-reduced system, scaled and factorised."""

    Npp_inv: tuple
    Y: tuple  # Npp^-1 Npz per family
    scale: Float[Array, " r"]  # 1/sqrt(diag N_zz), the unreduced diagonal
    L: Float[Array, "r r"]
    dependent: Bool[Array, " r"]
    pivots: Float[Array, " r"]
    Ks: Float[Array, "r r"]  # scaled reduced matrix with the datum closed (for diagnostics)


def reduce(spec, problem, blocks: Blocks, Hz, damping, rank_tolerance) -> Reduced:
    """Eliminate the primitives and factorise the reduced system (SPEC section 7).

    The reduced matrix K is scaled by the diagonal of the *unreduced* normal matrix,
    ``K_s = D^-1/2 K D^-1/2`` with ``D = diag(N_zz)``, so that the in-order Cholesky pivot of
    parameter j is ``1 - R^2`` of its column regressed on every other unknown, the eliminated
    targets and planes included. A parameter whose effect the primitives absorb entirely (A0
    with every scan at one station) has pivot 0 and is found dependent; on the unit-diagonal K
    its pivot would be rounding noise of any size. The test is a ratio, so it does not depend
    on the scale of the sigmas. The datum defect is closed by ``+ Q Q^T`` (Q an orthonormal
    basis of the rigid-motion null space in the scaled coordinates).
    """
    K = blocks.Nzz
    inv_list, Y_list = [], []
    for Npp, Npz, D in zip(blocks.Npp, blocks.Npz, blocks.Dp):
        Ninv = spd_inverse(Npp + damping * D[..., :, None] * jnp.eye(Npp.shape[-1]))
        Y = jnp.sum(Ninv[..., :, :, None] * Npz[..., None, :, :], axis=-2)  # (n, p, r)
        K = K - jnp.einsum("npr,npq->rq", Npz, Y)
        inv_list.append(Ninv)
        Y_list.append(Y)
    diag = jnp.diagonal(blocks.Nzz)
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
    L = lax.cond(
        damping > 0,
        lambda: rank_revealing_cholesky(Ks + damping * jnp.eye(Ks.shape[0]), dep, -1.0)[0],
        lambda: L,
    )
    return Reduced(tuple(inv_list), tuple(Y_list), scale, L, dep, piv, Ks)


def reduced_rhs(blocks: Blocks, red: Reduced):
    c = blocks.bz
    for Y, bp in zip(red.Y, blocks.bp):
        c = c - jnp.einsum("npr,np->r", Y, bp)
    return c


def solve_step(spec, problem, params, blocks, red: Reduced, Hp, Hz):
    """Solve for the update, back-substitute the primitives, apply the datum and retract the
    primitives onto their constraints. Returns (new parameters, applied primitive updates, dz)."""
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
    prims = tuple(fam.retract(P + dp) for fam, P, dp in zip(problem.families, params.prims, dps))
    # The update as applied (after the retraction onto the constraints): it measures convergence.
    dps = tuple(new - P for new, P in zip(prims, params.prims))
    new = Params(prims, params.eops + dz[: 6 * ns].reshape(ns, 6), params.aps + dz[6 * ns :])
    return new, dps, dz


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
    size = jnp.max(
        jnp.where(red.dependent | (q <= 0), 0.0, jnp.abs(dz) / jnp.sqrt(jnp.where(q > 0, q, 1.0))),
        initial=0.0,
    )
    for dp, Ninv in zip(dps, red.Npp_inv):
        qp = jnp.diagonal(Ninv, axis1=-2, axis2=-1)
        size = jnp.maximum(size, jnp.max(jnp.abs(dp) / jnp.sqrt(jnp.abs(qp)), initial=0.0))
    return size
