"""Results as the adjustment programs geodesists file them (JAG3D's per-point and
per-observation tables): the adjusted targets and planes with sigmas and confidence-ellipsoid
axes, one row per scalar observation with its residual, normalised residual, redundancy number,
minimal detectable bias, external reliability and test decision, and one row per observation
group with its variance factor and redundancy. In the result JSON (SI units) and as CSV tables
(``tlsjax calibrate --tables DIR``; mm and arc seconds, the unit in every header).

Rows are numbered twice: ``row``, the 1-based position among the observations of the file
(network order), and ``line``, the 1-based line of the input file that holds the observation
(header and comment lines counted, as an editor shows it; empty where the rows came from
arrays). The statistics are those of :func:`tlsjax.self_calibrate` when it ran (its
sigmas, critical value and removals), else of the plain adjustment with its a priori sigmas:

- normalised residual (Baarda's w): ``w_i = v_i / (sigma_i sqrt(r_i))`` (Baarda 1968);
- minimal detectable bias: ``MDB_i = delta0 sigma_i / sqrt(r_i)``;
- external reliability: Baarda's factor ``delta0 sqrt((1 - r_i) / r_i)`` (the largest effect
  of an undetected MDB-sized error on any function of the unknowns, in its sigmas), and, after
  testing, the largest effect on one AP (in that AP's sigmas) with the AP's name;
- decision: ``accepted``, ``rejected`` (|w| above the critical value but kept),
  ``removed (...)`` (by screening or data snooping, with the step), or ``not controlled``
  (redundancy number zero: no error of any size would be detected).
"""

from __future__ import annotations

import math
import os

import numpy as np

from .._adjustment._quality import (
    MIN_TESTABLE_REDUNDANCY,
    external_reliability_factor,
    minimal_detectable_bias,
    w_tests,
)
from .._stats import (
    DELTA0,
    ELLIPSOID_95,
    confidence_scale,
    group_variance_test,
    normal_critical_value,
)
from .._units import ARCSEC, DISPLAY_UNITS

GROUPS = ("range", "hz", "el")
#: Display unit and factor from SI of each group in the CSV tables.
DISPLAY = {"range": ("mm", 1e3), "hz": ("arcsec", 1 / ARCSEC), "el": ("arcsec", 1 / ARCSEC)}
#: Significance level of the w-test of a plain adjustment (no testing ran): Baarda's 0.001.
PLAIN_ALPHA = 0.001

OBSERVATION_COLUMNS = (
    "row",
    "line",
    "scan",
    "primitive",
    "group",
    "observed",
    "residual",
    "sigma",
    "redundancy",
    "w",
    "critical_value",
    "mdb",
    "external",
    "external_ap_sigmas",
    "external_ap",
    "decision",
)


def _finite(x):
    x = float(x)
    return x if math.isfinite(x) else None


def _removal_reasons(tested) -> dict:
    """(row, group) -> "removed (reason, step k)" for the removals of a tested calibration."""
    out = {}
    for o in getattr(tested, "outliers", ()) if tested is not None else ():
        out[(int(o.row), o.group)] = f"removed ({o.reason}, step {o.step})"
    return out


def _decisions(w, used, red, crit, removed_text) -> np.ndarray:
    """The test decision of each scalar observation (n, 3) as text."""
    dec = np.full(w.shape, "accepted", dtype=object)
    dec[np.abs(np.nan_to_num(w)) > crit] = "rejected"
    dec[used & (red <= MIN_TESTABLE_REDUNDANCY)] = "not controlled"
    dec[~used] = "removed"
    for (i, g), text in removed_text.items():
        if i < dec.shape[0] and g in GROUPS:
            dec[i, GROUPS.index(g)] = text
    return dec


def _target_columns(res, tested) -> dict:
    """Per-(n, 3) arrays of the target observations, before flattening."""
    net = res.network
    n = net.observations.shape[0]
    tests = {}
    if tested is not None:
        used, sig = np.asarray(tested.mask, bool), np.asarray(tested.sigmas)
        crit = float(tested.critical_value)
        delta0 = _delta0(tested)
        ext_ap_sig = np.where(used, tested.external, np.nan)
        ext_ap = np.asarray(tested.external_ap, dtype=object)
        tests = {"w": tested.w, "mdb": tested.mdb}  # read from the result, not recomputed
    else:
        used = np.ones((n, 3), bool) if res.used is None else np.asarray(res.used, bool)
        sig, crit, delta0 = np.asarray(net.sigmas), normal_critical_value(PLAIN_ALPHA), DELTA0
        ext_ap_sig, ext_ap = np.full((n, 3), np.nan), np.full((n, 3), "", dtype=object)
    return _columns(
        res.residuals,
        res.redundancy,
        sig,
        used,
        crit,
        delta0,
        extra={"external_ap_sigmas": ext_ap_sig, "external_ap": ext_ap},
        removed=_removal_reasons(tested),
        observed=net.observations,
        **tests,
    )


def _delta0(tested) -> float:
    return float(tested.options.tests.delta0)


def _columns(v, r, sig, used, crit, delta0, *, extra, removed, observed, w=None, mdb=None) -> dict:
    """The columns of the tables; ``w`` and ``mdb``: those of a tested calibration (else the
    w-tests and MDBs of the a priori sigmas, :mod:`tlsjax._adjustment._quality`)."""
    v, r, sig = (np.asarray(a, dtype=np.float64) for a in (v, r, sig))
    if w is None:
        w = np.where(used, w_tests(v, sig, r), np.nan)
    if mdb is None:
        mdb = np.where(used, minimal_detectable_bias(sig, r, delta0), np.nan)
    ext = np.where(used, external_reliability_factor(r, delta0), np.nan)
    return {
        "observed": np.asarray(observed, dtype=np.float64),
        "residual": v,
        "sigma": sig,
        "redundancy": np.where(used, r, 0.0),
        "w": w,
        "critical_value": np.full(v.shape, crit),
        "mdb": mdb,
        "external": ext,
        **extra,
        "decision": _decisions(w, used, r, crit, removed),
    }


def _plane_columns(res) -> dict:
    net = res.network
    m = net.plane_observations.shape[0]
    used = np.asarray(res.plane_used, bool)
    removed = {(int(i), GROUPS[g]): "removed (plane screening)" for i, g in zip(*np.nonzero(~used))}
    return _columns(
        res.plane_residuals,
        res.plane_redundancy,
        net.plane_sigmas,
        used,
        normal_critical_value(PLAIN_ALPHA),
        DELTA0,
        extra={
            "external_ap_sigmas": np.full((m, 3), np.nan),
            "external_ap": np.full((m, 3), "", dtype=object),
        },
        removed=removed,
        observed=net.plane_observations,
    )


def _kind_arrays(res, tested, kind):
    """(columns (n, 3) each, lines or None, scan names, primitive names) of the target
    observations or plane points of ``res``; None when it has none."""
    net = res.network
    if net is None:
        return None
    if kind == "target":
        if not net.has_targets or res.residuals is None:
            return None
        n = net.observations.shape[0]
        return (
            _target_columns(res, tested),
            _lines(net.lines, n),
            [net.scans[j] for j in net.scan_index],
            [net.targets[t] for t in net.target_index],
        )
    if not net.has_planes or res.plane_residuals is None:
        return None
    m = net.plane_observations.shape[0]
    return (
        _plane_columns(res),
        _lines(net.plane_lines, m) if _is_csv(net.plane_source or net.source) else None,
        [net.scans[j] for j in net.plane_scan_index],
        [net.planes[k] for k in net.plane_index],
    )


#: The groups of the weighted constraints' rows (``CalibrationResult.weighted_constraints``
#: kinds): tilt readings, observed kappa, AP priors.
PSEUDO_GROUPS = {"omega": "levelling", "phi": "levelling", "kappa": "heading", "ap": "ap prior"}


def _pseudo_arrays(res, tested):
    """(columns (p, 1) each, lines or None, scan names, names) of the weighted constraints
    with observed values (tilt readings, headings, AP priors; SPEC section 6), through the same
    :func:`_columns` as the target observations; None when there are none. ``primitive`` is
    the angle (omega, phi, kappa) or the AP, ``scan`` the scan (empty for an AP prior), ``line``
    that of the scan's row in the scans CSV. Each kind takes its variance group's VCE factor
    (:func:`tlsjax.self_calibrate`: levelling, heading, AP priors)."""
    cons = res.weighted_constraints()
    if not cons:
        return None
    net = res.network
    vc = {v.group: v for v in tested.variance_components} if tested is not None else {}

    def factor(kind):
        # Tilt readings and headings: the network's a priori sigma times their group's VCE
        # sigma factor. AP priors: the result's sigma is already the one the adjustment used
        # (the prior weights of the problem, VCE factor included).
        v = vc.get({"omega": "levelling", "phi": "levelling", "kappa": "heading"}.get(kind, ""))
        return v.sigma_factor if v is not None and np.isfinite(v.sigma_factor) else 1.0

    col = lambda key: np.array([[c[key]] for c in cons], dtype=np.float64)
    sig = col("sigma") * np.array([[factor(c["kind"])] for c in cons])
    crit, delta0 = (
        (float(tested.critical_value), _delta0(tested))
        if tested is not None
        else (normal_critical_value(PLAIN_ALPHA), DELTA0)
    )
    p = len(cons)
    cols = _columns(
        col("residual"),
        col("redundancy"),
        sig,
        np.ones((p, 1), bool),
        crit,
        delta0,
        extra={
            "external_ap_sigmas": np.full((p, 1), np.nan),
            "external_ap": np.full((p, 1), "", dtype=object),
        },
        removed={},
        observed=col("observed"),
    )
    scans = [c["name"] if c["kind"] != "ap" else "" for c in cons]
    line_of = {} if net.scan_lines is None else dict(zip(net.scans, net.scan_lines.tolist()))
    # 0: the scan has no row in the scans CSV (an orientation given in memory).
    lines = [line_of.get(c["name"]) or None if c["kind"] != "ap" else None for c in cons]
    names = [c["kind"] if c["kind"] != "ap" else c["name"] for c in cons]
    groups = [PSEUDO_GROUPS[c["kind"]] for c in cons]
    return cols, lines, scans, names, groups


def pseudo_records(res, tested=None) -> list[dict]:
    """One dict per weighted constraint with observed values (keys
    :data:`OBSERVATION_COLUMNS`, SI units: rad, or the AP's unit), in the order of
    ``res.weighted_constraints()``; ``row`` is null (the rows are not the observation
    file's)."""
    got = _pseudo_arrays(res, tested)
    if got is None:
        return []
    cols, lines, scans, names, groups = got
    out = []
    for i in range(len(scans)):
        rec = {
            "row": None,
            "line": lines[i],
            "scan": scans[i],
            "primitive": names[i],
            "group": groups[i],
        }
        for k in OBSERVATION_COLUMNS[5:]:
            x = cols[k][i, 0]
            rec[k] = x if isinstance(x, str) else _finite(x)
        out.append(rec)
    return out


def _is_csv(source) -> bool:
    # Plane points from an .npz of extract-planes or from memory have no file lines.
    return str(source).lower().endswith((".csv", ".txt"))


def _lines(lines, n):
    if lines is None or len(lines) != n:
        return None  # rows from arrays, or a network rebuilt without its lines
    return np.asarray(lines)


def observation_records(res, tested=None, *, kind: str = "target") -> list[dict]:
    """One dict per scalar observation (keys :data:`OBSERVATION_COLUMNS`, SI units: m and rad;
    ``external`` and ``external_ap_sigmas`` dimensionless) of the target observations
    (``kind="target"``) or the plane points (``kind="plane"``), rows in file order and
    range, hz, el within a row; [] when there are none."""
    got = _kind_arrays(res, tested, kind)
    if got is None:
        return []
    cols, lines, scans, prims = got
    per = {k: cols[k].reshape(-1).tolist() for k in OBSERVATION_COLUMNS[5:]}
    out = []
    for j in range(cols["residual"].size):
        i, g = divmod(j, 3)
        rec = {
            "row": i + 1,
            "line": None if lines is None else int(lines[i]),
            "scan": scans[i],
            "primitive": prims[i],
            "group": GROUPS[g],
        }
        for k, values in per.items():
            x = values[j]
            rec[k] = x if isinstance(x, str) else _finite(x)
        out.append(rec)
    return out


def group_records(res, tested=None) -> list[dict]:
    """One dict per observation group (target range/hz/el, plane range/hz/el, levelling when
    VCE estimated it): ``n`` used observations, ``redundancy`` r_g (the sum of their redundancy
    numbers), the variance factor of the final adjustment ``Omega_g / r_g`` with the sigmas it
    used and its test (``accepted``: two-sided at 5 %, as JAG3D's group test), the factor VCE
    estimated (``vce_factor``, null without VCE or where the group was held), and the factor of
    the first adjustment with the a priori sigmas with its test (``a_priori_*``, after testing)."""
    a_priori = tested.a_priori_tests[0]["groups"] if tested and tested.a_priori_tests else {}
    vce = {vc.group: vc for vc in tested.variance_components} if tested is not None else {}
    out = []
    for kind in ("target", "plane"):
        got = _kind_arrays(res, tested, kind)
        if got is None:
            continue
        cols = got[0]
        for g, name in enumerate(GROUPS):
            used = ~np.char.startswith(cols["decision"][:, g].astype(str), "removed")
            r = cols["redundancy"][used, g]
            e2 = (cols["residual"][used, g] / cols["sigma"][used, g]) ** 2
            test = group_variance_test(float(e2.sum()), float(r.sum()))
            target = kind == "target"
            out.append(
                _group_row(
                    name if target else f"plane {name}",
                    int(used.sum()),
                    float(r.sum()),
                    test,
                    vce.get(name) if target else None,
                    a_priori.get(name, {}) if target else {},
                )
            )
    for name, vc in vce.items():  # VCE groups without per-observation rows (levelling)
        if name not in GROUPS:
            out.append(_group_row(name, vc.n, vc.redundancy, {}, vc, a_priori.get(name, {})))
    return out


def _group_row(name, n, r_g, test, vc, a_priori) -> dict:
    return {
        "group": name,
        "n": int(n),
        "redundancy": _finite(r_g),
        "variance_factor": test.get("factor"),
        "accepted": test.get("accepted"),
        "vce_factor": _finite(vc.factor) if vc is not None and vc.estimated else None,
        "a_priori_factor": a_priori.get("factor"),
        "a_priori_accepted": a_priori.get("accepted"),
    }


def table_json(res, tested=None) -> dict:
    """The JSON fields of the tables (SI units): ``observation_table`` (the target
    observations, column-wise: ``columns`` and one list per row), ``group_table``, and a note
    where the plane points are (their table can hold millions of rows: CSV only)."""
    recs = observation_records(res, tested, kind="target") + pseudo_records(res, tested)
    net = res.network
    out = {
        "group_table": group_records(res, tested),
        "observation_table": {
            "source": None if net is None else net.source,
            "units": "observed, residual, sigma, mdb: m (range) or rad (hz, el); w, redundancy, "
            "external (Baarda's factor delta0 sqrt((1 - r) / r)), external_ap_sigmas: "
            "dimensionless",
            "rows_are": "row: 1-based position among the observations of the file; line: the "
            "file's line (1-based, header and comment lines counted; null for arrays); then one "
            "row per weighted constraint with an observed value (group levelling: the tilt "
            "readings omega, phi; heading: kappa; ap prior; row null, line that of the scan's "
            "row in scans_source, residual = adjusted orientation minus reading)",
            "scans_source": None if net is None or not net.scans_source else net.scans_source,
            "columns": list(OBSERVATION_COLUMNS),
            "rows": [[r[k] for k in OBSERVATION_COLUMNS] for r in recs],
        },
    }
    if net is not None and net.has_planes:
        out["plane_point_table"] = (
            "per plane point in plane_points.csv of `tlsjax calibrate --tables DIR` (not in the "
            "JSON: one row per point)"
        )
    return out


def _cell(x, scale=1.0) -> str:
    if x is None:
        return ""
    if isinstance(x, str):
        return '"' + x.replace('"', '""') + '"' if any(c in x for c in ',"\n') else x
    if isinstance(x, bool):
        return str(x).lower()
    if isinstance(x, int):
        return str(x)
    x = float(x) * scale
    return f"{x:.12g}" if math.isfinite(x) else ""


def observation_csv(res, tested=None, *, kind: str = "target") -> str:
    """The per-observation table as CSV text: residual, sigma and MDB in mm (range) or arc
    seconds (hz, el), the observation in m or degrees; for ``kind="target"`` followed by the
    rows of the weighted constraints (:func:`pseudo_records`: levelling and heading in arc
    seconds, AP priors in the AP's report unit)."""
    net = res.network
    source = net.source if kind == "target" else (net.plane_source or net.source)
    head = (
        "row,line,scan,"
        + ("target" if kind == "target" else "plane")
        + ",group,observed,observed_unit,residual,sigma,mdb,unit,redundancy,w,critical_value,"
        "external,external_ap_sigmas,external_ap,decision"
    )
    lines = [
        f"# tlsjax {kind} observations of {source}: line = that file's line (1-based, header "
        "and comment lines counted); row = 1-based position among its observations",
        "# w = v / (sigma sqrt(r)); mdb = delta0 sigma / sqrt(r); external = delta0 "
        "sqrt((1 - r) / r); external_ap_sigmas: largest effect on one AP (external_ap)",
        head,
    ]
    recs = observation_records(res, tested, kind=kind)
    if kind == "target":
        recs += pseudo_records(res, tested)
        if net.scans_source:
            lines.insert(2, f"# levelling and heading rows: line = that of {net.scans_source}")
    ap_unit = dict(zip(res.ap_names, res.ap_units))
    for r in recs:
        unit, f, obs_unit, fo = _display(r, ap_unit)
        cells = [
            _cell(r["row"]),
            _cell(r["line"]),
            _cell(r["scan"]),
            _cell(r["primitive"]),
            r["group"],
            _cell(r["observed"], fo),
            obs_unit,
            _cell(r["residual"], f),
            _cell(r["sigma"], f),
            _cell(r["mdb"], f),
            unit,
            _cell(r["redundancy"]),
            _cell(r["w"]),
            _cell(r["critical_value"]),
            _cell(r["external"]),
            _cell(r["external_ap_sigmas"]),
            _cell(r["external_ap"]),
            _cell(r["decision"]),
        ]
        lines.append(",".join(cells))
    return "\n".join(lines) + "\n"


def _display(rec, ap_unit) -> tuple:
    """(unit, factor from SI) of a row's residual, sigma and MDB, and of its observed value."""
    g = rec["group"]
    if g in DISPLAY:
        unit, f = DISPLAY[g]
        return (unit, f, "m", 1.0) if g == "range" else (unit, f, "deg", 180 / math.pi)
    if g == "ap prior":
        label, f = DISPLAY_UNITS[ap_unit[rec["primitive"]]]
        label = "arcsec" if label == '"' else label
        return label, f, label, f
    return "arcsec", 1 / ARCSEC, "arcsec", 1 / ARCSEC  # tilt readings and headings


def group_csv(res, tested=None) -> str:
    keys = (
        "group",
        "n",
        "redundancy",
        "variance_factor",
        "accepted",
        "vce_factor",
        "a_priori_factor",
        "a_priori_accepted",
    )
    lines = [
        "# tlsjax observation groups: redundancy = sum of the redundancy numbers; "
        "variance_factor = Omega_g / r_g of the final adjustment (accepted: two-sided 5 % "
        "test); vce_factor as estimated; a_priori_*: first adjustment, a priori sigmas",
        ",".join(keys),
    ]
    for g in group_records(res, tested):
        lines.append(",".join(_cell(g[k]) for k in keys))
    return "\n".join(lines) + "\n"


def planes_csv(res) -> str:
    """Adjusted planes: normal, d [m] and their sigmas [mm for d, 1 for the normal], the tilt
    sigmas of the normal ["] and the foot point ``d n`` [m] with its 1-sigma ellipsoid
    semi-axes [mm] (:func:`tlsjax._adjustment._json.plane_ellipsoids`)."""
    from .._adjustment._json import plane_ellipsoids

    lines = [
        "# tlsjax adjusted planes (n . X = d in the datum of the adjustment); sigmas a "
        "posteriori: of the normal's components (dimensionless) and of d [mm]; tilt_sigma_1..2: "
        "principal 1-sigma tilts of the normal [arcsec] (x "
        f"{round(confidence_scale(2), 4)} for the 95 % ellipse); foot = d n [m], "
        f"foot_axis_1..3: its 1-sigma ellipsoid semi-axes [mm] (x {ELLIPSOID_95} for 95 %)",
        "plane,nx,ny,nz,d_m,sigma_nx,sigma_ny,sigma_nz,sigma_d_mm,tilt_sigma_1_arcsec,"
        "tilt_sigma_2_arcsec,foot_x_m,foot_y_m,foot_z_m,foot_axis_1_mm,foot_axis_2_mm,"
        "foot_axis_3_mm,n_points,n_scans",
    ]
    net = res.network
    cov = res.plane_covariance
    e = plane_ellipsoids(
        res.plane_params, np.full((len(res.planes), 4, 4), np.nan) if cov is None else cov
    )
    for k, name in enumerate(res.planes):
        rows = net.plane_index == k
        P, S = res.plane_params[k], res.plane_sigmas[k]
        cells = [_cell(name), *(_cell(v) for v in P), *(_cell(v) for v in S[:3])]
        cells.append(_cell(S[3], 1e3))
        cells += [_cell(v, 1 / ARCSEC) for v in e["tilt_sigmas"][k]]
        cells += [_cell(v) for v in e["foot_point"][k]]
        cells += [_cell(v, 1e3) for v in e["foot_axes"][k]]
        cells += [str(int(rows.sum())), str(len(np.unique(net.plane_scan_index[rows])))]
        lines.append(",".join(cells))
    return "\n".join(lines) + "\n"


def write_adjusted_targets(res, path) -> None:
    """The adjusted targets of ``res`` (a :class:`tlsjax.CalibrationResult`) with sigmas and
    1-sigma ellipsoid semi-axes as CSV, in the datum of the adjustment
    (:func:`tlsjax._io._target_lists.write_target_csv`; axes empty where the covariance blocks
    were not computed)."""
    from .._adjustment._json import datum_text, target_ellipsoids, target_scan_counts
    from .._io._target_lists import write_target_csv

    cov = res.target_covariance
    axes, _ = target_ellipsoids(np.full((len(res.targets), 3, 3), np.nan) if cov is None else cov)
    write_target_csv(
        path,
        res.targets,
        res.target_xyz,
        res.target_sigmas,
        axes,
        target_scan_counts(res),
        datum_text(res),
    )


def write_tables(res, folder, tested=None) -> list[str]:
    """Write the CSV tables into ``folder`` (created): ``observations.csv`` (target
    observations), ``plane_points.csv``, ``groups.csv``, ``targets.csv`` (adjusted targets
    with sigmas and 1-sigma ellipsoid semi-axes; x :data:`ELLIPSOID_95` for 95 %) and
    ``planes.csv``, each where the network has them. None for a failed adjustment (its
    numbers would look plausible and be wrong). Returns the paths written."""
    from .._io._json import write_text_atomic

    if not res.ok:
        return []
    net = res.network
    written = []

    def put(name, text):
        path = os.path.join(os.fspath(folder), name)
        write_text_atomic(path, text, "--tables ")
        written.append(path)

    if net.has_targets or res.weighted_constraints():
        # Target observations and the weighted constraints (levelling, headings, AP priors).
        put("observations.csv", observation_csv(res, tested, kind="target"))
    if net.has_targets:
        path = os.path.join(os.fspath(folder), "targets.csv")
        write_adjusted_targets(res, path)
        written.append(path)
    if net.has_planes:
        put("plane_points.csv", observation_csv(res, kind="plane"))
        put("planes.csv", planes_csv(res))
    put("groups.csv", group_csv(res, tested))
    return written


def with_lines(outliers: list, res) -> list:
    """The ``outliers`` of the result JSON with ``line``, the input file's line (1-based) of
    each removed observation beside its 0-based network ``row``; null for arrays."""
    net = res.network
    lines = None if net is None else _lines(net.lines, net.observations.shape[0])
    return [
        {**o, "line": None if lines is None or o.get("row") is None else int(lines[o["row"]])}
        for o in outliers
    ]
