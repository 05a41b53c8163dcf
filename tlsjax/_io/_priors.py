"""AP priors from a prior calibration: ``B6 = 40" +- 5"`` as text, a priors CSV, or a result JSON.

The priors are weighted constraints with observed values (Chow et al. 2013, eq. 7; SPEC
section 6): ``AP = value +- sigma``, each a linear pseudo-observation of the coefficient with
its residual, redundancy number and variance group. They go to
``CalibrationModel(ap_priors=...)`` in SI units (m, rad, or 1 for scale terms).

Forms (the CLI's ``--ap-prior`` and ``--ap-priors``):

* text ``NAME=VALUE[UNIT]+-SIGMA[UNIT]`` (``±`` also accepted), e.g. ``B6=40arcsec+-5arcsec``,
  ``A0=-0.6mm+-0.05mm``, ``A1=12ppm+-3ppm``; a sigma without a unit takes the value's unit, a
  value without one is SI. Units: ``m mm`` for length terms, ``rad deg gon arcsec`` for angular
  ones, ``ppm`` or none for scale terms; the unit must fit the AP's dimension (a millimetre
  prior of an angular term is refused);
* a CSV with columns ``ap, value, sigma, unit`` (one prior per row, the unit of both numbers);
* a tlsjax result JSON (``tlsjax calibrate --json``): every AP with a value and a sigma there.
"""

from __future__ import annotations

import csv
import json
import math
import os
import re

from .._model._aps import get_ap
from .._units import UNITS
from ._json import check_result_doc

#: Units of a prior by the AP's SI unit.
_PRIOR_UNITS = {
    "m": {k: f for k, (d, f) in UNITS.items() if d == "length"},
    "rad": {k: f for k, (d, f) in UNITS.items() if d == "angle"},
    "1": {"ppm": 1e-6, "": 1.0},
}
_TEXT = re.compile(
    r"^\s*(?P<name>[^=\s]+)\s*=\s*(?P<value>[-+0-9.eE]+)\s*(?P<vu>[A-Za-z]*)\s*"
    r"(?:\+-|\+/-|±)\s*(?P<sigma>[-+0-9.eE]+)\s*(?P<su>[A-Za-z]*)\s*$"
)


def _base(label: str) -> str:
    """The registered term of an AP label (``B6[inst1]`` -> ``B6``)."""
    return label.split("[", 1)[0]


def _to_si(label: str, number: str, unit: str, where: str) -> float:
    try:
        term = get_ap(_base(label))
    except ValueError as err:
        raise ValueError(f"{where}: {err}") from None
    units = _PRIOR_UNITS[term.unit]
    if unit == "" and term.unit != "1":
        factor = 1.0  # SI
    elif unit in units:
        factor = units[unit]
    else:
        raise ValueError(
            f"{where}: unit {unit!r} does not fit {label} (a {term.unit!r} term); "
            f"accepted: {', '.join(u for u in units if u) or 'none'} (or none for SI)"
        )
    try:
        x = float(number) * factor
    except ValueError:
        raise ValueError(f"{where}: {number!r} is not a number") from None
    if not math.isfinite(x):
        raise ValueError(f"{where}: {number!r} is not finite")
    return x


def parse_ap_prior(text: str) -> tuple[str, float, float]:
    """``"B6=40arcsec+-5arcsec"`` -> ``("B6", 40", 5")`` in SI (module docstring)."""
    m = _TEXT.match(text)
    if not m:
        raise ValueError(
            f"AP prior {text!r}: expected NAME=VALUE[UNIT]+-SIGMA[UNIT], e.g. B6=40arcsec+-5arcsec"
        )
    name, vu = m["name"], m["vu"]
    su = m["su"] or vu
    where = f"AP prior {text!r}"
    value, sigma = _to_si(name, m["value"], vu, where), _to_si(name, m["sigma"], su, where)
    if not sigma > 0:
        raise ValueError(f"{where}: the sigma must be positive")
    return name, value, sigma


def read_ap_priors(path) -> dict[str, tuple[float, float]]:
    """AP priors from a CSV (``ap, value, sigma, unit``) or a tlsjax result JSON (by the file's
    extension): label -> (value, sigma) in SI units."""
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path must be a file path, got {type(path).__name__}")
    source = os.fspath(path)
    try:
        with open(source, encoding="utf-8-sig") as fh:
            text = fh.read()
    except OSError as err:
        raise ValueError(f"{source}: cannot read the AP priors: {err.strerror}") from None
    if source.lower().endswith(".json"):
        return _from_result_json(text, source)
    return _from_csv(text, source)


def _from_result_json(text: str, source: str) -> dict:
    """The APs with a value and a sigma of a calibration's result JSON; any other JSON of
    tlsjax (a simulation's truth, a Monte Carlo summary, ...) is refused naming what it is."""
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as err:
        raise ValueError(f"{source}: not JSON ({err.msg}, line {err.lineno})") from None
    check_result_doc(doc, source)
    aps = doc["aps"]
    out = {}
    for name, d in aps.items():
        v, s = (d or {}).get("value"), (d or {}).get("sigma")
        if isinstance(v, (int, float)) and isinstance(s, (int, float)) and s > 0:
            out[str(name)] = (float(v), float(s))
    if not out:
        raise ValueError(f"{source}: no AP with a value and a sigma")
    return out


def _from_csv(text: str, source: str) -> dict:
    rows = list(csv.reader(text.splitlines()))
    if not rows:
        raise ValueError(f"{source}: empty file; expected columns ap, value, sigma, unit")
    header = [h.strip().lower() for h in rows[0]]
    need = ("ap", "value", "sigma", "unit")
    missing = [c for c in need if c not in header]
    if missing:
        raise ValueError(f"{source}, line 1: missing column(s) {', '.join(missing)}")
    col = {c: header.index(c) for c in need}
    out = {}
    for line, row in enumerate(rows[1:], start=2):
        if not any(cell.strip() for cell in row):
            continue
        cell = lambda c, row=row: row[col[c]].strip() if col[c] < len(row) else ""
        name, where = cell("ap"), f"{source}, line {line}"
        if name in out:
            raise ValueError(f"{where}: AP {name} is given twice")
        value = _to_si(name, cell("value"), cell("unit"), where)
        sigma = _to_si(name, cell("sigma"), cell("unit"), where)
        if not sigma > 0:
            raise ValueError(f"{where}: the sigma of {name} must be positive")
        out[name] = (value, sigma)
    return out
