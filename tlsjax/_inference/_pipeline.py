"""The pipeline of :func:`tlsjax.self_calibrate`: an explicit state, the transitions of it that
the steps share, and the compiled adjustment they re-solve (SPEC sections 5 and 7).

* :class:`TestingState` (frozen) is everything a step reads and writes: the variance factors of
  the groups, the mask of the observations in use, the targets held by a pin, the removals, the
  latest adjustment and the last one that succeeded, the a priori tests, the history, the
  warnings and how VCE ended. A step never changes a state in place: it returns a new one
  (``dataclasses.replace``; arrays are copied before they change), so what a step did is its
  return value, and an earlier state can be kept and gone back to.
* :class:`TestingContext` (frozen) is what stays fixed while the model does: the network, the
  options (:class:`._options.CalibrationOptions`), the a priori sigmas and the analysed
  adjustment of the model (:class:`Reweighter`). A step that changes the model (selection) puts
  the new model in the state; the context of that model (:meth:`TestingContext.for_state`,
  analysed once) serves the steps after it.
* A step is a function ``step(ctx, state) -> state`` (:data:`Step`). The steps and their order
  are listed in one place, :data:`._steps.PIPELINE`, and :func:`run_pipeline` runs them. Each
  step reads from ``ctx.options`` whether it has work to do (its concern is None when not) and
  otherwise returns the state it was given; a new step joins by being written as such a
  function and put in the list.

Every re-adjustment is the same compiled adjustment with other weights (traced arrays) and
pinned targets: nothing recompiles. The weights are ``1 / (sigma sqrt(factor_g))`` for the
observations in use and 0 for the removed ones (a mask, never a new network: shapes stay
static).
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Mapping
from typing import NamedTuple

import jax
import numpy as np

from .._adjustment._calibrate import PIN_SIGMA, analyze
from .._adjustment._config import CalibrationModel, SolverOptions
from .._adjustment._network import Network
from .._adjustment._quality import condition_w_tests
from .._adjustment._result import CalibrationResult, assemble
from .._jit import jit
from .._model._geometry import rotation_matrix
from .._model._levelling import compensator_reading
from .._model._planes import observation_residuals
from .._model._scanner import Scanner
from .._units import display_group
from ._options import CalibrationOptions
from ._outcome import GROUPS, Removal, VCEResult
from ._score import ScoreTester
from ._variance_factors import variance_factor

#: Residual sigma of a group [m, rad, rad, rad] below which the residuals are rounding, not
#: measurement noise (noise-free data: about 1e-15 m and 1e-16 rad in a float64 adjustment;
#: the best scanners measure to 1e-4 m and 1e-6 rad).
ROUNDING_SIGMA = (1e-9, 1e-11, 1e-11, 1e-11, 1e-11, 1e-12)


class Adjusted(NamedTuple):
    """One adjustment of the pipeline: the :class:`tlsjax.CalibrationResult`, the solver's
    final state (its ``params`` warm-start the next adjustment) and the AP influence (n, 3, a)
    of every target observation and (m, 1, a) of every plane point's condition (external
    reliability)."""

    result: CalibrationResult
    solution: object
    influence: np.ndarray
    plane_influence: np.ndarray | None = None


class Reweighter:
    """One analysed adjustment (:class:`tlsjax.Adjustment`), re-solved with other weights and
    pinned targets; nothing recompiles."""

    def __init__(self, net: Network, model: CalibrationModel, options: SolverOptions):
        self.net, self.model, self.options = net, model, options
        self.adjustment = analyze(net, model, options)
        self.plan = self.adjustment.plan
        self.params0 = self.adjustment.initial

    def run(
        self,
        weight,
        levelling_weight,
        pinned: Mapping,
        params0=None,
        plane_weight=None,
        fixed_aps=None,
        max_iterations=None,
        heading_weight=None,
        ap_prior_weight=None,
    ) -> Adjusted:
        """``weight`` (n, 3) = 1/sigma or 0 (removed); ``pinned`` maps target -> xyz;
        ``plane_weight`` (m, 3) of the plane rows (None: the network's); ``fixed_aps``: AP
        labels held at zero (None: the model's), e.g. candidate terms of an analysed wider
        model that are not (yet) in the model: one compiled adjustment serves both;
        ``heading_weight`` (s,) and ``ap_prior_weight`` (a,) of the observed headings and AP
        priors (None: the network's and the model's)."""
        adj = self.adjustment
        control = {t: (xyz, PIN_SIGMA) for t, xyz in pinned.items()}
        problem = adj.problem(
            weights=weight,
            levelling_weights=levelling_weight,
            control=control,
            plane_weights=plane_weight,
            fixed_aps=fixed_aps,
            heading_weights=heading_weight,
            ap_prior_weights=ap_prior_weight,
        )
        opts = None
        if max_iterations is not None:
            # e.g. 0: the misclosures and redundancy numbers at params0 (data: the same program)
            opts = dataclasses.replace(
                adj.options.arrays(), max_iterations=np.asarray(int(max_iterations))
            )
        plan, state, q, absent = adj.run_estimable(problem, params0, opts)
        res = assemble(self.net, self.model, plan, state, q, absent)
        infl = np.zeros((self.net.observations.shape[0], 3, plan.spec.n_aps))
        for fi, rows in enumerate(plan.family_rows[: len(plan.family_targets)]):
            infl[rows] = np.asarray(q.ap_influence[fi])
        fp, plane_infl = plan.plane_family, None
        if fp is not None:
            plane_infl = np.zeros((self.net.plane_observations.shape[0], 1, plan.spec.n_aps))
            plane_infl[plan.family_rows[fp]] = np.asarray(q.ap_influence[fp])
        return Adjusted(res, state, infl, plane_infl)


@dataclasses.dataclass(frozen=True, eq=False)
class TestingContext:
    """What stays fixed while the model does: the network, the options, the analysed
    adjustment of the model and the a priori sigmas of the observations (n, 3), of the
    levelling readings (s, 2; inf where a scan is not levelled), of the observed headings (s,)
    and AP priors (a,) (inf where none) and of the plane points (m, 3; held fixed: no variance
    component, SPEC section 5)."""

    network: Network
    options: CalibrationOptions
    reweighter: Reweighter
    base_sigma: np.ndarray
    levelling_sigma: np.ndarray
    levelling_active: np.ndarray
    plane_sigma: np.ndarray
    heading_sigma: np.ndarray
    ap_prior_sigma: np.ndarray

    @property
    def heading_active(self) -> np.ndarray:
        return np.isfinite(self.heading_sigma)

    @property
    def ap_prior_active(self) -> np.ndarray:
        return np.isfinite(self.ap_prior_sigma)

    def group_sigma(self, g: int) -> np.ndarray:
        """The a priori sigmas of the used observations of group ``g`` (:data:`GROUPS`)."""
        if g < 3:
            return self.base_sigma[:, g]
        sig = (self.levelling_sigma, self.heading_sigma, self.ap_prior_sigma)[g - 3]
        return sig[np.isfinite(sig)]

    @property
    def model(self) -> CalibrationModel:
        return self.reweighter.model

    @property
    def vce(self) -> bool:
        """Variance components are estimated: asked for, and the network has target
        observations (a plane network keeps its weights, SPEC section 5)."""
        return bool(self.options.vce is not None and self.network.observations.shape[0])

    @property
    def plane_igg3(self) -> bool:
        """The plane points are screened by IGG-III reweighting (:mod:`._robust`) instead of the
        robust start and screening: a network with planes, ``plane_screening`` on and no
        snooping (with snooping, plane points and targets go through the same screening and
        tests)."""
        o = self.options
        return bool(
            self.network.has_planes and o.plane_screening is not None and o.snooping is None
        )

    @classmethod
    def make(cls, net: Network, model: CalibrationModel, options: CalibrationOptions):
        lev = np.asarray(net.levelling_sigma, dtype=float)
        reweighter = Reweighter(net, model, options.solver)
        wa = reweighter.plan.problem.ap_prior_weight
        wa = np.zeros(reweighter.plan.spec.n_aps) if wa is None else np.asarray(wa, dtype=float)
        return cls(
            net,
            options,
            reweighter,
            np.asarray(net.sigmas, dtype=float),
            lev,
            np.isfinite(lev),
            np.asarray(net.plane_sigmas, dtype=float).reshape(-1, 3),
            np.asarray(net.heading_sigmas, dtype=float),
            np.where(wa > 0, 1.0 / np.where(wa > 0, wa, 1.0), np.inf),
        )

    def for_state(self, state: TestingState) -> TestingContext:
        """The context of the model in use in ``state`` (this one, or that of the model a step
        chose, analysed at its first use and kept)."""
        if state.model is None or state.model is self.model:
            return self
        derived = self.__dict__.setdefault("_derived", {})
        if id(state.model) not in derived:
            derived[id(state.model)] = (
                state.model,
                TestingContext.make(self.network, state.model, self.options),
            )
        return derived[id(state.model)][1]

    @functools.cached_property
    def score_tester(self) -> ScoreTester | None:
        """The model analysed with the candidate terms held at zero (:mod:`._score`), built at
        first use; None for several instruments (the candidates would be per instrument)."""
        model = self.reweighter.model
        if not isinstance(model.scanner, Scanner):
            return None
        return ScoreTester(
            self.network, model, self.options.tests.candidates, self.reweighter.options
        )


@dataclasses.dataclass(frozen=True, eq=False)
class TestingState:
    """Everything the steps of :data:`._steps.PIPELINE` read and write (module docstring).

    ``factor`` (g,): variance factors of the groups :data:`GROUPS` (range, hz, el, levelling,
    heading, AP priors; the sigmas in use are ``sqrt(factor)`` times the a priori ones);
    ``estimated`` (g,) and ``notes``: which factors
    VCE estimated and why the others were held. ``mask`` (n, 3): True where an observation is
    used; ``plane_mask`` (m,): the same for plane points (one condition each, tested and
    removed as a whole). ``pinned``: target index -> xyz of the targets held at their last
    estimate. ``removals``, ``history``, ``warnings``, ``a_priori_tests``: what the run reports.
    ``adjusted``: the latest :class:`Adjusted` (None before the first); ``last_ok``: the last
    successful one with its variance factors; ``params``: the estimates that warm-start the
    next adjustment (None: the approximate values). ``removal_step`` counts rejections,
    ``n_adjustments`` adjustments; ``critical_value`` and ``screening_critical_value`` are
    those of the latest snooping and screening tests; ``vce_result`` and ``vce_iterations``
    say how VCE went. ``score_tests``: the score tests of the missing terms at the end
    (:mod:`._score`). ``robust_factor`` (n, 3): weight factors of a robust reweighting (the
    robust start; None: none); ``fixed_aps``: AP labels held at zero (None: the model's).
    ``model``: the model a step chose (selection; None: the context's); ``selection`` and
    ``plane_screening``: what those steps found (:mod:`._selection`, :mod:`._robust`);
    ``cross_validation``: the model's cross-validation by scan groups (:mod:`._crossval`).
    """

    factor: np.ndarray
    estimated: np.ndarray
    notes: tuple
    mask: np.ndarray
    plane_mask: np.ndarray
    pinned: Mapping = dataclasses.field(default_factory=dict)
    removals: tuple = ()
    history: tuple = ()
    warnings: tuple = ()
    a_priori_tests: tuple = ()
    adjusted: Adjusted | None = None
    last_ok: tuple | None = None
    params: object = None
    removal_step: int = 0
    n_adjustments: int = 0
    critical_value: float = float("nan")
    screening_critical_value: float | None = None
    vce_result: VCEResult = VCEResult.OFF
    vce_iterations: int = 0
    score_tests: object = None
    robust_factor: np.ndarray | None = None
    fixed_aps: tuple | None = None
    model: CalibrationModel | None = None
    selection: object = None
    plane_screening: object = None
    cross_validation: object = None

    @classmethod
    def initial(cls, ctx: TestingContext, critical_value: float) -> TestingState:
        """Before the first adjustment: a priori weights, every observation used."""
        net = ctx.network
        return cls(
            factor=np.ones(len(GROUPS)),
            estimated=np.zeros(len(GROUPS), dtype=bool),
            notes=("",) * len(GROUPS),
            mask=np.ones((net.observations.shape[0], 3), dtype=bool),
            plane_mask=np.ones(net.plane_observations.shape[0], dtype=bool),
            critical_value=critical_value,
            vce_result=VCEResult.CONVERGED if ctx.vce else VCEResult.OFF,
        )

    @property
    def result(self) -> CalibrationResult:
        """The latest adjustment's result."""
        return self.adjusted.result

    @property
    def ok(self) -> bool:
        """The latest adjustment succeeded."""
        return self.adjusted is not None and bool(self.adjusted.result.ok)


#: A step of the pipeline: a new state from the context and the state before it.
Step = Callable[[TestingContext, TestingState], TestingState]


@dataclasses.dataclass(frozen=True)
class NamedStep:
    """A step of the pipeline with the name it is listed (and reported) by."""

    name: str
    run: Step


def run_pipeline(ctx: TestingContext, state: TestingState, steps) -> TestingState:
    """Run ``steps`` (:class:`NamedStep`, in order) from ``state``, each with the context of
    the model in use (:meth:`TestingContext.for_state`)."""
    for step in steps:
        state = step.run(ctx.for_state(state), state)
    return state


# --- Transitions the steps share ------------------------------------------------------------


def sigmas(ctx: TestingContext, state: TestingState) -> np.ndarray:
    """Sigmas in use (n, 3): a priori times ``sqrt(factor)`` of the group."""
    return ctx.base_sigma * np.sqrt(state.factor[:3])[None, :]


def levelling_sigmas(ctx: TestingContext, state: TestingState) -> np.ndarray:
    return ctx.levelling_sigma * np.sqrt(state.factor[3])


def constraint_weights(ctx: TestingContext, state: TestingState) -> dict:
    """The weights in use of the observed headings and AP priors (their groups' factors), as
    keyword arguments of :meth:`Reweighter.run`; none where the network has none (the
    problem's own, no change of its structure)."""
    out = {}
    if ctx.heading_active.any():
        out["heading_weight"] = 1.0 / (ctx.heading_sigma * np.sqrt(state.factor[4]))
    if ctx.ap_prior_active.any():
        out["ap_prior_weight"] = 1.0 / (ctx.ap_prior_sigma * np.sqrt(state.factor[5]))
    return out


def adjust(ctx: TestingContext, state: TestingState, max_iterations=None) -> TestingState:
    """Re-adjust with the state's weights (factors, mask, pins), warm-started at its
    ``params``; a successful adjustment becomes ``last_ok`` and the next warm start (the datum,
    inner constraints, stays the same because the S-transformation is applied to every
    update)."""
    w, lw, _ = weights(ctx, state)
    pw = None
    if ctx.network.has_planes:
        pw = np.where(state.plane_mask[:, None], 1.0 / ctx.plane_sigma, 0.0)
    adjusted = ctx.reweighter.run(
        w,
        lw,
        state.pinned,
        state.params,
        plane_weight=pw,
        fixed_aps=state.fixed_aps,
        max_iterations=max_iterations,
        **constraint_weights(ctx, state),
    )
    changes = dict(adjusted=adjusted, n_adjustments=state.n_adjustments + 1)
    if adjusted.result.ok:
        changes.update(params=adjusted.solution.params, last_ok=(adjusted, state.factor.copy()))
    return dataclasses.replace(state, **changes)


def weights(ctx: TestingContext, state: TestingState):
    """The weights of the state's next adjustment: (n, 3) target rows (0 where removed), (s, 2)
    levelling readings, and the pinned targets as control."""
    w = np.where(state.mask, 1.0 / sigmas(ctx, state), 0.0)
    if state.robust_factor is not None:
        w = w * np.sqrt(state.robust_factor)
    lw = np.where(ctx.levelling_active, 1.0 / levelling_sigmas(ctx, state), 0.0)
    return w, lw, {t: (xyz, PIN_SIGMA) for t, xyz in state.pinned.items()}


def score_tests_at(ctx: TestingContext, state: TestingState):
    """Score tests of the candidate terms (:mod:`._score`) at the latest adjustment with the
    weights in use; None where there is no successful adjustment or no tester."""
    tester = ctx.score_tester if state.ok and state.fixed_aps is None else None
    if tester is None or not tester.candidates:
        return None
    w, lw, control = weights(ctx, state)
    return tester(
        state.adjusted.solution.params,
        weights=w,
        levelling_weights=lw,
        control=control,
        alpha=ctx.options.tests.score_test_level,
    )


#: Share of ``v^T P v`` above which one observation is said to dominate the misfit.
DOMINANT_SHARE = 0.5


def dominant_misfit(ctx: TestingContext, state: TestingState) -> str | None:
    """A sentence naming the observation that holds more than :data:`DOMINANT_SHARE` of its
    group's misfit ``sum (v_i / sigma_i)^2`` at the latest adjustment (a gross error: then a
    far-off variance factor says nothing about the units), or None."""
    res = state.result
    if not res.residuals.size:
        return None  # plane points only: their misfit is screened and snooped per point
    e2 = np.where(state.mask, (res.residuals / sigmas(ctx, state)) ** 2, 0.0)
    e2 = np.where(np.isfinite(e2), e2, 0.0)
    i, g = np.unravel_index(int(np.argmax(e2)), e2.shape)
    total = float(e2[:, g].sum())
    share = float(e2[i, g]) / total if total > 0 else 0.0
    if share <= DOMINANT_SHARE:
        return None
    net = ctx.network
    val, unit = display_group(int(g), res.residuals[i, g])
    return (
        f"one observation holds {100 * share:.0f}% of the {GROUPS[g]} misfit: {GROUPS[g]} of target "
        f"{net.targets[net.target_index[i]]} in scan {net.scans[net.scan_index[i]]} (residual "
        f"{val:.4g} {unit}, {np.sqrt(e2[i, g]):.3g} sigma): a gross error in that observation, "
        "not wrong units or sigmas"
    )


def with_factors(state: TestingState, factor) -> TestingState:
    """The state with other variance factors (not yet adjusted with them)."""
    return dataclasses.replace(state, factor=np.asarray(factor, dtype=float))


def restore_last_ok(state: TestingState) -> TestingState:
    """Back to the last successful adjustment and its variance factors (no re-run: the same
    weights need not converge again from another start)."""
    adjusted, factor = state.last_ok
    return dataclasses.replace(state, adjusted=adjusted, factor=factor)


def add_warning(state: TestingState, text: str) -> TestingState:
    return dataclasses.replace(state, warnings=state.warnings + (text,))


def add_history(state: TestingState, entry: dict) -> TestingState:
    return dataclasses.replace(state, history=state.history + (entry,))


def group_statistics(ctx: TestingContext, state: TestingState):
    """Per group (:data:`GROUPS`: range, hz, el, levelling, heading, AP priors) at the latest
    adjustment and the weights in use: the variance factor estimate
    ``s_g^2 = v_g^T P_g v_g / r_g`` (Förstner 1979; :func:`._variance_factors.variance_factor`), the
    group redundancy ``r_g`` and the number of observations used ``n_g``."""
    res, mask, ng = state.result, state.mask, len(GROUPS)
    e2 = np.where(mask, (res.residuals / sigmas(ctx, state)) ** 2, 0.0)
    r = np.where(mask, res.redundancy, 0.0)
    s2, r_g, n_g = np.ones(ng), np.zeros(ng), np.zeros(ng, dtype=int)
    for g in range(3):
        s2[g], r_g[g] = variance_factor(e2[:, g], r[:, g])
        n_g[g] = int(mask[:, g].sum())
    for g, (v, rr, sig, active) in _constraint_groups(ctx, state).items():
        e2c = np.where(active, (v / np.where(active, sig, 1.0)) ** 2, 0.0)
        s2[g], r_g[g] = variance_factor(e2c[active], rr[active])
        n_g[g] = int(active.sum())
    return s2, r_g, n_g


def _constraint_groups(ctx: TestingContext, state: TestingState) -> dict:
    """group index -> (residuals, redundancy numbers, sigmas in use, active) of the weighted
    constraints with observed values that the network has."""
    res, out = state.result, {}
    active = ctx.levelling_active
    if active.any():
        # Levelling residuals from the compensator readings of the final poses.
        read = compensator_reading(res.eops, np)
        v = read - res.network.levelling
        out[3] = (v, res.redundancy_levelling, levelling_sigmas(ctx, state), active)
    if ctx.heading_active.any() and res.orientation_residuals is not None:
        active = ctx.heading_active
        v, rr = res.orientation_residuals[:, 2], res.redundancy_orientation[:, 2]
        sig = ctx.heading_sigma * np.sqrt(state.factor[4])
        out[4] = (np.where(active, v, 0.0), np.where(active, rr, 0.0), sig, active)
    if ctx.ap_prior_active.any() and res.ap_prior_residuals is not None:
        active = ctx.ap_prior_active
        v, rr = res.ap_prior_residuals, res.redundancy_ap_prior
        sig = ctx.ap_prior_sigma * np.sqrt(state.factor[5])
        out[5] = (np.where(active, v, 0.0), np.where(active, rr, 0.0), sig, active)
    return out


def rounding_groups(ctx: TestingContext, state: TestingState, s2) -> list:
    """Groups whose residual sigma ``sqrt(factor s_g^2) * median sigma`` is rounding
    (:data:`ROUNDING_SIGMA`): noise-free data."""
    out = []
    for g in range(len(GROUPS)):
        sig = ctx.group_sigma(g)
        if sig.size and np.isfinite(s2[g]) and s2[g] >= 0:
            if np.sqrt(state.factor[g] * s2[g]) * np.median(sig) < ROUNDING_SIGMA[g]:
                out.append(GROUPS[g])
    return out


def remove(ctx: TestingContext, state: TestingState, i: int, g: int, w, reason: str):
    """Weight 0 for observation (i, g) (or the target's three with ``removal="target"``), each
    removal reported with its residual and test statistic ``w[i, g]``. A target that the
    removals leave without redundancy loses its other observations too and is pinned
    (:func:`_undetermined_targets`)."""
    step = state.removal_step + 1
    net, res = ctx.network, state.result
    mask = state.mask.copy()
    cols = (0, 1, 2) if ctx.options.removal == "target" else (g,)
    removals = []
    for c in cols:
        if mask[i, c]:
            why = reason if c == g else "same target observation as the rejected one"
            removals.append(_removal(net, res, step, i, c, float(w[i, c]), why))
            mask[i, c] = False
    extra, mask, pinned = _undetermined_targets(net, res, mask, state.pinned, step)
    return dataclasses.replace(
        state,
        removal_step=step,
        mask=mask,
        pinned=pinned,
        removals=state.removals + tuple(removals) + extra,
    )


def _removal(net: Network, res: CalibrationResult, step: int, i: int, c: int, w, why) -> Removal:
    val, unit = display_group(c, res.residuals[i, c])
    return Removal(
        step,
        int(i),
        net.scans[net.scan_index[i]],
        net.targets[net.target_index[i]],
        GROUPS[c],
        float(val),
        unit,
        w,
        why,
    )


def _undetermined_targets(net: Network, res: CalibrationResult, mask, pinned: Mapping, step: int):
    """The remaining observations of targets that the removals left without redundancy
    (observed in fewer than two scans or by fewer than four observations) or undetermined
    (their remaining observations do not fix three coordinates, :func:`_determined`), removed and
    reported, and the targets pinned at their last estimate. Such a target would otherwise be
    determined exactly by its last observations (nothing to test) or not at all (a rank
    defect). Returns (removals, mask, pinned), new objects."""
    out, mask, pinned = [], mask.copy(), dict(pinned)
    active = mask.any(axis=1)
    for t in np.unique(net.target_index[~mask.all(axis=1)]):
        if int(t) in pinned:
            continue
        rows = np.flatnonzero(net.target_index == t)
        n_scans = len(np.unique(net.scan_index[rows[active[rows]]]))
        if n_scans >= 2 and int(mask[rows].sum()) >= 4 and _determined(res, rows, mask[rows], t):
            continue
        why = "target left without redundancy by the removals; held at its last estimate"
        for i in rows:
            for c in range(3):
                if mask[i, c]:
                    out.append(_removal(net, res, step, i, c, float("nan"), why))
                    mask[i, c] = False
        pinned[int(t)] = res.target_xyz[t].copy()
    return tuple(out), mask, pinned


#: A target whose remaining observations' directions (unit gradients in object space) span 3D
#: only to this ratio of their singular values is not determined by them.
UNDETERMINED_RATIO = 1e-3


def _determined(res: CalibrationResult, rows, mask, t: int) -> bool:
    """Whether the remaining observations ``mask`` (k, 3) of target ``t`` (its rows) fix its
    three coordinates: the unit gradients of its ranges (along the line of sight) and of its
    directions and elevations (across it) span 3D. From one station with every range removed,
    or every direction, they do not, though they are four or more from two scans."""
    net = res.network
    X = res.target_xyz[t]
    grads = []
    for i, m in zip(rows, mask):
        j = net.scan_index[i]
        R = np.asarray(rotation_matrix(*res.eops[j, 3:], xp=np))
        x = R @ (X - res.eops[j, :3])
        rho, th = np.linalg.norm(x), np.arctan2(x[1], x[0])
        al = np.arcsin(np.clip(x[2] / rho, -1.0, 1.0))
        local = (
            x / rho,
            np.array([-np.sin(th), np.cos(th), 0.0]),
            np.array([-np.sin(al) * np.cos(th), -np.sin(al) * np.sin(th), np.cos(al)]),
        )
        grads += [R.T @ local[c] for c in range(3) if m[c]]
    if len(grads) < 3:
        return False
    sv = np.linalg.svd(np.asarray(grads), compute_uv=False)
    return bool(sv[-1] > UNDETERMINED_RATIO * sv[0])


# --- Plane points (one Gauss-Helmert condition each) -----------------------------------------


#: Fewest points a plane keeps in a scan through the removals.
MIN_PAIR_POINTS = 3


def plane_w(ctx: TestingContext, state: TestingState) -> np.ndarray:
    """The w-test of every plane point's condition at the latest adjustment (m,)
    (:func:`tlsjax._adjustment._quality.condition_w_tests`); NaN where removed or untestable."""
    res = state.result
    if res.plane_residuals is None:
        return np.zeros(0)
    w = condition_w_tests(res.plane_residuals, ctx.plane_sigma, res.plane_redundancy)
    return np.where(state.plane_mask, w, np.nan)


def remove_plane_point(ctx: TestingContext, state: TestingState, k: int, w: float, reason: str):
    """Weight 0 for plane point ``k`` (its condition: the point's three observations), reported
    like a target observation's removal (group ``plane``, the range residual). Returns (state,
    False) with a warning, nothing removed, where the point is one of the last
    :data:`MIN_PAIR_POINTS` of its plane in its scan (the scan's pose and the plane would lose
    what determines them)."""
    net, res = ctx.network, state.result
    pair = (net.plane_index == net.plane_index[k]) & (
        net.plane_scan_index == net.plane_scan_index[k]
    )
    scan, plane = net.scans[net.plane_scan_index[k]], net.planes[net.plane_index[k]]
    if int((pair & state.plane_mask).sum()) <= MIN_PAIR_POINTS:
        text = (
            f"plane point {k} (scan {scan}, plane {plane}, w = {w:.2f}) not removed: plane "
            f"{plane} keeps only {MIN_PAIR_POINTS} points in scan {scan}; check that plane"
        )
        return add_warning(state, text), False
    step = state.removal_step + 1
    val, unit = display_group(0, res.plane_residuals[k, 0])
    removal = Removal(step, int(k), scan, plane, "plane", float(val), unit, float(w), reason)
    mask = state.plane_mask.copy()
    mask[k] = False
    state = dataclasses.replace(
        state, removal_step=step, plane_mask=mask, removals=state.removals + (removal,)
    )
    return state, True


def removed_plane_residuals(ctx: TestingContext, state: TestingState) -> np.ndarray | None:
    """The plane residuals (m, 3) of the latest adjustment with those of the removed points
    filled in: the Gauss-Helmert residuals each would have at the final unknowns with its a
    priori sigmas (:func:`tlsjax._model._planes.observation_residuals`), so that a removed point
    is reported (and plotted) with its misfit, not at the 0 of its zero weight."""
    res = state.result
    if res.plane_residuals is None or state.plane_mask.all():
        return res.plane_residuals
    net, plan = ctx.network, ctx.reweighter.plan
    params, spec = state.adjusted.solution.params, plan.spec
    k = np.flatnonzero(~state.plane_mask)
    # The removed points padded to a power of two (copies of the first): one compiled program
    # serves runs that removed about as many.
    rows = np.concatenate([k, np.full(max(8, 1 << (len(k) - 1).bit_length()) - len(k), k[0])])
    si = net.plane_scan_index[rows]
    v = _removed_residuals(
        (spec.scanners, spec.ap_names, spec.ap_slices),
        params.prims[plan.plane_family],
        params.eops,
        params.aps,
        net.plane_index[rows],
        si,
        net.plane_observations[rows],
        1.0 / ctx.plane_sigma[rows],
        net.instrument_of_scan[si],
    )
    out = np.array(res.plane_residuals, dtype=float)
    out[k] = np.asarray(v)[: len(k)]
    return out


@functools.partial(jit, static_argnums=0)
def _removed_residuals(sl, prims, eops, aps, plane, scan, l, weight, instrument):
    """:func:`observation_residuals` of the points (plane, scan, l, weight, instrument), in one
    compiled program (vmapped eagerly, its operations and their derivatives ran one by one:
    about 2 s of a plane calibration's report)."""

    def one(p, s, l, w, i):
        return observation_residuals(prims[p], eops[s], aps, l, w, *sl, i)

    return jax.vmap(one)(plane, scan, l, weight, instrument)
