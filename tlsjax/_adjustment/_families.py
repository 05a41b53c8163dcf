"""The unknowns and data of the compiled adjustment, and the residual of each primitive family.

Unknowns: primitives (targets, scale bars, planes) in families of fixed block size p, scan poses
(6 per scan) and APs. A family holds the observations of its primitives with their weights
(1/sigma; 0 = removed) and the index plan built once on the host: which observations share a
primitive, which (primitive, scan) pairs exist.
"""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from .._model._levelling import compensator_reading
from .._model._planes import unit_normal_constraint, whitened_condition
from .._model._points import point_misclosure


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


def obs_residual(spec: Spec, fam: Family):
    if fam.kind == "plane":
        # One Gauss-Helmert condition per point, whitened by sqrt(B Sigma B^T) (_planes.py).
        def g(P, eop, aps, l, w, point, inst):
            return whitened_condition(
                P, eop, aps, l, w, spec.scanners, spec.ap_names, spec.ap_slices, inst
            )

        return g

    def f(P, eop, aps, l, w, point, inst):
        X = P.reshape(fam.k, 3)[point]
        return (
            point_misclosure(X, eop, aps, l, spec.scanners, spec.ap_names, spec.ap_slices, inst) * w
        )

    return f


def prior_residual(fam: Family):
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


def family_residuals(spec, problem, params, fi):
    fam = problem.families[fi]
    P = params.prims[fi]
    inst = problem.scan_instrument[fam.scan]
    e = jax.vmap(obs_residual(spec, fam), in_axes=(0, 0, None, 0, 0, 0, 0))(
        P[fam.prim], params.eops[fam.scan], params.aps, fam.obs, fam.weight, fam.point, inst
    )
    pr = jax.vmap(prior_residual(fam))(
        P, fam.ctrl_xyz, fam.ctrl_weight, fam.bar_length, fam.bar_weight
    )
    return e, pr


def levelling_residual(problem, eops):
    return (jax.vmap(compensator_reading)(eops) - problem.levelling) * problem.levelling_weight


def levelling_jacobian(problem, eops):
    # (s, 2, 6): whitened compensator residuals w.r.t. the scan's pose.
    return jax.vmap(jax.jacfwd(compensator_reading))(eops) * problem.levelling_weight[:, :, None]


OBS_AXES = (0, 0, None, 0, 0, 0, 0)


def family_args(problem, params, fi):
    fam = problem.families[fi]
    P = params.prims[fi]
    return (
        P[fam.prim],
        params.eops[fam.scan],
        params.aps,
        fam.obs,
        fam.weight,
        fam.point,
        problem.scan_instrument[fam.scan],
    )
