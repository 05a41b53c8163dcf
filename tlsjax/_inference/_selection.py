"""Stepwise selection of additional parameters that ends where prediction is best (SPEC
section 7, "Prediction"; issue 41 item 3).

It runs as the selection step of :func:`tlsjax.self_calibrate` (:mod:`._steps`), after the robust
start and screening of the start set: the observations they removed stay out of every fit of
the selection (the weights and pinned targets it is given), so a blunder can neither pose as a
term nor push one out.

**One statistic, one variance factor.** A term enters and leaves by the same measure: the
reduction of ``v^T P v`` that it brings, in units of the current fit's variance factor
``s0^2`` (a posteriori). Entering, the score test ``T_c / s0^2`` (:mod:`._score`: no refit per
candidate); leaving, the Wald statistic ``t^2 = (a / sigma_a)^2`` with the a posteriori sigma
(the same quantity to first order for a term in the model). Both against one critical value,
the chi^2(1) quantile at the family-wise level ``test_level`` (Bonferroni over the candidates), so a
term cannot enter on its raw score and leave on a t value scaled by a large sigma0. A term the
fit cannot estimate leaves first; a term that left is not tried again (no cycles).

**Alternatives decided by prediction.** The candidate with the largest statistic may belong to a
group of alternatives (:attr:`._score.ScoreTests.groups`: their effects after the model
correlate beyond 0.9, their statistics are nearly equal whatever the truth). Every significant
member of the group is fitted and cross-validated (:mod:`._crossval`). For terms of one
dimension every information criterion ranks them by their reduction of ``v^T P v``, i.e. by the
statistic; the cross-validation confirms it or overrides it: a member that predicts the
held-out scans better by more than twice the standard error of the paired difference over the
folds enters instead. (With a correct stochastic model the statistic is the more powerful
judge; where the misfit holds what the model does not describe, prediction is the honest one.)
The same holds for a term that would enter beside a near-equivalent already in the model
(their correlation beyond ``max_correlation``): its statistic passes on the small part of its
effect that the other does not carry, while the two estimates become inflated and opposite; it
enters only where the cross-validation confirms it, i.e. predicts held-out scans better than
the model without it (issue 41: C0 and C1 correlated 1.000 in a model of eight terms).

**The end point by prediction.** Every model on the path is cross-validated with the folds of
the calibration's ``cross_validation`` settings (one compiled adjustment serves every fit and
every fold). The selection ends where the tests end, provided
that model predicts held-out scans no worse than the start and not significantly worse than
another model of the path; otherwise at the model with the fewest terms among those whose
cross-validated misfit is within one standard error (paired over the folds) of the best,
never worse than the start's: equal within the folds' scatter means the simpler model. Without
a fold that can be held out (one station), or with cross-validation off, the path's last model
is kept and the result says that prediction was not checked.

Every fit is recorded (the statistic by which it moved, sigma0, RMS residual per group, the
cross-validated misfit), so a user can see why the final set was chosen.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .._adjustment._calibrate import analyze
from .._adjustment._config import CalibrationModel, SolverOptions
from .._adjustment._network import Network
from .._adjustment._result import CalibrationResult, assemble
from .._model._aps import resolve_aps
from .._model._scanner import Scanner
from .._stats import chi2_quantile
from .._summary import Settings, to_json_value
from .._units import ARCSEC
from ._crossval import (
    CrossValidation,
    CrossValidationOptions,
    FoldData,
    paired_difference,
    run_folds,
)
from ._score import tests_in


@dataclasses.dataclass(frozen=True)
class SelectionOptions(Settings):
    """Stepwise AP selection, starting from the model's APs (module docstring).
    ``candidates``: the terms that may be added (names or presets); ``test_level``: family-wise
    level of the one statistic by which terms enter and leave (1 %: each step tests many
    candidates); ``max_correlation``: a term whose absolute correlation with another unknown
    would exceed it enters only where it predicts held-out scans better than the model without
    it (with cross-validation; without, it enters and is reported as such);
    ``max_steps``: bound on add/remove steps. The prediction check of alternatives and of the
    end point uses the folds of ``cross_validation`` of :class:`tlsjax.CalibrationOptions` (None: not
    checked, the path's last model is the end point)."""

    candidates: tuple = ("chow2013-noscale",)
    test_level: float = 0.01
    max_correlation: float = 0.9
    max_steps: int = 30

    def __post_init__(self):
        if isinstance(self.candidates, str):
            object.__setattr__(self, "candidates", tuple(self.candidates.replace(",", " ").split()))
        if not 0 < self.test_level < 1:
            raise ValueError(
                f"SelectionOptions.test_level must be in (0, 1), got {self.test_level}"
            )
        if not 0 < self.max_correlation <= 1:
            raise ValueError(
                f"SelectionOptions.max_correlation must be in (0, 1], got {self.max_correlation}"
            )
        if self.max_steps < 1:
            raise ValueError(f"SelectionOptions.max_steps must be >= 1, got {self.max_steps}")


@dataclasses.dataclass(frozen=True)
class SelectionStep:
    """One fit of the procedure. ``action``: "start", "remove", "try", "add" or "final";
    ``term`` the AP concerned; ``aps`` the set fitted; ``statistic`` the one statistic by which
    it entered (``T_c / s0^2``) or left (``t^2``), NaN otherwise; ``score`` the raw score
    statistic ``T_c`` of an entered term; ``t``/``max_abs_corr``/``corr_with`` of that term;
    ``rms`` per group (mm, arcsec, arcsec); ``cv_mm``/``cv_se_mm``: the cross-validated 3D
    misfit of the set and its standard error (NaN when not cross-validated); ``reason``."""

    action: str
    term: str
    aps: tuple
    sigma0: float
    rms: dict
    t: float
    max_abs_corr: float
    corr_with: str
    max_ap_corr: float
    reason: str
    score: float = float("nan")
    statistic: float = float("nan")
    cv_mm: float = float("nan")
    cv_se_mm: float = float("nan")

    def to_dict(self) -> dict:
        return to_json_value(
            {
                "action": self.action,
                "term": self.term,
                "aps": list(self.aps),
                "statistic": self.statistic,
                "score": self.score,
                "sigma0": self.sigma0,
                "rms": self.rms,
                "t": self.t,
                "max_abs_corr": self.max_abs_corr,
                "corr_with": self.corr_with,
                "cv_mm": self.cv_mm,
                "cv_se_mm": self.cv_se_mm,
                "reason": self.reason,
            }
        )


@dataclasses.dataclass(frozen=True, eq=False)
class SelectionResult:
    """``aps`` chosen, every step (the path, with the cross-validated misfit of each set), the
    number of distinct fits, the ``critical`` value of the one statistic, ``screened``: the
    removals (:class:`tlsjax.Removal`) of the robust start and screening before the selection
    (left out of every fit), ``score_tests`` of the candidates left at the final set (judged in
    the selection's units, ``T / s0^2``), the ``cross_validation`` of the chosen set and of the
    start set (``start_cross_validation``) on the screened observations with a priori weights;
    ``end``: why the selection ended where it did. The calibration of the chosen set is the
    ``calibration`` of the :func:`tlsjax.self_calibrate` result that ran the selection."""

    aps: tuple
    steps: tuple
    n_fits: int
    critical: float
    screened: tuple = ()
    score_tests: object = None
    cross_validation: CrossValidation | None = None
    start_cross_validation: CrossValidation | None = None
    end: str = ""

    def summary(self) -> str:
        lines = [
            f"final APs: {' '.join(self.aps) or '(none)'} after {self.n_fits} fits (terms enter "
            f"and leave at T / s0^2 > {self.critical:.2f}); {self.end}"
        ]
        if self.screened:
            lines.append(
                f"  on the screened observations: {len(self.screened)} removed before selection"
            )
            lines += [
                f"    scan {o.scan} target {o.target} {o.group}: v = {o.residual:.4g} {o.unit}"
                for o in self.screened[:20]
            ]
        for s in self.steps:
            f = lambda x, spec: format(x, spec) if np.isfinite(x) else "n/a"  # never "nan"
            cv = f"  CV {s.cv_mm:.3f} mm" if np.isfinite(s.cv_mm) else ""
            lines.append(
                f"  {s.action:6s} {s.term:4s} sigma0 {f(s.sigma0, '7.3f')}  RMS range "
                f'{f(s.rms["range_mm"], ".3f")} mm, hz {f(s.rms["hz_arcsec"], ".2f")}", el '
                f'{f(s.rms["el_arcsec"], ".2f")}"{cv}: {s.reason}'
            )
        return "\n".join(lines)

    def to_dict(self) -> dict:
        """The result JSON's ``selection``: the chosen terms, the critical value, why it ended
        there, every step with its statistic and cross-validated misfit, the removals before
        it and the cross-validation of the chosen and the start set."""
        cv, start = self.cross_validation, self.start_cross_validation
        return to_json_value(
            {
                "aps": list(self.aps),
                "n_fits": self.n_fits,
                "critical_value": self.critical,
                "end": self.end,
                "steps": [s.to_dict() for s in self.steps],
                "n_screened": len(self.screened),
                "cross_validation": None if cv is None else cv.to_dict(),
                "start_cross_validation": None if start is None else start.to_dict(),
            }
        )


def _rms(res: CalibrationResult) -> dict:
    """RMS residual per group over the observations used (a screened-out blunder is not in it)."""
    v = res.residuals
    used = np.ones(v.shape, dtype=bool) if res.used is None else res.used
    rms = lambda g: float(np.sqrt(np.mean(v[used[:, g], g] ** 2))) if used[:, g].any() else np.nan
    return {"range_mm": rms(0) * 1e3, "hz_arcsec": rms(1) / ARCSEC, "el_arcsec": rms(2) / ARCSEC}


def _restrict(res: CalibrationResult, aps: tuple) -> CalibrationResult:
    """The result seen as a model of ``aps`` only (the fixed terms dropped from the AP fields)."""
    idx = [res.ap_names.index(a) for a in aps]
    keep = set(aps)
    cov = None if res.ap_covariance is None else res.ap_covariance[np.ix_(idx, idx)]
    return dataclasses.replace(
        res,
        ap_names=tuple(aps),
        ap_units=tuple(res.ap_units[i] for i in idx),
        ap_values=res.ap_values[idx],
        ap_sigmas=res.ap_sigmas[idx],
        ap_t=res.ap_t[idx],
        ap_max_abs_corr=res.ap_max_abs_corr[idx],
        ap_max_corr_with=tuple(res.ap_max_corr_with[i] for i in idx),
        ap_covariance=cov,
        not_estimable=tuple(x for x in res.not_estimable if x[0] in keep),
        weakly_determined=tuple(x for x in res.weakly_determined if x[0] in keep),
        ap_fixed=(),
    )


def _max_ap_corr(res: CalibrationResult) -> float:
    m = res.ap_max_abs_corr
    m = m[np.isfinite(m)]
    return float(m.max()) if m.size else 0.0


class _Fits:
    """The fits of stepwise selection. Every candidate set is the same parameter vector (the
    union of all terms) with the terms outside the set held at zero, so one analysed, compiled
    adjustment serves every fit, every score test and every fold of the cross-validation (with
    the screened weights ``data``); each set is fitted and cross-validated once."""

    def __init__(self, network, model, universe, solver, data, cv_options):
        self.network, self.universe = network, universe
        wide = dataclasses.replace(model, scanner=dataclasses.replace(model.scanner, aps=universe))
        self.adjustment = analyze(network, wide, solver)
        self.data = data
        self.cv_options = cv_options
        self.cache: dict = {}
        self.cv_cache: dict = {}
        self.none_cache: dict = {}

    def problem(self, aps):
        return self.adjustment.problem(**self.data, fixed_aps=self.held(aps))

    def held(self, aps):
        return tuple(a for a in self.universe if a not in aps)

    def __call__(self, aps) -> CalibrationResult:
        key = tuple(aps)
        if key not in self.cache:
            adj = self.adjustment
            plan, state, q, absent = adj.run_estimable(self.problem(key))
            res = assemble(self.network, adj.model, plan, state, q, absent)
            self.cache[key] = (_restrict(res, key), state.params, plan.problem, res)
        return self.cache[key][0]

    def score(self, aps, names, alpha):
        """Score tests of ``names`` at the fit of ``aps`` (:func:`._score.tests_in`)."""
        self(aps)
        _, params, problem, _ = self.cache[tuple(aps)]
        return tests_in(self.adjustment, problem, params, names, alpha)

    def cv(self, aps) -> CrossValidation | None:
        """The cross-validation of the set ``aps`` (None without options or a successful fit)."""
        key = tuple(aps)
        if self.cv_options is None:
            return None
        if key not in self.cv_cache:
            res = self(key)
            out = None
            if res.ok:
                _, params, _, wide = self.cache[key]
                net = self.network
                w = self.data.get("weights")
                w = 1.0 / net.sigmas if w is None else w
                lev = np.where(np.isfinite(net.levelling_sigma), 1.0 / net.levelling_sigma, 0.0)
                control = self.data.get("control") or {}
                data = FoldData(
                    w,
                    lev,
                    {},
                    {t: xyz for t, (xyz, _) in control.items()},
                    params,
                    wide.target_xyz,
                    (w > 0).all(axis=1),
                    self.held(key),
                    self.none_cache,
                )
                out = run_folds(self.adjustment, data, self.cv_options)
                out = dataclasses.replace(out, aps=key)
            self.cv_cache[key] = out
        return self.cv_cache[key]


def _record(action, term, aps, res, reason, cv=None, score=np.nan, statistic=np.nan):
    if term and term in res.ap_names:
        i = res.ap_names.index(term)
        t, c, w = float(res.ap_t[i]), float(res.ap_max_abs_corr[i]), res.ap_max_corr_with[i]
    else:
        t, c, w = np.nan, np.nan, ""
    cv_mm = cv.cv_mm if cv is not None and cv.ok else np.nan
    se = cv.se_mm if cv is not None and cv.ok else np.nan
    return SelectionStep(
        action,
        term,
        tuple(aps),
        float(res.sigma0),
        _rms(res),
        t,
        c,
        w,
        _max_ap_corr(res),
        reason,
        float(score),
        float(statistic),
        float(cv_mm),
        float(se),
    )


def _backward(fit, current, res, visited, unestimable, crit, steps):
    """Backward elimination: drop a non-estimable term, else the one with the smallest
    ``t^2`` below the critical value (the one statistic, module docstring), refit, and
    repeat; a removal that would return to a set already visited is not taken (no cycles).
    Returns the last fit."""
    while current:
        t2 = np.asarray(res.ap_t, dtype=float) ** 2
        bad = [i for i in range(len(current)) if not np.isfinite(t2[i])]
        order = [i for i in np.argsort(t2) if np.isfinite(t2[i]) and t2[i] < crit]
        order = [i for i in order if frozenset(current) - {current[i]} not in visited]
        if bad:
            i = bad[0]
            unestimable.add(current[i])
            why = "not estimable: " + next(
                (r for n, _, r in res.not_estimable if n == current[i]), "no finite sigma"
            )
        elif order:
            i = int(order[0])
            why = f"t^2 = {t2[i]:.2f} < {crit:.2f}: not significant"
        else:
            break
        term = current.pop(i)
        visited.add(frozenset(current))
        res = fit(current)
        steps.append(_record("remove", term, current, res, why, fit.cv(current), statistic=t2[i]))
    return res


def _forward(fit, current, res, visited, unestimable, crit, options, steps):
    """The score test of every term of the universe not in the model (a term removed earlier
    may enter again once the model has changed) at the current fit, in units of its variance
    factor; the significant one with the largest statistic (or, where it has alternatives, the
    one of them that the cross-validation prefers, :func:`_by_prediction`), refitted, as
    (term, fit, reason, T, T / s0^2), or None. A set already visited is not entered again; a
    candidate that the refit cannot estimate is recorded as tried and not offered again."""
    left = [
        c
        for c in fit.universe
        if c not in current and c not in unestimable and frozenset(current) | {c} not in visited
    ]
    s2 = float(res.sigma0) ** 2 if np.isfinite(res.sigma0) and res.sigma0 > 0 else 1.0
    while left:
        tests = fit.score(current, left, options.test_level)
        z = {t.name: t.statistic / s2 for t in tests.tests if t.testable}
        best = tests.best()
        if best is None or not z[best.name] > crit:
            return None
        group = [n for n in tests.group_of(best.name) if n in z and z[n] > crit]
        chosen, note = best.name, ""
        if len(group) > 1 and fit.cv_options is not None:
            chosen, note = _by_prediction(fit, current, group, z, steps)
        t = tests.test(chosen)
        trial = current + [chosen]
        r = fit(trial)
        i = r.ap_names.index(chosen)
        entered = (
            f"largest score statistic T / s0^2 = {z[chosen]:.1f} > {crit:.2f} (T = "
            f"{t.statistic:.1f}, would absorb "
            f"{100 * t.share:.1f}% of v^T P v){note}"
        )
        if not np.isfinite(r.ap_t[i]):
            steps.append(_record("try", chosen, trial, r, entered + "; not estimable"))
            unestimable.add(chosen)
            left.remove(chosen)
            continue
        corr, partner = float(r.ap_max_abs_corr[i]), r.ap_max_corr_with[i]
        why = f"{entered}; |t| = {abs(float(r.ap_t[i])):.2f}"
        worse = corr > options.max_correlation and _predicts_no_better(fit, trial, current)
        if worse:
            why = f"{entered}; |r| = {corr:.2f} with {partner}: {worse}"
            steps.append(
                _record("try", chosen, trial, r, why, fit.cv(trial), t.statistic, z[chosen])
            )
            left.remove(chosen)
            continue
        if corr > options.max_correlation:
            why += (
                f"; high correlation |r| = {corr:.2f} with {partner}: entered because it explains "
                "the misfit, but the design separates the two poorly (more stations or tilted "
                "scans would)"
            )
        else:
            why += f", max |corr| = {corr:.2f} with {partner}"
        return chosen, r, why, t.statistic, z[chosen]
    return None


def _predicts_no_better(fit, trial, current) -> str:
    """Why ``trial`` (``current`` and a term the design separates poorly from one in it) does
    not enter: it predicts held-out scans no better than ``current`` (module docstring); ""
    where it does, or where the two cannot be cross-validated."""
    a, b = fit.cv(trial), fit.cv(current)
    if a is None or b is None or not (a.ok and b.ok) or a.cv_mm < b.cv_mm:
        return ""
    return (
        f"the design separates the two poorly and it predicts held-out scans no better (CV "
        f"{a.cv_mm:.3f} mm against {b.cv_mm:.3f} mm without it): not entered"
    )


def _by_prediction(fit, current, group, z, steps):
    """The member of a group of alternatives that enters: each significant member fitted and
    cross-validated (recorded as tried); the one with the largest statistic (for terms of one
    dimension the information criteria agree with it: the largest reduction of ``v^T P v``)
    unless the cross-validation predicts held-out scans significantly better with another one
    (paired over the folds, by more than twice the standard error of the difference)."""
    cvs = {}
    for name in group:
        trial = current + [name]
        cv = fit.cv(trial)
        res = fit(trial)
        why = (
            f"alternative of {', '.join(n for n in group if n != name)} (T / s0^2 = {z[name]:.1f})"
        )
        steps.append(_record("try", name, trial, res, why, cv, statistic=z[name]))
        if cv is not None and cv.ok:
            cvs[name] = cv
    top = max(group, key=lambda n: z[n])
    if top not in cvs:
        return top, f"; alternatives {', '.join(group)} not cross-validated"
    figures = ", ".join(f"{n} {cv.cv_mm:.3f} mm" for n, cv in cvs.items())
    better = [n for n in cvs if _significantly_better(cvs[n], cvs[top])]
    if better:
        chosen = min(better, key=lambda n: cvs[n].cv_mm)
        return chosen, (
            f"; of the alternatives it predicts held-out scans significantly better than "
            f"{top}, which has the largest statistic (CV {figures})"
        )
    return top, (
        f"; the largest statistic among the alternatives, which predict held-out scans alike "
        f"within the folds' scatter (CV {figures})"
    )


def _significantly_better(a: CrossValidation, b: CrossValidation, k: float = 2.0) -> bool:
    """``a`` predicts better than ``b`` by more than ``k`` standard errors of the paired
    difference of the folds' mean squared misfits."""
    d, se = paired_difference(a, b)
    return bool(np.isfinite(d) and np.isfinite(se) and d < -k * se)


def _in_units_of(tests, s2: float):
    """The score tests with their significance judged as the selection judges it: ``T / s0^2``
    against the tests' critical value (``variance_factor`` s0^2 recorded)."""
    s2 = float(s2) if np.isfinite(s2) and s2 > 0 else 1.0
    out = tuple(
        dataclasses.replace(t, significant=t.testable and t.statistic / s2 > tests.critical)
        for t in tests.tests
    )
    return dataclasses.replace(tests, tests=out, variance_factor=s2)


def _end_point(fit, path) -> tuple:
    """(set, reason): the path's last set (where the tests ended) unless it predicts held-out
    scans worse than the start set (by more than one standard error of the paired difference:
    a term whose effect on the clouds is below the folds' scatter is no reason to drop a term
    the tests found), or significantly worse than another set of the path
    (:func:`_significantly_better`); then the fewest terms among the sets within one standard
    error (paired) of the best and not worse than the start (module docstring). The last set
    where the start could not be cross-validated."""
    start, last = path[0], path[-1]
    cvs = {p: fit.cv(p) for p in path}
    ok = {p: cv for p, cv in cvs.items() if cv is not None and cv.ok}
    if start not in ok or last not in ok:
        why = "prediction not checked (no fold could be held out)" if fit.cv_options else ""
        return last, why or "no significant candidate left"
    tail = f"; the start set: {cvs[start].cv_mm:.3f} mm"
    d, se = paired_difference(ok[last], ok[start])
    worse = ok[last].cv_mm > ok[start].cv_mm and not (np.isfinite(d) and d <= se)
    if not worse and not any(_significantly_better(cv, ok[last]) for cv in ok.values()):
        return last, (
            f"no significant candidate left; it predicts held-out scans no worse than the "
            f"start set within the folds' scatter: CV {ok[last].cv_mm:.3f} mm" + tail
        )
    ok = {p: cv for p, cv in ok.items() if cv.cv_mm <= ok[start].cv_mm}
    best = min(ok, key=lambda p: ok[p].cv_mm)
    near = []
    for p, cv in ok.items():
        d, se = paired_difference(cv, ok[best])
        if p == best or (np.isfinite(d) and d <= se):
            near.append(p)
    chosen = min(near, key=lambda p: (len(p), path.index(p)))
    text = (
        f"the tests ended at {' '.join(last) or '(none)'} (CV {cvs[last].cv_mm:.3f} mm), which "
        f"predicts held-out scans worse; ends at {' '.join(chosen) or '(none)'}, CV "
        f"{ok[chosen].cv_mm:.3f} mm"
    )
    if chosen != best:
        text += (
            f" (within the folds' scatter of the best, {ok[best].cv_mm:.3f} mm, with fewer terms)"
        )
    return chosen, text + tail


def select_terms(
    network: Network,
    model: CalibrationModel,
    options: SelectionOptions,
    solver: SolverOptions,
    data: dict,
    screened: tuple = (),
    cross_validation: CrossValidationOptions | None = None,
) -> SelectionResult:
    """Stepwise AP selection (forward with backward elimination) for one instrument, from
    ``model.scanner.aps`` over ``options.candidates``, ending where prediction on held-out scans
    is best (module docstring). Every fit with the weights and pinned targets ``data`` (keyword
    arguments of :meth:`tlsjax.Adjustment.problem`; ``screened``: the removals they hold,
    reported); ``cross_validation``: the folds of the prediction check (None: not checked).
    Returns the selected set and every step."""
    if not isinstance(model.scanner, Scanner):
        raise ValueError(
            "model.scanner: stepwise selection works on one instrument; pass one Scanner"
        )
    start = tuple(model.scanner.aps)
    candidates = resolve_aps(options.candidates)
    universe = tuple(dict.fromkeys(start + candidates))
    fit = _Fits(network, model, universe, solver, data, cross_validation)
    k = max(len([c for c in candidates if c not in start]), 1)
    crit = float(chi2_quantile(1 - options.test_level / k, 1.0))
    current = list(start)
    res = fit(current)
    steps = [_record("start", "", current, res, "initial set", fit.cv(current))]
    path = [tuple(current)]
    visited, unestimable = {frozenset(current)}, set()
    for _ in range(options.max_steps):
        res = _backward(fit, current, res, visited, unestimable, crit, steps)
        path.append(tuple(current))
        best = _forward(fit, current, res, visited, unestimable, crit, options, steps)
        if best is None:
            break
        current.append(best[0])
        visited.add(frozenset(current))
        res = best[1]
        steps.append(
            _record("add", best[0], current, res, best[2], fit.cv(current), best[3], best[4])
        )
        path.append(tuple(current))
    path = list(dict.fromkeys(path))
    chosen, end = _end_point(fit, path)
    current = list(chosen)
    res = fit(current)
    left = [c for c in universe if c not in current]
    final_tests = None
    if left and res.ok:
        # In the selection's own units: significant where T / s0^2 passes the critical value.
        final_tests = _in_units_of(fit.score(current, left, options.test_level), res.sigma0**2)
    steps.append(_record("final", "", current, res, end, fit.cv(current)))
    return SelectionResult(
        tuple(current),
        tuple(steps),
        len(fit.cache),
        crit,
        tuple(screened),
        final_tests,
        fit.cv(current),
        fit.cv(path[0]),
        end,
    )
