"""A calibration report a laboratory can file: one self-contained HTML page (no external
resources; plots embedded as base64 PNG) made from the result JSON of SPEC section 11, which
stays the machine-readable contract.

Sections: what was calibrated (design summary), the global test, the AP table (value, a
posteriori sigma, |t|, max |correlation| and the named partner, as in Chow et al. 2013, tables
2-5), non-estimable and weakly determined APs, variance components, redundancy and reliability
(minimal detectable bias ``MDB_i = delta0 sigma_i / sqrt(r_i)`` and Baarda's external reliability
factor ``sqrt((1 - r_i) / r_i) delta0``, delta0 = 4.13 for alpha0 = 0.1 %, power 80 %) per group
and per scan, outliers, plots, the scan poses, and what produced the report (tlsjax version,
command, SHA-256 of each input file). A field that the calibration did not compute (e.g. the
outliers of a run without data snooping) is shown as "not computed", never as zero.
"""

from __future__ import annotations

import base64
import datetime
import hashlib
import html
import io
import math
import os
import platform

import numpy as np

from .._adjustment._config import scanner_settings as scanner_settings
from .._adjustment._quality import external_reliability_factor, minimal_detectable_bias
from .._adjustment._text import confoundings
from .._io._json import read_result_json
from .._stats import DELTA0
from .._units import ARCSEC, DISPLAY_UNITS
from .._version import __version__

_GROUPS = ("range", "hz", "el")
_GROUP_UNIT = {
    "range": ("mm", 1e3),
    "hz": ('"', 1.0 / ARCSEC),
    "el": ('"', 1.0 / ARCSEC),
    "levelling": ('"', 1.0 / ARCSEC),
    "heading": ('"', 1.0 / ARCSEC),
    "ap_prior": ("(SI: m, rad or 1)", 1.0),  # the priors of one group have their APs' units
}
NOT_COMPUTED = "not computed"


# --- what goes into the JSON for the report (called by the CLI) ---------------------------


def sha256_of(path, block: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while chunk := fh.read(block):
            h.update(chunk)
    return h.hexdigest()


def provenance(files=(), command: str | None = None) -> dict:
    """tlsjax version, command line (None: not run from one), time (UTC), Python and
    platform, and the SHA-256 and size of each input file (once each; missing ones left out)."""
    inputs = [
        {"path": os.fspath(f), "bytes": os.path.getsize(f), "sha256": sha256_of(f)}
        for f in dict.fromkeys(f for f in files if f)
        if os.path.isfile(f)
    ]
    return {
        "tlsjax_version": __version__,
        "command": command,
        "created_utc": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "python": platform.python_version(),
        "platform": platform.platform(),
        "inputs": inputs,
    }


def _stats(a) -> dict:
    a = np.asarray(a, dtype=np.float64)
    a = a[np.isfinite(a)]
    if not a.size:
        return {"mean": None, "max": None, "n": 0}
    return {"mean": float(a.mean()), "max": float(a.max()), "n": int(a.size)}


def reliability_summary(result, *, mdb=None, mask=None) -> dict:
    """Internal reliability (MDB [m, rad]) and Baarda's external reliability factor
    ``sqrt((1 - r) / r) delta0`` of the target observations, mean and max per group and per
    scan. ``mdb``: the MDBs of :class:`~tlsjax.SelfCalibration` (default: from the a priori
    sigmas and the redundancy numbers); ``mask``: the observations used."""
    net = result.network
    r = np.asarray(result.redundancy, dtype=np.float64)
    if net is None or r.ndim != 2 or r.shape[0] == 0:
        return {}
    used = np.ones(r.shape, bool) if mask is None else np.asarray(mask, bool)
    if result.used is not None and mask is None:
        used = np.asarray(result.used, bool)
    if mdb is None:
        mdb = minimal_detectable_bias(np.asarray(net.sigmas, dtype=np.float64), r)
    mdb = np.where(used, mdb, np.nan)
    ext = np.where(used, external_reliability_factor(r), np.nan)
    out = {"delta0": DELTA0, "groups": {}, "per_scan": {}}
    for g, name in enumerate(_GROUPS):
        uncontrolled = int(np.sum(used[:, g] & ~np.isfinite(mdb[:, g])))
        out["groups"][name] = {
            "mdb": _stats(mdb[:, g]),
            "external": _stats(ext[:, g]),
            "uncontrolled": uncontrolled,
        }
    for j, s in enumerate(result.scans):
        rows = net.scan_index == j
        out["per_scan"][s] = {
            name: {"mdb": _stats(mdb[rows, g]), "external": _stats(ext[rows, g])}
            for g, name in enumerate(_GROUPS)
        }
    return out


# --- rendering -------------------------------------------------------------------------------


def _e(x) -> str:
    return html.escape(str(x))


def _fmt(v, digits=3, scale=1.0) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "&ndash;"
    return f"{v * scale:.{digits}f}"


def _table(head, rows, cls="") -> str:
    th = "".join(f"<th>{h}</th>" for h in head)
    body = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in row) + "</tr>" for row in rows)
    return f'<table class="{cls}"><thead><tr>{th}</tr></thead><tbody>{body}</tbody></table>'


def _na(what: str, hint: str = "") -> str:
    return f'<p class="na">{_e(what)}: {NOT_COMPUTED}{(" (" + _e(hint) + ")") if hint else ""}</p>'


def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    import matplotlib.pyplot as plt

    plt.close(fig)
    return base64.b64encode(buf.getvalue()).decode("ascii")


def _img(b64: str, alt: str) -> str:
    return f'<figure><img alt="{_e(alt)}" src="data:image/png;base64,{b64}"><figcaption>{_e(alt)}</figcaption></figure>'


def correlation_png(doc) -> str | None:
    """The AP correlation matrix from the JSON's ``ap_covariance``, as base64 PNG."""
    names, C = doc.get("ap_covariance_names"), doc.get("ap_covariance")
    if not names or C is None:
        return None
    C = np.array([[np.nan if v is None else v for v in row] for row in C], dtype=np.float64)
    s = np.sqrt(np.diag(C))
    with np.errstate(divide="ignore", invalid="ignore"):
        R = C / np.outer(s, s)
    from ._plots import _pyplot

    plt = _pyplot()
    n = len(names)
    fig, ax = plt.subplots(figsize=(min(1.2 + 0.42 * n, 11), min(1.0 + 0.38 * n, 9.5)))
    im = ax.imshow(R, vmin=-1, vmax=1, cmap="RdBu_r")
    ax.set_xticks(range(n), names, rotation=90)
    ax.set_yticks(range(n), names)
    fig.colorbar(im, ax=ax, label="correlation [-]")
    ax.set_title("AP correlation matrix (a posteriori)")
    return _png(fig)


def _ap_display(unit):
    label, factor = DISPLAY_UNITS.get(unit, (unit, 1.0))
    return label, factor


def _section_design(doc) -> str:
    sc = doc.get("scanner") or {}
    eops = doc.get("eops") or {}
    planes = doc.get("planes") or {}
    rows = [
        ("source", _e(doc.get("source") or "&ndash;")),
        ("scanner architecture", _e(sc.get("architecture", NOT_COMPUTED))),
        ("APs estimated", _e(" ".join(doc.get("aps", {})) or "none")),
        ("scans", len(eops)),
        ("planes", len(planes) if planes else "&ndash;"),
        ("plane points", doc.get("n_plane_points", "&ndash;")),
        ("observations n", doc.get("n_observations")),
        ("unknowns u", doc.get("n_unknowns")),
        ("degrees of freedom r = n - u + d", _fmt(doc.get("dof"), 0)),
        ("datum", _e(doc.get("datum"))),
        ("result", f"{doc.get('result')}: {_e(doc.get('message'))}"),
        ("converged / iterations", f"{doc.get('converged')} / {doc.get('iterations')}"),
    ]
    if "selection" in doc:
        rows.append(("AP selection", _e(" ".join(doc["selection"].get("aps", [])))))
    return "<h2>Design and adjustment</h2>" + _table(("quantity", "value"), rows, "kv")


def _verdict(accepted) -> str:
    if accepted is None:
        return f'<span class="na">{NOT_COMPUTED}</span>'
    v = "accepted" if accepted else "rejected"
    return f'<b class="{v}">{v}</b>'


def _test_row(test, stage, g, factor=False) -> tuple:
    """One row of the test sequence: a global test (T = s0^2 r) or a group test (its
    variance factor Omega_g / r_g), with the two-sided bounds of T and the p-value."""
    if not g or g.get("statistic") is None:
        return (test, _e(stage), "&ndash;", _fmt((g or {}).get("dof"), 1), "&ndash;", "&ndash;")
    value = _fmt(g.get("factor"), 4) if factor else _fmt(g["statistic"], 1)
    return (
        test,
        _e(stage),
        value,
        _fmt(g.get("dof"), 1),
        f"{_fmt(g['lower'], 1)} .. {_fmt(g['upper'], 1)}",
        _fmt(g.get("p_value"), 4),
        _verdict(g.get("accepted")),
    )


def _section_global(doc) -> str:
    """The test sequence in the order it ran: the global and group tests with the a priori
    sigmas (all observations, then after screening when it removed any), the removals (in
    :func:`_section_outliers`), the test of the final adjustment, and sigma0 after VCE, which
    is no test (the factors were fitted to its residuals)."""
    rows = []
    for st in doc.get("a_priori_tests") or []:
        stage = f"a priori sigmas, {st.get('stage', '')}"
        rows.append(_test_row("global (T = s0&sup2; r)", stage, st.get("global")))
        for name, t in (st.get("groups") or {}).items():
            rows.append(_test_row(f"group {_e(name)} (factor)", stage, t, factor=True))
    g = doc.get("global_test") or {}
    after_vce = doc.get("global_test_after_vce")
    if after_vce is None and g.get("stage") != "a priori":
        stage = "final adjustment" + (" (after the removals)" if doc.get("outliers") else "")
        rows.append(_test_row("global (T = s0&sup2; r)", stage, g))
    head = ("test", "stage", "T or factor", "dof / r_g", "two-sided bounds", "p-value", "decision")
    level = g.get("level", 0.05)
    out = (
        f"<h2>Tests (&chi;&sup2;, two-sided, level &alpha; = {level})</h2>"
        "<p>In the order they ran. A group's factor is &Omega;<sub>g</sub> / r<sub>g</sub>, its "
        "statistic &Omega;<sub>g</sub> = v<sub>g</sub><sup>T</sup> P<sub>g</sub> v<sub>g</sub> "
        "against &chi;&sup2;(r<sub>g</sub>).</p>" + _table(head, rows, "tests")
    )
    sigma0 = doc.get("sigma0")
    if after_vce is not None:
        out += (
            f"<p>sigma0 after variance component estimation = {_fmt(after_vce.get('sigma0'), 4)}"
            f": <b>not a test</b> ({_e(str(after_vce.get('note', '')).removesuffix(': not a test'))}).</p>"
        )
    else:
        out += f"<p>a posteriori sigma0 of the final adjustment = {_fmt(sigma0, 4)}.</p>"
    return out


def _section_aps(doc) -> str:
    weak = {w["name"]: w for w in doc.get("weakly_determined") or []}
    bad = {w["name"]: w for w in doc.get("not_estimable") or []}
    rows = []
    for name, a in (doc.get("aps") or {}).items():
        label, f = _ap_display(a.get("unit"))
        flag = "not estimable" if name in bad else ("weakly determined" if name in weak else "")
        if a.get("note"):  # why a number is missing or a t is no verdict, as in the JSON
            flag = a["note"]
        t = a.get("t")
        rows.append(
            (
                f"<b>{_e(name)}</b>",
                _e(a.get("description") or ""),
                _fmt(a.get("value"), 3, f),
                _fmt(a.get("sigma"), 3, f),
                _e(label),
                _fmt(abs(t) if t is not None else None, 1),
                _fmt(a.get("max_abs_corr"), 2),
                _e(a.get("max_corr_with")) if a.get("max_corr_with") else "&ndash;",
                f'<span class="flag">{flag}</span>' if flag else "",
            )
        )
    head = ("AP", "meaning", "value", "sigma", "unit", "|t|", "max |corr|", "with", "")
    out = "<h2>Additional parameters</h2>"
    if doc.get("estimates", "valid") != "valid":
        out += f'<p class="flag"><b>No calibration:</b> {_e(doc["estimates"])}</p>'
    out += _table(head, rows, "aps") if rows else _na("APs")
    found = doc.get("confoundings")
    if found is None:  # a JSON of an older tlsjax
        found = confoundings(doc.get("not_estimable"), doc.get("weakly_determined"))
    for kind in ("not estimable", "weakly determined"):
        items = "".join(f"<li>{_e(c['text'])}</li>" for c in found if c["kind"] == kind)
        title = kind[0].upper() + kind[1:]
        out += f"<h3>{title}</h3><ul>{items}</ul>" if items else f"<p>{title}: none.</p>"
    return out


def _section_variance(doc) -> str:
    vc = doc.get("variance_components") or {}
    if not vc or (doc.get("vce") or {}).get("status") == "off":  # a priori factors only
        return (
            "<h2>Variance components</h2>"
            + _na("variance components", "run calibrate with --vce (target networks)")
            + _group_table(doc)
        )
    rows = []
    items = vc.items() if isinstance(vc, dict) else [(v.get("group"), v) for v in vc]
    for g, v in items:
        if not isinstance(v, dict):
            rows.append((_e(g), _e(v), "", "", "", ""))
            continue
        unit, f = _GROUP_UNIT.get(g, ("", 1.0))
        rows.append(
            (
                _e(g),
                _fmt(v.get("factor"), 4),
                _fmt(v.get("a_priori_sigma"), 3, f) + f" {unit}",
                _fmt(v.get("sigma"), 3, f) + f" {unit}",
                _fmt(v.get("redundancy"), 1),
                _e(v.get("n", "")),
            )
        )
    head = ("group", "factor [-]", "a priori sigma", "estimated sigma", "r_g", "n")
    return "<h2>Variance components</h2>" + _table(head, rows) + _group_table(doc)


def _group_table(doc) -> str:
    """Per observation group: n, r_g, the variance factor of the final adjustment with its
    test, the factor as VCE estimated it and the a priori factor (the JSON's group_table)."""
    rows = [
        (
            _e(g["group"]),
            g["n"],
            _fmt(g.get("redundancy"), 1),
            _fmt(g.get("variance_factor"), 4),
            _verdict(g.get("accepted")) if g.get("variance_factor") is not None else "&ndash;",
            _fmt(g.get("vce_factor"), 4),
            _fmt(g.get("a_priori_factor"), 4),
        )
        for g in doc.get("group_table") or []
    ]
    if not rows:
        return ""
    head = ("group", "n", "r_g", "factor, final", "test", "factor, VCE", "factor, a priori")
    return "<h3>Observation groups</h3>" + _table(head, rows, "groups")


def _section_redundancy(doc) -> str:
    red = doc.get("redundancy") or {}
    if not red:
        return "<h2>Redundancy</h2>" + _na("redundancy numbers")
    rows = [
        (_e(k), _fmt(v.get("mean"), 3), _fmt(v.get("sum"), 1))
        for k, v in red.items()
        if k not in ("per_scan", "planes") and isinstance(v, dict)
    ]
    out = "<h2>Redundancy numbers</h2>" + _table(("group", "mean r_i", "sum r_i"), rows)
    if red.get("planes"):
        prow = [
            (_e(k), _fmt(v.get("mean"), 3), _fmt(v.get("sum"), 1)) for k, v in red["planes"].items()
        ]
        out += "<h3>Plane points</h3>" + _table(("group", "mean r_i", "sum r_i"), prow)
    per = red.get("per_scan") or {}
    if per:
        out += "<h3>Per scan</h3>" + _table(
            ("scan", "mean r_i"), [(_e(s), _fmt(v.get("mean"), 3)) for s, v in per.items()]
        )
    return out


def _mdb_cell(st, g):
    unit, f = _GROUP_UNIT[g]
    if not st or st.get("n", 0) == 0:
        return "&ndash;"
    return f"{_fmt(st['mean'], 2, f)} / {_fmt(st['max'], 2, f)} {unit}"


def _section_reliability(doc) -> str:
    rel = doc.get("reliability") or {}
    if not rel:
        return "<h2>Reliability</h2>" + _na(
            "internal and external reliability", "target networks through tlsjax calibrate"
        )
    head = ("group", "MDB mean / max", "external factor mean / max [-]", "uncontrolled")
    rows = [
        (
            g,
            _mdb_cell(v.get("mdb"), g),
            f"{_fmt(v['external']['mean'], 2)} / {_fmt(v['external']['max'], 2)}",
            v.get("uncontrolled", 0),
        )
        for g, v in rel.get("groups", {}).items()
    ]
    out = (
        f"<h2>Reliability (&delta;0 = {rel.get('delta0', DELTA0):.2f})</h2>"
        "<p>Internal: minimal detectable bias MDB = &delta;0 &sigma; / &radic;r. External: "
        "Baarda's factor &radic;((1 - r)/r) &delta;0, the effect of an undetected MDB-sized error "
        "on the unknowns in units of their sigma.</p>" + _table(head, rows)
    )
    per = rel.get("per_scan") or {}
    if per:
        prow = [
            (_e(s),) + tuple(_mdb_cell(v.get(g, {}).get("mdb"), g) for g in _GROUPS)
            for s, v in per.items()
        ]
        out += "<h3>MDB per scan (mean / max)</h3>" + _table(("scan", "range", "hz", "el"), prow)
    return out


def _removal_stages(outliers) -> dict:
    """step -> the stage that made its removals: the robust start, screening before VCE or data
    snooping (a consequential removal, e.g. the other two observations of a rejected target,
    shares its step)."""
    stages = {}
    for o in outliers:
        reason = str(o.get("reason", ""))
        if reason.startswith("robust start"):
            stages[o.get("step")] = "robust start"
        elif reason.startswith("screening"):
            stages[o.get("step")] = "screening (before VCE)"
    return {o.get("step"): stages.get(o.get("step"), "data snooping") for o in outliers}


def _section_outliers(doc) -> str:
    """Every removal with the stage that made it (screening before VCE, data snooping), the
    input file's line, the residual in mm or arc seconds and its test statistic."""
    parts = []
    scr, sn = doc.get("screening") or {}, doc.get("snooping") or {}
    if scr.get("enabled"):
        parts.append(
            f"screening before VCE (robust w, family-wise &alpha; = {_fmt(scr.get('family_level'), 4)}, "
            f"critical value {_fmt(scr.get('critical_value'), 2)}): {scr.get('n_removed', 0)} removal(s)"
        )
    if sn.get("enabled"):
        parts.append(
            f"Baarda data snooping (critical value {_fmt(sn.get('critical_value'), 2)}, "
            f"one removal per adjustment)"
        )
    ps = doc.get("plane_screening")
    if ps:
        parts.append(f"plane points: {_e(ps.get('method'))}: {ps.get('n_removed', 0)} removed")
    if not parts:
        return "<h2>Removals</h2>" + _na(
            "screening and data snooping", "run calibrate with --snoop"
        )
    out = doc.get("outliers") or []
    txt = "<p>" + "; ".join(parts) + f". {len(out)} target observation(s) removed.</p>"
    rows, stages = [], _removal_stages(out)
    for o in out:
        unit = "mm" if o.get("group") == "range" else '"'
        rows.append(
            (
                o.get("step"),
                stages[o.get("step")],
                _e(o.get("line") if o.get("line") is not None else "&ndash;"),
                _e(o.get("scan")),
                _e(o.get("target")),
                _e(o.get("group")),
                f"{_fmt(o.get('residual'), 2)} {unit}",
                _fmt(o.get("w"), 2),
                _e(o.get("reason")),
            )
        )
    head = ("step", "stage", "line", "scan", "target", "group", "residual", "w", "reason")
    return "<h2>Removals</h2>" + txt + (_table(head, rows, "removals") if rows else "")


def _section_score_tests(doc) -> str:
    """The score tests of the missing terms (``score_tests``: :meth:`tlsjax.ScoreTests.to_dict`):
    each testable candidate with T, its share of v^T P v, the one-step estimate, its group of
    alternatives and a plausibility flag; the candidates the design cannot estimate apart."""
    st = doc.get("score_tests")
    if not st:
        return "<h2>Missing terms (score tests)</h2>" + _na(
            "score tests of the terms not in the model",
            "they are run for target networks of one instrument",
        )
    crit, vf = st.get("critical_value"), st.get("variance_factor") or 1.0
    scale = "" if vf == 1.0 else f" / s0&sup2; (s0&sup2; = {_fmt(vf, 3)})"
    rows = []
    for c in st.get("candidates") or []:
        if not c.get("testable"):
            continue
        label, f = _ap_display(c.get("unit"))
        flags = []
        if c.get("significant"):
            flags.append("<b>significant</b>")
        if c.get("alternatives"):
            flags.append("alternatives: " + _e(", ".join(c["alternatives"])))
        if c.get("plausibility"):
            flags.append(f'<span class="flag">{_e(c["plausibility"])}: implausible estimate</span>')
        share = c.get("share")
        rows.append(
            (
                f"<b>{_e(c['name'])}</b>",
                _e(c.get("group", "")),
                _fmt(c.get("statistic"), 1),
                _fmt(share, 1, 100.0),
                _fmt(c.get("estimate"), 3, f),
                _fmt(c.get("sigma"), 3, f),
                _e(label),
                "; ".join(flags),
            )
        )
    head = ("term", "group", "T", "share of vTPv [%]", "one-step estimate", "sigma", "unit", "")
    out = (
        "<h2>Missing terms (score tests)</h2>"
        f"<p>T = (c<sup>T</sup>Pv)&sup2; / (c<sup>T</sup>PQ<sub>vv</sub>Pc) of each term not in "
        f"the model, &chi;&sup2;(1) under H0; significant where T{scale} &gt; {_fmt(crit, 2)} "
        f"(family-wise &alpha; = {_e(st.get('family_level'))}). Largest first.</p>"
        + (_table(head, rows, "small") if rows else "<p>No candidate could be tested.</p>")
    )
    groups = st.get("alternatives") or []
    if groups:
        items = "".join(f"<li>{_e(', '.join(g))}</li>" for g in groups)
        out += (
            "<h3>Groups of alternatives</h3><p>Their effects after the model correlate beyond "
            "0.9: they predict nearly the same residuals, and the larger T is no evidence that "
            "it is the right term. Only prediction on held-out scans tells them apart "
            f"(cross-validation, stepwise selection).</p><ul>{items}</ul>"
        )
    gone = st.get("not_estimable") or []
    if gone:
        items = "".join(f"<li>{_e(g['name'])}: {_e(g['reason'])}</li>" for g in gone)
        out += f"<h3>Not estimable in this design (never proposed)</h3><ul>{items}</ul>"
    return out


def _section_cross_validation(doc) -> str:
    """Prediction of held-out scans (``cross_validation``:
    :meth:`tlsjax.CrossValidation.to_dict`): the misfit RMS with the APs and without, overall
    and per fold, and the verdict."""
    cv = doc.get("cross_validation")
    if not cv:
        return "<h2>Prediction of held-out scans (cross-validation)</h2>" + _na(
            "cross-validation by scan groups", "tlsjax.cross_validate or the self-calibration"
        )
    axes = ("xyz", "x", "y", "z")
    head = ("", "3D [mm]", "X [mm]", "Y [mm]", "Z [mm]")
    with_, none = cv.get("rms_mm") or {}, cv.get("rms_none_mm") or {}
    rows = [
        ("with the APs", *(_fmt(with_.get(k), 3) for k in axes)),
        ("without APs", *(_fmt(none.get(k), 3) for k in axes)),
    ]
    code, improves = cv.get("code"), cv.get("improves")
    cls = "accepted" if improves else "rejected" if code in (1, 2) else "na"
    out = (
        "<h2>Prediction of held-out scans (cross-validation)</h2>"
        "<p>Each fold's scans are left out, the rest adjusted, the held-out scans corrected with "
        "the rest's APs and placed by their own pose on its targets; the misfit of the placed "
        "targets, RMS over all folds (without APs: the rest adjusted and the scans placed with "
        f"none). Standard error between folds: {_fmt(cv.get('se_mm'), 3)} mm.</p>"
        + _table(head, rows, "small")
        + f'<p class="{cls}"><b>{_e(cv.get("message", ""))}</b></p>'
    )
    folds = []
    for f in cv.get("folds") or []:
        name = "+".join(f.get("held_out") or [])
        if not f.get("ok"):
            folds.append((_e(name), "&ndash;", "&ndash;", "&ndash;", _e(f.get("note", ""))))
            continue
        folds.append(
            (
                _e(name),
                f.get("n_targets"),
                _fmt((f.get("rms_mm") or {}).get("xyz"), 3),
                _fmt((f.get("rms_none_mm") or {}).get("xyz"), 3),
                _e(", ".join(sorted(set(f.get("placement") or [])))),
            )
        )
    head = ("held out", "targets", "with [mm]", "without [mm]", "placement / note")
    return out + "<h3>Folds</h3>" + _table(head, folds, "small")


def _section_selection(doc) -> str:
    """The path of stepwise selection with the figure at each step (``selection``), when it ran."""
    sel = doc.get("selection")
    if not sel or not sel.get("steps"):
        return ""
    rows = []
    for st in sel["steps"]:
        rows.append(
            (
                _e(st.get("action", "")),
                _e(st.get("term", "")),
                _fmt(st.get("statistic"), 1),
                _fmt(st.get("sigma0"), 3),
                _fmt(st.get("cv_mm"), 3),
                _e(st.get("reason", "")),
            )
        )
    head = ("step", "term", "statistic", "sigma0", "CV [mm]", "why")
    end = f"<p>{_e(sel['end'])}</p>" if sel.get("end") else ""
    return (
        f"<h2>Stepwise selection: {_e(' '.join(sel.get('aps', [])) or '(none)')}</h2>"
        + end
        + _table(head, rows, "removals")
    )


def _section_architecture(doc) -> str:
    """Hybrid against panoramic (``architecture_check``:
    :meth:`tlsjax.ArchitectureComparison.to_dict`), when it ran."""
    ac = doc.get("architecture_check")
    if not ac:
        return ""
    rows = []
    for arch, f in (ac.get("fits") or {}).items():
        mark = " (as read)" if arch == ac.get("given") else ""
        rows.append(
            (
                _e(arch + mark),
                _fmt(f.get("sigma0"), 3),
                _fmt(f.get("cv_mm"), 3),
                f.get("n_removed"),
                _e(f.get("message", "") if not f.get("ok") else ""),
            )
        )
    head = ("architecture", "sigma0 (a priori)", "CV [mm]", "removed", "")
    warn = f'<p class="flag">{_e(ac["warning"])}</p>' if ac.get("warning") else ""
    return (
        "<h2>Architecture from the data</h2>"
        + _table(head, rows, "small")
        + (
            f"<p>Explains the data better: <b>{_e(ac['best'])}</b> ({_e(ac.get('reason'))}).</p>"
            if ac.get("best")
            else f"<p>{_e(ac.get('reason'))}.</p>"
        )
        + warn
    )


def _section_eops(doc) -> str:
    eops = doc.get("eops") or {}
    if not eops:
        return ""
    rows = []
    for s, e in eops.items():
        sg = e.get("sigma") or {}
        pos = tuple(
            f"{_fmt(e.get(k), 4)} &plusmn; {_fmt(sg.get(k), 2, 1e3)}" for k in ("Xs", "Ys", "Zs")
        )
        ang = tuple(
            f"{_fmt(e.get(k), 4, 180 / math.pi)} &plusmn; {_fmt(sg.get(k), 1, 1 / ARCSEC)}"
            for k in ("omega", "phi", "kappa")
        )
        rows.append((_e(s),) + pos + ang)
    head = ("scan", "Xs [m] &plusmn; [mm]", "Ys [m] &plusmn; [mm]", "Zs [m] &plusmn; [mm]")
    head += tuple(f"{k} [deg] &plusmn; [&quot;]" for k in ("omega", "phi", "kappa"))
    return "<h2>Scan poses</h2>" + _table(head, rows, "small")


def _section_planes(doc) -> str:
    planes = doc.get("planes") or {}
    if not planes:
        return ""
    rows = [
        (
            _e(k),
            " ".join(_fmt(v, 4) for v in p.get("normal", [])),
            _fmt(p.get("d"), 4),
            _fmt((p.get("sigma") or {}).get("d"), 3, 1e3),
            " / ".join(_fmt(v, 2, 1 / ARCSEC) for v in p.get("tilt_sigmas") or [None, None]),
            " / ".join(_fmt(v, 3, 1e3) for v in p.get("foot_point_ellipsoid_axes") or [None] * 3),
            p.get("n_points"),
            p.get("n_scans"),
        )
        for k, p in planes.items()
    ]
    head = (
        "plane",
        "normal [-]",
        "d [m]",
        "sigma d [mm]",
        "tilt sigmas [&quot;]",
        "foot point d&middot;n: semi-axes [mm]",
        "points",
        "scans",
    )
    note = (
        "<p>1-sigma, a posteriori: the principal tilts of the normal (x 2.45 for "
        "the 95 % ellipse) and the semi-axes of the foot point's ellipsoid (x 2.80 for 95 %), "
        "in the datum of the adjustment.</p>"
    )
    return "<h2>Planes</h2>" + _table(head, rows, "small") + note


def _section_provenance(doc) -> str:
    p = doc.get("provenance") or {}
    if not p:
        return "<h2>Produced by</h2>" + _na(
            "provenance", "the JSON was not written by tlsjax calibrate"
        )
    rows = [
        ("tlsjax version", _e(p.get("tlsjax_version"))),
        ("command", f"<code>{_e(p.get('command'))}</code>"),
        ("created (UTC)", _e(p.get("created_utc"))),
        ("Python / platform", _e(f"{p.get('python')} / {p.get('platform')}")),
    ]
    files = [
        (f"<code>{_e(f['path'])}</code>", f["bytes"], f"<code>{_e(f['sha256'])}</code>")
        for f in p.get("inputs", [])
    ]
    return (
        "<h2>Produced by</h2>"
        + _table(("item", "value"), rows, "kv")
        + ("<h3>Input files</h3>" + _table(("file", "bytes", "SHA-256"), files) if files else "")
    )


_CSS = """
body{font-family:DejaVu Sans,Arial,sans-serif;margin:24px auto;max-width:1100px;color:#111;font-size:14px}
h1{font-size:22px;border-bottom:2px solid #234;padding-bottom:4px}h2{font-size:18px;margin-top:28px;color:#234}
h3{font-size:15px}table{border-collapse:collapse;margin:8px 0}td,th{border:1px solid #bbb;padding:3px 8px;text-align:right}
th{background:#e8eef4}td:first-child,th:first-child{text-align:left}table.kv td:last-child{text-align:left}
table.aps td:nth-child(2){text-align:left;font-size:12px;color:#444}.flag{color:#b00;font-weight:bold}
.na{color:#777;font-style:italic}table.removals{font-size:12px}table.tests td:nth-child(2){text-align:left}.accepted{color:#070}.rejected{color:#b00}table.small{font-size:12px}
figure{margin:12px 0}img{max-width:100%;border:1px solid #ccc}figcaption{font-size:12px;color:#555}
"""


def render_html(doc: dict, plots: dict | None = None) -> str:
    """The report page of a result JSON ``doc``; ``plots``: title -> base64 PNG (the AP
    correlation matrix is drawn from the JSON when not given)."""
    plots = dict(plots or {})
    corr = correlation_png(doc)
    if corr and not any("correlation" in k.lower() for k in plots):
        plots["AP correlation matrix"] = corr
    figs = "".join(_img(b, t) for t, b in plots.items())
    if not any("residual" in k.lower() for k in plots):
        figs = (
            _na(
                "residual plots",
                "the JSON holds no residuals: use calibrate --report or --plots DIR",
            )
            + figs
        )
    title = f"tlsjax calibration report: {doc.get('source') or ''}"
    body = "".join(
        [
            f"<h1>{_e(title)}</h1>",
            _section_design(doc),
            _section_global(doc),
            _section_aps(doc),
            _section_variance(doc),
            _section_redundancy(doc),
            _section_reliability(doc),
            _section_outliers(doc),
            "<h2>Plots</h2>" + figs,
            _section_score_tests(doc),
            _section_cross_validation(doc),
            _section_selection(doc),
            _section_architecture(doc),
            _section_eops(doc),
            _section_planes(doc),
            _section_provenance(doc),
        ]
    )
    return (
        '<!DOCTYPE html><html lang="en"><head><meta charset="utf-8">'
        f"<title>{_e(title)}</title><style>{_CSS}</style></head><body>{body}</body></html>\n"
    )


def write_html_report(doc: dict, path, *, plots: dict | None = None) -> str:
    """Write :func:`render_html` to ``path`` (atomically: a temporary file renamed)."""
    from .._io._outputs import write_text_atomic

    path = os.fspath(path)
    write_text_atomic(path, render_html(doc, plots))
    return path


def png_files(folder) -> dict:
    """The PNG plots of a ``--plots`` folder as title -> base64."""
    out = {}
    for name in sorted(os.listdir(folder)):
        if name.lower().endswith(".png") and not name.startswith("."):
            with open(os.path.join(folder, name), "rb") as fh:
                title = os.path.splitext(name)[0].replace("_", " ")
                out[title] = base64.b64encode(fh.read()).decode("ascii")
    return out


def report_from_json(json_path, html_path, *, plots_dir=None) -> str:
    """``tlsjax report``: the HTML report of a result JSON file."""
    from .._io._outputs import check_outputs

    source = os.fspath(json_path)
    check_outputs([("--html", html_path)], [("calibration", source)])
    doc = read_result_json(source)
    plots = png_files(plots_dir) if plots_dir else None
    try:
        html = render_html(doc, plots)
    except (AttributeError, TypeError, KeyError, IndexError, ValueError) as err:
        # The contract fields are checked on reading; a field the report reads that has the
        # wrong JSON type is named here rather than as a traceback.
        raise ValueError(
            f"{source}: not a well-formed tlsjax result JSON ({type(err).__name__}: {err})"
        ) from None
    from .._io._outputs import write_text_atomic

    write_text_atomic(html_path, html, "--html ")
    return os.fspath(html_path)
