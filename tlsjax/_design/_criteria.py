"""Design criteria: scalar functions of the predicted covariance of a design (SPEC section 13).

The covariance of a design needs no noise draws: it is the inverse of the normal matrix of the
linearisation at the true (error-free) parameters, which depends only on the geometry and the
sigmas. :func:`predicted_cofactor` computes it with the engine's own quality function
(:func:`tlsjax._adjustment._quality.pose_ap_cofactor`: segment sums, Schur elimination of the
targets or planes, Cholesky of the reduced system, the inner-constraint S-transformation of
:mod:`tlsjax._model._datum`), with no iteration and no rank test, so it is a smooth,
differentiable function of the design arrays: a design that cannot determine an AP gets a huge
(or non-finite) sigma, never a masked zero.

Criteria (a priori, sigma0 = 1; ``tol_k`` the stated tolerance of AP k, in its SI unit):

* ``"max_sigma"``: ``max_k sigma_k / tol_k`` (optimised as the p-norm, p = ``sharpness``);
* ``"trace"``: ``sum_k sigma_k^2 / tol_k^2`` (A-optimality in tolerance units);
* ``"max_correlation"``: the largest |correlation| of the APs in ``aps`` with the other APs
  (and, with ``with_poses``, with the scan poses in the inner-constraint datum; e.g. B6 with
  kappa), optimised as the p-norm of the |correlations|.

The exact value (a hard max) is reported; the smooth one is what the optimiser descends.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import jax
import jax.numpy as jnp
import numpy as np

from .._adjustment._implicit import frozen_problem, problem_from_inputs
from .._adjustment._quality import pose_ap_cofactor
from .._jit import jit
from .._model._aps import get_ap
from .._units import ARCSEC

CRITERIA = ("max_sigma", "trace", "max_correlation")


def default_tolerance(name: str) -> float:
    """Default tolerance of an AP's sigma: 0.1 mm for lengths, 1" for angles, 10 ppm otherwise."""
    unit = get_ap(name).unit
    return 1e-4 if unit == "m" else ARCSEC if unit == "rad" else 1e-5


def predicted_cofactor(dn, design, information=None):
    """A priori covariance (sigma0 = 1) of the scan poses and APs, (6s + a, 6s + a), of
    ``design`` on the :class:`~tlsjax._design._design.DesignProblem` ``dn``, in the
    inner-constraint datum on the primitives (free network) or the template's datum.

    ``information`` (n,): optional factor on the information of every row (sigma divided by
    its square root), e.g. ~0 for the rows of a board left out: one compiled function then
    compares subsets of primitives."""
    adj = dn.template
    plan, spec = adj.plan, adj.plan.spec
    rows = tuple(jnp.asarray(r, dtype=jnp.int32) for r in plan.family_rows)
    inputs = dn.inputs(design)
    if information is not None:
        scale = 1.0 / jnp.sqrt(jnp.asarray(information))[:, None]
        inputs = dataclasses.replace(
            inputs,
            sigmas=inputs.sigmas * scale if not dn.is_plane else inputs.sigmas,
            plane_sigmas=inputs.plane_sigmas * scale if dn.is_plane else inputs.plane_sigmas,
        )
    problem = problem_from_inputs(plan.problem, rows, plan.plane_family, inputs)
    x = dn.truth(design)
    # rank_tolerance -1: no parameter is declared dependent (a rank test would hand the
    # optimiser a zero sigma for an AP the design cannot determine); only the held ones are.
    return pose_ap_cofactor(spec, frozen_problem(spec, problem, x), x, -1.0)


@dataclasses.dataclass(frozen=True)
class DesignCriterion:
    """A scalar criterion of the AP covariance (module docstring).

    ``kind``: one of ``CRITERIA``. ``aps``: the APs it covers (default: all of the model).
    ``tolerances``: AP name -> tolerance of its sigma [SI] (default :func:`default_tolerance`).
    ``with_poses``: for ``max_correlation``, also the correlations with the scan poses.
    ``sharpness``: the p of the p-norm that smooths the max.
    """

    kind: str = "max_sigma"
    aps: tuple | None = None
    tolerances: Mapping[str, float] | None = None
    with_poses: bool = False
    sharpness: float = 16.0

    def __post_init__(self):
        if self.kind not in CRITERIA:
            raise ValueError(f"design criterion {self.kind!r} is not one of {CRITERIA}")
        if isinstance(self.aps, str):
            object.__setattr__(self, "aps", tuple(self.aps.split()))
        for name, tol in (self.tolerances or {}).items():
            if not (np.isfinite(tol) and tol > 0):
                raise ValueError(f"tolerance of AP {name} must be positive, got {tol}")
        if not self.sharpness >= 1:
            raise ValueError(f"sharpness must be >= 1, got {self.sharpness}")

    def _select(self, ap_names):
        names = tuple(ap_names) if self.aps is None else self.aps
        for n in names:
            if n not in ap_names:
                raise ValueError(
                    f"criterion AP {n!r} is not an AP of the model: {' '.join(ap_names)}"
                )
        idx = np.array([ap_names.index(n) for n in names])
        tol = np.array([(self.tolerances or {}).get(n, default_tolerance(n)) for n in names])
        return idx, tol

    def terms(self, Q, n_scans: int, ap_names):
        """The quantities whose max (or sum) is the criterion: sigma/tol, or |correlations|;
        in numpy for a numpy ``Q`` (a report), in JAX otherwise (a traced criterion)."""
        xp = np if isinstance(Q, np.ndarray) else jnp
        na = len(ap_names)
        idx, tol = self._select(ap_names)
        d = xp.diagonal(Q)
        ok = d > 0
        sig = xp.where(ok, xp.sqrt(xp.where(ok, d, 1.0)), 0.0)
        ap = 6 * n_scans + idx
        if self.kind != "max_correlation":
            return sig[ap] / tol
        cols = np.arange(6 * n_scans + na) if self.with_poses else 6 * n_scans + np.arange(na)
        C = Q[ap][:, cols] / xp.maximum(sig[ap][:, None] * sig[cols][None, :], 1e-300)
        mask = np.asarray(cols)[None, :] != ap[:, None]
        # A pose parameter held by the datum (zero variance) has no correlation.
        return xp.where(mask & (sig[cols] > 0)[None, :], xp.abs(C), 0.0).reshape(-1)

    def smooth(self, Q, n_scans: int, ap_names):
        """The differentiable criterion the optimiser descends."""
        t = self.terms(Q, n_scans, ap_names)
        if self.kind == "trace":
            return jnp.sum(t**2)
        top = jnp.max(t)
        return top * jnp.sum((t / top) ** self.sharpness) ** (1.0 / self.sharpness)

    def exact(self, Q, n_scans: int, ap_names) -> float:
        t = self.terms(np.asarray(Q), n_scans, ap_names)
        return float(np.sum(t**2) if self.kind == "trace" else np.max(t))

    def describe(self, ap_names) -> str:
        idx, tol = self._select(ap_names)
        names = [ap_names[i] for i in idx]
        if self.kind == "max_correlation":
            other = "APs and scan poses" if self.with_poses else "APs"
            return f"largest |correlation| of {', '.join(names)} with the other {other}"
        what = (
            "largest sigma / tolerance" if self.kind == "max_sigma" else "sum (sigma / tolerance)^2"
        )
        return f"{what} of {', '.join(names)}"


def design_criterion(
    dn, design, criterion: DesignCriterion, *, smooth: bool = True, information=None
):
    """``criterion`` of ``design`` (a pure function of the design arrays when ``smooth``);
    ``information`` as in :func:`predicted_cofactor`.

    Called with concrete arrays (not inside the caller's ``jit``, ``grad`` or ``vmap``), it runs
    one compiled program per problem and criterion, kept on ``dn``: the cofactor is hundreds of
    array operations, which dispatched one by one cost seconds of compiling per call."""
    spec = dn.template.plan.spec
    names = dn.template.plan.ap_labels

    def value(d, info):
        Q = predicted_cofactor(dn, d, info)
        if smooth:
            return criterion.smooth(Q, spec.n_scans, names)
        return criterion.terms(Q, spec.n_scans, names)

    if any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves((design, information))):
        out = value(design, information)
    else:
        # Keyed on all the program closes over besides dn: the criterion's fields (its repr,
        # tolerances included), the mode and whether a weighting is given.
        key = ("design_criterion", repr(criterion), smooth, information is None)
        programs = dn.__dict__.setdefault("_programs", {})
        if key not in programs:
            programs[key] = jit(value)
        out = programs[key](design, information)
    if smooth:
        return out
    t = np.asarray(out)
    return float(np.sum(t**2) if criterion.kind == "trace" else np.max(t))


def criterion_of_result(criterion: DesignCriterion, result) -> float:
    """The exact criterion of an independent :func:`tlsjax.calibrate` (run with
    ``SolverOptions(full_covariance=True)``): its covariance of the scan poses and APs divided
    by sigma0^2 (a priori, as the prediction), in the adjustment's datum."""
    if result.covariance is None:
        raise ValueError(
            "criterion_of_result needs calibrate(..., SolverOptions(full_covariance=True))"
        )
    r = 6 * len(result.scans) + len(result.ap_names)
    Q = np.asarray(result.covariance)[-r:, -r:] / result.sigma0**2
    return criterion.exact(Q, len(result.scans), result.ap_names)
