"""Quality of an adjustment from the compiled normal equations (SPEC section 7).

* ``s0^2 = v^T P v / r`` with the redundancy ``r = n - u + d`` (d: datum defect).
* Cofactor matrix: ``K_s + Q Q^T`` (scaled reduced matrix plus the datum null space) inverts to
  a generalised inverse of the reduced normal matrix; the eliminated primitives follow from
  the block formulas ``Q_pz = -N_pp^-1 N_pz Q_zz``, ``Q_pp = N_pp^-1 + N_pp^-1 N_pz Q_zz N_zp
  N_pp^-1``; the S-transformation ``S Q S^T`` gives the inner-constraint cofactor matrix.
* Redundancy numbers ``r_i = (Q_vv P)_ii = 1 - (J Q J^T)_ii`` in whitened form, datum
  invariant; their sum equals the degrees of freedom.
* An observation with weight 0 is removed (data snooping masks, :mod:`._statistics`): it is not
  counted in the degrees of freedom, its redundancy number is 0, and its residual is still
  computed (the misclosure at the solution), so that a removed blunder can be reported.
* AP influence (external reliability, Baarda 1968): the change of the APs caused by an error of
  one a priori sigma in observation i, ``dx_a = Q_(a, u_i) J_i^T P_i sigma_i`` over the
  unknowns u_i that observation touches (its target, its scan, the APs), in units of the AP's
  a priori sigma ``sqrt(Q_aa)``; gathered from the Qpz/Qzz blocks, never a whole Jacobian.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from .._model._planes import condition_variance, observation_residuals
from ._families import (
    Params,
    Problem,
    Spec,
    levelling_jacobian,
    levelling_residual,
    obs_residual,
    prior_residual,
)
from ._linalg import cholesky_inverse
from ._normal import linearise, null_space, reduce


class Quality(eqx.Module):
    vtpv: Float[Array, ""]
    dof: Float[Array, ""]
    Qzz: Float[Array, "r r"]  # generalised inverse of the reduced system (APs: datum invariant)
    Qfull: object  # inner-constraint cofactor matrix of all unknowns, or None
    residuals: tuple  # per family (m, 3): v = F + Delta - l [m, rad, rad]
    redundancy: tuple  # per family (m, 3)
    redundancy_prior: tuple  # per family (n, q)
    redundancy_levelling: Float[Array, "s 2"]
    dependent: object
    pivots: object
    Ks: object
    Qs: object
    scale: object
    n_observations: object = None  # observations with nonzero weight (pseudo-observations included)
    ap_influence: tuple = ()  # per family (m, 3, a): dx_AP / sigma_AP for a 1-sigma error


def quality(
    spec: Spec, problem: Problem, params: Params, rank_tolerance, full_covariance: bool = True
) -> Quality:
    blocks = linearise(spec, problem, params)
    Hp, Hz = null_space(spec, params)
    red = reduce(spec, problem, blocks, Hz, jnp.asarray(0.0), rank_tolerance)
    dep = red.dependent
    Qs = cholesky_inverse(red.L)
    Qs = jnp.where(dep[:, None] | dep[None, :], 0.0, Qs)
    Qzz = Qs * red.scale[:, None] * red.scale[None, :]

    ns = spec.n_scans
    n_obs = 0.0
    vtpv = jnp.sum(levelling_residual(problem, params.eops) ** 2)
    n_obs = n_obs + jnp.sum(problem.levelling_weight > 0)
    residuals, redund, redund_prior, Qpp_list, Qpz_list, influence = [], [], [], [], [], []
    n_unknowns = jnp.sum(~dep)
    for fi, fam in enumerate(problem.families):
        P = params.prims[fi]
        inst = problem.scan_instrument[fam.scan]
        f = obs_residual(spec, fam)
        args = (
            P[fam.prim],
            params.eops[fam.scan],
            params.aps,
            fam.obs,
            fam.weight,
            fam.point,
            inst,
        )
        ax = (0, 0, None, 0, 0, 0, 0)
        # Misclosure at unit weight, so that a masked (weight 0) observation keeps its residual.
        raw = jax.vmap(f, in_axes=ax)(*args[:4], jnp.ones_like(fam.weight), *args[5:])
        e = raw * fam.weight
        active_obs = fam.weight > 0
        Jp, Js, Ja = jax.vmap(jax.jacfwd(f, argnums=(0, 1, 2)), in_axes=ax)(*args)
        Y = red.Y[fi]
        Qpz = -jnp.einsum("npr,rq->npq", Y, Qzz)  # (n, p, r)
        Qpp = red.Npp_inv[fi] - jnp.einsum("npr,nqr->npq", Qpz, Y)  # Ninv + Y Qzz Y^T
        Qpp_list.append(Qpp)
        Qpz_list.append(Qpz)
        # Diagonal of J Q J^T per observation row, gathering only the blocks each row touches.
        Qzz_s = Qzz[: 6 * ns].reshape(ns, 6, -1)
        Tss = Qzz_s[:, :, : 6 * ns].reshape(ns, 6, ns, 6)[
            jnp.arange(ns), :, jnp.arange(ns), :
        ]  # (s, 6, 6)
        Tsa = Qzz_s[:, :, 6 * ns :]  # (s, 6, a)
        Taa = Qzz[6 * ns :, 6 * ns :]
        Qpz_r = Qpz[:, :, : 6 * ns].reshape(fam.n, fam.p, ns, 6)
        Qps_obs = Qpz_r[fam.prim, :, fam.scan, :]  # (m, p, 6)
        Qpa_obs = Qpz[fam.prim][:, :, 6 * ns :]  # (m, p, a)

        def quad(Jl, Q, Jr):
            return jnp.sum(jnp.sum(Jl[..., :, :, None] * Q[..., None, :, :], axis=-2) * Jr, axis=-1)

        JQJ = (
            quad(Jp, Qpp[fam.prim], Jp)
            + 2 * quad(Jp, Qps_obs, Js)
            + 2 * quad(Jp, Qpa_obs, Ja)
            + quad(Js, Tss[fam.scan], Js)
            + 2 * quad(Js, Tsa[fam.scan], Ja)
            + quad(Ja, jnp.broadcast_to(Taa, (Ja.shape[0],) + Taa.shape), Ja)
        )
        if fam.kind == "plane":
            # Gauss-Helmert: one condition per point. Its redundancy r_c = 1 - (a Q a^T) splits
            # over the point's three observations in the ratio sigma_l^2 b_l^2 / m (SPEC 4).
            e = jax.vmap(f, in_axes=ax)(*args)  # (m, 1)
            rows = jnp.any(fam.weight > 0, axis=-1)
            sig = jnp.where(fam.weight > 0, 1.0 / jnp.where(fam.weight > 0, fam.weight, 1.0), 0.0)
            m, B = jax.vmap(
                lambda P_, E_, A_, l_, s_, i_: condition_variance(
                    P_, E_, A_, l_, s_, spec.scanners, spec.ap_names, spec.ap_slices, i_
                )
            )(
                args[0],
                args[1],
                jnp.broadcast_to(args[2], (fam.obs.shape[0],) + args[2].shape),
                fam.obs,
                sig,
                inst,
            )
            share = (sig * B) ** 2 / jnp.where(m > 0, m, 1.0)[:, None]
            redund.append(jnp.where(rows, 1.0 - JQJ[:, 0], 0.0)[:, None] * share)
            residuals.append(
                jax.vmap(
                    lambda P_, E_, l_, w_, i_: observation_residuals(
                        P_, E_, params.aps, l_, w_, spec.scanners, spec.ap_names, spec.ap_slices, i_
                    )
                )(args[0], args[1], fam.obs, fam.weight, inst)
            )
            vtpv = vtpv + jnp.sum(e**2)
            n_obs = n_obs + jnp.sum(rows)
        else:
            redund.append(jnp.where(active_obs, 1.0 - JQJ, 0.0))
            residuals.append(raw)
            vtpv = vtpv + jnp.sum(e**2)
            n_obs = n_obs + jnp.sum(active_obs)
        # External reliability: Q_(a, touched) J^T for every observation row, in AP sigmas.
        # Written as small matmuls: broadcast-multiply-sum over (m, 3, a, a) was 10x slower.
        infl = (
            jnp.einsum("mkp,mpa->mka", Jp, Qpa_obs)
            + jnp.einsum("mks,msa->mka", Js, Tsa[fam.scan])
            + jnp.einsum("mkb,ab->mka", Ja, Taa)
        )  # (m, 3, a)
        sa = jnp.sqrt(jnp.clip(jnp.diagonal(Taa), 0.0, None))
        influence.append(jnp.where(sa > 0, infl / jnp.where(sa > 0, sa, 1.0), 0.0))
        g = prior_residual(fam)
        pargs = (P, fam.ctrl_xyz, fam.ctrl_weight, fam.bar_length, fam.bar_weight)
        pr = jax.vmap(g)(*pargs)
        Jpr = jax.vmap(jax.jacfwd(g))(*pargs)
        active = jnp.any(Jpr != 0, axis=-1)
        redund_prior.append(jnp.where(active, 1.0 - quad(Jpr, Qpp, Jpr), 0.0))
        vtpv = vtpv + jnp.sum(pr**2)
        n_obs = n_obs + jnp.sum(active)
        n_unknowns = n_unknowns + P.size
    lw = problem.levelling_weight
    Jl = levelling_jacobian(problem, params.eops)  # (s, 2, 6)
    Tss = Qzz[: 6 * ns, : 6 * ns].reshape(ns, 6, ns, 6)[jnp.arange(ns), :, jnp.arange(ns), :]
    q_lev = jnp.sum(jnp.sum(Jl[:, :, :, None] * Tss[:, None, :, :], axis=-2) * Jl, axis=-1)
    redund_lev = jnp.where(lw > 0, 1.0 - q_lev, 0.0)
    d = Hz.shape[1]
    dof = n_obs - n_unknowns + d

    Qfull = None
    if full_covariance:
        Qfull = _full_cofactor(spec, red, Qzz, Qpp_list, Qpz_list, Hp, Hz)
    return Quality(
        vtpv,
        jnp.asarray(dof, dtype=jnp.float64),
        Qzz,
        Qfull,
        tuple(residuals),
        tuple(redund),
        tuple(redund_prior),
        redund_lev,
        dep,
        red.pivots,
        red.Ks,
        Qs,
        red.scale,
        jnp.asarray(n_obs, dtype=jnp.float64),
        tuple(influence),
    )


def _full_cofactor(spec, red, Qzz, Qpp_list, Qpz_list, Hp, Hz):
    """Dense cofactor matrix of [primitives..., EOPs, APs], S-transformed to inner constraints."""
    Y_all = jnp.concatenate([Y.reshape(-1, Y.shape[-1]) for Y in red.Y], axis=0)  # (np, r)
    n_p = Y_all.shape[0]
    Ninv = jnp.zeros((n_p, n_p))
    off = 0
    for Ni in red.Npp_inv:
        n, p, _ = Ni.shape
        idx = off + jnp.arange(n * p).reshape(n, p)
        Ninv = Ninv.at[idx[:, :, None], idx[:, None, :]].set(Ni)
        off += n * p
    Qpp = Ninv + Y_all @ Qzz @ Y_all.T
    Qpz = -Y_all @ Qzz
    Q = jnp.block([[Qpp, Qpz], [Qpz.T, Qzz]])
    if spec.inner and Hz.shape[1]:
        Hpf = jnp.concatenate([H.reshape(-1, H.shape[-1]) for H in Hp], axis=0)
        H = jnp.concatenate([Hpf, Hz], axis=0)
        G = jnp.concatenate([Hpf, jnp.zeros_like(Hz)], axis=0)
        M = jnp.linalg.inv(G.T @ H)
        SQ = Q - H @ (M @ (G.T @ Q))
        Q = SQ - (SQ @ G) @ M.T @ H.T
    return Q
