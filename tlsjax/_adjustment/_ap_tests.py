"""The t-tests of the APs of a calibration (SPEC section 7): ``t = x_a / s_a`` (a posteriori
sigma) against Student's t with the adjustment's degrees of freedom, and why an AP has no
verdict (not estimable, held fixed, weakly determined, undefined t), in the same words in the
text, the JSON and the report."""

from __future__ import annotations

import dataclasses

import numpy as np

from .._stats import t_critical_value


@dataclasses.dataclass(frozen=True)
class APTest:
    """The t-test of one AP. ``note`` says why there is no verdict (not estimable, held fixed,
    weakly determined: a t of an AP with |corr| near 1 is not interpretable, undefined t);
    then ``significant`` is False and the text never shows a number where none is defined."""

    name: str
    value: float
    sigma: float
    unit: str
    t: float
    critical: float
    significant: bool
    max_abs_corr: float
    max_corr_with: str
    note: str = ""

    def describe(self) -> str:
        """One line: ``B6: t = 12.30 (significant at |t| > 1.96)`` or the reason for none."""
        if self.note:
            return f"{self.name}: {self.note}"
        verdict = "significant" if self.significant else "not significant"
        return f"{self.name}: t = {self.t:.2f} ({verdict} at |t| > {self.critical:.2f})"


def _no_verdict(result, i: int, name: str) -> str:
    """Why AP ``i`` has no t-test verdict, or "" when it has one."""
    for n, _, reason in result.not_estimable:
        if n == name:
            return f"not estimable ({reason}): no t"
    if name in getattr(result, "ap_fixed", ()):
        return "held at 0 (fixed): no t"
    for n, partner, c in result.weakly_determined:
        if n == name:
            return (
                f"t = {float(result.ap_t[i]):.2f}, no verdict: weakly determined (|corr| = "
                f"{c:.3f} with {partner}), so its t is not interpretable"
            )
    if not np.isfinite(result.ap_t[i]):
        return "t undefined (the estimate or its sigma is not a number)"
    return ""


def ap_notes(result) -> dict:
    """AP name -> why it has no ordinary estimate and t-test verdict (not estimable, held
    fixed, weakly determined, undefined t); APs with an ordinary verdict are left out. The
    same words in the text table, the JSON (``aps.<name>.note``) and the report."""
    out = {}
    for i, name in enumerate(result.ap_names):
        note = _no_verdict(result, i, name)
        if note:
            out[name] = note
    return out


def ap_t_tests(result, level: float = 0.05) -> tuple:
    """t-test of every AP: ``t = x / s_x`` (a posteriori sigma) against Student's t with the
    adjustment's degrees of freedom, two-sided at ``level``. Non-estimable, fixed and weakly
    determined APs get no verdict (``significant`` False) and a ``note`` saying why."""
    crit = t_critical_value(level, result.dof)
    out = []
    for i, name in enumerate(result.ap_names):
        t = float(result.ap_t[i])
        note = _no_verdict(result, i, name)
        out.append(
            APTest(
                name,
                float(result.ap_values[i]),
                float(result.ap_sigmas[i]),
                result.ap_units[i],
                t,
                crit,
                bool(not note and np.isfinite(t) and abs(t) > crit),
                float(result.ap_max_abs_corr[i]),
                result.ap_max_corr_with[i],
                note,
            )
        )
    return tuple(out)
