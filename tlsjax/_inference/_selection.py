"""Stepwise selection of additional parameters (Chow et al. 2013, section on AP selection),
on observations freed of gross errors, entering terms by their score test (SPEC section 7).

It runs as the selection step of :func:`tlsjax.self_calibrate` (:mod:`._steps`), after the robust
start and screening of the start set: the observations they removed stay out of every fit of
the selection (the weights and pinned targets it is given), so a blunder can neither pose as a
term nor push one out. The procedure alternates

* backward: remove a term the network cannot determine, else the least significant one
  (``|t| <`` Student's critical value at ``alpha``), refit, one at a time;
* forward: the score test of every remaining candidate at the current fit (:mod:`._score`: the
  reduction of ``v^T P v`` each would bring, from the current residuals and normal matrix,
  no refit per candidate); the one with the largest statistic enters when it is significant at
  the family-wise level ``alpha`` (Bonferroni over the candidates) and estimable in the refit.
  A large correlation with another unknown (a scan pose) does not keep it out: it is reported
  with the step (the term explains the misfit; the design separates it poorly);

until no candidate is significant. A term removed by the backward step is not tried again, so
the procedure cannot cycle. Every fit is recorded (sigma0, RMS residual per group in mm and
arc seconds, largest AP correlation) so a user can see why the final set was chosen.

Every set is the one wide adjustment (the union of all terms) with the terms outside the set
held at zero: one compile serves every fit and every score test.
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
from .._stats import t_critical_value
from .._summary import Settings, to_json_value
from .._units import ARCSEC
from ._score import tests_in


@dataclasses.dataclass(frozen=True)
class SelectionOptions(Settings):
    """Stepwise AP selection, starting from the model's APs. ``candidates``: the terms that may
    be added (names or presets); ``test_level``: two-sided level of the AP t-tests and
    family-wise level of the score tests of the candidates (1 %: each forward step tests many
    candidates); ``max_correlation``: a term entered with a larger absolute correlation with
    another unknown is reported as such (Chow et al. 2013 read the correlation table; the term
    stays, since it explains the misfit); ``max_steps``: bound on add/remove steps."""

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
    ``score`` the score statistic by which an added term entered (NaN otherwise);
    ``term`` the AP concerned; ``aps`` the set fitted; ``t``/``max_abs_corr``/``corr_with``
    of that term; ``rms`` per group (mm, arcsec, arcsec); ``reason`` in words."""

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


@dataclasses.dataclass(frozen=True, eq=False)
class SelectionResult:
    """``aps`` chosen, every step, the number of distinct fits, the t critical value,
    ``screened``: the removals (:class:`Removal`) of the robust start and screening before the
    selection (left out of every fit), and ``score_tests`` of the candidates left at the final
    set. The calibration of the chosen set is the ``calibration`` of the
    :func:`tlsjax.self_calibrate` result that ran the selection."""

    aps: tuple
    steps: tuple
    n_fits: int
    critical: float
    screened: tuple = ()
    score_tests: object = None

    def summary(self) -> str:
        lines = [
            f"final APs: {' '.join(self.aps) or '(none)'} after {self.n_fits} fits (|t| > {self.critical:.2f})"
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
            if s.action == "try":
                continue
            lines.append(
                f"  {s.action:6s} {s.term:4s} sigma0 {s.sigma0:7.3f}  RMS range {s.rms['range_mm']:.3f} mm, "
                f'hz {s.rms["hz_arcsec"]:.2f}", el {s.rms["el_arcsec"]:.2f}"  max AP corr {s.max_ap_corr:.2f}: {s.reason}'
            )
        return "\n".join(lines)

    def to_dict(self) -> dict:
        """The result JSON's ``selection``: the chosen terms, the number of fits, the steps that
        changed the set (with the score a term entered by) and the removals before it."""
        return to_json_value(
            {
                "aps": list(self.aps),
                "n_fits": self.n_fits,
                "steps": [
                    {"action": s.action, "term": s.term, "score": s.score, "reason": s.reason}
                    for s in self.steps
                    if s.action != "try"
                ],
                "n_screened": len(self.screened),
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
    adjustment serves every fit (with the screened weights ``data``); each set is fitted once."""

    def __init__(self, network, model, universe, solver, data):
        self.network, self.universe = network, universe
        wide = dataclasses.replace(model, scanner=dataclasses.replace(model.scanner, aps=universe))
        self.adjustment = analyze(network, wide, solver)
        self.data = data
        self.cache: dict = {}

    def problem(self, aps):
        fixed = tuple(a for a in self.universe if a not in aps)
        return self.adjustment.problem(**self.data, fixed_aps=fixed)

    def __call__(self, aps) -> CalibrationResult:
        key = tuple(aps)
        if key not in self.cache:
            adj = self.adjustment
            problem = self.problem(key)
            state, q = adj.run(problem)
            plan = dataclasses.replace(adj.plan, problem=problem)
            res = assemble(self.network, adj.model, plan, state, q)
            self.cache[key] = (_restrict(res, key), state.params, problem)
        return self.cache[key][0]

    def score(self, aps, names, alpha):
        """Score tests of ``names`` at the fit of ``aps`` (:func:`._score.tests_in`)."""
        self(aps)
        _, params, problem = self.cache[tuple(aps)]
        return tests_in(self.adjustment, problem, params, names, alpha)


def _record(action, term, aps, res, reason, score=float("nan")) -> SelectionStep:
    if term and term in res.ap_names:
        i = res.ap_names.index(term)
        t, c, w = float(res.ap_t[i]), float(res.ap_max_abs_corr[i]), res.ap_max_corr_with[i]
    else:
        t, c, w = np.nan, np.nan, ""
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
    )


def _backward(fit, current, res, removed, alpha, steps):
    """Backward elimination: drop a non-estimable term, else the least significant one
    (``|t|`` below Student's critical value), refit, and repeat; returns the last fit."""
    while current:
        k = t_critical_value(alpha, res.dof)
        t = np.abs(res.ap_t)
        bad = [i for i in range(len(current)) if not np.isfinite(t[i])]
        if bad:
            i = bad[0]
            why = "not estimable: " + next(
                (r for n, _, r in res.not_estimable if n == current[i]), "no finite sigma"
            )
        elif t.size and t.min() < k:
            i = int(np.argmin(t))
            why = f"|t| = {t[i]:.2f} < {k:.2f}: not significant"
        else:
            break
        term = current.pop(i)
        removed.add(term)
        res = fit(current)
        steps.append(_record("remove", term, current, res, why))
    return res


def _forward(fit, current, removed, candidates, options, steps):
    """The score test of every remaining candidate at the current fit; the significant one with
    the largest statistic, refitted, as (term, fit, reason, T), or None. A candidate that the
    refit cannot estimate is recorded as tried and not offered again."""
    left = [c for c in candidates if c not in current and c not in removed]
    while left:
        tests = fit.score(current, left, options.test_level)
        best = tests.best()
        if best is None or not best.significant:
            return None
        trial = current + [best.name]
        r = fit(trial)
        i = r.ap_names.index(best.name)
        entered = (
            f"largest score statistic T = {best.statistic:.1f} > {tests.critical:.2f} (would "
            f"absorb {100 * best.share:.1f}% of v^T P v)"
        )
        if not np.isfinite(r.ap_t[i]):
            steps.append(_record("try", best.name, trial, r, entered + "; not estimable"))
            removed.add(best.name)
            left.remove(best.name)
            continue
        corr, partner = float(r.ap_max_abs_corr[i]), r.ap_max_corr_with[i]
        why = f"{entered}; |t| = {abs(float(r.ap_t[i])):.2f}"
        if corr > options.max_correlation:
            why += (
                f"; high correlation |r| = {corr:.2f} with {partner}: entered because it explains "
                "the misfit, but the design separates the two poorly (more stations or tilted "
                "scans would)"
            )
        else:
            why += f", max |corr| = {corr:.2f} with {partner}"
        return best.name, r, why, best.statistic
    return None


def select_terms(
    network: Network,
    model: CalibrationModel,
    options: SelectionOptions,
    solver: SolverOptions,
    data: dict,
    screened: tuple = (),
) -> SelectionResult:
    """Stepwise AP selection (forward with backward elimination) for one instrument, from
    ``model.scanner.aps`` over ``options.candidates``, every fit with the weights and pinned
    targets ``data`` (keyword arguments of :meth:`tlsjax.Adjustment.problem`; ``screened``:
    the removals they hold, reported). Returns the selected set and every step."""
    if not isinstance(model.scanner, Scanner):
        raise ValueError(
            "model.scanner: stepwise selection works on one instrument; pass one Scanner"
        )
    start = tuple(model.scanner.aps)
    candidates = resolve_aps(options.candidates)
    fit = _Fits(network, model, tuple(dict.fromkeys(start + candidates)), solver, data)
    current = list(start)
    res = fit(current)
    steps = [_record("start", "", current, res, "initial set")]
    removed: set = set()
    for _ in range(options.max_steps):
        res = _backward(fit, current, res, removed, options.test_level, steps)
        best = _forward(fit, current, removed, candidates, options, steps)
        if best is None:
            break
        current.append(best[0])
        res = best[1]
        steps.append(_record("add", best[0], current, res, best[2], best[3]))
    left = [c for c in candidates if c not in current]
    final_tests = fit.score(current, left, options.test_level) if left and res.ok else None
    steps.append(_record("final", "", current, res, "no significant candidate left"))
    crit = t_critical_value(options.test_level, res.dof)
    return SelectionResult(
        tuple(current), tuple(steps), len(fit.cache), crit, screened, final_tests
    )
