"""The named steps of :func:`tlsjax.self_calibrate`, and their order (:data:`PIPELINE`).

Each step is ``step(ctx, state) -> state`` over the explicit :class:`._pipeline.TestingState`
(see :mod:`._pipeline`); the statistics they call are pure functions (:mod:`tlsjax._stats`,
:mod:`tlsjax._adjustment._quality`, :mod:`._variance_factors`).

0. **Plane screening** (:func:`plane_screening`, with ``plane_screening``, plane points and no
   snooping): IGG-III reweighting of the plane points' conditions (:mod:`._robust`); the points
   beyond the family-wise value leave, the others keep their a priori weights.
1. **Robust start** (:func:`robust_start`, with ``screening.robust_start``): gross
   errors out before the first least-squares adjustment, which would spread a blunder of
   metres over correct observations (or not converge). The misclosures at the approximate
   values give the first IGG-III weights (Yang 1999); iteratively reweighted adjustments
   follow, first with the APs held at zero (a wide band: only errors far beyond the systematic
   misfit lose weight), then with the model's APs. The statistic is each observation's deleted
   residual over its standard deviation, divided by the group's robust scale. Observations
   beyond the family-wise critical value at the end are removed (attributed to the observation
   holding the error), unless a missing term's score test explains more; the least-squares
   steps start from its estimates.
2. **A priori tests** (:func:`a_priori_tests`): the first adjustment, with the a priori
   sigmas; the global test ``v^T P v ~ chi^2(r)`` and one test per group ``Omega_g = v_g^T P_g
   v_g ~ chi^2(r_g)`` (the group variance-factor test JAG3D reports). A global test computed
   after the variance factors were fitted to the same residuals cannot fail (its sigma0 is 1
   by construction), so these are the tests of the stochastic model.
3. **Screening** (:func:`screening`, with ``screening``, for any weighting): gross errors out
   before VCE (Koch
   1999, sec. 3.8). VCE fitted to data with blunders inflates the factors until the blunders
   look normal (a 1 m range error turns the range factor into ~5,000 and hides itself). Each
   group's scale is estimated robustly, ``s_g = median |u_i| / 0.6745`` of ``u_i = v_i /
   (sigma_i sqrt(r_i))`` (a few blunders do not move a median), which first rebalances groups
   whose a priori sigmas are far off (undone afterwards without VCE); then the largest
   ``|u_i| / s_g`` above the family-wise critical value ``N^-1(1 - alpha_s / (2 n))`` is
   removed and the network re-adjusted, until none is, or until a candidate term's score
   statistic exceeds ``u_i^2`` (:func:`_systematic`: the misfit is systematic, and a warning
   names the term); the a priori tests are repeated on the screened observations.
4. **Selection** (:func:`selection`, with ``selection``): stepwise AP selection
   (:func:`._selection.select_terms`) on the screened observations, entering terms by their
   score tests; the chosen model is the model of every step after it, and its a priori tests
   are recorded.
5. **Variance components** (:func:`variance_components`, with ``vce``): VCE per group, range, horizontal
   direction, elevation angle and levelling (Förstner 1979; Koch 1999, sec. 3.6), ``s_g^2 =
   v_g^T P_g v_g / r_g``; the group's sigmas are multiplied by ``s_g`` and the adjustment is
   repeated until every ``s_g^2`` is 1 within tolerance. Safeguards: the iteration runs in log
   space with a bounded step, halved where it changes sign (oscillation); a group with too
   little redundancy is held; residuals at rounding level (noise-free data) stop it; a factor
   beyond :data:`VCE_FACTOR_LIMIT` stops it. Every stop is a :class:`VCEResult` with its
   reason, never a NaN; only the weights change, and they are traced arrays of the compiled
   adjustment, so re-weighting never recompiles.
6. **Data snooping** (:func:`data_snooping`, with ``snooping``; Baarda 1968): ``w_i = v_i / (sigma_i sqrt(r_i))``
   with the sigmas in use (after VCE: the re-estimated group sigmas); the largest ``|w_i|``
   above the critical value (3.29 for alpha = 0.1 %) is removed, the network re-adjusted and
   the variance components re-estimated, until no test rejects. Every removal is reported.
7. **Missing terms** (:func:`missing_terms`, with ``tests.score_tests``): the score test of
   every candidate term not in the model at the final adjustment (:mod:`._score`).
8. **Cross-validation** (:func:`cross_validation`): the slot of the prediction of held-out
   scans (issue 41); it changes nothing yet.

Both screening and the robust start weigh a removal against the candidate terms (Baarda's
alternative hypotheses, SPEC section 7: the score test ``T_c`` of a term missing from the model
against the largest ``w_i^2``), so a systematic misfit becomes a term and only an isolated one
a removal.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .._adjustment._quality import w_tests
from .._stats import (
    global_test,
    group_variance_test,
    normal_critical_value,
    robust_scale,
    snooping_critical_value,
)
from ._options import SnoopingOptions
from ._outcome import GROUPS, VCEResult
from ._pipeline import (
    PIN_SIGMA,
    ROUNDING_SIGMA,
    NamedStep,
    TestingContext,
    TestingState,
    add_history,
    add_warning,
    adjust,
    dominant_misfit,
    group_statistics,
    plane_w,
    remove,
    remove_plane_point,
    restore_last_ok,
    rounding_groups,
    score_tests_at,
    sigmas,
    with_factors,
)
from ._robust import screen_planes
from ._selection import select_terms
from ._variance_factors import bounded_log_step, implausible_factor

#: Largest change of a variance factor in one VCE iteration (a factor 100 in sigma).
VCE_MAX_STEP = np.log(1e4)
#: Variance factors beyond this (either way; a factor 1e10 in sigma) stop VCE.
VCE_FACTOR_LIMIT = 1e20
#: Fewest testable observations of a group for a robust scale.
MIN_SCREENED = 10
#: Robust re-weighting steps that balance the groups before screening.
ROBUST_REWEIGHTING = 4


# --- 1. Robust start --------------------------------------------------------------------------


def robust_start(ctx: TestingContext, state: TestingState) -> TestingState:
    """Gross errors out before the first least-squares adjustment (module docstring, step 1):
    iteratively reweighted adjustments with the IGG-III weight of the robustly normalised
    residuals, first with the APs held at zero (the geometry alone: a blunder of metres stands
    out of any systematic misfit), then with the model's APs; the observations beyond the
    family-wise critical value at the last reweighting are removed and reported, and the
    least-squares steps start from their estimates. On with ``screening`` and ``robust_start``."""
    t = ctx.options.screening
    if t is None or not t.robust_start or ctx.plane_igg3:
        return state
    start = state
    labels = tuple(ctx.reweighter.plan.ap_labels)
    # Before any step: the misclosures at the approximate values (APs at zero) set the first
    # weights, so that the first adjustment already gives a blunder of metres no weight.
    at_x0 = adjust(ctx, dataclasses.replace(state, fixed_aps=labels or None), max_iterations=0)
    z, _ = _robust_normalised(ctx, at_x0)
    factor = _igg3_factor(ctx, z, np.ones_like(ctx.base_sigma), gross=True)
    state = dataclasses.replace(state, n_adjustments=at_x0.n_adjustments)
    for fixed in (labels, None) if labels else (None,):
        state = dataclasses.replace(state, fixed_aps=fixed)
        state, factor = _reweight(ctx, state, factor, gross=fixed is not None)
    if state.adjusted is None or not state.adjusted.result.ok:
        # Nothing robust to go on: the least-squares steps start as before (and report).
        return dataclasses.replace(start, n_adjustments=state.n_adjustments)
    u, scale = _robust_normalised(ctx, state)
    n = int(np.isfinite(u).sum())
    k1 = normal_critical_value(t.family_level / max(n, 1))
    # Baarda's alternatives compared (SPEC section 7): where a missing term explains more of
    # the misfit than removing an observation would, that observation stays (the tails of a
    # systematic misfit are not blunders); the term is named by the score tests at the end.
    tests = score_tests_at(ctx, state) if ctx.options.tests.score_tests else None
    best = tests.best() if tests is not None else None
    floor = best.statistic if best is not None and best.significant else 0.0
    state = dataclasses.replace(state, robust_factor=None, fixed_aps=None)
    why = f"robust start: |w| / robust scale above the family-wise critical value {k1:.2f}"
    kept = 0
    for i, g in _beyond(u, k1):
        if u[i, g] ** 2 * scale[g] ** 2 <= floor:
            kept += 1
        elif state.mask[i, g]:
            state = remove(ctx, state, i, g, u, why)
    if kept:
        state = add_warning(
            state,
            f"robust start: {kept} observation(s) beyond {k1:.2f} kept: the term {best.name} "
            f"({best.group}) explains more of the misfit (T = {best.statistic:.1f}) than "
            "removing any of them would",
        )
    return dataclasses.replace(state, last_ok=None, adjusted=None)


#: Upper end of the IGG-III band of the stages without APs, in family-wise critical values.
GROSS_BAND = 4.0
#: Largest number of reweighted adjustments per stage of the robust start.
ROBUST_ITERATIONS = 8
#: Smallest weight factor of the robust start: small enough that a blunder of metres has no
#: effect, large enough that its residual and redundancy number stay defined (weight 0 means
#: removed, :mod:`tlsjax._adjustment._quality`).
ROBUST_FLOOR = 1e-8


def _robust_normalised(ctx: TestingContext, state: TestingState):
    """``u_i / s_g``, NaN where removed or untestable, and the scales ``s_g`` (the robust scale
    of each group's u's). ``u_i`` is the residual of observation i deleted from the reweighted
    adjustment, ``d_i = v_i / r_i``, over its standard deviation ``sqrt(sigma_i^2 + q_i)``
    (``q_i`` the variance of its prediction by the others): with weight factor ``f`` and
    redundancy number ``r`` of the reweighted adjustment (Sherman-Morrison),

        u_i = v_i sqrt(f) / (sigma_i sqrt(r) sqrt(f r + 1 - r)),

    Baarda's w-test when f = 1, and for a down-weighted observation its misclosure against
    the others in units of its full standard deviation: near the nadir, where the others fix
    a target's horizontal direction poorly, a correct direction is not mistaken for a blunder."""
    res = state.result
    f = np.ones_like(ctx.base_sigma) if state.robust_factor is None else state.robust_factor
    r = np.clip(res.redundancy, 0.0, 1.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        r_full = r * (f * r + 1.0 - r) / f  # so that v / (sigma sqrt(r_full)) is u above
    u = np.where(state.mask, w_tests(res.residuals, sigmas(ctx, state), r_full), np.nan)
    scale = np.full(3, np.nan)
    for g in range(3):
        keep = np.isfinite(u[:, g]) & (res.redundancy[:, g] >= ctx.options.tests.min_redundancy)
        scale[g] = robust_scale(u[:, g], keep, MIN_SCREENED)
    # Residuals at rounding level (noise-free data): nothing to judge (rounding is no blunder).
    rounding = scale * np.median(ctx.base_sigma, axis=0) < np.asarray(ROUNDING_SIGMA[:3])
    ok = np.isfinite(scale) & (scale > 0) & ~rounding
    with np.errstate(invalid="ignore", divide="ignore"):
        return u / np.where(ok, scale, np.nan)[None, :], scale


def _reweight(ctx: TestingContext, state: TestingState, factor, gross: bool):
    """IGG-III reweighting (Yang 1999; :func:`._robust.igg3`) to a fixed point: k0 the per-test
    critical value of the w-test, k1 the family-wise one. Returns the state (with the weight
    factors in use) and the factors; an adjustment that fails ends it at the last good one."""
    for _ in range(ROBUST_ITERATIONS):
        trial = adjust(ctx, dataclasses.replace(state, robust_factor=factor))
        if not trial.ok:
            return (state if state.adjusted is not None else trial), factor
        state = trial
        z, _ = _robust_normalised(ctx, state)
        if not np.isfinite(z).any():
            return state, factor
        new = _igg3_factor(ctx, z, factor, gross)
        done = np.max(np.abs(new - factor)) < 1e-3
        factor = new
        if done:
            break
    return state, factor


def _igg3_factor(ctx: TestingContext, z, factor, gross: bool = False):
    """IGG-III weight factors of the robustly normalised residuals ``z`` (k0 the per-test
    critical value, k1 the family-wise one), at least :data:`ROBUST_FLOOR`; ``factor`` where
    ``z`` is not finite. ``gross``: the band of the stages with the APs held at zero, from the
    family-wise value to :data:`GROSS_BAND` times it: there the systematic misfit of the
    missing APs widens the tails (steep targets under collimation and trunnion errors), and
    only errors far beyond it may lose their weight, or the APs lose the observations that
    determine them."""
    from ._robust import igg3

    n = max(int(np.isfinite(z).sum()), 1)
    k0 = normal_critical_value(ctx.options.w_test_level)
    k1 = max(normal_critical_value(ctx.options.screening.family_level / n), k0 + 0.5)
    if gross:
        k0, k1 = k1, GROSS_BAND * k1
    return np.where(np.isfinite(z), np.maximum(igg3(z, k0, k1), ROBUST_FLOOR), factor)


def _beyond(z, k):
    """(row, group) of every finite ``|z| > k``, largest first."""
    az = np.where(np.isfinite(z), np.abs(z), -1.0)
    idx = np.argwhere(az > k)
    order = np.argsort(-az[idx[:, 0], idx[:, 1]]) if len(idx) else []
    return [(int(idx[j, 0]), int(idx[j, 1])) for j in order]


# --- 2. A priori tests ------------------------------------------------------------------------


def a_priori_tests(ctx: TestingContext, state: TestingState) -> TestingState:
    """The first adjustment, with the a priori sigmas, and its global and group tests; when it
    fails, a warning that names a far-off sigma0 (a unit mix-up of all groups)."""
    state = adjust(ctx, state)
    if state.ok:
        return record_a_priori_tests(ctx, state, _first_stage(state))
    dominant = dominant_misfit(ctx, state)
    if dominant:
        return add_warning(state, f"at the failed first adjustment: {dominant}")
    if np.isfinite(state.result.sigma0):
        hint = implausible_factor("all groups", state.result.sigma0**2)
        if hint:
            state = add_warning(state, f"at the failed first adjustment: {hint}")
    return state


def _first_stage(state: TestingState) -> str:
    """The name of the observations of the first least-squares adjustment."""
    n = len(state.removals)
    if n:
        return f"after the robust start ({n} removed)"
    k = 0 if state.plane_screening is None else len(state.plane_screening.removed)
    return f"after the plane screening ({k} plane points removed)" if k else "all observations"


def record_a_priori_tests(ctx: TestingContext, state: TestingState, stage: str) -> TestingState:
    """Global and group tests at the latest adjustment (a priori weights), as one stage."""
    alpha = ctx.options.tests.global_test_level
    s2, r_g, n_g = group_statistics(ctx, state)
    groups = {
        g: group_variance_test(float(s2[i] * r_g[i]), float(r_g[i]), alpha)
        for i, g in enumerate(GROUPS)
        if n_g[i] > 0
    }
    res = state.result
    entry = {"stage": stage, "global": global_test(res.sigma0, res.dof, alpha), "groups": groups}
    return dataclasses.replace(state, a_priori_tests=state.a_priori_tests + (entry,))


# --- 3. Screening -----------------------------------------------------------------------------


def screening(ctx: TestingContext, state: TestingState) -> TestingState:
    """Gross-error screening before VCE (module docstring), then the a priori tests again on
    the screened observations. With ``screening`` (any weighting: without ``vce`` the robust
    group balancing is undone afterwards and the a priori sigmas kept; plane points have no VCE,
    and the robust scale protects the snooping that follows) and a first adjustment that
    succeeded."""
    if not (state.ok and ctx.options.screening is not None) or ctx.plane_igg3:
        return state
    n_before = len(state.removals)
    state = _screen(ctx, state)
    if len(state.removals) > n_before and state.ok:
        state = _a_priori_after_screening(ctx, state)
    if ctx.options.vce is None and np.any(state.factor != 1.0):
        state = adjust(ctx, with_factors(state, np.ones(len(GROUPS))))
    return state


def _standardised(ctx: TestingContext, state: TestingState):
    """``u = v / (sigma sqrt(r))`` at the weights in use (NaN where removed or untestable) and
    each group's robust scale (NaN for a group with too few testable observations)."""
    res = state.result
    u = np.where(state.mask, w_tests(res.residuals, sigmas(ctx, state), res.redundancy), np.nan)
    scale = np.full(3, np.nan)
    for g in range(3):
        keep = np.isfinite(u[:, g]) & (res.redundancy[:, g] >= ctx.options.tests.min_redundancy)
        scale[g] = robust_scale(u[:, g], keep, MIN_SCREENED)
    return u, scale


def _balance_groups(ctx: TestingContext, state: TestingState):
    """Robust re-weighting before screening: a priori sigmas far off between the groups (e.g.
    ranges in mm read as m) distort the residuals of the others; each group's factor is set to
    its robust scale squared (bounded steps) until they agree within 10 %. Returns the state
    and False when the residuals are at rounding level (nothing to screen)."""
    for _ in range(ROBUST_REWEIGHTING):
        _, scale = _standardised(ctx, state)
        n_constraint = len(GROUPS) - 3
        if rounding_groups(ctx, state, np.append(scale**2, np.full(n_constraint, np.nan))):
            return state, False
        ok = np.isfinite(scale) & (scale > 0)
        step = bounded_log_step(scale, ok, VCE_MAX_STEP, power=2)
        if np.all(np.abs(step) < np.log(1.1)):
            return state, True
        # The weighted constraints (a few readings each, no robust scale of their own) move with
        # the others.
        step = np.append(step, np.full(n_constraint, step[ok].mean() if ok.any() else 0.0))
        limit = np.log(VCE_FACTOR_LIMIT)
        state = adjust(
            ctx, with_factors(state, np.exp(np.clip(np.log(state.factor) + step, -limit, limit)))
        )
        if not state.ok:
            return restore_last_ok(state), True
    return state, True


def _largest_w(w, wp=None):
    """Row, group and size of the largest finite ``|w|`` (-1 where there is none) over the
    target observations ``w`` (n, 3) and the plane points' conditions ``wp`` (m,); a plane
    point comes back as (row, :data:`PLANE`, size)."""
    aw = np.where(np.isfinite(w), np.abs(w), -1.0)
    i, g = np.unravel_index(int(np.argmax(aw)), aw.shape) if aw.size else (0, 0)
    top = float(aw[i, g]) if aw.size else -1.0
    if wp is not None and wp.size:
        ap = np.where(np.isfinite(wp), np.abs(wp), -1.0)
        k = int(np.argmax(ap))
        if ap[k] > top:
            return k, PLANE, float(ap[k])
    return int(i), int(g), top


#: The "group" of a plane point in :func:`_largest_w`: its condition, tested as a whole.
PLANE = -1


def _remove(ctx, state, i: int, g: int, w, wp, reason: str):
    """Remove what :func:`_largest_w` found: a target observation (:func:`._pipeline.remove`)
    or a plane point (:func:`._pipeline.remove_plane_point`); (state, removed)."""
    if g == PLANE:
        return remove_plane_point(ctx, state, i, float(wp[i]), reason)
    return remove(ctx, state, i, g, w, reason), True


def _plane_screening_w(ctx: TestingContext, state: TestingState):
    """The plane points' w-tests over their robust scale (the plane group's own
    ``median |w| / 0.6745``, so that plane sigmas off by any factor neither hide nor invent
    outliers), (m,); None without planes."""
    if not ctx.network.has_planes:
        return None
    wp = plane_w(ctx, state)
    scale = robust_scale(wp, np.isfinite(wp), MIN_SCREENED)
    return wp / scale if scale > 0 else np.full_like(wp, np.nan)


def _screen(ctx: TestingContext, state: TestingState) -> TestingState:
    """Robust group scales, family-wise critical value, largest first, re-adjusting after each
    removal; stops with a warning when more than ``max_share`` would go."""
    t = ctx.options.screening
    limit = max(1, int(t.max_share * (state.mask.sum() + state.plane_mask.sum())))
    state, balanced = _balance_groups(ctx, state)
    if not balanced:
        return state  # noise-free: nothing to screen; VCE says so
    removed = 0
    while True:
        u, scale = _standardised(ctx, state)
        with np.errstate(invalid="ignore", divide="ignore"):
            w = u / np.where(scale > 0, scale, np.nan)[None, :]
        wp = _plane_screening_w(ctx, state)
        n_tested = int(np.isfinite(w).sum()) + (0 if wp is None else int(np.isfinite(wp).sum()))
        if n_tested == 0:
            return state
        crit = normal_critical_value(t.family_level / n_tested)
        state = dataclasses.replace(state, screening_critical_value=crit)
        i, g, top = _largest_w(w, wp)
        if top <= crit:
            return state
        # A gross error (far beyond the band of a systematic misfit's tails, GROSS_BAND) is
        # removed without asking: a first least-squares adjustment spreads it over the
        # residuals, so a candidate term can look as if it explained it.
        # Score tests are of the target observations' model (:mod:`._score`): a plane point's
        # misfit is not weighed against a missing term.
        target = g != PLANE
        term = _systematic(ctx, state, u[i, g]) if target and top <= GROSS_BAND * crit else None
        if term is not None:
            return add_warning(state, term)
        if removed >= limit or len(state.removals) >= ctx.options.max_removals:
            return add_warning(
                state,
                f"screening stopped after {removed} removal(s) with |w| = {top:.1f} still above "
                f"{crit:.2f}: more than {100 * t.max_share:.0f}% of the observations "
                "fail; the functional model (APs, architecture) or the sigmas are wrong, not a "
                "few blunders",
            )
        why = "screening before VCE: robust |w| above the family-wise critical value"
        state, done = _remove(ctx, state, i, g, w, wp, why)
        if not done:
            return state
        state = adjust(ctx, state)
        removed += 1
        if not state.ok:
            return state


def _systematic(ctx: TestingContext, state: TestingState, u_top: float) -> str | None:
    """Baarda's alternative hypotheses compared (SPEC section 7): the reduction of ``v^T P v``
    by removing the observation with the largest w-test, ``w^2``, against the largest score
    statistic ``T_c`` of a candidate term (:mod:`._score`), both with the weights in use. When a
    significant term explains more, the misfit is systematic: screening stops (a warning
    names the term) instead of removing correct observations."""
    tests = score_tests_at(ctx, state) if ctx.options.tests.score_tests else None
    best = tests.best() if tests is not None else None
    if best is None or not best.significant or not best.statistic > u_top**2:
        return None
    return (
        f"screening stopped: the largest misfit is systematic, not a blunder: the term "
        f"{best.name} ({best.group}) would reduce v^T P v by {best.statistic:.1f} "
        f"({100 * best.share:.1f}%), more than removing the observation with the largest w-test "
        f"(w^2 = {u_top**2:.1f}); add it to the model (or use stepwise selection)"
    )


def _a_priori_after_screening(ctx: TestingContext, state: TestingState) -> TestingState:
    """The a priori tests again, on the screened observations (a priori weights)."""
    fitted = state.factor.copy()
    state = adjust(ctx, with_factors(state, np.ones(len(GROUPS))))
    if state.ok:
        state = record_a_priori_tests(ctx, state, "after screening")
    return adjust(ctx, with_factors(state, fitted))


# --- 4. Variance components -------------------------------------------------------------------


def variance_components(ctx: TestingContext, state: TestingState) -> TestingState:
    """VCE to its fixed point or to a safeguard's stop (module docstring), when ``vce`` is on,
    the latest adjustment succeeded and VCE has not stopped before."""
    if state.ok and ctx.options.vce is not None and state.vce_result == VCEResult.CONVERGED:
        return _vce(ctx, state)
    return state


def _vce(ctx: TestingContext, state: TestingState) -> TestingState:
    """Every stop leaves the state at weights whose adjustment succeeded."""
    t = ctx.options.vce
    prev_step = np.zeros(len(GROUPS))
    relax = np.ones(len(GROUPS))  # halved at every change of direction of a group's step
    flips = 0
    for it in range(t.max_iterations):
        s2, r_g, n_g = group_statistics(ctx, state)
        est = (r_g >= t.min_redundancy) & (n_g > 0)
        notes = tuple(
            f"redundancy r_g = {r_g[g]:.2f} < {t.min_redundancy:g}" if n_g[g] and not est[g] else ""
            for g in range(len(GROUPS))
        )
        state = dataclasses.replace(state, estimated=est, notes=notes)
        res = state.result
        entry = {"step": state.removal_step, "vce_iteration": it, "sigma0": res.sigma0}
        state = add_history(state, {**entry, "factors": state.factor.tolist(), "s2": s2.tolist()})
        if not est.any():
            return _stop(ctx, state, VCEResult.NO_REDUNDANCY)
        noise_free = rounding_groups(ctx, state, np.where(est, s2, np.nan))
        if noise_free:
            state = add_warning(
                state, f"residuals of {', '.join(noise_free)} at rounding level: noise-free data?"
            )
            return _stop(ctx, state, VCEResult.NOISE_FREE, reset=True)
        if not np.all(np.isfinite(s2[est]) & (s2[est] > 0)):
            return _stop(ctx, state, VCEResult.NONFINITE)
        if np.all(np.abs(s2[est] - 1.0) < t.tolerance):
            return dataclasses.replace(state, vce_result=VCEResult.CONVERGED)
        step = bounded_log_step(s2, est, VCE_MAX_STEP)
        flip = step * prev_step < 0
        relax = np.where(flip, 0.5 * relax, relax)  # damp an oscillation geometrically
        step = relax * step
        flips += int(flip.any())
        new = np.log(state.factor) + step
        if np.any(np.abs(new) > np.log(VCE_FACTOR_LIMIT)):
            g = int(np.argmax(np.abs(new)))
            state = add_warning(
                state,
                f"{GROUPS[g]}: the variance factor would pass {np.exp(new[g]):.3g}, beyond "
                f"{VCE_FACTOR_LIMIT:.0e} either way: the a priori sigmas are not plausible",
            )
            return _stop(ctx, state, VCEResult.FACTOR_LIMIT)
        state = adjust(ctx, with_factors(state, np.exp(new)))
        state = dataclasses.replace(state, vce_iterations=state.vce_iterations + 1)
        if not state.ok:
            return _adjustment_failed(ctx, state, est)
        prev_step = step
    return _stop(ctx, state, VCEResult.OSCILLATING if flips >= 3 else VCEResult.MAX_ITERATIONS)


def _adjustment_failed(ctx: TestingContext, state: TestingState, est) -> TestingState:
    """VCE stops where an adjustment with the new weights failed: the last weights whose
    adjustment succeeded are kept."""
    factors = ", ".join(f"{GROUPS[g]} {state.factor[g]:.4g}" for g in range(len(GROUPS)) if est[g])
    state = add_warning(
        state,
        f"VCE stopped: with the re-estimated weights (variance factors {factors}) the "
        f"adjustment failed: {state.result.message}; the last weights whose adjustment "
        "succeeded are kept",
    )
    return _stop(ctx, restore_last_ok(state), VCEResult.ADJUSTMENT_FAILED)


def _stop(ctx, state: TestingState, result: VCEResult, reset: bool = False) -> TestingState:
    """End VCE with ``result``; ``reset``: back to the a priori weights (re-adjusted)."""
    state = dataclasses.replace(state, vce_result=result)
    if reset and np.any(state.factor != 1.0):
        state = adjust(ctx, with_factors(state, np.ones(len(GROUPS))))
    if reset:
        notes = (result.message.split(":")[0],) * len(GROUPS)
        state = dataclasses.replace(state, estimated=np.zeros(len(GROUPS), dtype=bool), notes=notes)
    return state


# --- 5. Data snooping -------------------------------------------------------------------------


def data_snooping(ctx: TestingContext, state: TestingState) -> TestingState:
    """Baarda's data snooping (module docstring): one rejection at a time, each followed by a
    re-adjustment and the variance components re-estimated. Without ``snooping`` it only
    records the w-tests' critical value and the history line of the final adjustment."""
    while state.ok:
        state, removed = _snoop_once(ctx, state)
        if not removed:
            break
        state = adjust(ctx, state)
        if not state.ok:
            break
        state = variance_components(ctx, state)
    return state


def _snoop_once(ctx: TestingContext, state: TestingState):
    """One test of every observation; (state, True) when the largest |w| was removed."""
    t, res = ctx.options.snooping or SnoopingOptions(), state.result
    w = np.where(state.mask, w_tests(res.residuals, sigmas(ctx, state), res.redundancy), np.nan)
    wp = plane_w(ctx, state) if ctx.network.has_planes else None
    n_tested = int(np.isfinite(w).sum()) + (0 if wp is None else int(np.isfinite(wp).sum()))
    crit = snooping_critical_value(
        t.w_test_level, n_tested, bonferroni=t.bonferroni, given=t.critical_value
    )
    state = add_history(
        dataclasses.replace(state, critical_value=crit),
        {
            "step": state.removal_step,
            "sigma0": res.sigma0,
            "max_abs_w": _largest_w(w, wp)[2] if n_tested else None,
            "critical": crit,
            "factors": state.factor.tolist(),
        },
    )
    if ctx.options.snooping is None or n_tested == 0:
        return state, False
    i, g, top = _largest_w(w, wp)
    if top <= crit:
        return state, False
    if len(state.removals) >= t.max_removals:
        text = (
            f"snooping stopped after max_removals = {t.max_removals} with |w| = {top:.2f} "
            f"still above {crit:.2f}"
        )
        return add_warning(state, text), False
    return _remove(ctx, state, i, g, w, wp, "largest |w| above critical value")


# --- Plane screening (IGG-III) ----------------------------------------------------------------


def plane_screening(ctx: TestingContext, state: TestingState) -> TestingState:
    """The IGG-III screening of the plane points (:func:`._robust.screen_planes`) on the
    analysed adjustment, where :attr:`._pipeline.TestingContext.plane_igg3`: the points beyond
    k1 leave the plane mask, and the estimates of its last reweighting warm-start the first
    least-squares adjustment (the a priori tests), whose a priori weights of the points kept
    give the estimates, sigmas and tests."""
    if not ctx.plane_igg3:
        return state
    found, params = screen_planes(ctx.reweighter.adjustment, ctx.options.plane_screening)
    mask = state.plane_mask.copy()
    mask[found.removed] = False
    return dataclasses.replace(
        state,
        plane_mask=mask,
        plane_screening=found,
        params=params,
        n_adjustments=state.n_adjustments + found.iterations,
    )


# --- Selection --------------------------------------------------------------------------------


def selection(ctx: TestingContext, state: TestingState) -> TestingState:
    """Stepwise AP selection (:func:`._selection.select_terms`, with ``selection``) from the
    model's APs, every fit with the a priori weights of the observations the robust start and
    screening kept and their pinned targets; the chosen model replaces the model for the steps
    after it (its context is analysed once: :meth:`._pipeline.TestingContext.for_state`), and
    its a priori tests are recorded on the screened observations."""
    options = ctx.options.selection
    if options is None or not state.ok:
        return state
    data = {"weights": np.where(state.mask, 1.0 / ctx.base_sigma, 0.0)}
    if state.pinned:
        data["control"] = {t: (xyz, PIN_SIGMA) for t, xyz in state.pinned.items()}
    if ctx.network.has_planes:
        data["plane_weights"] = np.where(state.plane_mask[:, None], 1.0 / ctx.plane_sigma, 0.0)
    chosen = select_terms(
        ctx.network, ctx.model, options, ctx.reweighter.options, data, state.removals
    )
    if chosen.aps == tuple(ctx.model.scanner.aps):
        return dataclasses.replace(state, selection=chosen)
    scanner = dataclasses.replace(ctx.model.scanner, aps=chosen.aps)
    model = dataclasses.replace(ctx.model, scanner=scanner)
    state = dataclasses.replace(
        state, model=model, selection=chosen, params=None, adjusted=None, last_ok=None
    )
    new = ctx.for_state(state)
    fitted = state.factor.copy()
    state = adjust(new, with_factors(state, np.ones(len(GROUPS))))
    if state.ok:
        state = record_a_priori_tests(new, state, f"after selection ({' '.join(chosen.aps)})")
    if np.any(fitted != 1.0):
        state = adjust(new, with_factors(state, fitted))
    return state


# --- Score tests of the missing terms ---------------------------------------------------------


def missing_terms(ctx: TestingContext, state: TestingState) -> TestingState:
    """The score test of every candidate term not in the model at the final adjustment
    (:mod:`._score`), with ``tests.score_tests``; target networks (the plane conditions are not
    tested for missing terms)."""
    if not ctx.options.tests.score_tests or ctx.network.has_planes:
        return state
    return dataclasses.replace(state, score_tests=score_tests_at(ctx, state))


# --- Cross-validation -------------------------------------------------------------------------


def cross_validation(ctx: TestingContext, state: TestingState) -> TestingState:
    """Slot for cross-validation by scan groups (issue 41): calibrate on the other scans,
    predict the held-out ones. It returns the state it was given until the module that does it
    lands; it will read its settings from ``ctx.options`` and put what it finds in the state,
    like the other steps."""
    return state


#: The steps of :func:`tlsjax.self_calibrate`, in order: the one place they are listed.
PIPELINE = (
    NamedStep("plane screening", plane_screening),
    NamedStep("robust start", robust_start),
    NamedStep("a priori tests", a_priori_tests),
    NamedStep("screening", screening),
    NamedStep("selection", selection),
    NamedStep("variance components", variance_components),
    NamedStep("data snooping", data_snooping),
    NamedStep("missing terms", missing_terms),
    NamedStep("cross-validation", cross_validation),
)
