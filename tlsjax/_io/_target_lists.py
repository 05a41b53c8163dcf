"""Vendor target lists and reference surveys: lists of named points ``name, x, y, z`` as scanner
software and survey programs export them (SPEC section 11, "Vendor target lists").

A target list holds the centres of the targets found in one scan, in that scanner's own frame
(Leica Cyclone / Register 360, FARO SCENE, RIEGL RiSCAN PRO "SOCS", Trimble RealWorks, Z+F
LaserControl exports); a reference survey holds independently surveyed coordinates in object
space. Both are read by one parser, which finds the layout itself and says what it found
(``notes``):

- **separator**: ``;``, tab, ``,`` or runs of spaces, tried in that order; the first that splits
  every data line into the same number of fields with numeric coordinates wins. With ``;``, tab or
  spaces a decimal comma (``12,345``) is read as a decimal point (European exports).
- **header**: optional. A first line naming x, y and z columns is a header; column names are
  matched without case, spaces or underscores (``Name``, ``Target ID``, ``Point``, ``X[m]``,
  ``X (mm)``, ``x_m``, ``Easting``...), units in brackets, parentheses or a ``_m``/``_mm``
  suffix. A commented header (``//X,Y,Z`` as CloudCompare writes) counts. Columns that are not
  name, scan, x, y, z or a sigma (intensity, colour, residual, type) are ignored and listed.
- **without a header**: the first column is the name, the next three x, y, z (a second text
  column makes the layout ``scan, name, x, y, z``; a first numeric column and a text column last
  ``x, y, z, ..., name``); further numeric columns are ignored and listed. A name column of
  decimal numbers is refused (it is a coordinate: the points need names to be matched). A first
  line holding only the number of points (PTS) and leading title lines without numbers are
  skipped and noted. ``columns`` (e.g. ``"scan,name,x,y,z,-,sigma"``) overrides the detection.
- **units**: an explicit ``length_unit``, else the unit in the header, else the rule of
  :func:`detect_length_unit`; an ambiguous file is refused, naming the fix.
- **sigma**: optional, one isotropic sigma per point (``sigma``, ``std``, ``precision``) or one
  per axis (``sigma_x``, ``sx``...); in the coordinates' unit unless the header names its own.

:func:`read_target_list` converts scanner-frame lists to range, horizontal direction and
elevation angle by SPEC section 1 (:func:`~tlsjax._io._point_clouds.observations_from_points`):
``rho = |x|``, ``theta = atan2(y, x)`` in [0, 2pi), ``alpha = atan2(z, hypot(x, y))``; for a
panoramic scanner a direction with ``theta >= pi`` is its second face, ``(theta - pi,
pi - alpha)``. ``x = rho (cos alpha cos theta, cos alpha sin theta, sin alpha)`` inverts both
forms exactly (to rounding, 1e-15 of the range).
"""

from __future__ import annotations

import csv
import dataclasses
import os
import re
from collections.abc import Sequence

import numpy as np

from .._adjustment._network import ObservationTable
from .._model._plausibility import MAX_RANGE, MIN_MEDIAN_RANGE
from .._model._scanner import ARCHITECTURES
from .._stats import ELLIPSOID_95
from ._point_clouds import observations_from_points

#: Length unit names -> factor to metres.
LENGTH_UNITS = {"m": 1.0, "cm": 1e-2, "mm": 1e-3}
_UNIT_ALIASES = {
    "m": "m",
    "meter": "m",
    "metre": "m",
    "meters": "m",
    "metres": "m",
    "cm": "cm",
    "mm": "mm",
    "millimeter": "mm",
    "millimetre": "mm",
    "millimeters": "mm",
    "millimetres": "mm",
}

#: Unit detection (:func:`detect_length_unit`): a list whose typical length (median range in
#: the scanner frame, median distance from the median point in object space: one wrong cell
#: cannot change the unit of the others) is at most this many file
#: units is in metres (in millimetres it would be a target network within 30 cm) ...
METRES_UP_TO = 300.0
#: ... and at least this many is in millimetres (in metres it would be kilometres).
MILLIMETRES_FROM = 3000.0

_ROLES = {
    "name": (
        "name id target targetid targetname point pointid pointname pointno pt ptid label "
        "tiepoint tiepointname tiepointid marker markerid reference referenceid nr no number"
    ),
    "scan": (
        "scan scanid scanname scanworld scanworldname scanposition scanpos scanposname setup "
        "setupid station stationid stationname sp position"
    ),
    "x": "x xs xcoord xcoordinate",
    "y": "y ys ycoord ycoordinate",
    "z": "z zs zcoord zcoordinate",
    "sigma": "sigma std stdev stddev sd sigma3d precision accuracy",
    "sigma_x": "sigmax sx stdx stdevx stddevx sdx",
    "sigma_y": "sigmay sy stdy stdevy stddevy sdy",
    "sigma_z": "sigmaz sz stdz stdevz stddevz sdz",
}
_ROLE_OF = {alias: role for role, names in _ROLES.items() for alias in names.split()}
#: Survey names of the axes, used only where a file has no x, y, z column (a RiSCAN list has
#: both ``Z[m]`` and ``Height[m]``).
#: 1-sigma semi-axes scale to the 95 % confidence ellipsoid of a 3D point by
#: sqrt(chi2_3(0.95)) = 2.7955 (normal errors, known variance factor), rounded for the headers.

_SECONDARY = {
    **dict.fromkeys("easting east e".split(), "x"),
    **dict.fromkeys("northing north n".split(), "y"),
    **dict.fromkeys("height elevation elev h up".split(), "z"),
}
_SKIP = ("-", "skip", "ignore", "_")
_COMMENTS = ("#", "//", "%", "!")
_UNIT_RE = re.compile(
    r"^(?P<q>.*?)\s*(?:\[(?P<a>[^\]]*)\]|\((?P<b>[^)]*)\)|[_ ](?P<c>mm|cm|m)|/(?P<d>mm|cm|m))$"
)
_DECIMAL_COMMA = re.compile(r"^[+-]?\d*,\d+(?:[eE][+-]?\d+)?$")


@dataclasses.dataclass(frozen=True)
class PointList:
    """Named points of one file in metres: ``names`` (n,), ``xyz`` (n, 3), ``scans`` (n,) or
    None (no scan column), ``sigma`` (n, 3) per-axis standard deviations or None, ``lines``
    (n,) the 1-based file line of each point, ``unit`` the length unit read and ``notes`` what
    the parser decided (layout, header, unit and its rule, skipped lines, ignored columns)."""

    source: str
    names: tuple
    xyz: np.ndarray
    scans: tuple | None
    sigma: np.ndarray | None
    lines: np.ndarray
    unit: str
    notes: tuple = ()

    def as_dict(self) -> dict:
        """name -> (x, y, z) [m]."""
        return {n: self.xyz[i] for i, n in enumerate(self.names)}


def _read_text_lines(source: str) -> list[str]:
    if os.path.isdir(source):
        raise ValueError(f"{source}: is a directory, not a point list")
    try:
        with open(source, "rb") as fh:
            raw = fh.read()
    except FileNotFoundError:
        raise
    except OSError as err:
        raise ValueError(f"{source}: cannot be read ({err.strerror or err})") from None
    if b"\0" in raw[:4096]:
        raise ValueError(f"{source}: a binary file, not a text point list")
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        text = raw.decode("cp1252", errors="replace")  # Windows exports with umlauts in names
    return text.splitlines()


def _number(cell: str, decimal_comma: bool):
    cell = cell.strip().strip('"').strip()
    if decimal_comma and _DECIMAL_COMMA.match(cell):
        cell = cell.replace(",", ".")
    try:
        v = float(cell)
    except ValueError:
        return None
    return v


def _split(line: str, sep):
    if sep is None:
        fields = line.split()
    else:
        fields = next(csv.reader([line], delimiter=sep, skipinitialspace=True), [])
    fields = [f.strip().strip('"').strip() for f in fields]
    while fields and fields[-1] == "":
        fields.pop()  # a trailing separator
    return fields


def _column_key(header: str) -> tuple[str, str | None]:
    """(name without unit, spaces, underscores; unit or None) of a header field."""
    text = header.strip().strip('"').strip().lower()
    unit = None
    m = _UNIT_RE.match(text)
    if m and m.group("q"):
        raw = next(g for g in (m.group("a"), m.group("b"), m.group("c"), m.group("d")) if g)
        unit = _UNIT_ALIASES.get(raw.strip(), raw.strip())
        text = m.group("q")
    return re.sub(r"[\s_\-.#/]", "", text), unit


def _column(header: str):
    """(role or None, unit or None) of a header field."""
    key, unit = _column_key(header)
    return _ROLE_OF.get(key, _SECONDARY.get(key)), unit


def _is_header(fields) -> bool:
    roles = {_column(f)[0] for f in fields}
    return {"x", "y", "z"} <= roles and any(_number(f, True) is None for f in fields)


def _strip_comment(line: str) -> str | None:
    s = line.strip()
    for c in _COMMENTS:
        if s.startswith(c):
            return s[len(c) :].strip()
    return None


class _Lines:
    """The file's lines sorted into comments, an optional header and data lines."""

    def __init__(self, source: str, lines: list[str]):
        self.source = source
        self.notes: list[str] = []
        self.header: tuple[int, str] | None = None
        self.data: list[tuple[int, str]] = []
        last_comment = None
        started = False
        for i, line in enumerate(lines, start=1):
            if not line.strip():
                continue
            body = _strip_comment(line)
            if body is not None:
                if not started:
                    last_comment = (i, body)
                continue
            if not started:
                started = True
                if self._header_like(line):
                    self.header = (i, line)
                    continue
                if last_comment is not None and self._header_like(last_comment[1]):
                    self.header = last_comment
                    self.notes.append(f"header from the comment on line {last_comment[0]}")
            self.data.append((i, line))
        self._skip_preamble()

    @staticmethod
    def _header_like(line: str) -> bool:
        return any(_is_header(_split(line, sep)) for sep in (";", "\t", ",", None))

    def _skip_preamble(self):
        # Title lines without digits before the data (and before no header), and the point
        # count of a PTS file.
        while self.header is None and self.data and not re.search(r"\d", self.data[0][1]):
            i, line = self.data.pop(0)
            self.notes.append(f"line {i} skipped (a title: {line.strip()[:40]!r})")
            if self.data and self._header_like(self.data[0][1]):
                self.header = self.data.pop(0)
        if self.data and re.fullmatch(r"\s*\d+\s*", self.data[0][1]):
            i, line = self.data[0]
            if int(line) == len(self.data) - 1:
                self.data.pop(0)
                self.notes.append(f"line {i} skipped (the point count of a PTS layout)")


_SEP_NAMES = {";": "semicolon-separated", "\t": "tab-separated", ",": "comma-separated"}


class _NoLayout(Exception):
    """This separator does not give a consistent layout (try the next one)."""


def _rows(lines: _Lines, sep, columns):
    """Rows of fields split by ``sep``, one field count on every line (else _NoLayout)."""
    rows = [_split(line, sep) for _, line in lines.data]
    counts = {len(r) for r in rows}
    if len(counts) != 1 or min(counts) < 3:
        raise _NoLayout("different numbers of fields per line")
    n = counts.pop()
    if lines.header is not None and len(_split(lines.header[1], sep)) != n:
        raise _NoLayout(f"{n} fields per line but a header of another length")
    if columns is not None and len(columns) != n:
        raise _NoLayout(f"{n} fields per line, --columns names {len(columns)}")
    return rows


def _roles_from_header(fields, source, line):
    roles, units, ignored = [], {}, []
    primary = {_ROLE_OF.get(_column_key(f)[0]) for f in fields}
    for f in fields:
        role, unit = _column(f)
        if role in ("x", "y", "z") and role in primary and _column_key(f)[0] in _SECONDARY:
            role = None  # Height beside Z: a survey column, not the coordinate
        if role is not None and role in roles:
            raise ValueError(f"{source}, line {line}: two columns for {role} ({f!r})")
        roles.append(role)
        if role is None:
            ignored.append(f)
        elif unit is not None:
            if unit not in LENGTH_UNITS:
                raise ValueError(
                    f"{source}, line {line}, column {f}: unknown length unit {unit!r}; "
                    f"accepted: {', '.join(LENGTH_UNITS)}"
                )
            units[role] = unit
    return roles, units, ignored


def _numeric_column(rows, j, decimal_comma) -> bool:
    return all(_number(r[j], decimal_comma) is not None for r in rows)


def _roles_without_header(rows, decimal_comma):
    n = len(rows[0])
    num = [_numeric_column(rows, j, decimal_comma) for j in range(n)]
    if num[0] and num[1] and num[2] and not num[-1] and n >= 4:
        roles = ["x", "y", "z"] + [None] * (n - 4) + ["name"]
    elif n >= 5 and not num[1] and all(num[2:5]):
        roles = ["scan", "name", "x", "y", "z"] + [None] * (n - 5)
    elif n >= 4 and all(num[1:4]):
        roles = ["name", "x", "y", "z"] + [None] * (n - 4)
    else:
        raise _NoLayout("no header and no name, x, y, z columns")
    name_col = roles.index("name")
    if num[name_col]:
        values = [_number(r[name_col], decimal_comma) for r in rows]
        if not all(float(v).is_integer() for v in values):
            raise _NoLayout(
                f"without a header column {name_col + 1} would be the names, but it holds "
                "decimal numbers (points need names to be matched across scans: add a header)"
            )
    ignored = [f"column {j + 1}" for j, r in enumerate(roles) if r is None]
    return roles, ignored


def _parse_columns(columns) -> list | None:
    if columns is None:
        return None
    items = columns.split(",") if isinstance(columns, str) else list(columns)
    roles = []
    for c in items:
        c = str(c).strip().lower()
        if c in _SKIP:
            roles.append(None)
            continue
        role = _ROLE_OF.get(re.sub(r"[\s_\-.]", "", c))
        if role is None:
            raise ValueError(
                f"columns: unknown column {c!r}; use name, scan, x, y, z, sigma, sigma_x, "
                "sigma_y, sigma_z or '-' for a column to ignore"
            )
        roles.append(role)
    for need in ("name", "x", "y", "z"):
        if need not in roles:
            raise ValueError(f"columns: {need!r} is missing (given {items})")
    return roles


def detect_length_unit(typical_length: float) -> str | None:
    """The length unit of a point list from its typical length in file units (the median
    range of a scanner-frame list, the RMS distance from the centroid of an object-space list):
    metres up to :data:`METRES_UP_TO` (300), millimetres from :data:`MILLIMETRES_FROM` (3000),
    None (ambiguous: 0.3-3 m in millimetres or 300 m-3 km in metres) between."""
    if typical_length <= METRES_UP_TO:
        return "m"
    if typical_length >= MILLIMETRES_FROM:
        return "mm"
    return None


def _unit(length_unit, header_units, xyz_file, frame, source):
    coord_units = {header_units[k] for k in ("x", "y", "z") if k in header_units}
    if len(coord_units) > 1:
        raise ValueError(f"{source}: x, y, z are given in different units {sorted(coord_units)}")
    header = coord_units.pop() if coord_units else None
    if length_unit is not None:
        if length_unit not in LENGTH_UNITS:
            raise ValueError(f"length_unit {length_unit!r} is not one of {', '.join(LENGTH_UNITS)}")
        if header is not None and header != length_unit:
            raise ValueError(
                f"{source}: the header says {header} but length_unit {length_unit} was given"
            )
        return length_unit, f"{length_unit} (given)"
    if header is not None:
        return header, f"{header} (from the header)"
    if frame == "scanner":
        with np.errstate(over="ignore"):  # a wrong cell of 1e300: refused by its line later
            typical, what = float(np.median(np.linalg.norm(xyz_file, axis=1))), "median range"
    else:
        typical = float(np.median(_spread(xyz_file)))
        what = "median distance from the median point"
    unit = detect_length_unit(typical)
    if unit is None:
        raise ValueError(
            f"{source}: the length unit is ambiguous: {what} {typical:.4g} file units is "
            f"{typical / 1000:.3g} m in millimetres or {typical:.4g} m in metres; give "
            "--length-unit m|mm (length_unit=...) or put the unit in the header (e.g. X[mm])"
        )
    return unit, f"{unit} (detected: {what} {typical:.4g} file units; metres up to " + (
        f"{METRES_UP_TO:g}, millimetres from {MILLIMETRES_FROM:g})"
    )


def read_point_list(path, *, frame: str = "scanner", length_unit=None, columns=None) -> PointList:
    """Read one list of named points (see the module docstring for the layouts). ``frame``
    ("scanner" or "object") only selects the typical length of the unit rule. Every problem is
    a one-line ValueError naming the file (and line)."""
    if frame not in ("scanner", "object"):
        raise ValueError(f"frame must be 'scanner' or 'object', got {frame!r}")
    source = os.fspath(path)
    lines = _Lines(source, _read_text_lines(source))
    if not lines.data:
        raise ValueError(f"{source}: no data lines (an empty point list)")
    roles_given = _parse_columns(columns)
    tried = []
    for sep in (";", "\t", ",", None):
        try:
            layout = _columns_of(lines, sep, roles_given)
        except _NoLayout as why:
            tried.append(f"{_SEP_NAMES.get(sep, 'spaces')}: {why}")
            continue
        return _point_list(lines, sep, layout, frame, length_unit)
    raise ValueError(
        f"{source}: no layout found ({'; '.join(tried)}); check for names with spaces in a "
        "space-separated file (use ',' or ';'), or give --columns (e.g. 'name,x,y,z')"
    )


def _columns_of(lines: _Lines, sep, roles_given):
    """(rows, roles, header units, ignored columns, decimal comma) for separator ``sep``."""
    rows = _rows(lines, sep, roles_given)
    dc = sep != ","
    header_units, ignored = {}, []
    if roles_given is not None:
        roles = roles_given
    elif lines.header is not None:
        roles, header_units, ignored = _roles_from_header(
            _split(lines.header[1], sep), lines.source, lines.header[0]
        )
        missing = [r for r in ("name", "x", "y", "z") if r not in roles]
        if missing:
            raise _NoLayout(f"no {' or '.join(missing)} column in the header (name it, e.g. Name)")
    else:
        roles, ignored = _roles_without_header(rows, dc)
    for r in ("x", "y", "z"):
        if not _numeric_column(rows, roles.index(r), dc):
            raise _NoLayout(f"the {r} column is not numeric")
    return rows, roles, header_units, ignored, dc


def _point_list(lines: _Lines, sep, layout, frame, length_unit) -> PointList:
    rows, roles, header_units, ignored, dc = layout
    source = lines.source
    data_lines = np.array([i for i, _ in lines.data], dtype=np.int64)
    col = {r: j for j, r in enumerate(roles) if r is not None}
    numbers = {}
    for r in ("x", "y", "z", "sigma", "sigma_x", "sigma_y", "sigma_z"):
        if r not in col:
            continue
        vals = np.empty(len(rows))
        for k, fields in enumerate(rows):
            v = _number(fields[col[r]], dc)
            if v is None or not np.isfinite(v):
                raise ValueError(
                    f"{source}, line {data_lines[k]}: {r} = {fields[col[r]]!r} is not a number"
                )
            vals[k] = v
        numbers[r] = vals
    names = tuple(fields[col["name"]] for fields in rows)
    for k, n in enumerate(names):
        if not n:
            raise ValueError(f"{source}, line {data_lines[k]}: empty point name")
    scans = tuple(fields[col["scan"]] for fields in rows) if "scan" in col else None
    xyz_file = np.stack([numbers["x"], numbers["y"], numbers["z"]], axis=1)
    unit, unit_note = _unit(length_unit, header_units, xyz_file, frame, source)
    sigma = _sigmas(numbers, header_units, unit, source, data_lines)
    notes = [
        f"{_SEP_NAMES.get(sep, 'space-separated')}"
        + (", decimal comma" if dc and _uses_decimal_comma(rows, col) else ""),
        "header: " + " | ".join(_split(lines.header[1], sep))
        if lines.header is not None
        else "no header: columns " + ", ".join(r or "-" for r in roles),
        f"units: {unit_note}",
        *lines.notes,
    ]
    if ignored:
        notes.append("ignored columns: " + ", ".join(ignored))
    xyz = xyz_file * LENGTH_UNITS[unit]
    _check_magnitudes(xyz, frame, source, names, data_lines, unit_note)
    return PointList(source, names, xyz, scans, sigma, data_lines, unit, tuple(notes))


def _spread(xyz: np.ndarray) -> np.ndarray:
    """Distance of each point from the coordinate-wise median point (robust to a few wrong
    cells, unlike the centroid)."""
    with np.errstate(over="ignore", invalid="ignore"):
        return np.linalg.norm(xyz - np.median(xyz, axis=0), axis=1)


def _check_magnitudes(xyz, frame, source, names, data_lines, unit_note) -> None:
    """The plausibility rules of the observation CSV (``_model/_plausibility``) for a point
    list [m]: a point farther than :data:`MAX_RANGE` from its scanner (scanner frame) or from
    the list's median point (object space) is a wrong cell or unit, named by its line; a
    scanner-frame list whose median range is closer than any scanner measures is a unit
    mix-up."""
    if frame == "scanner":
        with np.errstate(over="ignore", invalid="ignore"):
            dist = np.linalg.norm(xyz, axis=1)
        what = "from the scanner"
    else:
        dist, what = _spread(xyz), "from the median point of the list"
    far = np.flatnonzero(~(dist <= MAX_RANGE))
    if far.size:
        k = int(far[0])
        far_m = f"{dist[k]:.4g} m" if np.isfinite(dist[k]) else "more than 1e308 m"
        raise ValueError(
            f"{source}, line {data_lines[k]}: point {names[k]} lies {far_m} {what} "
            f"(units: {unit_note}), beyond any laser scan ({MAX_RANGE / 1e3:g} km): check the "
            "coordinates on that line and the length unit"
        )
    median = float(np.median(dist))
    if frame == "scanner" and median < MIN_MEDIAN_RANGE:
        raise ValueError(
            f"{source}: the points have a median range of {median * 1e3:.3g} mm (units: "
            f"{unit_note}), closer than any scanner measures: probably metres read as "
            "millimetres; give --length-unit m (length_unit='m') or fix the header's unit"
        )


def _uses_decimal_comma(rows, col) -> bool:
    return any(
        "," in r[col[q]] for r in rows[:50] for q in ("x", "y", "z") if q in col and col[q] < len(r)
    )


def _sigmas(numbers, header_units, unit, source, lines):
    """Per-axis sigmas [m] (n, 3) of the point list, or None."""
    if "sigma" in numbers and any(k in numbers for k in ("sigma_x", "sigma_y", "sigma_z")):
        raise ValueError(f"{source}: both an isotropic sigma and per-axis sigma columns")
    if "sigma" in numbers:
        f = LENGTH_UNITS[header_units.get("sigma", unit)]
        s = np.repeat(numbers["sigma"][:, None] * f, 3, axis=1)
    elif any(k in numbers for k in ("sigma_x", "sigma_y", "sigma_z")):
        missing = [k for k in ("sigma_x", "sigma_y", "sigma_z") if k not in numbers]
        if missing:
            raise ValueError(f"{source}: per-axis sigmas need all three columns; {missing} missing")
        keys = ("sigma_x", "sigma_y", "sigma_z")
        s = np.stack([numbers[k] * LENGTH_UNITS[header_units.get(k, unit)] for k in keys], axis=1)
    else:
        return None
    bad = np.flatnonzero(~(s > 0).all(axis=1))
    if bad.size:
        raise ValueError(f"{source}, line {lines[bad[0]]}: a sigma must be positive")
    return s


def polar_sigmas(x: np.ndarray, sigma_xyz: np.ndarray) -> np.ndarray:
    """Standard deviations of (rho, theta, alpha) [m, rad, rad] of scanner-space points ``x``
    (n, 3) whose coordinates have independent standard deviations ``sigma_xyz`` (n, 3): the
    diagonal of ``J diag(sigma^2) J^T``, J the Jacobian of SPEC section 1's conversion. An
    isotropic sigma s gives exactly (s, s / (rho cos alpha), s / rho); per-axis sigmas leave
    out the correlations between the three (the network takes independent observations)."""
    x = np.asarray(x, dtype=np.float64)
    rho = np.linalg.norm(x, axis=1)
    h2 = x[:, 0] ** 2 + x[:, 1] ** 2
    h = np.sqrt(h2)
    J = np.zeros((len(x), 3, 3))
    J[:, 0] = x / rho[:, None]
    J[:, 1, 0], J[:, 1, 1] = -x[:, 1] / h2, x[:, 0] / h2
    J[:, 2, 0] = -x[:, 0] * x[:, 2] / (h * rho**2)
    J[:, 2, 1] = -x[:, 1] * x[:, 2] / (h * rho**2)
    J[:, 2, 2] = h / rho**2
    var = np.einsum("nij,nj->ni", J**2, np.asarray(sigma_xyz, dtype=np.float64) ** 2)
    return np.sqrt(var)


def _as_paths(paths) -> list[str]:
    if isinstance(paths, (str, os.PathLike)):
        return [os.fspath(paths)]
    if (
        isinstance(paths, Sequence)
        and paths
        and all(isinstance(p, (str, os.PathLike)) for p in paths)
    ):
        return [os.fspath(p) for p in paths]
    raise TypeError("paths must be a file path or a non-empty sequence of file paths")


def read_target_list(
    paths, architecture: str, *, length_unit=None, scan=None, columns=None
) -> ObservationTable:
    """Vendor target lists (Cartesian target centres in each scanner's frame) as target
    observations (range, horizontal direction, elevation angle) of ``architecture``.

    ``paths``: one file per scan (the scan is named by the file name without its extension,
    or by ``scan`` for a single file) or files with a scan column. ``length_unit`` ("m",
    "cm", "mm"): the unit of every file; default from each file's header or the rule of
    :func:`detect_length_unit` (files whose detected units differ are refused). ``columns``:
    the column roles when the layout is not detected (``"scan,name,x,y,z"``; ``-`` ignores a
    column). A sigma column gives per-observation sigmas (:func:`polar_sigmas`). For a
    panoramic scanner the back half (``theta >= 180 deg``) is folded into the second face
    (SPEC section 1). The result records the architecture and what was read (``notes``); give
    it to :func:`~tlsjax.read_network` or :func:`~tlsjax.write_observations`.
    """
    if architecture not in ARCHITECTURES:
        raise ValueError(f"architecture {architecture!r} is not one of {ARCHITECTURES}")
    files = _as_paths(paths)
    if scan is not None and len(files) > 1:
        raise ValueError(
            "scan= names the scan of a single file; several files are named by their file names"
        )
    lists = [read_point_list(p, length_unit=length_unit, columns=columns) for p in files]
    _check_units_agree(lists, length_unit)
    scans, names, xyz, sig, lines, notes = _combine(lists, scan)
    rho = np.linalg.norm(xyz, axis=1)
    if (rho == 0).any():
        k = int(np.argmax(rho == 0))
        raise ValueError(
            f"{lines[k][0]}, line {lines[k][1]}: target {names[k]} is at the scanner's origin (0, 0, 0)"
        )
    obs = observations_from_points(xyz, architecture)
    sigmas = None
    if any(pl.sigma is not None for pl in lists):
        if not all(pl.sigma is not None for pl in lists):
            raise ValueError(
                "some target lists have sigma columns and others not; give all or none"
            )
        sigmas = polar_sigmas(xyz, sig)
    source = files[0] if len(files) == 1 else f"{len(files)} target lists ({', '.join(files)})"
    return ObservationTable(
        kind="target",
        source=source,
        scans=tuple(scans),
        primitives=tuple(names),
        observations=obs,
        sigmas=sigmas,
        incidence=None,
        instruments=None,
        rows=np.array([ln for _, ln in lines], dtype=np.int64),
        architecture=architecture,
        notes=tuple(notes),
    )


def _check_units_agree(lists, length_unit):
    if length_unit is not None:
        return
    detected = {pl.source: pl.unit for pl in lists if any("(detected" in n for n in pl.notes)}
    if len(set(detected.values())) > 1:
        listed = ", ".join(f"{s}: {u}" for s, u in detected.items())
        raise ValueError(
            f"the target lists' detected length units differ ({listed}); give --length-unit "
            "(length_unit=...) or put the unit in the headers"
        )


def _combine(lists, scan):
    scans, names, xyz, sig, lines, notes = [], [], [], [], [], []
    stems: dict[str, str] = {}
    first: dict[tuple[str, str], tuple[str, int]] = {}
    for pl in lists:
        if pl.scans is not None:
            if scan is not None:
                raise ValueError(f"{pl.source}: has a scan column; scan= is for files without one")
            file_scans = pl.scans
            how = "scan column"
        else:
            name = scan if scan is not None else os.path.splitext(os.path.basename(pl.source))[0]
            if name in stems:
                raise ValueError(
                    f"{pl.source}: scan {name!r} is also the scan of {stems[name]} (scans are "
                    "named by the file names); rename one file or use a scan column"
                )
            stems[name] = pl.source
            file_scans = (name,) * len(pl.names)
            how = f"scan {name} ({'given' if scan is not None else 'the file name'})"
        for k, (s, n) in enumerate(zip(file_scans, pl.names)):
            key = (s, n)
            if key in first:
                src, ln = first[key]
                raise ValueError(
                    f"{pl.source}, line {pl.lines[k]}: target {n} of scan {s} is listed twice "
                    f"(also {src}, line {ln})"
                )
            first[key] = (pl.source, int(pl.lines[k]))
            lines.append((pl.source, int(pl.lines[k])))
        scans += list(file_scans)
        names += list(pl.names)
        xyz.append(pl.xyz)
        if pl.sigma is not None:
            sig.append(pl.sigma)
        notes.append(f"{pl.source}: {len(pl.names)} targets, {how}; " + "; ".join(pl.notes))
    return (
        scans,
        names,
        np.concatenate(xyz),
        np.concatenate(sig) if sig else None,
        lines,
        notes,
    )


def read_reference(path, *, length_unit=None, columns=None) -> dict:
    """Reference coordinates, name -> (X, Y, Z) [m]: a point list in object space (any layout
    :func:`read_point_list` reads; the unit rule uses the spread about the centroid), or the
    ``targets`` of a tlsjax result JSON (the targets of another calibration: cross-validation
    of held-out scans)."""
    source = os.fspath(path)
    if source.lower().endswith(".json"):
        from ._json import read_result_json

        doc = read_result_json(source)
        targets = doc.get("targets")
        if not isinstance(targets, dict) or not targets:
            raise ValueError(f"{source}: no 'targets' in this JSON (written by an older tlsjax?)")
        out = {}
        for name, t in targets.items():
            xyz = t.get("xyz") if isinstance(t, dict) else None
            if isinstance(xyz, list) and len(xyz) == 3 and None not in xyz:
                out[str(name)] = np.asarray(xyz, dtype=np.float64)
        if not out:
            raise ValueError(f"{source}: its targets have no coordinates ({doc.get('estimates')})")
        return out
    pl = read_point_list(source, frame="object", length_unit=length_unit, columns=columns)
    if pl.scans is not None:
        raise ValueError(f"{source}: a reference has one set of coordinates, not a scan column")
    seen: dict[str, int] = {}
    for k, n in enumerate(pl.names):
        if n in seen:
            raise ValueError(
                f"{source}, line {pl.lines[k]}: {n} is listed twice (also line {seen[n]})"
            )
        seen[n] = int(pl.lines[k])
    return pl.as_dict()


def write_target_csv(path, names, xyz, sigma, axes, n_scans, frame: str) -> None:
    """Adjusted target coordinates as CSV: ``target, x_m, y_m, z_m, sigma_x_mm, sigma_y_mm,
    sigma_z_mm, axis_1_mm, axis_2_mm, axis_3_mm`` (1-sigma ellipsoid semi-axes, largest first),
    ``n_scans``, with the frame in a comment line before the header; written atomically. It
    reads back as a point list (:func:`read_point_list`, e.g. as ``check-targets --reference``)."""
    from ._json import write_text_atomic

    def f(v, scale=1.0):
        return "" if not np.isfinite(v) else f"{v * scale:.17g}"

    out = [
        f"# tlsjax adjusted targets: {frame}; axis_1..3: 1-sigma ellipsoid semi-axes, largest "
        f"first (x {ELLIPSOID_95} for 95 %)"
    ]
    out.append(
        "target,x_m,y_m,z_m,sigma_x_mm,sigma_y_mm,sigma_z_mm,axis_1_mm,axis_2_mm,axis_3_mm,n_scans"
    )
    for i, n in enumerate(names):
        cells = (
            [f(v) for v in xyz[i]] + [f(v, 1e3) for v in sigma[i]] + [f(v, 1e3) for v in axes[i]]
        )
        out.append(",".join([_csv_cell(n), *cells, str(int(n_scans[i]))]))
    write_text_atomic(path, "\n".join(out) + "\n", "--targets-out ")


def _csv_cell(text: str) -> str:
    if any(c in text for c in ',"\n'):
        return '"' + text.replace('"', '""') + '"'
    return text
