"""The unknowns and data of the compiled adjustment, and one object per primitive family.

Unknowns: primitives (targets, scale bars, planes) in families of fixed block size p, scan poses
(6 per scan) and APs. A family holds the observations of its primitives with their weights
(1/sigma; 0 = removed) and the index plan built once on the host: which observations share a
primitive, which (primitive, scan) pairs exist. Each family supplies, for the solver and the
quality pass, what differs between kinds of primitive:

* ``residual``: the whitened residual rows of one observation (SPEC sections 2 and 4);
* ``prior``: the per-primitive pseudo-observations (control points, scale-bar lengths, the
  unit-normal constraint of a plane);
* ``motion``: the rigid-motion action on one primitive, whose derivative gives the datum's
  null-space columns (:mod:`tlsjax._model._datum`);
* ``observation_quality``: residuals and redundancy numbers in observation space.

The solver and the quality pass loop over families and never ask which kind they hold.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._model._aps import corrected_observations
from .._model._datum import move_plane, move_points
from .._model._geometry import (
    cartesian_from_spherical,
    is_face2,
    rotation_matrix,
    spherical_from_cartesian,
    wrap_angle,
)
from .._model._levelling import compensator_reading
from .._model._planes import (
    condition_variance,
    unit_normal_constraint,
    whitened_condition,
)
from .._model._points import point_misclosure

#: vmap axes of :meth:`Family.residual` over the observations of a family.
OBS_AXES = (0, 0, None, 0, 0, 0, 0)


class Spec(eqx.Module):
    """Static description of the model: instruments, AP blocks, datum defect columns.

    Every field is static: a compiled adjustment is specialised on it (and only on it), so it is
    the key of the compilation cache (the scanners carry the identity of their AP terms).
    """

    scanners: tuple = eqx.field(static=True)
    ap_names: tuple = eqx.field(static=True)
    ap_slices: tuple = eqx.field(static=True)
    n_scans: int = eqx.field(static=True)
    datum_columns: tuple = eqx.field(static=True)  # rigid motions that leave the data invariant
    inner: bool = eqx.field(static=True)  # inner constraints on the primitives

    @property
    def n_aps(self) -> int:
        return self.ap_slices[-1][1] if self.ap_slices else 0

    @property
    def r(self) -> int:
        return 6 * self.n_scans + self.n_aps


class Family(eqx.Module):
    """Observations of one family of eliminated primitives and their index plan.

    ``obs`` (m, 3) = (rho, theta, alpha), ``weight`` = 1/sigma (m, 3), ``prim``, ``point``,
    ``scan``, ``pair`` (m,), ``pair_prim``/``pair_scan`` of the (primitive, scan) pairs.
    """

    obs: Float[Array, "m 3"]
    weight: Float[Array, "m 3"]
    prim: Int[Array, " m"]
    point: Int[Array, " m"]
    scan: Int[Array, " m"]
    pair: Int[Array, " m"]
    pair_prim: Int[Array, " q"]
    pair_scan: Int[Array, " q"]

    #: Whitened residual rows per observation.
    rows: ClassVar[int] = 3
    #: True when ``d residual / d AP`` does not change during an adjustment (taken once).
    constant_ap_jacobian: ClassVar[bool] = True
    #: True when a step's acceptance must compare costs at the linearisation point's weights.
    frozen_cost: ClassVar[bool] = False

    @property
    def n(self) -> int:
        return self.prior_args()[0].shape[0]

    def observation_args(self, problem, params, fi):
        """Per-observation arguments of :meth:`residual`, in the order of ``OBS_AXES``."""
        P = params.prims[fi]
        inst = problem.scan_instrument[self.scan]
        return (
            P[self.prim],
            params.eops[self.scan],
            params.aps,
            self.obs,
            self.weight,
            self.point,
            inst,
        )

    def at_rows(self, problem, fi, v, by: str):
        """Per-primitive (n, ...), per-scan (s, ...) or per-pair (n, s, ...) values ``v`` at
        the family's rows (``by`` = "prim", "scan" or "pair"): on the family's grid a broadcast
        over the slots, which XLA fuses into the consumer (no gather, no copy); a gather
        otherwise."""
        grid = problem.grids[fi] if problem.grids else None
        tail = v.shape[2 if by == "pair" else 1 :]
        if not grid:
            return v[
                {"prim": (self.prim,), "scan": (self.scan,), "pair": (self.prim, self.scan)}[by]
            ]
        n, ns, c = grid
        lead = {"prim": (n, 1, 1), "scan": (1, ns, 1), "pair": (n, ns, 1)}[by]
        v = jnp.broadcast_to(v.reshape(lead + tail), (n, ns, c) + tail)
        return v.reshape((n * ns * c,) + tail)

    def ap_block(self, spec, problem, params, fi):
        """``d e / d AP`` (m, rows, a) when it is constant in an adjustment
        (``constant_ap_jacobian``), else None."""
        return None

    def residuals(self, spec, problem, params, fi, unit_weight: bool = False, ap_jac=None):
        """Whitened residual rows of every observation, (m, rows)."""
        args = list(self.observation_args(problem, params, fi))
        if unit_weight:
            args[4] = jnp.ones_like(self.weight)
        return jax.vmap(lambda *a: self.residual(spec, *a), in_axes=OBS_AXES)(*args)

    def linear_rows(self, spec, problem, params, fi, ap_jac=None):
        """Whitened residual rows and their Jacobian blocks w.r.t. the primitive, the pose and
        the APs (``ap_jac``: the constant AP block, if the family has one), plus what the
        quality pass reports as the observation residual: (e, Jp, Js, Ja, raw)."""
        args = self.observation_args(problem, params, fi)
        f = lambda *a: (lambda r: (r, r))(self.residual(spec, *a))
        if ap_jac is None:
            (Jp, Js, Ja), e = jax.vmap(
                jax.jacfwd(f, argnums=(0, 1, 2), has_aux=True), in_axes=OBS_AXES
            )(*args)
        else:
            (Jp, Js), e = jax.vmap(jax.jacfwd(f, argnums=(0, 1), has_aux=True), in_axes=OBS_AXES)(
                *args
            )
            Ja = ap_jac
        return e, Jp, Js, Ja, e

    def prior_residuals(self, P):
        return jax.vmap(self.prior)(P, *self.prior_args())

    def prior_jacobian(self, P):
        return jax.vmap(jax.jacfwd(self.prior))(P, *self.prior_args())

    def cost_rows(self, spec, problem, params, fi, frozen, ap_jac=None):
        """Rows whose squares a step's acceptance compares (the residuals unless the family
        holds weights at the linearisation point; ``frozen``: its :class:`._normal.Rows`)."""
        return self.residuals(spec, problem, params, fi, ap_jac=ap_jac)

    def tangent_gradient(self, P, b):
        """The part of a gradient ``b`` (n, p) that moves the primitives along their
        constraint manifold (identity here). At a constrained solution the rest is the
        constraint's reaction, which the retraction removes from every step."""
        return b

    def frozen_rows(self, rows, frozen):
        """:meth:`cost_rows` from the rows already evaluated at the new estimate (``rows``) and
        those of the linearisation point (``frozen``), with no further residual evaluation."""
        return rows.e

    def active_rows(self):
        """Which residual rows are observations in the adjustment (weight > 0), (m, rows)."""
        return self.weight > 0

    def retract(self, P):
        """The primitives after an update, on their constraint manifold (identity here)."""
        return P

    def rounding(self):
        """Rounding error of the whitened residuals, (m, rows): float64 resolves an observation
        to ``eps |l|``; this sets how small an update can usefully be (noise-free data)."""
        return np.finfo(np.float64).eps * jnp.abs(self.obs) * self.weight


class PointFamily(Family):
    """Primitives made of ``k`` points (k = 1 targets, k = 2 scale bars; SPEC section 2).

    Per primitive: control coordinates with weights (0 = none) and, for scale bars, the bar
    length with its weight.
    """

    ctrl_xyz: Float[Array, "n k 3"]
    ctrl_weight: Float[Array, "n k 3"]
    bar_length: Float[Array, " n"]
    bar_weight: Float[Array, " n"]
    k: int = eqx.field(static=True)

    @property
    def p(self) -> int:
        return 3 * self.k

    def residual(self, spec, P, eop, aps, l, w, point, inst):
        """``wrap(F(X, EOP) + Delta(l) - l) / sigma`` (Chow et al. 2013, eqs. 1-3)."""
        X = P.reshape(self.k, 3)[point]
        f = point_misclosure(X, eop, aps, l, spec.scanners, spec.ap_names, spec.ap_slices, inst)
        return f * w

    def ap_block(self, spec, problem, params, fi):
        """The AP bases at the observations, ``d f / d AP`` of the *unweighted* misclosure
        (m, 3, a): Delta is linear in the AP coefficients with its bases evaluated at the
        observations (SPEC section 2), so this is constant in an adjustment; taken once.
        Forward mode: reverse mode is 7 % faster for one 23-AP adjustment but 2.4x slower under
        the Monte Carlo vmap (measured)."""
        args = list(self.observation_args(problem, params, fi))
        args[4] = jnp.ones_like(self.weight)
        jac = jax.jacfwd(lambda *a: self.residual(spec, *a), argnums=2)
        return jax.vmap(jac, in_axes=OBS_AXES)(*args)

    def residuals(self, spec, problem, params, fi, unit_weight: bool = False, ap_jac=None):
        if ap_jac is None:
            return Family.residuals(self, spec, problem, params, fi, unit_weight)
        f = self._misclosure(spec, problem, params, fi, ap_jac, jacobian=False)[0]
        return f if unit_weight else f * self.weight

    def _misclosure(self, spec, problem, params, fi, ap_basis, jacobian: bool):
        """The unweighted misclosure ``f = wrap(sph(x) + B_a a - l)``, ``x = R (X - S)``, and
        (``jacobian``) its blocks ``d f / d X``, ``d f / d pose`` by the chain rule.

        The point model ``F = sph(x)`` with the rotation taken once per scan (and on the grid,
        with the scan as an axis: no gathers), ``d sph / d x`` per observation (``jacfwd`` with
        3 tangents), ``J_X = J_x R``, ``J_S = -J_x R``, ``J_angles = J_x (dR/dangle) (X - S)``;
        ``Delta = B_a a`` with the constant AP bases ``B_a`` (:meth:`ap_block`). The same
        numbers as ``jacfwd`` of :func:`point_misclosure` (tested), with a third of its
        arithmetic and no rotation matrix per observation.
        """
        E = params.eops
        rot = lambda a: rotation_matrix(a[0], a[1], a[2])
        R = jax.vmap(rot)(E[:, 3:])  # (s, 3, 3)
        X = params.prims[fi].reshape(-1, self.k, 3)
        X = X[:, 0] if self.k == 1 else X[self.prim, self.point]
        pano = np.array([sc.architecture == "panoramic" for sc in spec.scanners])
        face2 = jnp.asarray(pano)[problem.scan_instrument[self.scan]] & is_face2(self.obs[:, 2])
        grid = problem.grids[fi] if problem.grids else None
        if grid:
            n, ns, c = grid
            Xg = X[:, None, None, :] if self.k == 1 else X.reshape(n, ns, c, 3)
            d = Xg - E[None, :, None, :3]  # (n, s, c, 3)
            x = jnp.einsum("sij,nscj->nsci", R, d).reshape(-1, 3)
        else:
            X = X[self.prim] if self.k == 1 else X
            d = X - E[self.scan, :3]
            x = jnp.einsum("mij,mj->mi", R[self.scan], d)
        sph = lambda x_, f2: (lambda F: (F, F))(spherical_from_cartesian(x_, f2))
        if jacobian:
            Jx, F = jax.vmap(jax.jacfwd(sph, has_aux=True))(x, face2)  # (m, 3, 3)
        else:
            F = spherical_from_cartesian(x, face2)
        f = F + jnp.einsum("mka,a->mk", ap_basis, params.aps) - self.obs
        f = f.at[:, 1:].set(wrap_angle(f[:, 1:]))
        if not jacobian:
            return (f,)
        dR = jax.vmap(jax.jacfwd(rot))(E[:, 3:])  # (s, 3, 3, 3): d R_ij / d angle_k
        if grid:
            Jx5 = Jx.reshape(n, ns, c, 3, 3)
            JX = jnp.einsum("nscij,sjk->nscik", Jx5, R).reshape(-1, 3, 3)
            dRd = jnp.einsum("sjlk,nscl->nscjk", dR, d)
            Jang = jnp.einsum("nscij,nscjk->nscik", Jx5, dRd).reshape(-1, 3, 3)
        else:
            JX = jnp.einsum("mij,mjk->mik", Jx, R[self.scan])
            Jang = jnp.einsum("mij,mjk->mik", Jx, jnp.einsum("mjlk,ml->mjk", dR[self.scan], d))
        Js = jnp.concatenate([-JX, Jang], axis=-1)
        if self.k == 1:
            Jp = JX
        else:  # the observed end of a scale bar
            one = jax.nn.one_hot(self.point, self.k, dtype=JX.dtype)
            Jp = (one[:, None, :, None] * JX[:, :, None, :]).reshape(JX.shape[0], 3, -1)
        return f, Jp, Js

    def linear_rows(self, spec, problem, params, fi, ap_jac=None):
        """As :meth:`Family.linear_rows`, with the unweighted misclosure ``f`` whitened after
        (``e = f w``, ``J = J_f w``): ``raw = f`` is the residual ``F + Delta - l`` even of a
        removed (weight-0) observation. See :meth:`_misclosure`; ``ap_jac`` is the AP block of
        :meth:`ap_block` (taken here when not given)."""
        B = self.ap_block(spec, problem, params, fi) if ap_jac is None else ap_jac
        raw, Jp, Js = self._misclosure(spec, problem, params, fi, B, jacobian=True)
        w = self.weight[:, :, None]
        return raw * self.weight, Jp * w, Js * w, B * w, raw

    def prior_args(self):
        return (self.ctrl_xyz, self.ctrl_weight, self.bar_length, self.bar_weight)

    def prior(self, P, cx, cw, L, lw):
        pts = P.reshape(self.k, 3)
        out = ((pts - cx) * cw).reshape(-1)
        if self.k == 2:
            d = jnp.sqrt(jnp.sum((pts[0] - pts[1]) ** 2))
            out = jnp.concatenate([out, ((d - L) * lw)[None]])
        return out

    def motion(self, P, motion):
        return move_points(P, motion)

    def observation_quality(self, spec, problem, params, fi, JQJ, rows):
        """Residuals ``v = F + Delta - l`` [m, rad, rad] (a removed observation keeps its
        misclosure, so that a rejected blunder can be reported), redundancy numbers
        ``1 - (J Q J^T)_ii``, the number of active observations and their ``v^T P v``.
        ``rows``: the linearisation of :meth:`linear_rows` at ``params``."""
        raw = rows.raw
        active = self.active_rows()
        redundancy = jnp.where(active, 1.0 - JQJ, 0.0)
        return raw, redundancy, jnp.sum(active), jnp.sum((raw * self.weight) ** 2)


def _dot3(a, b):
    """``sum(a * b, axis=-1)`` over an axis of 3, written out: XLA then fuses it with its
    operands (a reduction of these shapes goes to a separate, slower library kernel on CPU)."""
    return a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1] + a[..., 2] * b[..., 2]


class PlaneFamily(Family):
    """Planes ``(n_x, n_y, n_z, d)``, one Gauss-Helmert condition per point (SPEC section 4).

    The condition is whitened by ``sqrt(m)``, ``m = B Sigma B^T``, held fixed in the
    linearisation; the unit-normal constraint is a heavy pseudo-observation of weight
    ``unit_weight`` (counted in the degrees of freedom).
    """

    unit_weight: Float[Array, " n"]

    rows: ClassVar[int] = 1
    # The condition mixes the corrected observation with the plane and the pose, so d g / d AP
    # changes with them.
    constant_ap_jacobian: ClassVar[bool] = False
    # A Gauss-Helmert step holds M at its linearisation point; with M re-evaluated the step
    # can look like an ascent near the solution and Levenberg-Marquardt would stall.
    frozen_cost: ClassVar[bool] = True

    p: ClassVar[int] = 4

    def residual(self, spec, P, eop, aps, l, w, point, inst):
        return whitened_condition(
            P, eop, aps, l, w, spec.scanners, spec.ap_names, spec.ap_slices, inst
        )

    def _pair_geometry(self, problem, params, fi, jacobian: bool):
        """At the rows, from each (plane, scan) pair: the rotated normal ``u = R n`` and ``c =
        n . S - d`` (so ``g = u . x + c``); with ``jacobian`` also ``R``, ``S`` and ``du_k =
        dR_k n``. The rotation and its derivative are taken once per scan."""
        P, E = params.prims[fi], params.eops
        rot = lambda a: rotation_matrix(a[0], a[1], a[2])
        n, S = P[:, :3], E[:, :3]
        R = jax.vmap(rot)(E[:, 3:])  # (s, 3, 3)
        at = lambda v, by: self.at_rows(problem, fi, v, by)
        geo = dict(
            u=at(jnp.einsum("sij,nj->nsi", R, n), "pair"),
            c=at(n @ S.T - P[:, 3:], "pair"),
        )
        if jacobian:
            dR = jax.vmap(jax.jacfwd(rot))(E[:, 3:])  # (s, 3, 3, 3): dR_ij / d angle_k
            du = jnp.einsum("sijk,nj->nski", dR, n)
            geo.update(R=at(R, "scan"), S=at(S, "scan"), du=at(du, "pair"))
        return geo

    def _instruments(self, spec, problem):
        """Per instrument: (rows of its scans, AP names, AP slice, scanner)."""
        inst = problem.scan_instrument[self.scan]
        for i, (scanner, names, sl) in enumerate(zip(spec.scanners, spec.ap_names, spec.ap_slices)):
            yield inst == i, names, sl, scanner

    def _condition(self, spec, problem, params, fi):
        """The condition ``g = n . (R^T x + S) - d`` of every row, ``x = cart(l - Delta(l))``
        (:func:`tlsjax._model._planes.plane_condition`), rotations once per scan."""
        geo = self._pair_geometry(problem, params, fi, jacobian=False)
        g = jnp.zeros(self.obs.shape[0])
        for sel, names, (a, b), scanner in self._instruments(spec, problem):
            x = cartesian_from_spherical(
                corrected_observations(params.aps[a:b], names, self.obs, scanner)
            )
            g = jnp.where(sel, _dot3(geo["u"], x) + geo["c"], g)
        return g

    def linear_rows(self, spec, problem, params, fi, ap_jac=None):
        """The whitened condition ``e = g / sqrt(m)`` (m held) and its Jacobian blocks by the
        chain rule, with the rotation and its derivatives taken once per scan; returns (e, Jp,
        Js, Ja, raw = e, B) with ``B = dg/dl`` (m, 3) for the step's cost and the quality.

        Per instrument: ``y = l - Delta(l)``, ``x = cart(y)``. With ``X = R^T x + S`` and ``u =
        R n`` (``g = u . x + n . S - d``): ``dg/d(n, d) = (X, -1)``, ``dg/dS = n``, ``dg/d
        angle_k = x . (dR_k n)``; ``b = dg/dy = u^T dx/dy`` is the VJP of ``cart`` with ``u``,
        and ``(B, dg/da) = (b (I - dDelta/dl), -b dDelta/da)`` the VJP of ``y(l, a)`` with ``b``
        (the APs broadcast per row, so the VJP gives each row its own ``dg/da``); ``m = sum (B
        sigma)^2`` (SPEC section 4). No Jacobian of ``cart`` or ``Delta`` is formed. The same
        numbers as ``jacfwd`` of :func:`tlsjax._model._planes.whitened_condition` (tested).
        """
        geo = self._pair_geometry(problem, params, fi, jacobian=True)
        P = self.at_rows(problem, fi, params.prims[fi], "prim")
        n, d = P[:, :3], P[:, 3]
        m_rows = self.obs.shape[0]
        g, X, Jang, B = 0.0, 0.0, 0.0, 0.0
        Ja = jnp.zeros((m_rows, spec.n_aps))
        for sel, names, (a, b), scanner in self._instruments(spec, problem):
            coeffs = jnp.broadcast_to(params.aps[a:b], (m_rows, b - a))
            observed = lambda l, c, names=names, sc=scanner: corrected_observations(c, names, l, sc)
            y, pull_y = jax.vjp(observed, self.obs, coeffs)
            x, pull_x = jax.vjp(cartesian_from_spherical, y)
            (bv,) = pull_x(geo["u"])
            Bi, Jai = pull_y(bv)
            # Materialised once: otherwise XLA recomputes their trigonometry inside every
            # fusion that consumes them (measured: plane run 93 -> 77 ms, 39k conditions).
            x, Bi, Jai = jax.lax.optimization_barrier((x, Bi, Jai))
            Xi = _dot3(jnp.swapaxes(geo["R"], -1, -2), x[:, None, :]) + geo["S"]
            g = jnp.where(sel, _dot3(geo["u"], x) + geo["c"], g)
            X = jnp.where(sel[:, None], Xi, X)
            Jang = jnp.where(sel[:, None], _dot3(x[:, None, :], geo["du"]), Jang)
            B = jnp.where(sel[:, None], Bi, B)
            Ja = Ja.at[:, a:b].set(jnp.where(sel[:, None], Jai, 0.0))
        w = self._whitening(B)[:, None]
        e = g[:, None] * w
        Jp = jnp.concatenate([X, -jnp.ones_like(d)[:, None]], axis=-1) * w
        Js = jnp.concatenate([n, Jang], axis=-1) * w
        return e, Jp[:, None], Js[:, None], (Ja * w)[:, None], e, B

    def _variance_from(self, B):
        """``m = B Sigma_l B^T`` of each condition."""
        return jnp.sum((B * self._sigma()) ** 2, axis=-1)

    def _whitening(self, B):
        """``1 / sqrt(m)`` of the active rows, 0 for removed ones."""
        m = self._variance_from(B)
        active = self.active_rows()[:, 0]
        return jnp.where(active, 1.0 / jnp.sqrt(jnp.where(m > 0, m, 1.0)), 0.0)

    def prior_args(self):
        return (self.unit_weight,)

    def prior(self, P, uw):
        return (unit_normal_constraint(P) * uw)[None]

    def motion(self, P, motion):
        return move_plane(P, motion)

    def retract(self, P):
        """``(n, d) / |n|``: the same plane with a unit normal. A Gauss-Newton step satisfies the
        unit-normal constraint only to first order; its second-order error, times the heavy
        weight, would make Levenberg-Marquardt reject good steps (Maratos effect)."""
        return P / jnp.linalg.norm(P[:, :3], axis=1, keepdims=True)

    def active_rows(self):
        return jnp.any(self.weight > 0, axis=-1, keepdims=True)

    def rounding(self):
        eps = np.finfo(np.float64).eps
        return eps * jnp.sum(jnp.abs(self.obs) * self.weight, axis=-1, keepdims=True)

    def _sigma(self):
        w = self.weight
        return jnp.where(w > 0, 1.0 / jnp.where(w > 0, w, 1.0), 0.0)

    def _variance(self, spec, args, aps):
        P, E, _, l, _, _, inst = args
        sl = (spec.scanners, spec.ap_names, spec.ap_slices)
        return jax.vmap(
            lambda P_, E_, l_, s_, i_: condition_variance(P_, E_, aps, l_, s_, *sl, i_)
        )(P, E, l, self._sigma(), inst)

    def cost_rows(self, spec, problem, params, fi, frozen, ap_jac=None):
        """``g / sqrt(m)`` at ``params`` with m of the linearisation point (``frozen``: its
        :class:`Rows`, whose ``B`` gives m)."""
        return (self._condition(spec, problem, params, fi) * self._whitening(frozen.B))[:, None]

    def tangent_gradient(self, P, b):
        """``b`` without its component along ``(n, 0)``, the gradient of ``|n|^2``: at the
        solution the observations pull each normal along itself with the constraint's
        Lagrange multiplier, and :meth:`retract` undoes every step's share of it."""
        a = jnp.concatenate([P[:, :3], jnp.zeros_like(P[:, 3:])], axis=-1)
        return b - a * (jnp.sum(a * b, axis=-1) / jnp.sum(a * a, axis=-1))[:, None]

    def frozen_rows(self, rows, frozen):
        """``g / sqrt(m)`` with m of the linearisation point: ``rows.e`` re-whitened."""
        w_new, w_old = self._whitening(rows.B), self._whitening(frozen.B)
        g = rows.e[:, 0] / jnp.where(w_new > 0, w_new, 1.0)
        return jnp.where(w_new > 0, g * w_old, 0.0)[:, None]

    def observation_quality(self, spec, problem, params, fi, JQJ, rows):
        """Gauss-Helmert residuals ``v = -Sigma_l B^T g / m`` of the three observations; the
        condition's redundancy ``1 - a Q a^T`` split over them in the ratio
        ``sigma_l^2 b_l^2 / m`` (so the three sum to at most 1, SPEC section 4)."""
        active = self.active_rows()[:, 0]
        B = rows.B
        m = self._variance_from(B)
        share = (self._sigma() * B) ** 2 / jnp.where(m > 0, m, 1.0)[:, None]
        redundancy = jnp.where(active, 1.0 - JQJ[:, 0], 0.0)[:, None] * share
        # The condition itself from the linearisation's whitened row, e = g / sqrt(m).
        m_ = jnp.where(m > 0, m, 1.0)
        g = rows.e[:, 0] * jnp.sqrt(m_)
        v = -(self._sigma() ** 2) * B * (g / m_)[:, None]
        return v, redundancy, jnp.sum(active), jnp.sum(rows.e**2)


class Problem(eqx.Module):
    """Everything the compiled adjustment needs: families, scans, levelling, fixed parameters.

    ``layouts``: per family a :class:`Layout` or None, chosen on the host from the static
    structure of the network (:func:`grid_layout`); the engine moves such a family onto its
    grid (:func:`on_grid`) and records the grid shape in ``grids``.
    """

    families: tuple
    scan_instrument: Int[Array, " s"]
    levelling: Float[Array, "s 2"]
    levelling_weight: Float[Array, "s 2"]
    fixed: Bool[Array, " r"]
    layouts: tuple = ()
    grids: tuple = eqx.field(static=True, default=())


class Params(eqx.Module):
    prims: tuple  # per family (n, p)
    eops: Float[Array, "s 6"]
    aps: Float[Array, " a"]


class Options(eqx.Module):
    """Numerical settings as traced arrays, so changing them never recompiles (see
    :class:`tlsjax.SolverOptions` for their meaning)."""

    max_iterations: Int[Array, ""]
    tolerance: Float[Array, ""]
    rank_tolerance: Float[Array, ""]
    damping_initial: Float[Array, ""]
    damping_increase: Float[Array, ""]
    damping_decrease: Float[Array, ""]
    damping_min: Float[Array, ""]
    damping_max: Float[Array, ""]


def levelling_residual(problem, eops):
    return (jax.vmap(compensator_reading)(eops) - problem.levelling) * problem.levelling_weight


def levelling_jacobian(problem, eops):
    # (s, 2, 6): whitened compensator residuals w.r.t. the scan's pose.
    return jax.vmap(jax.jacfwd(compensator_reading))(eops) * problem.levelling_weight[:, :, None]


def cost(spec, problem, params, frozen: tuple | None = None, ap_jac: tuple | None = None):
    """``v^T P v``: sum of squared whitened residuals, observations and pseudo-observations.

    ``frozen``: the :class:`._normal.Rows` per family of the linearisation point, at which
    families with ``frozen_cost`` hold their weights (a Gauss-Helmert step is accepted under
    its own M). ``ap_jac``: the constant AP blocks (``Family.ap_block``), if taken.
    """
    total = jnp.sum(levelling_residual(problem, params.eops) ** 2)
    for fi, fam in enumerate(problem.families):
        aj = None if ap_jac is None else ap_jac[fi]
        if frozen is not None and fam.frozen_cost:
            e = fam.cost_rows(spec, problem, params, fi, frozen[fi], aj)
        else:
            e = fam.residuals(spec, problem, params, fi, ap_jac=aj)
        total = total + jnp.sum(e**2) + jnp.sum(fam.prior_residuals(params.prims[fi]) ** 2)
    return total


def count_observations(problem, params):
    """Active scalar observations and pseudo-observations (one condition per plane point)."""
    n = jnp.sum(problem.levelling_weight > 0)
    for fi, fam in enumerate(problem.families):
        active_prior = jnp.any(fam.prior_jacobian(params.prims[fi]) != 0, axis=-1)
        n = n + jnp.sum(fam.active_rows()) + jnp.sum(active_prior)
    return n


class Layout(eqx.Module):
    """A family's observations on a regular grid of (primitive, scan, slot), ``shape`` = (n, s,
    c) with c the most observations of one primitive in one scan. Slot g holds family row
    ``rows[g]`` (``valid``) or is padding (weight 0, a real row of the same primitive so that
    its geometry stays finite); ``pos[i]`` is the slot of family row i.

    On the grid, every sum of the normal equations (per primitive, per scan, per pair) is a
    reshape and a sum over an axis: no segment sums or scatters, which XLA runs as serial loops
    on the CPU. It pays when most slots are real (every target seen in every scan; planes with
    similar numbers of points per scan).
    """

    rows: Int[Array, " g"]
    valid: Bool[Array, " g"]
    pos: Int[Array, " m"]
    shape: tuple = eqx.field(static=True)


#: A grid layout is used when at least this share of its slots holds real observations.
GRID_MIN_FILL = 0.5


def grid_layout(fam: Family, n_scans: int) -> Layout | None:
    """The grid :class:`Layout` of a family (host side, from its index plan), or None when
    fewer than ``GRID_MIN_FILL`` of the slots would be real."""
    prim, scan = np.asarray(fam.prim), np.asarray(fam.scan)
    n, m = fam.n, prim.shape[0]
    if m == 0:
        return None
    pair = prim * n_scans + scan
    counts = np.bincount(pair, minlength=n * n_scans)
    c = int(counts.max())
    if m < GRID_MIN_FILL * n * n_scans * c:
        return None
    order = np.argsort(pair, kind="stable")
    start = np.concatenate([[0], np.cumsum(counts)[:-1]])
    slot = pair[order] * c + (np.arange(m) - start[pair[order]])
    rows = np.full(n * n_scans * c, -1, dtype=np.int64)
    rows[slot] = order
    first = np.zeros(n, dtype=np.int64)
    first[prim[::-1]] = np.arange(m)[::-1]  # first row of each primitive
    valid = rows >= 0
    rows = np.where(valid, rows, first[np.arange(rows.size) // (n_scans * c)])
    pos = np.empty(m, dtype=np.int64)
    pos[order] = slot
    return Layout(rows, valid, pos, (n, n_scans, c))


def on_grid(problem: Problem) -> Problem:
    """The problem with every family that has a layout moved onto its grid (traced gathers;
    pure), and the grid shapes recorded in ``grids``."""
    if not problem.layouts:
        return problem
    fams, grids = [], []
    for fam, lay in zip(problem.families, problem.layouts):
        if lay is None:
            fams.append(fam)
            grids.append(None)
            continue
        n, ns, c = lay.shape
        slot = np.arange(n * ns * c)
        prim, scan = slot // (ns * c), (slot // c) % ns
        changes = dict(
            obs=fam.obs[lay.rows],
            weight=jnp.where(lay.valid[:, None], fam.weight[lay.rows], 0.0),
            prim=jnp.asarray(prim),
            point=fam.point[lay.rows],
            scan=jnp.asarray(scan),
            pair=jnp.asarray(prim * ns + scan),
            pair_prim=jnp.asarray(np.repeat(np.arange(n), ns)),
            pair_scan=jnp.asarray(np.tile(np.arange(ns), n)),
        )
        fams.append(
            eqx.tree_at(
                lambda f, c=changes: [getattr(f, k) for k in c], fam, list(changes.values())
            )
        )
        grids.append(lay.shape)
    return Problem(
        tuple(fams),
        problem.scan_instrument,
        problem.levelling,
        problem.levelling_weight,
        problem.fixed,
        (),
        tuple(grids),
    )


def from_grid(problem: Problem, per_family: tuple) -> tuple:
    """Per-observation arrays of a gridded problem back in each family's row order."""
    if not problem.layouts:
        return per_family
    return tuple(
        a if lay is None or a is None else a[lay.pos] for a, lay in zip(per_family, problem.layouts)
    )
