"""Quality of an adjustment from the compiled normal equations (SPEC section 7).

* ``s0^2 = v^T P v / r`` with the redundancy ``r = n - u + d`` (d: datum defect).
* Cofactor matrix: ``K_s + Q Q^T`` (scaled reduced matrix plus the datum null space) inverts to
  a generalised inverse of the reduced normal matrix; the eliminated primitives follow from
  the block formulas ``Q_pz = -N_pp^-1 N_pz Q_zz``, ``Q_pp = N_pp^-1 + N_pp^-1 N_pz Q_zz N_zp
  N_pp^-1``; the S-transformation ``S Q S^T`` gives the inner-constraint cofactor matrix, block
  by block (:func:`tlsjax._model._datum.inner_constraint_cofactor`): the diagonal block of every
  primitive, its block with the scan poses and APs, and the reduced block. Nothing of size u^2
  is formed unless the dense matrix is asked for (``full_covariance``).
* Redundancy numbers ``r_i = (Q_vv P)_ii = 1 - (J Q J^T)_ii`` in whitened form, datum
  invariant; their sum equals the degrees of freedom.
* An observation with weight 0 is removed (data snooping masks, :mod:`tlsjax._inference._steps`): it is not
  counted in the degrees of freedom, its redundancy number is 0, and its residual is still
  computed (the misclosure at the solution), so that a removed blunder can be reported.
* AP influence (external reliability, Baarda 1968): the change of the APs caused by an error of
  one a priori sigma in observation i, ``dx_a = Q_(a, u_i) J_i^T P_i sigma_i`` over the
  unknowns u_i that observation touches (its target, its scan, the APs), in units of the AP's
  a priori sigma ``sqrt(Q_aa)``; gathered from the Qpz/Qzz blocks, never a whole Jacobian.
* Internal reliability (Baarda 1968): the minimal detectable bias ``MDB_i = delta0 sigma_i /
  sqrt(r_i)`` (:func:`minimal_detectable_bias`) and Baarda's external reliability factor
  ``sqrt((1 - r_i) / r_i) delta0`` (:func:`external_reliability_factor`), with ``delta0`` from
  :mod:`tlsjax._stats` (4.13 for alpha0 = 0.1 %, power 80 %). An observation whose redundancy
  number is at most :data:`MIN_TESTABLE_REDUNDANCY` is not controlled: no error of any size is
  detected (MDB infinite) and its w-test is not computed.
* The cofactor matrix of the scan poses and APs predicted from one linearisation, without
  iterations or rank test (:func:`pose_ap_cofactor`; network design, SPEC section 13).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._linalg import UNROLL_MAX, bmm, cholesky_inverse, mm, triangular_inverse
from .._model._datum import inner_constraint_cofactor
from .._pytree import Module
from .._stats import DELTA0
from ._families import (
    Params,
    Problem,
    Spec,
    ap_prior_weight,
    count_observations,
    from_grid,
    levelling_jacobian,
    n_pseudo,
    on_grid,
    orientation_observations,
    orientation_residual,
    pseudo_cost,
    settled_state,
)
from ._normal import (
    datum_projector,
    linearise,
    linearise_rows,
    linearised_cost,
    null_space,
    reduce,
)
from ._solver import Linearisation

#: Redundancy number at or below which an observation is not controlled by the tests: its
#: w-test is not computed and its minimal detectable bias is infinite. Redundancy numbers of
#: uncontrolled observations are zero in exact arithmetic and rounding (about 1e-12 here)
#: in the computed ``Q_vv P``; 1e-6 (an MDB of 4,000 sigma) is well above both.
MIN_TESTABLE_REDUNDANCY = 1e-6


def _xp(*arrays):
    return jnp if any(isinstance(a, jax.Array) for a in arrays) else np


def minimal_detectable_bias(sigmas, redundancy, delta0: float = DELTA0):
    """Internal reliability (Baarda 1968): ``MDB_i = delta0 sigma_i / sqrt(r_i)``, in the units
    of the sigmas; inf where ``r_i <= MIN_TESTABLE_REDUNDANCY`` (not controlled). numpy or jax
    (traceable, with a finite derivative everywhere)."""
    xp = _xp(sigmas, redundancy)
    ok = redundancy > MIN_TESTABLE_REDUNDANCY
    return xp.where(ok, delta0 * sigmas / xp.sqrt(xp.where(ok, redundancy, 1.0)), xp.inf)


def external_reliability_factor(redundancy, delta0: float = DELTA0):
    """Baarda's external reliability factor ``sqrt((1 - r_i) / r_i) delta0``: the effect of an
    undetected MDB-sized error on the unknowns, in units of their sigmas (the largest over all
    linear functions of them); inf where ``r_i <= MIN_TESTABLE_REDUNDANCY``."""
    xp = _xp(redundancy)
    ok = redundancy > MIN_TESTABLE_REDUNDANCY
    r = xp.where(ok, redundancy, 1.0)
    return xp.where(ok, xp.sqrt(xp.maximum(1.0 - r, 0.0) / r) * delta0, xp.inf)


class Quality(Module):
    vtpv: Float[Array, ""]
    dof: Float[Array, ""]
    # Conditions with nonzero weight (three per target observation, one per plane point),
    # pseudo-observations and hard constraints (a plane's unit normal): the n of r = n - u + d.
    n_observations: Float[Array, ""]
    Qzz: Float[Array, "r r"]  # datum cofactor of the scan poses and APs (AP block: invariant)
    prim_cofactor: tuple  # per family (n, p, p): diagonal blocks in the datum
    prim_cross: tuple  # per family (n, p, r): blocks with the scan poses and APs, in the datum
    Qfull: object  # dense datum cofactor matrix of all unknowns, or None
    residuals: tuple  # per family (m, 3): observation residuals [m, rad, rad]
    redundancy: tuple  # per family (m, 3)
    redundancy_prior: tuple  # per family (n, q)
    # Orientation pseudo-observations per scan: tilt readings (omega_c, phi_c) and kappa.
    redundancy_levelling: Float[Array, "s 3"]
    misclosure: tuple  # per family (m, rows): whitened residual rows at the solution
    dependent: object
    pivots: object  # 1 - R^2 of every reduced parameter (rank test)
    K_over_N: object  # diag(K) / diag(N_zz): share of a parameter the primitives do not explain
    ap_influence: tuple = ()  # per family (m, rows, a): dx_AP / sigma_AP for a 1-sigma error
    redundancy_ap_prior: object = None  # (a,): of the AP priors (0 where none)
    # Orientation pseudo-observations per scan (s, 3): residuals v = f(x) - l [rad] (also where
    # not observed) and weights (0: not observed), for the result's table of constraints.
    orientation_residuals: object = None
    orientation_weight: object = None


def w_tests(
    residuals: np.ndarray,
    sigmas: np.ndarray,
    redundancy: np.ndarray,
    *,
    min_redundancy: float = MIN_TESTABLE_REDUNDANCY,
) -> np.ndarray:
    """Baarda's ``w_i = v_i / (sigma_i sqrt(r_i))`` (Baarda 1968); NaN where ``r_i`` is at most
    ``min_redundancy`` (an observation with no redundancy cannot be tested; the minimal
    detectable bias is infinite there, :func:`minimal_detectable_bias`)."""
    r = np.asarray(redundancy, dtype=float)
    ok = r > min_redundancy
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(
            ok, np.asarray(residuals) / (np.asarray(sigmas) * np.sqrt(np.where(ok, r, 1.0))), np.nan
        )


def condition_w_tests(
    residuals: np.ndarray,
    sigmas: np.ndarray,
    redundancy: np.ndarray,
    *,
    min_redundancy: float = MIN_TESTABLE_REDUNDANCY,
) -> np.ndarray:
    """Baarda's w-test of one Gauss-Helmert condition per point (a plane point, SPEC sections 4
    and 7), (m,): ``w_i = e_i / sqrt(r_i)`` with ``e_i`` the whitened condition at the solution,
    ``e_i^2 = sum_k (v_k / sigma_k)^2`` (its share of ``v^T P v``), and ``r_i = sum_k r_k`` the
    condition's redundancy number; signed as the range residual. ``residuals``, ``sigmas``,
    ``redundancy`` (m, 3). NaN where ``r_i`` is at most ``min_redundancy``."""
    v, s = np.asarray(residuals, dtype=float), np.asarray(sigmas, dtype=float)
    with np.errstate(invalid="ignore", divide="ignore"):
        e = np.sqrt(np.sum(np.where(s > 0, v / np.where(s > 0, s, 1.0), 0.0) ** 2, axis=-1))
    return w_tests(
        np.where(v[:, 0] < 0, -e, e),
        np.ones(len(e)),
        np.sum(redundancy, axis=-1),
        min_redundancy=min_redundancy,
    )


def external_reliability(influence, redundancy, mask, delta0: float, ap_names):
    """Baarda's external reliability of every observation: the largest change of an AP caused
    by an undetected MDB-sized error, ``delta0 / sqrt(r_i)`` times the AP influence of a
    one-sigma error (:func:`quality_from`), in a priori AP sigmas, and the name of
    that AP. ``influence`` (n, 3, a), ``redundancy`` and ``mask`` (n, 3). Inf where an observation
    has no redundancy (no error of any size is detected), NaN where it is not used."""
    n = mask.shape[0]
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(
            redundancy > MIN_TESTABLE_REDUNDANCY,
            delta0 / np.sqrt(np.where(redundancy > MIN_TESTABLE_REDUNDANCY, redundancy, 1.0)),
            np.inf,
        )
    if not influence.shape[-1]:
        return np.zeros((n, 3)), np.full((n, 3), "", dtype=object)
    ext_all = np.abs(influence) * np.where(np.isfinite(scale), scale, 0.0)[..., None]
    ext = np.where(mask & np.isfinite(scale), ext_all.max(axis=-1), np.where(mask, np.inf, np.nan))
    ext_ap = np.array(ap_names, dtype=object)[ext_all.argmax(axis=-1)]
    return ext, ext_ap


def _quad(Jl, Q, Jr):
    """``diag(Jl Q Jr^T)`` per observation, (..., k). The sums are written out over the small
    axes: XLA then makes one loop of the whole expression, where ``jnp.sum`` or ``einsum``
    sends each reduction to a library kernel that is slow at these shapes on CPU (measured:
    13 ms less in a plane adjustment of 39k conditions, 76 against 89 ms)."""
    if Q.shape[-2] > UNROLL_MAX:  # a long sum (the APs): one reduction, a smaller program
        T = jnp.sum(Jl[..., :, :, None] * Q[..., None, :, :], axis=-2)
    else:
        T = sum(Jl[..., :, i, None] * Q[..., None, i, :] for i in range(Q.shape[-2]))
    if Q.shape[-1] > UNROLL_MAX:
        return jnp.sum(T * Jr, axis=-1)
    return sum(T[..., j] * Jr[..., j] for j in range(Q.shape[-1]))


def _scan_blocks(Qzz, ns):
    """Per-scan diagonal blocks (s, 6, 6), scan-AP blocks (s, 6, a) and the AP block of Q_zz."""
    Qs = Qzz[: 6 * ns].reshape(ns, 6, -1)
    Tss = Qs[:, :, : 6 * ns].reshape(ns, 6, ns, 6)[jnp.arange(ns), :, jnp.arange(ns), :]
    return Tss, Qs[:, :, 6 * ns :], Qzz[6 * ns :, 6 * ns :]


def _family_quality(spec, problem, params, fi, red, Qzz, r):
    """Residuals, redundancy numbers, AP influence and prior redundancy of one family from its
    linearised rows ``r`` (:class:`._normal.Rows`); the diagonal of ``J Q J^T`` gathers only the
    blocks each observation touches."""
    fam = problem.families[fi]
    ns = spec.n_scans
    Jp, Js, Ja = r.Jp, r.Js, r.Ja
    Y = red.Y[fi]
    Qpz = -mm(Y, Qzz)  # (n, p, r)
    Qpp = red.Npp_inv[fi] - bmm(Qpz, jnp.swapaxes(Y, -1, -2))  # Ninv + Y Qzz Y^T
    Tss, Tsa, Taa = _scan_blocks(Qzz, ns)
    at = lambda v, by: fam.at_rows(problem, fi, v, by)
    Qps = jnp.swapaxes(Qpz[:, :, : 6 * ns].reshape(fam.n, fam.p, ns, 6), 1, 2)  # (n, s, p, 6)
    Qps_obs = at(Qps, "pair")
    Qpa_obs = at(Qpz[:, :, 6 * ns :], "prim")  # (m, p, a)
    Tsa_obs = at(Tsa, "scan")
    JQJ = (
        _quad(Jp, at(Qpp, "prim"), Jp)
        + 2 * _quad(Jp, Qps_obs, Js)
        + 2 * _quad(Jp, Qpa_obs, Ja)
        + _quad(Js, at(Tss, "scan"), Js)
        + 2 * _quad(Js, Tsa_obs, Ja)
        + _quad(Ja, jnp.broadcast_to(Taa, (Ja.shape[0],) + Taa.shape), Ja)
    )
    v, redundancy, n_active, vtpv = fam.observation_quality(spec, problem, params, fi, JQJ, r)
    # External reliability: Q_(a, touched) J^T for every observation row, in AP sigmas; the
    # per-observation products written out (:func:`._linalg.bmm`), the one with the shared
    # AP block as a matrix product.
    infl = bmm(Jp, Qpa_obs) + bmm(Js, Tsa_obs) + mm(Ja, Taa)
    sa = jnp.sqrt(jnp.clip(jnp.diagonal(Taa), 0.0, None))
    influence = jnp.where(sa > 0, infl / jnp.where(sa > 0, sa, 1.0), 0.0)
    P = params.prims[fi]
    pr, Jpr = fam.prior_residuals(P), fam.prior_jacobian(P)
    active = jnp.any(Jpr != 0, axis=-1)
    redundancy_prior = jnp.where(active, 1.0 - _quad(Jpr, Qpp, Jpr), 0.0)
    return dict(
        v=v,
        redundancy=redundancy,
        influence=influence,
        redundancy_prior=redundancy_prior,
        misclosure=r.e,
        n=n_active + jnp.sum(active) + fam.hard_constraints(),
        vtpv=vtpv + jnp.sum(pr**2),
    )


def linearisation_at(spec: Spec, problem: Problem, params: Params, rank_tolerance, state=None):
    """The undamped :class:`._solver.Linearisation` at ``params`` (of a problem on its grid),
    with the families' states ``state`` (default: settled at ``params``,
    :func:`._families.settled_state`: the Gauss-Helmert residuals of the solution)."""
    if state is None:
        state = settled_state(spec, problem, params)
    blocks, rows = linearise_rows(spec, problem, params, state=state)
    Hp, Hz = null_space(spec, problem.families, params)
    red = reduce(spec, problem, blocks, Hz, jnp.asarray(0.0), rank_tolerance)
    return Linearisation(rows, Hp, Hz, red)


def quality(
    spec: Spec, problem: Problem, params: Params, rank_tolerance, full_covariance: bool = False
) -> Quality:
    """Quality of the adjustment at ``params`` (SPEC section 7); see the module docstring."""
    grid = on_grid(problem)
    lin = linearisation_at(spec, grid, params, rank_tolerance)
    return quality_from(spec, problem, grid, params, lin, full_covariance)


def quality_from(spec, problem, grid, params, lin, full_covariance: bool = False) -> Quality:
    """:func:`quality` from the linearisation the solver's loop ends with; ``grid`` is
    ``problem`` on its grid (the per-observation results come back in ``problem``'s order)."""
    red, Hp, Hz = lin.reduced, lin.Hp, lin.Hz
    dep = red.dependent
    Qzz = reduced_cofactor(red)
    ns = spec.n_scans

    fams = [
        _family_quality(spec, grid, params, fi, red, Qzz, lin.rows[fi])
        for fi in range(len(grid.families))
    ]
    na = spec.n_aps
    n_obs = n_pseudo(grid, na) + sum(f["n"] for f in fams)
    vtpv = pseudo_cost(grid, params) + sum(f["vtpv"] for f in fams)
    n_unknowns = jnp.sum(~dep) + sum(P.size for P in params.prims)
    dof = n_obs - n_unknowns + Hz.shape[1]

    Jl = levelling_jacobian(grid, params.eops)  # (s, 3, 6)
    Tss, _, Taa = _scan_blocks(Qzz, ns)
    lw = orientation_observations(grid)[1]
    redundancy_levelling = jnp.where(lw > 0, 1.0 - _quad(Jl, Tss, Jl), 0.0)
    wa = ap_prior_weight(grid, na)
    redundancy_ap_prior = jnp.where(wa > 0, 1.0 - wa**2 * jnp.diagonal(Taa), 0.0)

    Ninv = red.Npp_inv
    if spec.inner and Hz.shape[1]:
        diag, cross, Qzz_d = inner_constraint_cofactor(Hp, Hz, Ninv, red.Y, Qzz)
    else:
        cross = tuple(-mm(Y, Qzz) for Y in red.Y)
        diag = tuple(Ni - bmm(c, jnp.swapaxes(Y, -1, -2)) for Ni, c, Y in zip(Ninv, cross, red.Y))
        Qzz_d = Qzz
    zero = dep[:, None] | dep[None, :]
    Qfull = _full_cofactor(spec, red, Qzz, Hp, Hz) if full_covariance else None
    K_over_N = jnp.diagonal(red.Ks) - (jnp.diagonal(_closure(red, Hz)) if Hz.shape[1] else 0.0)
    back = lambda key: from_grid(problem, tuple(f[key] for f in fams))
    return Quality(
        vtpv=vtpv,
        dof=jnp.asarray(dof, dtype=jnp.float64),
        n_observations=jnp.asarray(n_obs, dtype=jnp.float64),
        Qzz=jnp.where(zero, 0.0, Qzz_d),
        prim_cofactor=diag,
        prim_cross=tuple(jnp.where(dep[None, None, :], 0.0, c) for c in cross),
        Qfull=Qfull,
        residuals=back("v"),
        redundancy=back("redundancy"),
        redundancy_prior=tuple(f["redundancy_prior"] for f in fams),
        redundancy_levelling=redundancy_levelling,
        redundancy_ap_prior=redundancy_ap_prior,
        misclosure=back("misclosure"),
        dependent=dep,
        pivots=red.pivots,
        K_over_N=K_over_N,
        ap_influence=back("influence"),
        orientation_residuals=orientation_residual(grid, params.eops),
        orientation_weight=lw,
    )


def reduced_cofactor(red):
    """Cofactor matrix ``Q_zz`` of the scan poses and APs in the datum the reduced system was
    closed with: the inverse of the scaled reduced matrix (its Cholesky factor), scaled back,
    zero in the rows and columns of dependent (held or not estimable) parameters."""
    dep = red.dependent
    Qs = cholesky_inverse(red.L)
    Qs = jnp.where(dep[:, None] | dep[None, :], 0.0, Qs)
    return Qs * red.scale[:, None] * red.scale[None, :]


def pose_ap_cofactor(spec: Spec, problem: Problem, params: Params, rank_tolerance):
    """Cofactor matrix (sigma0 = 1) of the scan poses and APs, (6s + a, 6s + a), from one
    linearisation at ``params`` (no iteration): segment-sum assembly, Schur elimination of the
    primitives, Cholesky of the reduced system (:mod:`._normal`), in the inner-constraint
    datum on the primitives (S-transformed, :func:`tlsjax._model._datum.inner_constraint_cofactor`)
    when the spec says so, else in the problem's datum. A negative ``rank_tolerance`` declares
    no parameter dependent: the result is then a smooth function of the inputs (design
    optimisation), and a parameter the network cannot determine gets a huge variance."""
    blocks = linearise(spec, problem, params)
    Hp, Hz = null_space(spec, problem.families, params)
    red = reduce(spec, problem, blocks, Hz, jnp.asarray(0.0), jnp.asarray(rank_tolerance))
    Q = reduced_cofactor(red)
    if spec.inner and Hz.shape[1]:
        _, _, Q = inner_constraint_cofactor(Hp, Hz, red.Npp_inv, red.Y, Q)
    return Q


def _closure(red, Hz):
    """The datum closure ``Q Q^T`` that :func:`reduce` added to the scaled reduced matrix."""
    ok = red.scale > 0
    return datum_projector(Hz / jnp.where(ok, red.scale, 1.0)[:, None])


def _full_cofactor(spec, red, Qzz, Hp, Hz):
    """Dense cofactor matrix of [primitives..., EOPs, APs] in the datum (S-transformed to inner
    constraints in a free network); u^2 memory, only when asked for (and as the dense check of
    the blockwise path)."""
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


class Summary(Module):
    """The estimable part of the quality that a Monte Carlo realisation needs (SPEC section 9):
    ``v^T P v``, the redundancy ``r = n - u + d``, the AP cofactor block (datum invariant) and
    the parameters the rank test found dependent."""

    vtpv: Float[Array, ""]
    dof: Float[Array, ""]
    Qaa: Float[Array, "a a"]
    dependent: object


def summary(spec: Spec, problem: Problem, params: Params, rank_tolerance) -> Summary:
    """:func:`quality` reduced to what is estimable and small (see :func:`summary_from`)."""
    grid = on_grid(problem)
    return summary_from(spec, grid, params, linearisation_at(spec, grid, params, rank_tolerance))


def summary_from(spec: Spec, grid: Problem, params: Params, lin, vtpv=None) -> Summary:
    """No observation-space or primitive blocks: ``Q_aa`` comes from the AP columns of the
    triangular inverse, ``W = L^-1 E_a`` (the inverse of L's trailing AP block), ``Q_aa = W^T
    W`` (scaled back), instead of the whole ``L^-T L^-1``; ``v^T P v`` from the
    linearisation's rows."""
    red = lin.reduced
    dep = red.dependent
    a0 = 6 * spec.n_scans
    # L^-1 is lower triangular: its AP columns are the inverse of L's trailing block.
    W = triangular_inverse(red.L[a0:, a0:])
    s = red.scale[a0:]
    Qaa = (W.T @ W) * s[:, None] * s[None, :]
    Qaa = jnp.where(dep[a0:, None] | dep[None, a0:], 0.0, Qaa)
    n_unknowns = jnp.sum(~dep) + sum(P.size for P in params.prims)
    dof = count_observations(grid, params) - n_unknowns + lin.Hz.shape[1]
    if vtpv is None:  # the linearisation is at params
        vtpv = linearised_cost(grid, params, lin.rows)
    return Summary(vtpv, jnp.asarray(dof, dtype=jnp.float64), Qaa, dep)
