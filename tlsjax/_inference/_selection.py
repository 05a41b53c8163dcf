"""Stepwise selection of additional parameters (Chow et al. 2013, section on AP selection).

Starting from a chosen set, the procedure alternates

* backward: refit; remove the least significant AP (``|t| <`` Student's critical value at
  ``alpha``) or any AP the network cannot determine, one at a time;
* forward: try every remaining candidate term on top of the current set; a candidate is
  admissible when it is estimable, significant (``|t| >`` the critical value) and its largest
  absolute correlation with any other unknown is below ``max_correlation``; the admissible
  candidate with the largest ``|t|`` is added;

until no candidate is admissible. A term removed by the backward step is not tried again, so
the procedure cannot cycle. Every fit is recorded (sigma0, RMS residual per group in mm and
arc seconds, largest AP correlation) so a user can see why the final set was chosen.

Each AP set is a new static shape of the compiled adjustment: one compile per distinct set.
Trial sets are bounded by ``len(candidates)`` per forward step.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .._adjustment._calibrate import calibrate
from .._adjustment._config import CalibrationModel, SolverOptions
from .._adjustment._network import Network
from .._adjustment._result import CalibrationResult
from .._model._aps import resolve_aps
from .._model._scanner import Scanner
from .._stats import t_critical_value
from .._units import ARCSEC


@dataclasses.dataclass(frozen=True)
class SelectionOptions:
    """``alpha``: two-sided level of the AP t-tests (1 %: each forward step tests several
    candidates, so a 5 % level would add a spurious term in about one network in five); ``max_correlation``: a candidate whose
    largest absolute correlation with another unknown exceeds it is not added (Chow et al.
    2013 use the correlation table to reject terms); ``max_steps``: bound on add/remove steps."""

    alpha: float = 0.01
    max_correlation: float = 0.9
    max_steps: int = 30

    def __post_init__(self):
        if not 0 < self.alpha < 1:
            raise ValueError(f"alpha must be in (0, 1), got {self.alpha}")
        if not 0 < self.max_correlation <= 1:
            raise ValueError(f"max_correlation must be in (0, 1], got {self.max_correlation}")
        if self.max_steps < 1:
            raise ValueError(f"max_steps must be >= 1, got {self.max_steps}")


@dataclasses.dataclass(frozen=True)
class SelectionStep:
    """One fit of the procedure. ``action``: "start", "remove", "try", "add" or "final";
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


@dataclasses.dataclass(frozen=True, eq=False)
class SelectionResult:
    aps: tuple
    calibration: CalibrationResult
    steps: tuple
    n_fits: int
    critical: float

    def report(self) -> str:
        lines = [
            f"final APs: {' '.join(self.aps) or '(none)'} after {self.n_fits} fits (|t| > {self.critical:.2f})"
        ]
        for s in self.steps:
            if s.action == "try":
                continue
            lines.append(
                f"  {s.action:6s} {s.term:4s} sigma0 {s.sigma0:7.3f}  RMS range {s.rms['range_mm']:.3f} mm, "
                f'hz {s.rms["hz_arcsec"]:.2f}", el {s.rms["el_arcsec"]:.2f}"  max AP corr {s.max_ap_corr:.2f}: {s.reason}'
            )
        return "\n".join(lines)


def _rms(res: CalibrationResult) -> dict:
    v = res.residuals
    return {
        "range_mm": float(np.sqrt(np.mean(v[:, 0] ** 2)) * 1e3),
        "hz_arcsec": float(np.sqrt(np.mean(v[:, 1] ** 2)) / ARCSEC),
        "el_arcsec": float(np.sqrt(np.mean(v[:, 2] ** 2)) / ARCSEC),
    }


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
    union of all terms) with the terms outside the set held at zero, so one compiled adjustment
    serves every fit; each set is fitted once."""

    def __init__(self, network, model, universe, solver):
        self.network, self.universe, self.solver = network, universe, solver
        self.wide = dataclasses.replace(
            model, scanner=dataclasses.replace(model.scanner, aps=universe)
        )
        self.cache: dict = {}

    def __call__(self, aps) -> CalibrationResult:
        key = tuple(aps)
        if key not in self.cache:
            fixed = tuple(a for a in self.universe if a not in key)
            res = calibrate(
                self.network, dataclasses.replace(self.wide, fixed_aps=fixed), self.solver
            )
            self.cache[key] = _restrict(res, key)
        return self.cache[key]


def _record(action, term, aps, res, reason) -> SelectionStep:
    if term and term in res.ap_names:
        i = res.ap_names.index(term)
        t, c, w = float(res.ap_t[i]), float(res.ap_max_abs_corr[i]), res.ap_max_corr_with[i]
    else:
        t, c, w = np.nan, np.nan, ""
    return SelectionStep(
        action, term, tuple(aps), float(res.sigma0), _rms(res), t, c, w, _max_ap_corr(res), reason
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


def _admissible(r, c, options: SelectionOptions):
    """Whether candidate ``c`` in the trial fit ``r`` may be added: estimable, significant and
    not too correlated; (ok, |t|, reason)."""
    i = r.ap_names.index(c)
    t, corr = abs(float(r.ap_t[i])), float(r.ap_max_abs_corr[i])
    k = t_critical_value(options.alpha, r.dof)
    if not np.isfinite(t):
        return False, t, "not estimable"
    if t <= k:
        return False, t, f"|t| = {t:.2f} <= {k:.2f}"
    if corr > options.max_correlation:
        return (
            False,
            t,
            f"|corr| = {corr:.2f} with {r.ap_max_corr_with[i]} > {options.max_correlation}",
        )
    return True, t, f"|t| = {t:.2f}, max |corr| = {corr:.2f} with {r.ap_max_corr_with[i]}"


def _forward(fit, current, removed, candidates, options, steps):
    """Every remaining candidate tried on top of the current set; the admissible one with the
    largest ``|t|`` as (term, |t|, fit, reason), or None."""
    best = None
    for c in candidates:
        if c in current or c in removed:
            continue
        trial = current + [c]
        r = fit(trial)
        ok, t, why = _admissible(r, c, options)
        steps.append(_record("try", c, trial, r, why + ("" if ok else ": not admissible")))
        if ok and (best is None or t > best[1]):
            best = (c, t, r, why)
    return best


def select_aps(
    network: Network,
    model: CalibrationModel | None = None,
    *,
    start=(),
    candidates="chow2013-noscale",
    options: SelectionOptions | None = None,
    solver: SolverOptions | None = None,
) -> SelectionResult:
    """Stepwise AP selection (forward with backward elimination) for one instrument.

    ``model.scanner`` gives the architecture and unit lengths (its ``aps`` are ignored);
    ``start`` the initial set; ``candidates`` the terms that may be added (names or presets).
    Returns the selected set, its calibration and every step.
    """
    model = model or CalibrationModel()
    options = options or SelectionOptions()
    solver = solver or SolverOptions(full_covariance=False)
    if not isinstance(model.scanner, Scanner):
        raise ValueError(
            "model.scanner: stepwise selection works on one instrument; pass one Scanner"
        )
    start = resolve_aps(start)
    candidates = resolve_aps(candidates)
    fit = _Fits(network, model, tuple(dict.fromkeys(start + candidates)), solver)
    current = list(start)
    res = fit(current)
    steps = [_record("start", "", current, res, "initial set")]
    removed: set = set()
    for _ in range(options.max_steps):
        res = _backward(fit, current, res, removed, options.alpha, steps)
        best = _forward(fit, current, removed, candidates, options, steps)
        if best is None:
            break
        current.append(best[0])
        res = best[2]
        why = "most significant admissible candidate: " + best[3]
        steps.append(_record("add", best[0], current, res, why))
    steps.append(_record("final", "", current, res, "no admissible candidate left"))
    # The chosen set once more as a model of its own, so the result carries only its terms.
    final = calibrate(
        network,
        dataclasses.replace(model, scanner=dataclasses.replace(model.scanner, aps=tuple(current))),
        solver,
    )
    crit = t_critical_value(options.alpha, res.dof)
    return SelectionResult(tuple(current), final, tuple(steps), len(fit.cache), crit)
