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
from ._csv import (
    COMMENT,
    Located,
    accepted_units,
    number,
    open_text,
    parse_header,
    read_rows,
    row_cells,
)
from ._outputs import atomic_output

_OBS_NUMERIC = ("range", "hz", "el", "sigma_range", "sigma_hz", "sigma_el", "incidence")
_OBS_TEXT = ("scan", "target", "plane", "instrument")
_SCAN_NUMERIC = ("omega", "phi", "sigma_omega", "sigma_phi", "kappa", "sigma_kappa")
_SCAN_TEXT = ("scan",)
_TWO_PI = 2.0 * math.pi


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


def _observation_kind(seen, header_line, loc, data) -> str:
    """ "target" or "plane" from the header; every required column present, data rows too."""
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
    return kind


_SIGMAS = ("sigma_range", "sigma_hz", "sigma_el")


def _observation_row(cells, line, loc, kind):
    """One row's names checked, observations (3,), sigmas (3,; NaN where empty or absent) and
    incidence (NaN where absent), in SI units."""
    for q in ("scan", kind) + (("instrument",) if "instrument" in cells else ()):
        text, name, _ = cells[q]
        if not text:
            raise loc.error(f"empty {q} name", line, name)
    obs = np.empty(3)
    for j, q in enumerate(("range", "hz", "el")):
        text, name, factor = cells[q]
        obs[j] = number(text, line, name, loc, required=True) * factor
    if obs[0] <= 0.0:
        raise loc.error(
            f"range must be positive, got {cells['range'][0]!r}", line, cells["range"][1]
        )
    _check_directions(obs, cells, line, loc)
    sig = np.full(3, np.nan)
    for j, q in enumerate(_SIGMAS):
        if q in cells:
            text, name, factor = cells[q]
            sig[j] = number(text, line, name, loc, required=False) * factor
            if sig[j] <= 0.0:
                raise loc.error(f"sigma must be positive, got {text!r}", line, name)
    inc = np.nan
    if "incidence" in cells:
        text, name, factor = cells["incidence"]
        inc = number(text, line, name, loc, required=False) * factor
    return obs, sig, inc


def read_observations(path) -> ObservationTable:
    """Read a target or plane observation CSV (SPEC section 11) into SI units.

    The kind comes from the presence of a ``target`` or a ``plane`` column; hz is wrapped into
    [0, 2pi), el is left as given (panoramic elevations reach past pi/2). The architecture
    recorded in a comment line before the header (files tlsjax writes) is in
    ``table.architecture``.
    """
    _check_path(path, "path")
    source = os.fspath(path)
    loc = Located(source)
    architecture = recorded_architecture(source)
    header_line, names, data = read_rows(path, loc)
    columns, seen = parse_header(names, header_line, loc, _OBS_TEXT, _OBS_NUMERIC)
    kind = _observation_kind(seen, header_line, loc, data)
    scans, prims, instruments, lines = [], [], [], []
    obs = np.empty((len(data), 3))
    sig = np.full((len(data), 3), np.nan)
    inc = np.full(len(data), np.nan)
    first_line: dict[tuple[str, str], int] = {}
    for i, (line, cells) in enumerate(row_cells(data, columns, loc)):
        obs[i], sig[i], inc[i] = _observation_row(cells, line, loc, kind)
        scan, prim = cells["scan"][0], cells[kind][0]
        # Planes carry many points per (scan, plane); a target is observed once per scan.
        if kind == "target":
            if (scan, prim) in first_line:
                raise loc.error(
                    f"duplicate observation of target '{prim}' in scan '{scan}' "
                    f"(lines {first_line[scan, prim]} and {line})",
                    line,
                    cells["target"][1],
                )
            first_line[scan, prim] = line
        scans.append(scan)
        prims.append(prim)
        if "instrument" in cells:
            instruments.append(cells["instrument"][0])
        lines.append(line)
    if kind == "plane":
        _refuse_repeated_points(scans, prims, obs, lines, loc)
    hz = np.mod(obs[:, 1], _TWO_PI)
    # np.mod returns 2pi itself for tiny negative inputs; the contract is the half-open interval.
    obs[:, 1] = np.where(hz >= _TWO_PI, 0.0, hz)
    return ObservationTable(
        kind=kind,
        source=source,
        scans=tuple(scans),
        primitives=tuple(prims),
        observations=obs,
        sigmas=sig if any(q in seen for q in _SIGMAS) else None,
        incidence=inc if "incidence" in seen else None,
        instruments=tuple(instruments) if "instrument" in seen else None,
        rows=np.asarray(lines, dtype=np.int64),
        architecture=architecture,
    )


def _refuse_repeated_points(scans, planes, obs, lines, loc) -> None:
    """A plane has many points per scan, but one row repeated would count one observation
    twice (and thinning would hide it): the first repeated (scan, plane, range, hz, el) row is
    refused with both lines. Sorted, not hashed row by row: files hold millions of points."""
    if len(scans) < 2:
        return
    codes = [np.unique(np.asarray(a), return_inverse=True)[1] for a in (scans, planes)]
    keys = np.column_stack([*codes, obs])
    order = np.lexsort(keys.T[::-1])
    same = np.all(keys[order[1:]] == keys[order[:-1]], axis=1)
    if same.any():
        k = int(np.argmax(same))
        a, b = sorted((int(order[k]), int(order[k + 1])))
        raise loc.error(
            f"duplicate point of plane '{planes[b]}' in scan '{scans[b]}' (lines {lines[a]} and "
            f"{lines[b]}: the same observation twice)",
            lines[b],
            None,
        )


def read_scans(path) -> dict[str, dict[str, float]]:
    """Read the optional scans CSV: the observed orientation angles of the scans (Chow et al.
    2013, eq. 7; the ``orientation`` mapping of :func:`~tlsjax.make_network`), in radians.

    Columns ``scan`` and any of ``omega_<u>``, ``phi_<u>`` (default 0), ``sigma_omega_<u>``,
    ``sigma_phi_<u>`` (the tilt readings of a compensator or tilt sensor: levelled scans, and
    tilted ones with a tilt sensor) and ``kappa_<u>``, ``sigma_kappa_<u>`` (a known heading).
    A scan has tilt readings when both its tilt sigma cells are filled, a heading when its
    kappa and sigma_kappa cells are; scans with neither are left out of the result. Angles in a
    file without their sigma columns are refused (they could not be weighted, and dropping them
    would go unnoticed).
    """
    return _read_scans(path)[0]


def _read_scans(path) -> tuple[dict[str, dict[str, float]], dict[str, int]]:
    """:func:`read_scans` and the file line (1-based) of each scan's row."""
    _check_path(path, "path")
    source = os.fspath(path)
    loc = Located(source)
    header_line, names, data = read_rows(path, loc)
    columns, seen = parse_header(names, header_line, loc, _SCAN_TEXT, _SCAN_NUMERIC)
    if "scan" not in seen:
        raise loc.error("missing required column", header_line, "scan")
    # A lone sigma column could only describe half a levelling observation.
    for a, b in (
        ("sigma_omega", "sigma_phi"),
        ("sigma_phi", "sigma_omega"),
        ("kappa", "sigma_kappa"),
        ("sigma_kappa", "kappa"),
    ):
        if a in seen and b not in seen:
            raise loc.error(
                f"column '{b}_<unit>' is required with '{seen[a]}'", header_line, seen[a]
            )

    result: dict[str, dict[str, float]] = {}
    first_line: dict[str, int] = {}
    for line, cells in row_cells(data, columns, loc):
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
                values[q] = number(text, line, name, loc, required=False) * factor
                if q.startswith("sigma") and values[q] <= 0.0:
                    raise loc.error(f"sigma must be positive, got {text!r}", line, name)
            else:
                values[q] = math.nan
        out = _scan_angles(scan, values, seen, line, loc)
        if out:
            result[scan] = out
    return result, first_line


def _scan_angles(scan, values, seen, line, loc) -> dict[str, float]:
    """One scans-CSV row's observed angles [rad]: tilt readings when both tilt sigmas are
    given (omega and phi default to 0, a levelled scan), a heading when kappa and its sigma
    are; {} when neither."""
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
    if len(empty) == 1:
        raise loc.error(
            f"scan '{scan}' has one levelling sigma but not the other (both or neither)",
            line,
            seen[empty[0]],
        )
    out = {}
    if not empty:
        out = {
            "omega": 0.0 if math.isnan(values["omega"]) else values["omega"],
            "phi": 0.0 if math.isnan(values["phi"]) else values["phi"],
            "sigma_omega": values["sigma_omega"],
            "sigma_phi": values["sigma_phi"],
        }
    heading = [q for q in ("kappa", "sigma_kappa") if not math.isnan(values[q])]
    if len(heading) == 1:
        other = "sigma_kappa" if heading[0] == "kappa" else "kappa"
        raise loc.error(
            f"scan '{scan}' has {heading[0]} but no {other} (both or neither)",
            line,
            seen[other],
        )
    if heading:
        out.update(kappa=values["kappa"], sigma_kappa=values["sigma_kappa"])
    return out


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
    """Write the scans CSV (orientation observations) that :func:`read_scans` reads back.

    ``levelling`` maps scan -> any of {"omega", "phi", "sigma_omega", "sigma_phi", "kappa",
    "sigma_kappa"} in radians (a missing angle is an empty cell); the kappa columns are written
    when some scan has a heading.
    """
    if angle_unit not in UNITS or UNITS[angle_unit][0] != "angle":
        raise ValueError(
            f"angle_unit {angle_unit!r} is not an angle unit; accepted: {accepted_units('angle')}"
        )
    f = UNITS[angle_unit][1]
    with atomic_output(path) as tmp, open(tmp, "w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh, delimiter=",", lineterminator="\n")
        cols = [
            q for q in _SCAN_NUMERIC if "kappa" not in q or any(q in d for d in levelling.values())
        ]
        writer.writerow(["scan"] + [f"{q}_{angle_unit}" for q in cols])
        for scan, d in levelling.items():
            writer.writerow([scan] + [_format(float(d.get(q, math.nan)) / f) for q in cols])


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
    """Orientation observations of a network (tilt readings and observed kappa) as the
    ``orientation`` mapping :func:`make_network` takes (and :func:`write_scans` writes)."""
    out = {}
    for j, s in enumerate(net.scans):
        d = {}
        if net.is_levelled[j]:
            d.update(
                omega=float(net.levelling[j, 0]),
                phi=float(net.levelling[j, 1]),
                sigma_omega=float(net.levelling_sigma[j, 0]),
                sigma_phi=float(net.levelling_sigma[j, 1]),
            )
        if np.isfinite(net.heading_sigmas[j]):
            d.update(kappa=float(net.heading_values[j]), sigma_kappa=float(net.heading_sigmas[j]))
        if d:
            out[s] = d
    return out


def write_network(
    path, network, *, scans_path=None, architecture=None, length_unit="m", angle_unit="deg"
) -> None:
    """Write the target observations of ``network`` as the CSV ``tlsjax calibrate`` reads
    (:func:`write_observations`; sigmas as used, ``architecture`` recorded in the file), and
    with ``scans_path`` its tilt readings and headings as the scans CSV (:func:`write_scans`):
    what ``tlsjax simulate`` writes of a simulated network."""
    table = table_from_network(network, architecture)
    write_observations(path, table, length_unit=length_unit, angle_unit=angle_unit)
    if scans_path is not None:
        write_scans(scans_path, levelling_of_network(network))


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
        from ._plane_files import read_extracted_planes

        planes = read_extracted_planes(source)
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
    file (a combined network), or instead of it, or a plane table already read (e.g. thinned by
    :func:`~tlsjax.thin_planes`). Missing sigma cells take the group defaults of
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
    plane_table = planes
    if planes is not None and not isinstance(planes, ObservationTable):
        plane_table = read_planes(planes)
    if table is not None and table.kind == "plane":
        if plane_table is not None:
            raise ValueError(
                f"{table.source}: a plane file; a combined network takes one target file and one plane file"
            )
        table, plane_table = None, table
    kwargs["architecture"] = _agreed_architecture(kwargs.get("architecture"), table, plane_table)
    # The scans CSV holds the observed orientation angles of eq. (7): tilt readings of levelled
    # and tilted scans, headings.
    orientation, scan_lines = None, {}
    if scans_path is not None:
        orientation, scan_lines = _read_scans(scans_path)
    if table is None:
        net = make_network(
            (),
            (),
            np.zeros((0, 3)),
            planes=plane_table,
            orientation=orientation,
            source=plane_table.source,
            **kwargs,
        )
    else:
        net = make_network(
            table.scans,
            table.primitives,
            table.observations,
            sigmas=table.sigmas,
            incidence=None if table.incidence is None else np.nan_to_num(table.incidence, nan=0.0),
            instruments=table.instruments,
            orientation=orientation,
            drop_single_targets=drop_single_targets,
            source=table.source,
            rows=table.rows,
            planes=plane_table,
            **kwargs,
        )
    if scans_path is None:
        return net
    # The line of each scan's row in the scans CSV, for the per-observation tables.
    lines = np.array([scan_lines.get(s, 0) for s in net.scans], dtype=np.int64)
    return dataclasses.replace(net, scans_source=os.fspath(scans_path), scan_lines=lines)


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
