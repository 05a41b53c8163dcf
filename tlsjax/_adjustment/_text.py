"""The text of a calibration (:meth:`tlsjax.CalibrationResult.summary`): the summary lines and
the paper-style AP table.

Host side only. SI inside the result; the table shows millimetres for lengths, arc seconds (")
for angles and ppm for dimensionless scale terms, with the unit in every label. The JSON keeps
SI units and states them (SPEC section 11).
"""

from __future__ import annotations

import numpy as np

from .._stats import global_test
from .._units import display
from ._redundancy import redundancy_summary

EOP_NAMES = ("Xs", "Ys", "Zs", "omega", "phi", "kappa")


def not_estimable_sentence(name: str, reason: str) -> str:
    """The one sentence that names a non-estimable AP and why: the result's ``message`` and
    :func:`tlsjax._report._text.confoundings` (the text summary, the JSON's ``confoundings``,
    the HTML report) all print it."""
    return f"{name} is not estimable: {reason}"


def confoundings(not_estimable, weakly_determined) -> list[dict]:
    """Every confounding named once: the non-estimable APs (with what each is confounded with)
    first, then the weakly determined pairs, a pair and its mirror (C0 with C3, C3 with C0)
    counted once. ``parameters``, ``kind``, ``max_abs_corr`` (null where not estimable) and
    ``text``, the one sentence that the text summary, the JSON (``confoundings``) and the HTML
    report all print. Entries are tuples ``(name, partner, reason or |corr|)`` as in
    :class:`tlsjax.CalibrationResult` or dicts as in the result JSON."""

    def triples(items, keys):
        for it in items or ():
            yield tuple(it[k] for k in keys) if isinstance(it, dict) else tuple(it)

    out, seen = [], set()
    for n, w, reason in triples(not_estimable, ("name", "confounded_with", "reason")):
        seen.add(frozenset((n, w)))
        out.append(
            {
                "parameters": [n, w],
                "kind": "not estimable",
                "max_abs_corr": None,
                "text": not_estimable_sentence(n, reason),
            }
        )
    for n, w, c in triples(weakly_determined, ("name", "correlated_with", "max_abs_corr")):
        if frozenset((n, w)) in seen:
            continue
        seen.add(frozenset((n, w)))
        out.append(
            {
                "parameters": [n, w],
                "kind": "weakly determined",
                "max_abs_corr": float(c),
                "text": f"{n} and {w} are weakly determined together: |corr| = {float(c):.4f}",
            }
        )
    return out


def _number(x: float, width: int, digits: int) -> str:
    """A right-aligned number, or "undefined" where it is not one (never "nan")."""
    return f"{x:{width}.{digits}f}" if np.isfinite(x) else f"{'undefined':>{width}}"


def ap_table(res, truth: dict | None = None, *, withheld: str | None = None) -> str:
    """The papers' AP table (Chow et al. 2013, tables 3-6): estimate, standard deviation,
    t statistic and the largest absolute correlation with the parameter it is with.

    A failed adjustment (or ``withheld``: the reason its estimates are not a calibration, e.g.
    variance components that failed) shows no numbers; a quantity that is not defined is said
    to be so in words, with the reason the JSON gives (``aps.<name>.note``)."""
    head = f"{'AP':<8} {'estimate':>12} {'sigma':>10} {'unit':<4} {'|t|':>8} {'max |corr|':>10}  {'with':<14}"
    if truth is not None:
        head += f" {'true':>10}"
    lines = [head, "-" * len(head)]
    if int(res.result) not in (0, 2):
        # A failed adjustment's numbers would look plausible and be wrong.
        return "\n".join(lines + [f"no estimates: the adjustment failed ({res.message})"])
    if withheld:
        return "\n".join(lines + [f"no estimates: {withheld}"])
    not_est = {n: r for n, _, r in res.not_estimable}
    weak = {n for n, _, _ in res.weakly_determined}
    found = res.plausibility()[0] if hasattr(res, "plausibility") else ()
    implausible = {f.name: f.level for f in found}
    for i, name in enumerate(res.ap_names):
        if name in not_est:
            lines.append(f"{name:<8} not estimable: {not_est[name]}")
            continue
        if name in getattr(res, "ap_fixed", ()):
            lines.append(f"{name:<8} held at 0 (fixed)")
            continue
        v, u = display(res.ap_values[i], res.ap_units[i])
        s, _ = display(res.ap_sigmas[i], res.ap_units[i])
        row = (
            f"{name:<8} {_number(v, 12, 4)} {_number(s, 10, 4)} {u:<4} "
            f"{_number(abs(res.ap_t[i]), 8, 1)} {_number(res.ap_max_abs_corr[i], 10, 3)}  "
            f"{res.ap_max_corr_with[i]:<14}"
        )
        if truth is not None:
            tv = truth.get(name.split("[")[0])
            row += f" {display(tv, res.ap_units[i])[0]:10.4f}" if tv is not None else f" {'':>10}"
        if name in weak:
            row += "  (weakly determined: t not interpretable)"
        if name in implausible:
            row += f"  ({'impossible' if implausible[name] == 'impossible' else 'implausible'} magnitude)"
        lines.append(row)
    return "\n".join(lines)


def summary(res, alpha: float = 0.05, *, after_vce: bool = False) -> str:
    """A few lines: result, sigma0 with the global test, redundancy, flags. ``after_vce``: the
    weights were fitted to these residuals (VCE), so sigma0 is no test of them."""
    gt = global_test(res.sigma0, res.dof, alpha)
    red = redundancy_summary(res)
    out = [
        f"result: {res.result} ({res.message}); {res.iterations} iterations; datum: {res.datum}",
        f"observations n = {res.n_observations}, unknowns u = {res.n_unknowns}, "
        + (
            f"degrees of freedom r = n - u + d = {res.dof:.0f}"
            if not getattr(res, "planes", ())
            else f"conditions c = {res.n_conditions}, constraints h = {res.n_constraints}, degrees of "
            f"freedom r = c - u + h + d = {res.dof:.0f} (Gauss-Helmert, {len(res.planes)} planes, "
            f"{int(res.plane_used.any(axis=1).sum())} plane points; h: unit normals)"
        ),
    ]
    if after_vce and gt["statistic"] is not None:
        out.append(
            f"sigma0 = {res.sigma0:.4f} with variance factors fitted to these residuals: not a test "
            "(the global test with the a priori sigmas is above)"
        )
    elif gt["statistic"] is not None:
        out.append(
            f"sigma0 = {res.sigma0:.4f} (s0^2 = {res.sigma0**2:.4f}); global test chi^2 = {gt['statistic']:.1f}, "
            f"{100 * (1 - alpha):.0f}% interval [{gt['lower']:.1f}, {gt['upper']:.1f}]: "
            f"{'accepted' if gt['accepted'] else 'REJECTED'} (p = {gt['p_value']:.3f})"
        )
    groups = ", ".join(
        f"{g} {_number(red[g]['mean'], 0, 3).strip()}"
        for g in ("range", "hz", "el", "levelling", "heading", "ap_priors")
        if g in red
    )
    if groups:
        out.append(f"mean redundancy numbers: {groups}")
    if "planes" in red:
        pl = red["planes"]
        out.append(
            f"mean redundancy numbers of plane observations: range {pl['range']['mean']:.3f}, hz {pl['hz']['mean']:.3f}, "
            f"el {pl['el']['mean']:.3f}; all {pl['all']['mean']:.3f} (at most 1/3: one condition per point)"
        )
    constraints = res.weighted_constraints() if hasattr(res, "weighted_constraints") else []
    if constraints:
        worst = max(constraints, key=lambda c: -1.0 if c["w"] is None else abs(c["w"]))
        rejected = [
            f"{c['kind']} {c['name']} (w = {c['w']:.2f})" for c in constraints if c["rejected"]
        ]
        out.append(
            f"weighted constraints (eq. 7): {len(constraints)}; largest |w| "
            + (
                "n/a"
                if worst["w"] is None
                else f"{abs(worst['w']):.2f} ({worst['kind']} {worst['name']})"
            )
            + ("; REJECTED: " + ", ".join(rejected) if rejected else "")
        )
    for c in confoundings(res.not_estimable, res.weakly_determined):
        out.append(f"warning: {c['text']}")
    findings, implausible = res.plausibility() if hasattr(res, "plausibility") else ((), "")
    if findings:
        level = "error" if any(f.level == "impossible" for f in findings) else "warning"
        out.append(f"{level}: implausible estimates: {implausible}")
    if res.rank_deficient:
        out.append("error: the network does not determine " + ", ".join(res.rank_deficient))
    return "\n".join(out)
