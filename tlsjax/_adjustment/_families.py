"""The unknowns and data of the compiled adjustment, and one object per primitive family.

Unknowns: primitives (targets, scale bars, planes) in families of fixed block size p, scan poses
(6 per scan) and APs. A family holds the observations of its primitives with their weights
(1/sigma; 0 = removed) and the index plan built once on the host: which observations share a
primitive, which (primitive, scan) pairs exist. Each family supplies, for the solver and the
quality pass, what differs between kinds of primitive:

* ``residual``: the whitened residual rows of one observation (SPEC sections 2 and 4);
* ``prior``: the per-primitive pseudo-observations (control points, scale-bar lengths);
* ``constraint_basis``, ``hard_constraints``: hard constraints on a primitive (a plane's unit
  normal), in null-space form: a step of the primitive is ``E delta``;
* ``state_init``, ``cost_state``, ``state_from_rows``: what a family carries through the
  iterations besides the unknowns (a Gauss-Helmert family: the residuals v at which it is
  linearised);
* ``motion``: the rigid-motion action on one primitive, whose derivative gives the datum's
  null-space columns (:mod:`tlsjax._model._datum`);
* ``observation_quality``: residuals and redundancy numbers in observation space.

The solver and the quality pass loop over families and never ask which kind they hold.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._linalg import bmm, matvec_t, mm, small_sum
from .._model._aps import corrected_observations
from .._model._datum import move_plane, move_points
from .._model._geometry import (
    cartesian_from_spherical,
    is_face2,
    rotation_matrix,
    spherical_from_cartesian,
    wrap_angle,
)
from .._model._levelling import orientation_reading
from .._model._planes import PROJECTION_STEPS, plane_step_basis, whitened_condition
from .._model._points import point_misclosure
from .._pytree import Module, field

#: vmap axes of :meth:`Family.residual` over the observations of a family.
OBS_AXES = (0, 0, None, 0, 0, 0, 0)


class Spec(Module):
    """Static description of the model: instruments, AP blocks, datum defect columns.

    Every field is static: a compiled adjustment is specialised on it (and only on it), so it is
    the key of the compilation cache (the scanners carry the identity of their AP terms).
    """

    scanners: tuple = field(static=True)
    ap_names: tuple = field(static=True)
    ap_slices: tuple = field(static=True)
    n_scans: int = field(static=True)
    datum_columns: tuple = field(static=True)  # rigid motions that leave the data invariant
    inner: bool = field(static=True)  # inner constraints on the primitives

    @property
    def n_aps(self) -> int:
        return self.ap_slices[-1][1] if self.ap_slices else 0

    @property
    def r(self) -> int:
        return 6 * self.n_scans + self.n_aps


class Family(Module):
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

    @property
    def n(self) -> int:
        return self.prior_args()[0].shape[0]

    def observation_args(self, problem, params, fi, state=None):
        """Per-observation arguments of :meth:`residual`, in the order of ``OBS_AXES``
        (``state``: the family's iteration state, :meth:`state_init`)."""
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

    def residuals(
        self, spec, problem, params, fi, unit_weight: bool = False, ap_jac=None, state=None
    ):
        """Whitened residual rows of every observation, (m, rows)."""
        args = list(self.observation_args(problem, params, fi, state))
        if unit_weight:
            args[4] = jnp.ones_like(self.weight)
        return jax.vmap(lambda *a: self.residual(spec, *a), in_axes=OBS_AXES)(*args)

    def linear_rows(self, spec, problem, params, fi, ap_jac=None, state=None):
        """Whitened residual rows and their Jacobian blocks w.r.t. the primitive, the pose and
        the APs (``ap_jac``: the constant AP block, if the family has one), plus what the
        quality pass reports as the observation residual: (e, Jp, Js, Ja, raw)."""
        args = self.observation_args(problem, params, fi, state)
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

    def state_init(self):
        """The family's state before the first step (None: it has none)."""
        return None

    def cost_state(self, spec, problem, params, fi, state, ap_jac=None):
        """The rows whose squares are ``v^T P v`` at ``params``, the family's next state and how
        far (in a priori sigmas) the state moved: (e, state, change)."""
        return self.residuals(spec, problem, params, fi, ap_jac=ap_jac), state, 0.0

    def state_from_rows(self, rows, state):
        """The next state and its change from the rows (:class:`._normal.Rows`) evaluated with
        ``state``: one update at the rows' unknowns."""
        return state, 0.0

    def rows_after(self, problem, fi, rows, dp, ds, da):
        """The rows (:class:`._normal.Rows`) moved to the end of a step ``(dp (n, p), ds (s, 6),
        da (a,))`` to first order, ``e + J dx``, for a family with a state (whose residuals are
        computed from the rows); the rows themselves otherwise."""
        return rows

    def constraint_basis(self, P):
        """Hard constraints on the primitives in null-space form, ``E`` (n, p, p - c), or None."""
        return None

    def hard_constraints(self) -> int:
        """Number of hard constraints on the family's primitives (counted in the dof)."""
        return 0

    def tangent_gradient(self, P, b):
        """The part of a gradient ``b`` (n, p) that moves the primitives along their
        constraint manifold (identity here). At a constrained solution the rest is the
        constraint's reaction, which the retraction removes from every step."""
        return b

    def active_rows(self, xp=jnp):
        """Which residual rows are observations in the adjustment (weight > 0), (m, rows);
        ``xp=np`` on the host."""
        return xp.asarray(self.weight) > 0

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
    k: int = field(static=True)

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

    def residuals(
        self, spec, problem, params, fi, unit_weight: bool = False, ap_jac=None, state=None
    ):
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
            x = matvec_t(jnp.swapaxes(R, -1, -2)[None, :, None], d).reshape(-1, 3)
        else:
            X = X[self.prim] if self.k == 1 else X
            d = X - E[self.scan, :3]
            x = matvec_t(jnp.swapaxes(R, -1, -2)[self.scan], d)
        sph = lambda x_, f2: (lambda F: (F, F))(spherical_from_cartesian(x_, f2))
        if jacobian:
            Jx, F = jax.vmap(jax.jacfwd(sph, has_aux=True))(x, face2)  # (m, 3, 3)
        else:
            F = spherical_from_cartesian(x, face2)
        f = F + mm(ap_basis, params.aps) - self.obs
        f = f.at[:, 1:].set(wrap_angle(f[:, 1:]))
        if not jacobian:
            return (f,)
        dR = jax.vmap(jax.jacfwd(rot))(E[:, 3:])  # (s, 3, 3, 3): d R_ij / d angle_k
        if grid:
            # The small products written out (:func:`._linalg.bmm`): no batched dots.
            Jx5 = Jx.reshape(n, ns, c, 3, 3)
            JX = bmm(Jx5, R[None, :, None]).reshape(-1, 3, 3)
            dRd = small_sum(dR[None, :, None] * d[:, :, :, None, :, None], -2)  # (n,s,c,3,3)
            Jang = bmm(Jx5, dRd).reshape(-1, 3, 3)
        else:
            JX = bmm(Jx, R[self.scan])
            Jang = bmm(Jx, small_sum(dR[self.scan] * d[:, None, :, None], -2))
        Js = jnp.concatenate([-JX, Jang], axis=-1)
        if self.k == 1:
            Jp = JX
        else:  # the observed end of a scale bar
            one = jax.nn.one_hot(self.point, self.k, dtype=JX.dtype)
            Jp = (one[:, None, :, None] * JX[:, :, None, :]).reshape(JX.shape[0], 3, -1)
        return f, Jp, Js

    def linear_rows(self, spec, problem, params, fi, ap_jac=None, state=None):
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

    The rigorous Gauss-Helmert iteration (:mod:`tlsjax._model._planes`): every linearisation is
    taken at the current unknowns and at the observations ``l + v`` of the current residuals
    v, the family's state in the solver's loop (:meth:`state_init`, :meth:`cost_state`); the row
    of a point is ``w / sqrt(m)`` with ``w = g(x, l + v) - B v``, ``m = B Sigma_l B^T``. The unit
    normal is a hard constraint: a step moves n in its tangent plane
    (:meth:`constraint_basis`: three unknowns per plane in the step, one constraint each in the
    degrees of freedom) and :meth:`retract` renormalises it.
    """

    n_planes: int = field(static=True)

    rows: ClassVar[int] = 1
    # The condition mixes the corrected observation with the plane and the pose, so d g / d AP
    # changes with them.
    constant_ap_jacobian: ClassVar[bool] = False

    p: ClassVar[int] = 4

    @property
    def n(self) -> int:
        return self.n_planes

    def observation_args(self, problem, params, fi, state=None):
        """As :meth:`Family.observation_args`, with the observations and the residuals of the
        current state stacked, (m, 2, 3): the linearisation point is ``l + v``."""
        args = Family.observation_args(self, problem, params, fi)
        lv = jnp.stack([self.obs, self.residual_state(state)], axis=1)
        return args[:3] + (lv,) + args[4:]

    def residual(self, spec, P, eop, aps, lv, w, point, inst):
        sl = (spec.scanners, spec.ap_names, spec.ap_slices, inst)
        return whitened_condition(P, eop, aps, lv[0], lv[1], w, *sl)

    def residual_state(self, state):
        """The residuals v (m, 3) at which the family is linearised (0 before the first step)."""
        return jnp.zeros_like(self.obs) if state is None else state

    def state_init(self):
        return jnp.zeros_like(self.obs)

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

    def _gauss_helmert(self, spec, problem, params, fi, state, jacobian: bool):
        """At ``(x, l + v)`` of every row: ``g``, ``B = dg/dl`` (m, 3), ``w = g - B v`` and ``m =
        B Sigma B^T``; with ``jacobian`` also ``X = R^T x + S``, ``dg/d angle`` and ``dg/da``.

        Per instrument: ``y = (l + v) - Delta(l + v)``, ``x = cart(y)``. With ``u = R n`` (``g
        = u . x + n . S - d``): ``b = dg/dy = u^T dx/dy`` is the VJP of ``cart`` with ``u``, and
        ``(B, dg/da) = (b (I - dDelta/dl), -b dDelta/da)`` the VJP of ``y(l, a)`` with ``b`` (the
        APs broadcast per row, so the VJP gives each row its own ``dg/da``). No Jacobian of
        ``cart`` or ``Delta`` is formed; the rotation and its derivatives are taken once per
        scan. The same numbers as ``jacfwd`` of
        :func:`tlsjax._model._planes.whitened_condition` (tested).
        """
        geo = self._pair_geometry(problem, params, fi, jacobian)
        v0 = self.residual_state(state)
        lhat = self.obs + v0
        m_rows = self.obs.shape[0]
        g, X, Jang, B = 0.0, 0.0, 0.0, 0.0
        Ja = jnp.zeros((m_rows, spec.n_aps))
        for sel, names, (a, b), scanner in self._instruments(spec, problem):
            coeffs = jnp.broadcast_to(params.aps[a:b], (m_rows, b - a))
            observed = lambda l, c, names=names, sc=scanner: corrected_observations(c, names, l, sc)
            y, pull_y = jax.vjp(observed, lhat, coeffs)
            x, pull_x = jax.vjp(cartesian_from_spherical, y)
            (bv,) = pull_x(geo["u"])
            Bi, Jai = pull_y(bv)
            # Materialised once: otherwise XLA recomputes their trigonometry inside every
            # fusion that consumes them (measured: plane run 93 -> 77 ms, 39k conditions).
            x, Bi, Jai = jax.lax.optimization_barrier((x, Bi, Jai))
            g = jnp.where(sel, _dot3(geo["u"], x) + geo["c"], g)
            B = jnp.where(sel[:, None], Bi, B)
            if jacobian:
                Xi = _dot3(jnp.swapaxes(geo["R"], -1, -2), x[:, None, :]) + geo["S"]
                X = jnp.where(sel[:, None], Xi, X)
                Jang = jnp.where(sel[:, None], _dot3(x[:, None, :], geo["du"]), Jang)
                Ja = Ja.at[:, a:b].set(jnp.where(sel[:, None], Jai, 0.0))
        return dict(g=g, B=B, w=g - _dot3(B, v0), m=self._variance_from(B), X=X, Jang=Jang, Ja=Ja)

    def linear_rows(self, spec, problem, params, fi, ap_jac=None, state=None):
        """The whitened Gauss-Helmert row ``e = w / sqrt(m)`` at ``(x, l + v)`` (``state`` = v)
        and its Jacobian blocks ``A / sqrt(m)`` by the chain rule (:meth:`_gauss_helmert`);
        returns (e, Jp, Js, Ja, raw = e, B) with ``B = dg/dl`` (m, 3) for the residuals and the
        quality. With ``X = R^T x + S``: ``dg/d(n, d) = (X, -1)``, ``dg/dS = n``, ``dg/d
        angle_k = x . (dR_k n)``."""
        t = self._gauss_helmert(spec, problem, params, fi, state, jacobian=True)
        P = self.at_rows(problem, fi, params.prims[fi], "prim")
        n = P[:, :3]
        w = self._whitening_of(t["m"])[:, None]
        e = t["w"][:, None] * w
        Jp = jnp.concatenate([t["X"], -jnp.ones_like(P[:, 3:])], axis=-1) * w
        Js = jnp.concatenate([n, t["Jang"]], axis=-1) * w
        return e, Jp[:, None], Js[:, None], (t["Ja"] * w)[:, None], e, t["B"]

    def cost_state(self, spec, problem, params, fi, state, ap_jac=None):
        """The rows ``w / sqrt(m)`` at ``(params, l + v0)`` (``state`` = v0), the next residuals
        ``v1 = -Sigma_l B^T w / m`` there (one Gauss-Helmert update at fixed unknowns) and
        ``max |v1 - v0| / sigma``, how far the residuals still move."""
        t = self._gauss_helmert(spec, problem, params, fi, state, jacobian=False)
        return self._state_update(t["w"], t["B"], t["m"], state)

    def _state_update(self, w, B, m, state):
        whiten = self._whitening_of(m)
        v1 = -(self._sigma() ** 2) * B * (w * whiten**2)[:, None]
        change = jnp.max(jnp.abs(v1 - self.residual_state(state)) * self.weight, initial=0.0)
        return (w * whiten)[:, None], v1, change

    def state_from_rows(self, rows, state):
        """The residual update and its size from a linearisation's rows (``e = w / sqrt(m)``)."""
        m = self._variance_from(rows.B)
        return self._state_update(
            rows.e[:, 0] * jnp.sqrt(jnp.where(m > 0, m, 1.0)), rows.B, m, state
        )[1:]

    def rows_after(self, problem, fi, rows, dp, ds, da):
        """The rows with ``e + J dx`` (and the reported residual, which is e): their
        Gauss-Helmert update (:meth:`state_from_rows`) is then ``v = -Sigma_l B^T M^-1 (A dx +
        w)`` with A, B, w and M of the rows at the step's start, the residuals of the step in the
        rigorous iteration (Lenzmann & Lenzmann 2004)."""
        at = lambda v, by: self.at_rows(problem, fi, v, by)
        Jdx = (
            jnp.sum(rows.Jp * at(dp, "prim")[:, None, :], axis=-1)
            + jnp.sum(rows.Js * at(ds, "scan")[:, None, :], axis=-1)
            + rows.Ja @ da
        )
        return dataclasses.replace(rows, e=rows.e + Jdx, raw=rows.raw + Jdx)

    def _variance_from(self, B):
        """``m = B Sigma_l B^T`` of each condition."""
        return jnp.sum((B * self._sigma()) ** 2, axis=-1)

    def _whitening_of(self, m):
        """``1 / sqrt(m)`` of the active rows, 0 for removed ones."""
        active = self.active_rows()[:, 0]
        return jnp.where(active, 1.0 / jnp.sqrt(jnp.where(m > 0, m, 1.0)), 0.0)

    def prior_args(self):
        return ()

    def prior(self, P):
        return jnp.zeros((0,), dtype=P.dtype)

    def constraint_basis(self, P):
        """``E`` (n, 4, 3): the unit normal as a hard constraint, a step is ``E delta``."""
        return jax.vmap(plane_step_basis)(P)

    def hard_constraints(self):
        return self.n_planes

    def motion(self, P, motion):
        return move_plane(P, motion)

    def retract(self, P):
        """``(n, d) / |n|``: the same plane with a unit normal (a step in the tangent plane
        keeps ``|n| = 1`` to first order)."""
        return P / jnp.linalg.norm(P[:, :3], axis=1, keepdims=True)

    def active_rows(self, xp=jnp):
        return xp.any(xp.asarray(self.weight) > 0, axis=-1, keepdims=True)

    def rounding(self):
        eps = np.finfo(np.float64).eps
        return eps * jnp.sum(jnp.abs(self.obs) * self.weight, axis=-1, keepdims=True)

    def _sigma(self):
        w = self.weight
        return jnp.where(w > 0, 1.0 / jnp.where(w > 0, w, 1.0), 0.0)

    def tangent_gradient(self, P, b):
        """``b`` without its component along ``(n, 0)``, the gradient of ``|n|^2``: at the
        solution the observations pull each normal along itself with the unit-normal
        constraint's Lagrange multiplier. A factorisation's step basis (:meth:`constraint_basis`)
        taken at another estimate (the chord steps) would otherwise pass a share of it on."""
        a = jnp.concatenate([P[:, :3], jnp.zeros_like(P[:, 3:])], axis=-1)
        return b - a * (jnp.sum(a * b, axis=-1) / jnp.sum(a * a, axis=-1))[:, None]

    def observation_quality(self, spec, problem, params, fi, JQJ, rows):
        """Gauss-Helmert residuals ``v = -Sigma_l B^T w / m`` of the three observations (the
        residuals of the last step, ``dx = 0`` at the solution); the condition's redundancy
        ``1 - a Q a^T`` split over them in the ratio ``sigma_l^2 b_l^2 / m`` (so the three sum
        to at most 1, SPEC section 4)."""
        active = self.active_rows()[:, 0]
        B = rows.B
        m = self._variance_from(B)
        share = (self._sigma() * B) ** 2 / jnp.where(m > 0, m, 1.0)[:, None]
        redundancy = jnp.where(active, 1.0 - JQJ[:, 0], 0.0)[:, None] * share
        v = self.state_from_rows(rows, None)[0]
        return v, redundancy, jnp.sum(active), jnp.sum(rows.e**2)


class Problem(Module):
    """Everything the compiled adjustment needs: families, scans, levelling, fixed parameters.

    ``layouts``: per family a :class:`Layout` or None, chosen on the host from the static
    structure of the network (:func:`grid_layout`); the engine moves such a family onto its
    grid (:func:`on_grid`) and records the grid shape in ``grids``.

    Weighted constraints with observed values (Chow et al. 2013, eq. 7; SPEC section 6), each a
    pseudo-observation with its weight 1/sigma (0: none): ``levelling`` (s, 2) the tilt readings
    (omega_c, phi_c) of a compensator or tilt sensor, ``heading`` (s,) an observed kappa,
    ``ap_prior`` (a,) the APs of a prior calibration. None: no such observations.
    """

    families: tuple
    scan_instrument: Int[Array, " s"]
    levelling: Float[Array, "s 2"]
    levelling_weight: Float[Array, "s 2"]
    fixed: Bool[Array, " r"]
    layouts: tuple = ()
    grids: tuple = field(static=True, default=())
    heading: Float[Array, " s"] | None = None
    heading_weight: Float[Array, " s"] | None = None
    ap_prior: Float[Array, " a"] | None = None
    ap_prior_weight: Float[Array, " a"] | None = None


class Params(Module):
    prims: tuple  # per family (n, p)
    eops: Float[Array, "s 6"]
    aps: Float[Array, " a"]


class Options(Module):
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


def orientation_observations(problem):
    """The observed values (s, 3) and weights (s, 3) of :func:`orientation_reading`."""
    s = problem.levelling.shape[0]
    heading = jnp.zeros(s) if problem.heading is None else problem.heading
    hw = jnp.zeros(s) if problem.heading_weight is None else problem.heading_weight
    values = jnp.concatenate([problem.levelling, heading[:, None]], axis=1)
    return values, jnp.concatenate([problem.levelling_weight, hw[:, None]], axis=1)


def orientation_residual(problem, eops):
    """Residuals ``v = f(x) - l`` (s, 3) [rad] of the scans' orientation pseudo-observations
    (tilt readings and kappa; also where not observed), wrapped to (-pi, pi]."""
    values = orientation_observations(problem)[0]
    return wrap_angle(jax.vmap(orientation_reading)(eops) - values)


def levelling_residual(problem, eops):
    """Whitened residuals (s, 3) of the scans' orientation pseudo-observations: tilt readings
    and observed kappa (0 where not observed); angles wrapped to (-pi, pi]."""
    return orientation_residual(problem, eops) * orientation_observations(problem)[1]


def levelling_jacobian(problem, eops):
    # (s, 3, 6): whitened orientation residuals w.r.t. the scan's pose.
    weight = orientation_observations(problem)[1]
    return jax.vmap(jax.jacfwd(orientation_reading))(eops) * weight[:, :, None]


def ap_prior_weight(problem, n_aps: int):
    """Weights (a,) of the AP priors (0: none)."""
    return jnp.zeros(n_aps) if problem.ap_prior_weight is None else problem.ap_prior_weight


def ap_prior_residual(problem, aps):
    """Whitened residuals (a,) of the AP priors, ``(a - a_prior) / sigma`` (a linear
    pseudo-observation of each coefficient, SPEC section 6)."""
    if problem.ap_prior is None:
        return jnp.zeros_like(aps)
    return (aps - problem.ap_prior) * problem.ap_prior_weight


def pseudo_cost(problem, params):
    """``v^T P v`` of the pseudo-observations of the scan poses and APs."""
    return jnp.sum(levelling_residual(problem, params.eops) ** 2) + jnp.sum(
        ap_prior_residual(problem, params.aps) ** 2
    )


def n_pseudo(problem, n_aps: int):
    """Number of active pseudo-observations of the scan poses and APs."""
    weight = orientation_observations(problem)[1]
    return jnp.sum(weight > 0) + jnp.sum(ap_prior_weight(problem, n_aps) > 0)


def cost_and_state(spec, problem, params, state: tuple | None = None, ap_jac: tuple | None = None):
    """``v^T P v`` (observations and pseudo-observations) at ``params`` with the families'
    states ``state`` (None: their initial states), the families' next states and the largest
    change of a state in a priori sigmas (:meth:`Family.cost_state`). ``ap_jac``: the constant
    AP blocks (``Family.ap_block``), if taken."""
    total = pseudo_cost(problem, params)
    states, change = [], jnp.asarray(0.0)
    for fi, fam in enumerate(problem.families):
        aj = None if ap_jac is None else ap_jac[fi]
        st = fam.state_init() if state is None else state[fi]
        e, st, ch = fam.cost_state(spec, problem, params, fi, st, aj)
        total = total + jnp.sum(e**2) + jnp.sum(fam.prior_residuals(params.prims[fi]) ** 2)
        states.append(st)
        change = jnp.maximum(change, ch)
    return total, tuple(states), change


def cost(spec, problem, params, state: tuple | None = None, ap_jac: tuple | None = None):
    """``v^T P v`` of :func:`cost_and_state`."""
    return cost_and_state(spec, problem, params, state, ap_jac)[0]


def initial_state(problem) -> tuple:
    """The families' states before the first step (:meth:`Family.state_init`)."""
    return tuple(fam.state_init() for fam in problem.families)


def state_from_rows(problem, rows, state):
    """The families' next states at the linearisation point of ``rows`` and the largest change
    (a rejected step: the unknowns stay, the Gauss-Helmert residuals still settle)."""
    out = [fam.state_from_rows(r, st) for fam, r, st in zip(problem.families, rows, state)]
    change = jnp.max(jnp.asarray([0.0] + [jnp.asarray(c, dtype=jnp.float64) for _, c in out]))
    return tuple(st for st, _ in out), change


def rows_after(problem, rows, dps, dz, n_scans: int) -> tuple:
    """The families' rows moved to the end of the step ``(dps, dz)`` to first order
    (:meth:`Family.rows_after`; unchanged for a family without a state)."""
    ds, da = dz[: 6 * n_scans].reshape(n_scans, 6), dz[6 * n_scans :]
    return tuple(
        fam.rows_after(problem, fi, r, dp, ds, da)
        for fi, (fam, r, dp) in enumerate(zip(problem.families, rows, dps))
    )


def predicted_state(problem, rows, state, dps, dz, n_scans: int) -> tuple:
    """The families' states after the step ``(dps, dz)``, predicted from the rows at its start
    (evaluated with ``state``): the update from the rows moved by the step (:func:`rows_after`);
    for a Gauss-Helmert family ``v = -Sigma_l B^T M^-1 (A dx + w)``."""
    moved = rows_after(problem, rows, dps, dz, n_scans)
    return state_from_rows(problem, moved, state)[0]


def settled_state(spec, problem, params, steps: int = PROJECTION_STEPS) -> tuple:
    """The families' states settled at fixed ``params``: ``steps`` updates from the initial
    state (for a Gauss-Helmert family, the residuals projected onto the conditions,
    :func:`tlsjax._model._planes.projection_step`). Differentiable (a rolled loop)."""
    step = lambda _, st: cost_and_state(spec, problem, params, st)[1]
    return jax.lax.fori_loop(0, steps, step, initial_state(problem))


def count_observations(problem, params):
    """Active scalar observations and pseudo-observations (one condition per plane point) plus
    the hard constraints on the primitives (a plane's unit normal): what the degrees of freedom
    ``r = n - u + d`` count as n, with u the unknowns (four per plane)."""
    n = n_pseudo(problem, params.aps.shape[0])
    for fi, fam in enumerate(problem.families):
        active_prior = jnp.any(fam.prior_jacobian(params.prims[fi]) != 0, axis=-1)
        n = n + jnp.sum(fam.active_rows()) + jnp.sum(active_prior) + fam.hard_constraints()
    return n


class Layout(Module):
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
    shape: tuple = field(static=True)


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
        fams.append(dataclasses.replace(fam, **changes))
        grids.append(lay.shape)
    return dataclasses.replace(problem, families=tuple(fams), layouts=(), grids=tuple(grids))


def from_grid(problem: Problem, per_family: tuple) -> tuple:
    """Per-observation arrays of a gridded problem back in each family's row order."""
    if not problem.layouts:
        return per_family
    return tuple(
        a if lay is None or a is None else a[lay.pos] for a, lay in zip(per_family, problem.layouts)
    )
