"""The grammar of tlsjax's CSV files (SPEC section 11), shared by every reader of them: unit
suffixes of numeric columns (``range_m``, ``hz_deg``, ``sigma_hz_arcsec``), rows with their
line numbers, numbers checked one by one, and errors that name the file, the line and the
column."""

from __future__ import annotations

import csv
import math
import os

from .._units import UNITS

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


def accepted_units(dimension: str | None = None) -> str:
    return ", ".join("_" + u for u, (d, _) in UNITS.items() if dimension in (None, d))


def split_unit(header: str) -> tuple[str, str, float]:
    """Split ``header`` into (quantity, unit, factor); raise ValueError without location."""
    # Longest known quantity first, so that "sigma_range_mm" is not read as "sigma" + "range_mm".
    for q in sorted(QUANTITIES, key=len, reverse=True):
        if header == q:
            dim = QUANTITIES[q]
            raise ValueError(f"missing unit suffix; accepted for {dim}s: {accepted_units(dim)}")
        if header.startswith(q + "_"):
            unit, dim = header[len(q) + 1 :], QUANTITIES[q]
            if unit not in UNITS:
                raise ValueError(
                    f"unknown unit suffix '_{unit}'; accepted for {dim}s: {accepted_units(dim)}"
                )
            if UNITS[unit][0] != dim:
                raise ValueError(
                    f"'{q}' is a{'n' if dim == 'angle' else ''} {dim} but '_{unit}' is a unit of "
                    f"{UNITS[unit][0]}; accepted for {dim}s: {accepted_units(dim)}"
                )
            return q, unit, UNITS[unit][1]
    # Not a tlsjax quantity: still usable for any "<name>_<unit>" header.
    name, sep, unit = header.rpartition("_")
    if not sep or not name:
        raise ValueError(f"missing unit suffix; accepted: {accepted_units()}")
    if unit not in UNITS:
        raise ValueError(f"unknown unit suffix '_{unit}'; accepted: {accepted_units()}")
    return name, unit, UNITS[unit][1]


def parse_unit_column(header: str) -> tuple[str, str, float]:
    """``"hz_deg"`` -> ``("hz", "deg", pi/180)``: quantity, unit and the factor to SI units.

    Raises ValueError for a missing or unknown suffix, or a unit of the wrong dimension
    (``range_deg``).
    """
    try:
        return split_unit(header.strip())
    except ValueError as err:
        raise ValueError(f"column {header}: {err}") from None


class Located:
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
#: ``# tlsjax target observations: architecture=panoramic`` there
#: (:func:`tlsjax._io._tables.recorded_architecture`).
COMMENT = "#"


def read_rows(path, loc: Located):
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


def parse_header(names, header_line, loc, text_cols, numeric_cols):
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
                q, _, factor = split_unit(key)
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


def number(text, line, column, loc, required):
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


def row_cells(data, columns, loc):
    """Yield (line, {quantity: stripped text}) for each data row, checking the field count."""
    for line, fields in data:
        if len(fields) != len(columns):
            raise loc.error(f"expected {len(columns)} fields, found {len(fields)}", line)
        yield line, {q: (f.strip(), name, factor) for (name, q, factor), f in zip(columns, fields)}
