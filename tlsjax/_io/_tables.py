"""Observation and scan CSV files (SPEC section 11), read and written on the host with numpy.

Every numeric column carries its unit as a header suffix (``range_m``, ``hz_deg``,
``sigma_hz_arcsec``); values are converted to metres and radians on reading. Files come from
people and other programs, so every problem is reported as a ``ValueError`` naming the file, the
line and the column, and nothing unexpected (an unknown column, a missing unit) is ignored.
"""

from __future__ import annotations

import csv
import dataclasses
import math
import os
import re

import numpy as np

from .._adjustment._network import ObservationTable
from .._model._scanner import ARCHITECTURES
from .._units import UNITS
from ._outputs import atomic_output

#: Numeric quantity -> dimension, for both file kinds.
QUANTITIES: dict[str, str] = {
    "range": "length",
    "hz": "angle",
    "el": "angle",
    "sigma_range": "length",
    "sigma_hz": "angle",
    "sigma_el": "angle",
    "incidence": "angle",
    "omega": "angle",
    "phi": "angle",
    "sigma_omega": "angle",
    "sigma_phi": "angle",
}

_OBS_NUMERIC = ("range", "hz", "el", "sigma_range", "sigma_hz", "sigma_el", "incidence")
_OBS_TEXT = ("scan", "target", "plane", "instrument")
_SCAN_NUMERIC = ("omega", "phi", "sigma_omega", "sigma_phi")
_SCAN_TEXT = ("scan",)
_TWO_PI = 2.0 * math.pi


def _accepted(dimension: str | None = None) -> str:
    return ", ".join("_" + u for u, (d, _) in UNITS.items() if dimension in (None, d))


def _split_unit(header: str) -> tuple[str, str, float]:
    """Split ``header`` into (quantity, unit, factor); raise ValueError without location."""
    # Longest known quantity first, so that "sigma_range_mm" is not read as "sigma" + "range_mm".
    for q in sorted(QUANTITIES, key=len, reverse=True):
        if header == q:
            dim = QUANTITIES[q]
            raise ValueError(f"missing unit suffix; accepted for {dim}s: {_accepted(dim)}")
        if header.startswith(q + "_"):
            unit, dim = header[len(q) + 1 :], QUANTITIES[q]
            if unit not in UNITS:
                raise ValueError(
                    f"unknown unit suffix '_{unit}'; accepted for {dim}s: {_accepted(dim)}"
                )
            if UNITS[unit][0] != dim:
                raise ValueError(
                    f"'{q}' is a{'n' if dim == 'angle' else ''} {dim} but '_{unit}' is a unit of "
                    f"{UNITS[unit][0]}; accepted for {dim}s: {_accepted(dim)}"
                )
            return q, unit, UNITS[unit][1]
    # Not a tlsjax quantity: still usable for any "<name>_<unit>" header.
    name, sep, unit = header.rpartition("_")
    if not sep or not name:
        raise ValueError(f"missing unit suffix; accepted: {_accepted()}")
    if unit not in UNITS:
        raise ValueError(f"unknown unit suffix '_{unit}'; accepted: {_accepted()}")
    return name, unit, UNITS[unit][1]


def parse_unit_column(header: str) -> tuple[str, str, float]:
    """``"hz_deg"`` -> ``("hz", "deg", pi/180)``: quantity, unit and the factor to SI units.

    Raises ValueError for a missing or unknown suffix, or a unit of the wrong dimension
    (``range_deg``).
    """
    try:
        return _split_unit(header.strip())
    except ValueError as err:
        raise ValueError(f"column {header}: {err}") from None


class _Located:
    """Formats error messages as ``file, line L, column C: message``."""

    def __init__(self, source: str):
        self.source = source

    def error(self, message: str, line: int | None = None, column: str | None = None) -> ValueError:
        where = [self.source]
        if line is not None:
            where.append(f"line {line}")
        if column is not None:
            where.append(f"column {column}")
        return ValueError(", ".join(where) + ": " + message)


def open_text(path, what: str = "CSV file"):
    """``open(path)`` for reading text; a directory, a missing or unreadable file is one
    ``ValueError`` naming the path (FileNotFoundError stays one: it is the usual mistake)."""
    source = os.fspath(path)
    if os.path.isdir(source):
        raise ValueError(f"{source}: is a directory, not a {what}")
    try:
        # utf-8-sig: spreadsheet programs often write a byte-order mark before the header.
        return open(source, newline="", encoding="utf-8-sig")
    except FileNotFoundError:
        raise
    except OSError as err:
        raise ValueError(f"{source}: cannot be read ({err.strerror or err})") from None


#: First characters of a comment line before the header: tlsjax writes
#: ``# tlsjax target observations: architecture=panoramic`` there (:func:`recorded_architecture`).
COMMENT = "#"


def _read_rows(path, loc: _Located):
    """Header (list of (line, names)) and data rows as (line, fields), blank lines and comment
    lines before the header (``#``) skipped."""
    with open_text(path) as fh:
        reader = csv.reader(fh, delimiter=",", strict=True)
        records = []
        last = 0
        try:
            for fields in reader:
                start, last = last + 1, reader.line_num
                if not fields or all(not f.strip() for f in fields):
                    continue
                if not records and fields[0].lstrip().startswith(COMMENT):
                    continue
                records.append((start, fields))
        except csv.Error as err:
            raise loc.error(f"malformed CSV: {err}", last + 1) from None
        except UnicodeDecodeError:
            raise loc.error("not a text CSV file (it is not UTF-8 text)", last + 1) from None
    if not records:
        raise loc.error("empty file: no header", 1)
    (header_line, header), data = records[0], records[1:]
    names = [h.strip() for h in header]
    if len(names) == 1 and any(c in names[0] for c in ";\t"):
        raise loc.error("only one column in the header: the delimiter must be ','", header_line)
    for i, name in enumerate(names):
        if not name:
            raise loc.error(f"header field {i + 1} is empty", header_line)
    return header_line, names, data


def _parse_header(names, header_line, loc, text_cols, numeric_cols):
    """Map each column to (name, quantity, factor); quantity == name for text columns."""
    columns = []
    seen: dict[str, str] = {}
    unknown = []
    for name in names:
        key = name.lower()
        if key in text_cols:
            q, factor = key, None
        elif any(key == q or key.startswith(q + "_") for q in numeric_cols):
            try:
                q, _, factor = _split_unit(key)
            except ValueError as err:
                raise loc.error(str(err), header_line, name) from None
            if q not in numeric_cols:
                unknown.append(name)
                continue
        else:
            unknown.append(name)
            continue
        if q in seen:
            raise loc.error(
                f"'{q}' given twice, as columns '{seen[q]}' and '{name}'", header_line, name
            )
        seen[q] = name
        columns.append((name, q, factor))
    if unknown:
        accepted = ", ".join(list(text_cols) + [q + "_<unit>" for q in numeric_cols])
        listed = ", ".join(f"'{u}'" for u in unknown)
        raise loc.error(f"unknown column(s) {listed}; accepted columns: {accepted}", header_line)
    return columns, seen


def _number(text, line, column, loc, required):
    text = text.strip()
    if not text:
        if required:
            raise loc.error("empty value", line, column)
        return math.nan
    try:
        value = float(text)
    except ValueError:
        raise loc.error(f"{text!r} is not a number", line, column) from None
    if not math.isfinite(value):
        raise loc.error(f"{text!r} is not a finite number", line, column)
    return value


def _cells(data, columns, loc):
    """Yield (line, {quantity: stripped text}) for each data row, checking the field count."""
    for line, fields in data:
        if len(fields) != len(columns):
            raise loc.error(f"expected {len(columns)} fields, found {len(fields)}", line)
        yield line, {q: (f.strip(), name, factor) for (name, q, factor), f in zip(columns, fields)}


def _check_directions(row, cells, line, loc) -> None:
    """|hz| below two turns and el in [-90, 270) deg, before hz is wrapped: 720 deg would wrap
    to a plausible 0, and degrees in a ``_rad`` column exceed the limits (SPEC section 1). A
    reading one turn off (370 deg) is a direction; the architecture's own limits are checked by
    make_network."""
    limits = (
        ("hz", abs(row[1]) >= 2 * _TWO_PI, "is two turns or more (|hz| must be below 720 deg)"),
        ("el", row[2] < -0.5 * math.pi - 1e-9, "is below -90 deg (the nadir)"),
        ("el", row[2] >= 1.5 * math.pi, "is not below 270 deg"),
    )
    for q, bad, why in limits:
        if bad:
            text, name, _ = cells[q]
            raise loc.error(
                f"{q} = {text} ({math.degrees(row[1 if q == 'hz' else 2]):.6g} deg) {why}: "
                f"check the value and the unit in the column name",
                line,
                name,
            )


_ARCH_KEY = re.compile(r"architecture\s*[=:]\s*([A-Za-z]+)")


def recorded_architecture(path) -> str | None:
    """The scanner architecture recorded in the comment lines before the header of an
    observation CSV (``# tlsjax ...: architecture=panoramic``), or None."""
    source = os.fspath(path)
    found = None
    with open_text(source) as fh:
        try:
            for line in fh:
                text = line.strip()
                if not text:
                    continue
                if not text.startswith(COMMENT):
                    break
                m = _ARCH_KEY.search(text)
                if m:
                    found = m.group(1).lower()
        except UnicodeDecodeError:
            return None  # not text: the reader says so, with the line
    if found is not None and found not in ARCHITECTURES:
        raise ValueError(
            f"{source}: the recorded scanner architecture {found!r} is not one of {ARCHITECTURES}"
        )
    return found


def architecture_comment(kind: str, architecture: str) -> str:
    """The comment line that records the architecture (read back by
    :func:`recorded_architecture`)."""
    return f"# tlsjax {kind} observations: architecture={architecture}"


def read_observations(path) -> ObservationTable:
    """Read a target or plane observation CSV (SPEC section 11) into SI units.

    The kind comes from the presence of a ``target`` or a ``plane`` column; hz is wrapped into
    [0, 2pi), el is left as given (panoramic elevations reach past pi/2). The architecture
    recorded in a comment line before the header (files tlsjax writes) is in
    ``table.architecture``.
    """
    _check_path(path, "path")
    source = os.fspath(path)
    loc = _Located(source)
    architecture = recorded_architecture(source)
    header_line, names, data = _read_rows(path, loc)
    columns, seen = _parse_header(names, header_line, loc, _OBS_TEXT, _OBS_NUMERIC)

    if "target" in seen and "plane" in seen:
        raise loc.error(
            "a file may not mix targets and planes: it has both a 'target' and a 'plane' column",
            header_line,
            seen["plane"],
        )
    kind = "target" if "target" in seen else "plane" if "plane" in seen else None
    for q, what in (
        ("scan", "scan"),
        (kind, "target"),
        ("range", "range_<unit>"),
        ("hz", "hz_<unit>"),
        ("el", "el_<unit>"),
    ):
        if q is None or q not in seen:
            extra = " (or 'plane' for a plane file)" if q is None else ""
            raise loc.error(f"missing required column{extra}", header_line, what)
    if not data:
        raise loc.error("no data rows after the header", header_line + 1)

    sigma_qs = ("sigma_range", "sigma_hz", "sigma_el")
    has_sigma = any(q in seen for q in sigma_qs)
    scans, prims, instruments, lines = [], [], [], []
    obs = np.empty((len(data), 3))
    sig = np.full((len(data), 3), np.nan)
    inc = np.full(len(data), np.nan)
    first_line: dict[tuple[str, str], int] = {}

    for i, (line, cells) in enumerate(_cells(data, columns, loc)):
        for q in ("scan", kind) + (("instrument",) if "instrument" in seen else ()):
            text, name, _ = cells[q]
            if not text:
                raise loc.error(f"empty {q} name", line, name)
        scan, prim = cells["scan"][0], cells[kind][0]
        for j, q in enumerate(("range", "hz", "el")):
            text, name, factor = cells[q]
            obs[i, j] = _number(text, line, name, loc, required=True) * factor
        if obs[i, 0] <= 0.0:
            raise loc.error(
                f"range must be positive, got {cells['range'][0]!r}", line, cells["range"][1]
            )
        _check_directions(obs[i], cells, line, loc)
        for j, q in enumerate(sigma_qs):
            if q in cells:
                text, name, factor = cells[q]
                sig[i, j] = _number(text, line, name, loc, required=False) * factor
                if sig[i, j] <= 0.0:
                    raise loc.error(f"sigma must be positive, got {text!r}", line, name)
        if "incidence" in cells:
            text, name, factor = cells["incidence"]
            inc[i] = _number(text, line, name, loc, required=False) * factor
        # Planes carry many points per (scan, plane); a target is observed once per scan.
        if kind == "target":
            key = (scan, prim)
            if key in first_line:
                raise loc.error(
                    f"duplicate observation of target '{prim}' in scan '{scan}' "
                    f"(lines {first_line[key]} and {line})",
                    line,
                    cells["target"][1],
                )
            first_line[key] = line
        scans.append(scan)
        prims.append(prim)
        if "instrument" in cells:
            instruments.append(cells["instrument"][0])
        lines.append(line)

    hz = np.mod(obs[:, 1], _TWO_PI)
    # np.mod returns 2pi itself for tiny negative inputs; the contract is the half-open interval.
    obs[:, 1] = np.where(hz >= _TWO_PI, 0.0, hz)
    return ObservationTable(
        kind=kind,
        source=source,
        scans=tuple(scans),
        primitives=tuple(prims),
        observations=obs,
        sigmas=sig if has_sigma else None,
        incidence=inc if "incidence" in seen else None,
        instruments=tuple(instruments) if "instrument" in seen else None,
        rows=np.asarray(lines, dtype=np.int64),
        architecture=architecture,
    )


def read_scans(path) -> dict[str, dict[str, float]]:
    """Read the optional scans CSV: levelling observations of the levelled scans, in radians.

    Columns ``scan`` and any of ``omega_<u>``, ``phi_<u>`` (default 0), ``sigma_omega_<u>``,
    ``sigma_phi_<u>``. A scan is levelled when both its sigma cells are filled; scans with both
    empty are left out of the result. Levelling angles in a file without sigma columns are
    refused (they could not be weighted, and dropping them would go unnoticed).
    """
    _check_path(path, "path")
    source = os.fspath(path)
    loc = _Located(source)
    header_line, names, data = _read_rows(path, loc)
    columns, seen = _parse_header(names, header_line, loc, _SCAN_TEXT, _SCAN_NUMERIC)
    if "scan" not in seen:
        raise loc.error("missing required column", header_line, "scan")
    # A lone sigma column could only describe half a levelling observation.
    for a, b in (("sigma_omega", "sigma_phi"), ("sigma_phi", "sigma_omega")):
        if a in seen and b not in seen:
            raise loc.error(
                f"column '{b}_<unit>' is required with '{seen[a]}'", header_line, seen[a]
            )

    result: dict[str, dict[str, float]] = {}
    first_line: dict[str, int] = {}
    for line, cells in _cells(data, columns, loc):
        scan, scan_col = cells["scan"][0], cells["scan"][1]
        if not scan:
            raise loc.error("empty scan name", line, scan_col)
        if scan in first_line:
            raise loc.error(
                f"duplicate scan '{scan}' (lines {first_line[scan]} and {line})", line, scan_col
            )
        first_line[scan] = line
        values = {}
        for q in _SCAN_NUMERIC:
            if q in cells:
                text, name, factor = cells[q]
                values[q] = _number(text, line, name, loc, required=False) * factor
                if q.startswith("sigma") and values[q] <= 0.0:
                    raise loc.error(f"sigma must be positive, got {text!r}", line, name)
            else:
                values[q] = math.nan
        empty = [q for q in ("sigma_omega", "sigma_phi") if math.isnan(values[q])]
        angles = [q for q in ("omega", "phi") if not math.isnan(values[q])]
        if angles and "sigma_omega" not in seen:
            # Without sigmas the angles cannot be weighted; dropping them would be silent.
            raise loc.error(
                f"scan '{scan}' has a levelling angle but the file has no sigma columns; give "
                "sigma_omega_<unit> and sigma_phi_<unit> (e.g. sigma_omega_arcsec: a compensator "
                "is good to a few arc seconds), or leave the angle columns out",
                line,
                seen[angles[0]],
            )
        if len(empty) == 2:
            continue
        if empty:
            raise loc.error(
                f"scan '{scan}' has one levelling sigma but not the other (both or neither)",
                line,
                seen[empty[0]],
            )
        result[scan] = {
            "omega": 0.0 if math.isnan(values["omega"]) else values["omega"],
            "phi": 0.0 if math.isnan(values["phi"]) else values["phi"],
            "sigma_omega": values["sigma_omega"],
            "sigma_phi": values["sigma_phi"],
        }
    return result


def _format(value: float) -> str:
    # An empty cell reads back as NaN in optional columns, so NaN round-trips.
    return "" if math.isnan(value) else f"{value:.17g}"


def write_observations(path, table: ObservationTable, *, length_unit="m", angle_unit="deg") -> None:
    """Write ``table`` as a CSV that :func:`read_observations` reads back to the same numbers.

    Lengths go out in ``length_unit`` (m, mm), angles in ``angle_unit`` (rad, deg, gon, arcsec),
    with 17 significant digits; the table's architecture, when known, in a comment line before
    the header (the units are in the column names).
    """
    for unit, dim in ((length_unit, "length"), (angle_unit, "angle")):
        if unit not in UNITS or UNITS[unit][0] != dim:
            raise ValueError(
                f"{dim}_unit {unit!r} is not a {dim} unit; accepted: "
                + ", ".join(u for u, (d, _) in UNITS.items() if d == dim)
            )
    if table.kind not in ("target", "plane"):
        raise ValueError(f"table kind must be 'target' or 'plane', got {table.kind!r}")
    n = len(table.scans)
    obs = np.asarray(table.observations, dtype=np.float64).reshape(n, 3)
    lf, af = UNITS[length_unit][1], UNITS[angle_unit][1]
    units = {
        "range": (length_unit, lf),
        "hz": (angle_unit, af),
        "el": (angle_unit, af),
        "sigma_range": (length_unit, lf),
        "sigma_hz": (angle_unit, af),
        "sigma_el": (angle_unit, af),
        "incidence": (angle_unit, af),
    }

    header = ["scan", table.kind]
    numeric = [("range", obs[:, 0]), ("hz", obs[:, 1]), ("el", obs[:, 2])]
    if table.sigmas is not None:
        sig = np.asarray(table.sigmas, dtype=np.float64).reshape(n, 3)
        numeric += [("sigma_range", sig[:, 0]), ("sigma_hz", sig[:, 1]), ("sigma_el", sig[:, 2])]
    if table.incidence is not None:
        numeric.append(("incidence", np.asarray(table.incidence, dtype=np.float64).reshape(n)))
    header += [f"{q}_{units[q][0]}" for q, _ in numeric]
    if table.instruments is not None:
        header.append("instrument")
    if len(table.primitives) != n or (
        table.instruments is not None and len(table.instruments) != n
    ):
        raise ValueError("table columns have different lengths")

    with atomic_output(path) as tmp, open(tmp, "w", newline="", encoding="utf-8") as fh:
        if table.architecture is not None:
            fh.write(architecture_comment(table.kind, table.architecture) + "\n")
        writer = csv.writer(fh, delimiter=",", lineterminator="\n")
        writer.writerow(header)
        for i in range(n):
            row = [table.scans[i], table.primitives[i]]
            row += [_format(float(values[i]) / units[q][1]) for q, values in numeric]
            if table.instruments is not None:
                row.append(table.instruments[i])
            writer.writerow(row)


def write_scans(path, levelling: dict, *, angle_unit="arcsec") -> None:
    """Write the scans CSV (levelling observations) that :func:`read_scans` reads back.

    ``levelling`` maps scan -> {"omega", "phi", "sigma_omega", "sigma_phi"} in radians.
    """
    if angle_unit not in UNITS or UNITS[angle_unit][0] != "angle":
        raise ValueError(
            f"angle_unit {angle_unit!r} is not an angle unit; accepted: {_accepted('angle')}"
        )
    f = UNITS[angle_unit][1]
    with atomic_output(path) as tmp, open(tmp, "w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh, delimiter=",", lineterminator="\n")
        writer.writerow(["scan"] + [f"{q}_{angle_unit}" for q in _SCAN_NUMERIC])
        for scan, d in levelling.items():
            writer.writerow([scan] + [_format(float(d[q]) / f) for q in _SCAN_NUMERIC])


def table_from_network(net, architecture: str | None = None) -> ObservationTable:
    """The target observations of a :class:`~tlsjax.Network` as a table (sigmas as used, i.e.
    with the incidence scaling of the range already applied), recording ``architecture``."""
    inst = None
    if len(net.instruments) > 1:
        inst = tuple(net.instruments[net.instrument_of_scan[j]] for j in net.scan_index)
    return ObservationTable(
        kind="target",
        source=net.source,
        scans=tuple(net.scans[j] for j in net.scan_index),
        primitives=tuple(net.targets[t] for t in net.target_index),
        observations=np.asarray(net.observations),
        sigmas=np.asarray(net.sigmas),
        incidence=None,
        instruments=inst,
        rows=np.arange(2, len(net.scan_index) + 2),
        architecture=architecture,
    )


def levelling_of_network(net) -> dict:
    """Levelling observations of a network as the mapping :func:`make_network` takes."""
    return {
        s: {
            "omega": float(net.levelling[j, 0]),
            "phi": float(net.levelling[j, 1]),
            "sigma_omega": float(net.levelling_sigma[j, 0]),
            "sigma_phi": float(net.levelling_sigma[j, 1]),
        }
        for j, s in enumerate(net.scans)
        if net.is_levelled[j]
    }


def _check_path(value, name: str) -> None:
    if not isinstance(value, (str, os.PathLike)):
        raise TypeError(
            f"{name} must be a file path (str or os.PathLike), got {type(value).__name__}"
        )


def read_planes(path) -> ObservationTable:
    """Plane observations from a plane CSV (SPEC section 11) or from the ``.npz`` of
    ``tlsjax extract-planes`` (matched across scans; its kept points, sigmas from the defaults
    and the incidence angles of the extraction)."""
    _check_path(path, "planes")
    source = os.fspath(path)
    if os.path.isdir(source):
        raise ValueError(f"{source}: is a directory, not a plane file (.csv or .npz)")
    if source.lower().endswith(".npz"):
        from ._plane_files import load_planes

        planes = load_planes(source)
        if planes.planes is None:
            raise ValueError(
                f"{source}: the planes are not matched across scans (no scan poses at extraction); "
                "run tlsjax extract-planes with --poses"
            )
        return dataclasses.replace(planes.to_table(), source=source)
    table = read_observations(source)
    if table.kind != "plane":
        raise ValueError(
            f"{source}: this is a target observation file ('target' column), not a plane file"
        )
    return table


def read_network(
    observations_path=None,
    scans_path=None,
    *,
    planes=None,
    drop_single_targets: bool = False,
    **kwargs,
):
    """Read observation files (and the optional scans CSV) into a validated Network.

    ``observations_path``: a target or a plane observation CSV (told apart by its ``target`` or
    ``plane`` column), or a table already read (e.g. :func:`~tlsjax.read_target_list` of vendor
    target lists). ``planes``: a plane CSV or an extracted-planes ``.npz`` besides a target
    file (a combined network), or instead of it. Missing sigma cells take the group defaults of
    :func:`~tlsjax.make_network` (or the ``sigma_range``/``sigma_hz``/``sigma_el`` given here);
    errors name the file and line. The architecture a file records is checked against
    ``architecture`` (and used for the angle checks when that is None).
    """
    from .._adjustment._network import make_network

    for value, name in ((observations_path, "observations_path"), (scans_path, "scans_path")):
        if value is not None and not isinstance(value, ObservationTable):
            _check_path(value, name)
    if observations_path is None and planes is None:
        raise ValueError("give an observation file, a planes file, or both")
    table = observations_path
    if table is not None and not isinstance(table, ObservationTable):
        table = read_observations(observations_path)
    plane_table = read_planes(planes) if planes is not None else None
    if table is not None and table.kind == "plane":
        if plane_table is not None:
            raise ValueError(
                f"{table.source}: a plane file; a combined network takes one target file and one plane file"
            )
        table, plane_table = None, table
    kwargs["architecture"] = _agreed_architecture(kwargs.get("architecture"), table, plane_table)
    levelling = read_scans(scans_path) if scans_path is not None else None
    if table is None:
        return make_network(
            (),
            (),
            np.zeros((0, 3)),
            planes=plane_table,
            levelling=levelling,
            source=plane_table.source,
            **kwargs,
        )
    return make_network(
        table.scans,
        table.primitives,
        table.observations,
        sigmas=table.sigmas,
        incidence=None if table.incidence is None else np.nan_to_num(table.incidence, nan=0.0),
        instruments=table.instruments,
        levelling=levelling,
        drop_single_targets=drop_single_targets,
        source=table.source,
        rows=table.rows,
        planes=plane_table,
        **kwargs,
    )


def _agreed_architecture(architecture, *tables):
    """``architecture``, or the one the tables record; a table recorded for another
    architecture is refused (its elevations and directions would be misread)."""
    for t in tables:
        rec = getattr(t, "architecture", None) if t is not None else None
        if rec is None:
            continue
        if architecture is None:
            architecture = rec
        elif rec != architecture:
            raise ValueError(
                f"{t.source}: the observations are recorded for a {rec} scanner, but the "
                f"architecture given is {architecture}; give --architecture {rec} (or "
                f"architecture='{rec}'), or convert the file again"
            )
    return architecture
