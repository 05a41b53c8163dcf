"""The run of the pipeline of :func:`tlsjax.self_calibrate` (SPEC sections 5 and 7) and the
outcome it assembles from the pipeline's final state.

The parts live in their own modules:

* :mod:`._options`: the settings, one object per concern (:class:`._options.CalibrationOptions`);
* :mod:`._outcome`: what the run finds (:class:`._outcome.TestedCalibration`,
  :class:`._outcome.VCEResult`, :class:`._outcome.Removal`, :class:`._outcome.VarianceComponent`);
* the statistics, pure functions: :mod:`tlsjax._stats` (distributions, critical values, global
  and group tests, robust scales), :mod:`tlsjax._adjustment._quality` (w-tests, MDB, external
  reliability), :mod:`tlsjax._adjustment._ap_tests`, :mod:`._variance_factors`;
* :mod:`._pipeline`: the explicit state of a run (:class:`._pipeline.TestingState`), what stays
  fixed (:class:`._pipeline.TestingContext`) and the transitions the steps share;
* :mod:`._steps`: the named steps and their order, :data:`._steps.PIPELINE`.

Units: SI inside, millimetres and arc seconds in the reports.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from .._adjustment._ap_tests import ap_t_tests
from .._adjustment._config import CalibrationModel
from .._adjustment._families import Params
from .._adjustment._network import Network
from .._adjustment._plan import initial_params
from .._adjustment._quality import external_reliability, minimal_detectable_bias, w_tests
from .._stats import snooping_critical_value
from ._crossval import CrossValidation, CrossValidationOptions, validate
from ._options import CalibrationOptions, SnoopingOptions
from ._outcome import GROUPS, TestedCalibration, VarianceComponent, VCEResult
from ._pipeline import (
    TestingContext,
    TestingState,
    dominant_misfit,
    group_statistics,
    plane_w,
    removed_plane_residuals,
    run_pipeline,
    sigmas,
)
from ._score import ScoreTester, ScoreTests
from ._steps import PIPELINE
from ._variance_factors import implausible_factor


def run_tests(
    network: Network,
    model: CalibrationModel,
    options: CalibrationOptions,
    steps=PIPELINE,
    warnings: tuple = (),
) -> TestedCalibration:
    """Run ``steps`` (default the whole :data:`._steps.PIPELINE`) on ``network`` with
    ``model`` and ``options`` (checked by the caller) and assemble what they found;
    ``warnings``: what the caller found before (reported with the steps' own). Every
    re-adjustment is the one compiled adjustment of the model with other weights: nothing
    recompiles, except once for a model that selection chose."""
    ctx = TestingContext.make(network, model, options)
    if options.tests.score_tests and ctx.score_tester is not None and ctx.score_tester.candidates:
        # Compiled while the model's adjustment compiles (XLA runs without Python's lock):
        # a first run waits for the longer of the two programs, not for both.
        ctx.score_tester.prepare()
    snooping = options.snooping or SnoopingOptions()
    crit = snooping_critical_value(
        snooping.w_test_level,
        int(network.observations.size) + int(network.plane_observations.shape[0]),
        bonferroni=snooping.bonferroni,
        given=snooping.critical_value,
    )
    start = dataclasses.replace(TestingState.initial(ctx, crit), warnings=tuple(warnings))
    state = run_pipeline(ctx, start, steps)
    return tested_calibration(ctx.for_state(state), state)


def tested_calibration(ctx: TestingContext, state: TestingState) -> TestedCalibration:
    """Final quantities at the last adjustment: w-tests, reliability, variance components,
    warnings and the message."""
    t, res, mask = ctx.options.tests, state.result, state.mask
    vce_result = state.vce_result
    if ctx.vce and not state.ok and vce_result == VCEResult.CONVERGED:
        vce_result = VCEResult.ADJUSTMENT_FAILED
    delta0 = t.delta0
    sig = sigmas(ctx, state)
    w = np.where(mask, w_tests(res.residuals, sig, res.redundancy), np.nan)
    mdb = np.where(mask, minimal_detectable_bias(sig, res.redundancy, delta0), np.nan)
    ext, ext_ap = external_reliability(
        state.adjusted.influence, res.redundancy, mask, delta0, res.ap_names
    )
    unc = tuple(
        (int(i), GROUPS[g]) for i, g in zip(*np.nonzero(mask & (res.redundancy < t.min_redundancy)))
    )
    vcs = _variance_components(ctx, state)
    dominant = dominant_misfit(ctx, state) if state.adjusted is not None else None
    warnings = state.warnings + (
        () if dominant else _factor_warnings(state, vcs, vce_result)
    )  # one observation holding the misfit says nothing about the units
    if dominant and not any(dominant in w for w in warnings):
        warnings += (dominant,)
    parts = [res.message]
    if ctx.vce:
        parts.append(vce_result.message)
    n_points = sum(o.group == "plane" for o in state.removals)
    if len(state.removals) > n_points:
        parts.append(f"{len(state.removals) - n_points} observation(s) removed")
    if n_points:
        parts.append(f"{n_points} plane point(s) removed")
    if warnings:
        parts.append(f"{len(warnings)} warning(s)")
    planes = _plane_quality(ctx, state, delta0)
    if planes:
        res = dataclasses.replace(res, plane_residuals=planes.pop("residuals"))
    return TestedCalibration(
        calibration=res,
        model=ctx.model,
        options=ctx.options,
        outliers=state.removals,
        variance_components=tuple(vcs),
        mask=mask,
        sigmas=sig,
        w=w,
        critical_value=float(state.critical_value),
        mdb=mdb,
        external=ext,
        external_ap=ext_ap,
        uncontrolled=unc,
        ap_tests=ap_t_tests(res, t.ap_test_level) if res.ok else (),
        pinned_targets=tuple(ctx.network.targets[i] for i in state.pinned),
        history=state.history,
        n_adjustments=state.n_adjustments,
        message="; ".join(parts),
        a_priori_tests=state.a_priori_tests,
        vce_result=vce_result,
        vce_iterations=state.vce_iterations,
        screening_critical_value=state.screening_critical_value,
        warnings=warnings,
        score_tests=state.score_tests,
        selection=state.selection,
        plane_screening=state.plane_screening,
        cross_validation=state.cross_validation,
        **planes,
    )


def _plane_quality(ctx: TestingContext, state: TestingState, delta0: float) -> dict:
    """The plane points' tests and reliability at the final adjustment ({} without planes):
    ``plane_w`` (m,), ``plane_mdb`` (m, 3) the bias of each observation that the point's
    condition test detects, ``delta0 sigma_k / sqrt(r_k)`` (:func:`minimal_detectable_bias`
    with the observation's share of the condition's redundancy), ``plane_external`` (m,) and
    ``plane_external_ap``, and the residuals with those of the removed points filled in."""
    if not ctx.network.has_planes:
        return {}
    res, mask = state.result, state.plane_mask
    ext, ext_ap = external_reliability(
        state.adjusted.plane_influence,
        res.plane_redundancy.sum(axis=1, keepdims=True),
        mask[:, None],
        delta0,
        res.ap_names,
    )
    mdb = minimal_detectable_bias(ctx.plane_sigma, res.plane_redundancy, delta0)
    return dict(
        residuals=removed_plane_residuals(ctx, state),
        plane_mask=mask,
        plane_w=plane_w(ctx, state),
        plane_mdb=np.where(mask[:, None], mdb, np.nan),
        plane_external=ext[:, 0],
        plane_external_ap=ext_ap[:, 0],
    )


def _variance_components(ctx: TestingContext, state: TestingState) -> list:
    """One :class:`VarianceComponent` per group with observations, at the final weights."""
    s2, r_g, n_g = group_statistics(ctx, state)
    vce = ctx.vce
    out = []
    for gi, gname in enumerate(GROUPS):
        if n_g[gi] == 0:
            continue
        base = ctx.group_sigma(gi)
        ap = float(np.median(base))
        f = float(state.factor[gi])
        out.append(
            VarianceComponent(
                gname,
                f,
                float(np.sqrt(f)),
                float(r_g[gi]),
                int(n_g[gi]),
                bool(state.estimated[gi]) if vce else False,
                ap,
                ap * float(np.sqrt(f)),
                state.notes[gi] if vce else "",
            )
        )
    return out


def _factor_warnings(state: TestingState, vcs, vce_result: VCEResult) -> tuple:
    """Implausible variance factors, named: the estimated ones, or (without VCE, or where a
    group was held) the a priori group factors of the last a priori test."""
    groups = state.a_priori_tests[-1]["groups"] if state.a_priori_tests else {}
    out = []
    for vc in vcs:
        if vc.estimated:
            text = implausible_factor(vc.group, vc.factor)
        elif vc.group in groups and groups[vc.group]["factor"] is not None:
            text = implausible_factor(vc.group + " (a priori)", groups[vc.group]["factor"])
        else:
            text = None
        if text and vce_result != VCEResult.NOISE_FREE:
            out.append(text)
    return tuple(out)


def score_tests(
    network: Network,
    model: CalibrationModel | None,
    result,
    options: CalibrationOptions | None = None,
) -> ScoreTests:
    """Score tests of the terms missing from ``model`` at ``result`` (a
    :class:`tlsjax.CalibrationResult` of ``network`` with the network's weights): the
    missing-terms step of :func:`tlsjax.self_calibrate` on a result of one's own. From
    ``options``: the candidates and the family-wise level (``options.tests``: default every
    registered term of the model's naming at 5 %) and the solver. See :mod:`._score`."""
    if network.has_planes:
        raise ValueError(
            f"{network.source}: score tests of missing terms are for target networks (the plane "
            "conditions are not tested yet)"
        )
    model = model or CalibrationModel()
    options = options or CalibrationOptions()
    tester = ScoreTester(network, model, options.tests.candidates, options.solver)
    p = initial_params(network, tester.adjustment.plan, result.target_xyz, result.eops)
    narrow = Params(p.prims, p.eops, jnp.asarray(result.ap_values))
    return tester(narrow, alpha=options.tests.score_test_level)


def cross_validate(
    network: Network,
    model: CalibrationModel | None = None,
    options: CalibrationOptions | None = None,
    *,
    result=None,
) -> CrossValidation:
    """Cross-validation of ``model`` on ``network`` by scan groups (SPEC section 7,
    "Prediction"; :mod:`._crossval`): each fold's scans held out, the rest adjusted (the one
    compiled adjustment, held-out weights zeroed), the held-out scans corrected with the rest's
    APs and placed by their own pose on its targets; the misfit RMS (3D and per axis, mm) with
    the APs and with none, per fold and overall, and a code that says whether the calibration
    improves the prediction. The cross-validation step of :func:`tlsjax.self_calibrate` on a
    model and weights of one's own.

    ``options``: the folds and placement (``options.cross_validation``, default
    :class:`tlsjax.CrossValidationOptions`) and the solver. ``result``: a
    :class:`tlsjax.CalibrationResult` of this network and model whose removed observations
    stay out (of the folds' adjustments and of the placement) and whose estimates warm-start
    the folds; None: the network is calibrated first with its own weights.
    """
    options = options or CalibrationOptions()
    folds = options.cross_validation or CrossValidationOptions()
    return validate(network, model, folds, options.solver, result)
