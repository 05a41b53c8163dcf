"""Units: SI inside the engine (metres, radians), millimetres, arc seconds and ppm in reports.

SPEC section 1. This module is the one home of the conversion factors, of the unit suffixes of
the exchange files (SPEC section 11) and of the display units of reports and plots.
"""

from __future__ import annotations

import math

#: One arc second in radians (the unit of the angle APs and sigmas in reports):
#: ``sigma_angle = 20 * tj.ARCSEC``.
ARCSEC = math.pi / 648000.0
#: One degree in radians: ``tilt = 45 * tj.DEG``.
DEG = math.pi / 180.0
GON = math.pi / 200.0

#: Unit suffix of a file column -> (dimension, factor to SI).
UNITS: dict[str, tuple[str, float]] = {
    "m": ("length", 1.0),
    "mm": ("length", 1e-3),
    "rad": ("angle", 1.0),
    "deg": ("angle", DEG),
    "gon": ("angle", GON),
    "arcsec": ("angle", ARCSEC),
}

#: SI unit of an AP coefficient -> (report unit, factor from SI).
DISPLAY_UNITS = {"m": ("mm", 1e3), "rad": ('"', 1.0 / ARCSEC), "1": ("ppm", 1e6)}

#: Observation groups (range, hz, el) -> (report unit, factor from SI).
GROUP_DISPLAY = (("mm", 1e3), ("arcsec", 1.0 / ARCSEC), ("arcsec", 1.0 / ARCSEC))


def display_unit(unit: str):
    """Factor from the SI ``unit`` of an AP ("m", "rad" or "1") to its report unit, and the label."""
    label, factor = DISPLAY_UNITS[unit]
    return factor, label


def display(value, unit: str):
    """A value in SI ``unit`` ("m", "rad" or "1") in its report unit: (number, unit label)."""
    label, factor = DISPLAY_UNITS[unit]
    return value * factor, label


def display_group(group: int, value):
    """A residual or sigma of observation group ``group`` (0 range, 1 hz, 2 el) in its report
    unit: (number, unit label)."""
    label, factor = GROUP_DISPLAY[group]
    return value * factor, label
