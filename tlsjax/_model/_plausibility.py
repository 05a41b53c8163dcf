"""Plausibility of magnitudes: the one home of the rules that ``calibrate``, ``correct`` and
the API apply alike (issue 27 item 6, issue 28 item 3).

A value that no terrestrial laser scanner or calibration field produces is not data to adjust
or a correction to apply; it is almost always a unit mix-up, a design that cannot determine the
chosen APs, or a blunder. Each rule either refuses (a one-line ValueError with the reason and
the likely fix) or warns (:class:`PlausibilityWarning`, printed by the CLI as a ``warning:``
line), and always names the likely cause.

Ranges (SPEC section 1): a single range beyond :data:`MAX_RANGE` is refused (no TLS measures
10 km; 1e300 is a corrupt cell); a median range below :data:`MIN_MEDIAN_RANGE` is refused (no
scanner measures targets at a few millimetres: metres in a millimetre column); a median beyond
:data:`FAR_MEDIAN_RANGE` is a warning (millimetres in a metre column make a 14 m room 14 km).

AP magnitudes (:data:`AP_LIMITS`, per coefficient unit): beyond the first bound a warning
(larger than instruments have after their maker's calibration), beyond the second the value is
impossible for a working instrument: ``calibrate`` reports it as a result that is not a
calibration (exit 1) and ``correct`` refuses to apply it.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .._units import ARCSEC


class PlausibilityWarning(UserWarning):
    """A magnitude that no scanner or calibration field produces (a unit mix-up, a design that
    cannot determine the chosen APs, a blunder); the message names the likely cause."""


#: A single range beyond this is refused [m] (the longest-range terrestrial scanners reach a
#: few km on large natural surfaces, never on calibration targets).
MAX_RANGE = 10_000.0
#: A median range below this is refused [m]: scanners do not measure closer than tens of cm.
MIN_MEDIAN_RANGE = 0.1
#: A median range beyond this is a warning [m]: targets and planes of a calibration field are
#: resolved within a few hundred metres.
FAR_MEDIAN_RANGE = 1_000.0

#: Coefficient unit -> (warning bound, impossible bound) of |AP| in SI units: lengths 0.1 m
#: and 1 m (rangefinder offsets and eccentricities are millimetres to centimetres), angles
#: 0.5 and 5 deg (axis errors are arc seconds to arc minutes), scale terms 0.5 % and 5 % (the
#: angular bounds over about a radian of elevation or direction; the simulated room plants
#: 1,000 ppm, SPEC section 8, which stays below the warning).
AP_LIMITS = {
    "m": (0.1, 1.0),
    "rad": (np.radians(0.5), np.radians(5.0)),
    "1": (5e-3, 5e-2),
}


def _display(value: float, unit: str) -> str:
    if unit == "m":
        return f"{value * 1e3:,.4g} mm"
    if unit == "rad":
        return f'{value / ARCSEC:,.0f}" ({np.degrees(value):.3g} deg)'
    return f"{value * 1e6:,.0f} ppm"


def check_ranges(ranges, where, what, source: str) -> list[str]:
    """Refuse impossible ranges [m] (ValueError naming the row, or the file for the median);
    return the warnings (a median range far beyond a calibration field)."""
    r = np.asarray(ranges, dtype=np.float64).reshape(-1)
    if r.size == 0:
        return []
    med = float(np.median(r))
    far = (
        f"{source}: the ranges have a median of {med / 1e3:.3g} km, far beyond a calibration "
        "field (its targets and planes are resolved within a few hundred metres): probably "
        "millimetres read as metres; check the unit suffix of the range column (range_mm for "
        "millimetres)"
    )
    bad = np.flatnonzero(r > MAX_RANGE)
    if bad.size and med > FAR_MEDIAN_RANGE:
        raise ValueError(f"{far}; the longest is {r.max() / 1e3:.3g} km")
    if bad.size:
        i = int(bad[0])
        raise ValueError(
            f"{where(i)}: range of {what(i)} = {r[i]:.6g} m is beyond what any terrestrial laser "
            f"scanner measures ({MAX_RANGE / 1e3:g} km): check the value and the unit suffix of "
            "the range column"
        )
    if med < MIN_MEDIAN_RANGE:
        raise ValueError(
            f"{source}: the ranges have a median of {med * 1e3:.3g} mm, closer than any scanner "
            "measures: probably metres read as millimetres; check the unit suffix of the range "
            "column (range_m for metres)"
        )
    return [far] if med > FAR_MEDIAN_RANGE else []


def design_warnings(*, n_scans: int, n_targets: int, n_planes: int, n_aps: int) -> list[str]:
    """Designs too small for the chosen APs, said before the adjustment runs (its result will
    name the APs it cannot determine; these say why)."""
    out = []
    if not n_aps:
        return out
    if n_scans == 1:
        out.append(
            f"1 scan for {n_aps} AP(s): only the shape of what one scan sees separates the APs "
            "from its pose and the planes/targets, so expect weak or implausible estimates; "
            "self-calibration needs scans from two or more stations, some tilted (Chow et al. "
            "2013)"
        )
    n_prim = n_targets + n_planes
    if n_prim < n_aps:
        kind = "planes" if not n_targets else "targets" if not n_planes else "targets and planes"
        out.append(
            f"{n_prim} {kind} for {n_aps} APs: fewer primitives than APs, so the terms cannot be "
            "told apart; use fewer APs (e.g. physical) or more targets/planes spread over the room"
        )
    return out


@dataclasses.dataclass(frozen=True)
class Finding:
    """An AP value judged implausible: ``level`` "warning" or "impossible", the AP ``name``
    and the sentence ``text`` naming the value and the bound."""

    level: str
    name: str
    text: str


def ap_findings(names, values, units, descriptions=None) -> tuple[Finding, ...]:
    """The APs whose |value| is beyond the bounds of :data:`AP_LIMITS` for their unit (values
    that are not numbers, e.g. a non-estimable AP, are skipped)."""
    out = []
    descriptions = descriptions or [""] * len(names)
    for name, v, unit, desc in zip(names, values, units, descriptions):
        v = float(v)
        if not np.isfinite(v) or unit not in AP_LIMITS:
            continue
        warn, impossible = AP_LIMITS[unit]
        what = f"{name}{f' ({desc})' if desc else ''} = {_display(v, unit)}"
        if abs(v) > impossible:
            out.append(
                Finding(
                    "impossible",
                    name,
                    f"{what} is beyond {_display(impossible, unit)}: no working instrument has "
                    "such an error",
                )
            )
        elif abs(v) > warn:
            out.append(
                Finding(
                    "warning",
                    name,
                    f"{what} is beyond {_display(warn, unit)}: larger than instruments have",
                )
            )
    return tuple(out)


def likely_causes(
    *,
    n_scans: int,
    n_stations: int | None,
    n_primitives: int,
    n_aps: int,
    kind: str = "targets",
    not_estimable=(),
    weakly_determined=(),
    median_range: float | None = None,
) -> list[str]:
    """What in the design or the data most likely produced implausible APs, in words."""
    causes = []
    if median_range is not None and median_range > FAR_MEDIAN_RANGE:
        causes.append(
            f"ranges with a median of {median_range / 1e3:.3g} km (millimetres read as metres?)"
        )
    if n_scans == 1:
        causes.append(
            "a single scan (the APs are then separated only by the shape of what it sees)"
        )
    elif n_stations == 1:
        causes.append("every scan from one station")
    if n_aps and n_primitives < 3 * n_aps:
        causes.append(f"{n_primitives} {kind} for {n_aps} APs")
    if not_estimable:
        causes.append(f"{len(not_estimable)} AP(s) not estimable")
    if weakly_determined:
        causes.append(f"{len(weakly_determined)} AP(s) with |corr| near 1")
    return causes


def implausible_summary(findings, causes) -> str:
    """One line: the findings and the likely causes with the usual fix."""
    text = "; ".join(f.text for f in findings)
    why = "; ".join(causes) if causes else "a blunder or a unit mix-up in the data"
    return (
        f"{text}. Likely cause: {why}. Use fewer APs (e.g. --aps physical), more targets spread "
        "over the room, scans from two or more stations with tilted scans, and check the units"
    )
