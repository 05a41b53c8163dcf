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

from .._model._datum import move_plane, move_points
from .._model._levelling import compensator_reading
from .._model._planes import (
    condition_variance,
    observation_residuals,
    plane_condition,
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

    def residuals(self, spec, problem, params, fi, unit_weight: bool = False):
        """Whitened residual rows of every observation, (m, rows)."""
        args = list(self.observation_args(problem, params, fi))
        if unit_weight:
            args[4] = jnp.ones_like(self.weight)
        return jax.vmap(lambda *a: self.residual(spec, *a), in_axes=OBS_AXES)(*args)

    def prior_residuals(self, P):
        return jax.vmap(self.prior)(P, *self.prior_args())

    def prior_jacobian(self, P):
        return jax.vmap(jax.jacfwd(self.prior))(P, *self.prior_args())

    def cost_rows(self, spec, problem, params, fi, frozen):
        """Rows whose squares a step's acceptance compares (the residuals unless the family
        holds weights at the linearisation point ``frozen``)."""
        return self.residuals(spec, problem, params, fi)

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

    def observation_quality(self, spec, problem, params, fi, JQJ):
        """Residuals ``v = F + Delta - l`` [m, rad, rad] (a removed observation keeps its
        misclosure, so that a rejected blunder can be reported), redundancy numbers
        ``1 - (J Q J^T)_ii``, the number of active observations and their ``v^T P v``."""
        raw = self.residuals(spec, problem, params, fi, unit_weight=True)
        active = self.active_rows()
        redundancy = jnp.where(active, 1.0 - JQJ, 0.0)
        return raw, redundancy, jnp.sum(active), jnp.sum((raw * self.weight) ** 2)


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

    def cost_rows(self, spec, problem, params, fi, frozen):
        new = self.observation_args(problem, params, fi)
        m, _ = self._variance(spec, self.observation_args(problem, frozen, fi), frozen.aps)
        sl = (spec.scanners, spec.ap_names, spec.ap_slices)
        g = jax.vmap(lambda P_, E_, l_, i_: plane_condition(P_, E_, params.aps, l_, *sl, i_))(
            new[0], new[1], self.obs, new[6]
        )
        rows = self.active_rows()[:, 0]
        return jnp.where(rows, g / jnp.sqrt(jnp.where(m > 0, m, 1.0)), 0.0)[:, None]

    def observation_quality(self, spec, problem, params, fi, JQJ):
        """Gauss-Helmert residuals ``v = -Sigma_l B^T g / m`` of the three observations; the
        condition's redundancy ``1 - a Q a^T`` split over them in the ratio
        ``sigma_l^2 b_l^2 / m`` (so the three sum to at most 1, SPEC section 4)."""
        args = self.observation_args(problem, params, fi)
        rows = self.active_rows()[:, 0]
        m, B = self._variance(spec, args, params.aps)
        share = (self._sigma() * B) ** 2 / jnp.where(m > 0, m, 1.0)[:, None]
        redundancy = jnp.where(rows, 1.0 - JQJ[:, 0], 0.0)[:, None] * share
        sl = (spec.scanners, spec.ap_names, spec.ap_slices)
        v = jax.vmap(
            lambda P_, E_, l_, w_, i_: observation_residuals(P_, E_, params.aps, l_, w_, *sl, i_)
        )(args[0], args[1], self.obs, self.weight, args[6])
        e = self.residuals(spec, problem, params, fi)
        return v, redundancy, jnp.sum(rows), jnp.sum(e**2)


class Problem(eqx.Module):
    """Everything the compiled adjustment needs: families, scans, levelling, fixed parameters."""

    families: tuple
    scan_instrument: Int[Array, " s"]
    levelling: Float[Array, "s 2"]
    levelling_weight: Float[Array, "s 2"]
    fixed: Bool[Array, " r"]


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


def cost(spec, problem, params, frozen: Params | None = None):
    """``v^T P v``: sum of squared whitened residuals, observations and pseudo-observations.

    ``frozen``: the linearisation point at which families with ``frozen_cost`` hold their
    weights (a Gauss-Helmert step is accepted under its own M).
    """
    total = jnp.sum(levelling_residual(problem, params.eops) ** 2)
    for fi, fam in enumerate(problem.families):
        if frozen is not None and fam.frozen_cost:
            e = fam.cost_rows(spec, problem, params, fi, frozen)
        else:
            e = fam.residuals(spec, problem, params, fi)
        total = total + jnp.sum(e**2) + jnp.sum(fam.prior_residuals(params.prims[fi]) ** 2)
    return total


def count_observations(problem, params):
    """Active scalar observations and pseudo-observations (one condition per plane point)."""
    n = jnp.sum(problem.levelling_weight > 0)
    for fi, fam in enumerate(problem.families):
        active_prior = jnp.any(fam.prior_jacobian(params.prims[fi]) != 0, axis=-1)
        n = n + jnp.sum(fam.active_rows()) + jnp.sum(active_prior)
    return n
