"""``tlsjax calibrate``: self-calibration from target and/or plane observation files."""

from __future__ import annotations

import argparse
import dataclasses
import os
import time
import warnings

import numpy as np

from .._clouds._thin import DEFAULT_PLANE_SPACING
from .._model._plausibility import PlausibilityWarning
from .._units import ARCSEC
from ._checks import correlation, positive_float, positive_int, probability, refuse_unless, warn
from ._common import EXIT_FAILED, EXIT_OK, scanner_args


def add_calibrate_parser(sub):
    """The options of ``tlsjax calibrate``, declared one after another (long because there are many
    of them; there is no logic here)."""
    c = sub.add_parser("calibrate", help="self-calibrate from target and/or plane observations")
    c.add_argument(
        "observations",
        nargs="?",
        help="target or plane observation CSV (SPEC section 11; units from the header suffixes)",
    )
    c.add_argument(
        "--planes",
        help="plane observations: a plane CSV or the .npz of `tlsjax extract-planes`; "
        "alone (plane-based) or with a target CSV (combined network)",
    )
    c.add_argument(
        "--plane-spacing",
        type=float,
        default=DEFAULT_PLANE_SPACING,
        metavar="M",
        help="thin the plane points to one per voxel of this side [m] per scan and plane "
        f"(default {DEFAULT_PLANE_SPACING:g}: noise of points closer than about a third of it is "
        "correlated, and the sigmas of all points would be too small; 0 keeps all points)",
    )
    c.add_argument(
        "--quiet", action="store_true", help="no progress lines (phases and times) on stderr"
    )
    c.add_argument(
        "--scans",
        help="scans CSV with the observed orientation angles: tilt readings (omega, phi) of "
        "levelled and tilted scans, headings (kappa), each with its sigma",
    )
    c.add_argument(
        "--ap-prior",
        action="append",
        default=[],
        metavar="NAME=VALUE+-SIGMA",
        help='an AP prior from an earlier calibration, e.g. "B6=40arcsec+-5arcsec", '
        '"A0=-0.6mm+-0.05mm" (units m mm rad deg gon arcsec ppm; repeatable): a weighted '
        "constraint AP = value +- sigma (Chow et al. 2013, eq. 7)",
    )
    c.add_argument(
        "--ap-priors",
        metavar="FILE",
        help="AP priors from a CSV (columns ap, value, sigma, unit) or from a result JSON of "
        "tlsjax calibrate --json (every AP with a value and a sigma)",
    )
    c.add_argument(
        "--aps",
        default="physical",
        help='APs to estimate, e.g. "A0 B6 B7 C0" or a preset (default: physical)',
    )
    c.add_argument(
        "--datum",
        choices=("auto", "inner", "fixed-scan"),
        default="auto",
        help="inner constraints on the targets/planes, or a fixed scan (default auto: inner, or "
        "fixed-scan when --fixed-scan is given)",
    )
    c.add_argument("--fixed-scan", help="scan held fixed (implies --datum fixed-scan)")
    c.add_argument("--json", help="write the result JSON here")
    c.add_argument("--plots", help="write residual and correlation plots into this folder")
    c.add_argument(
        "--report",
        metavar="HTML",
        help="also write the calibration report: one self-contained HTML file",
    )
    c.add_argument(
        "--drop-single-targets",
        action="store_true",
        help="drop targets seen in one scan only (reported)",
    )
    c.add_argument(
        "--sigma-range-mm",
        type=positive_float,
        default=None,
        help="a priori range sigma [mm] where the file has none (default 0.5)",
    )
    c.add_argument(
        "--sigma-hz-arcsec",
        type=positive_float,
        default=None,
        help='a priori hz sigma ["] where the file has none (default 20)',
    )
    c.add_argument(
        "--sigma-el-arcsec",
        type=positive_float,
        default=None,
        help='a priori el sigma ["] where the file has none (default 20)',
    )
    c.add_argument("--max-iterations", type=positive_int, default=30)
    c.add_argument(
        "--correlation-threshold",
        type=correlation,
        default=0.99,
        help="flag APs whose max |correlation| exceeds this (default 0.99)",
    )
    c.add_argument(
        "--vce",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="variance component estimation per group (range, hz, el, levelling); default on for "
        "target networks, off with planes (SPEC section 5: the near-zero angular residuals of "
        "plane points bias it)",
    )
    c.add_argument(
        "--screen",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="remove gross errors before the least-squares tests, for any weighting (with or "
        "without --vce): a robust start (IGG-III reweighting from the misclosures at the "
        "approximate values) and screening (robust group scales, family-wise level "
        "--screen-alpha), both attributed to the observation holding the error; with --select "
        "the selection runs on the screened observations. Default on; --no-screen turns it off. "
        "With planes: screen the plane points (IGG-III reweighting, family-wise removal, then "
        "the a priori weights); with planes and --snoop: the robust screening of "
        "calibrate_and_test, then snooping, plane points and targets alike",
    )
    c.add_argument(
        "--screen-alpha",
        type=probability,
        default=None,
        help="family-wise significance level of the screening before VCE (default 0.001)",
    )
    c.add_argument(
        "--snoop",
        action="store_true",
        help="Baarda data snooping: remove rejected observations, re-adjust",
    )
    c.add_argument(
        "--snoop-alpha",
        type=probability,
        default=None,
        help="significance level of each w-test (default 0.001: critical value 3.29)",
    )
    c.add_argument(
        "--bonferroni",
        action="store_true",
        help="divide --snoop-alpha by the number of tests (family-wise level; no clean observation "
        "removed with probability 1 - alpha)",
    )
    c.add_argument(
        "--snoop-removal",
        choices=("observation", "target"),
        default=None,
        help="remove one scalar observation or all three of the target in that scan",
    )
    c.add_argument(
        "--select",
        action="store_true",
        help="stepwise AP selection starting from --aps, adding from --select-candidates by "
        "their score tests, on the observations the robust start and screening keep",
    )
    c.add_argument(
        "--select-candidates",
        default=None,
        help="candidate terms (names or presets; default chow2013-noscale)",
    )
    c.add_argument(
        "--select-alpha",
        type=probability,
        default=None,
        help="significance level of the selection t-tests (default 0.01)",
    )
    c.add_argument(
        "--max-correlation",
        type=correlation,
        default=None,
        help="a term entered with a larger correlation with another unknown is reported as "
        "such in its selection step (default 0.9)",
    )
    c.add_argument(
        "--targets-out",
        metavar="CSV",
        help="write the adjusted target coordinates with sigmas and ellipsoid axes here (in "
        "the datum of the adjustment; the JSON has them too)",
    )
    c.add_argument(
        "--tables",
        metavar="DIR",
        help="write the result tables as CSV into this folder: observations.csv (per "
        "observation: residual, normalised residual, redundancy number, MDB, external "
        "reliability, test decision; line = the input file's line), plane_points.csv, "
        "groups.csv (variance factors with their redundancy), targets.csv, planes.csv",
    )
    scanner_args(
        c, default=None, default_help="the one recorded in the observation file, else hybrid"
    )
    c.set_defaults(func=_calibrate)
    return c


def _ap_priors(args) -> dict:
    """The AP priors of ``--ap-priors FILE`` and ``--ap-prior`` (SI units)."""
    from .._io._priors import parse_ap_prior, read_ap_priors

    priors = read_ap_priors(args.ap_priors) if args.ap_priors else {}
    for text in args.ap_prior:
        name, value, sigma = parse_ap_prior(text)
        if name in priors:
            raise ValueError(f"--ap-prior {text!r}: {name} has a prior already")
        priors[name] = (value, sigma)
    return priors


#: Defaults of the options that are None when not given (so that a given one can be judged).
_DEFAULTS = {
    "sigma_range_mm": 0.5,
    "sigma_hz_arcsec": 20.0,
    "sigma_el_arcsec": 20.0,
    "screen_alpha": 0.001,
    "snoop_alpha": 0.001,
    "snoop_removal": "observation",
    "select_candidates": "chow2013-noscale",
    "select_alpha": 0.01,
    "max_correlation": 0.9,
}
#: The files --plots writes.
PLOT_FILES = ("residuals.png", "ap_correlations.png")
#: The files --tables may write.
TABLE_FILES = ("observations.csv", "plane_points.csv", "groups.csv", "targets.csv", "planes.csv")


def _check_options(args) -> None:
    """Refuse options that cannot take effect together (before any file is read), then fill
    the defaults of those left out."""
    if args.observations is None and args.planes is None:
        raise ValueError("give an observation CSV, --planes FILE, or both")
    if not str(args.aps).replace(",", " ").split():
        raise ValueError(
            f'--aps {args.aps!r}: no AP named; give names (e.g. "A0 B6 B7 C0") or a preset '
            "(physical, chow2013, chow2013-noscale, lichti2006, nist)"
        )
    if args.fixed_scan is not None and args.datum == "auto":
        args.datum = "fixed-scan"
    refuse_unless(
        args.fixed_scan is None or args.datum == "fixed-scan", "--fixed-scan", "--datum fixed-scan"
    )
    if args.datum == "fixed-scan" and args.fixed_scan is None:
        raise ValueError("--datum fixed-scan needs the scan to hold: --fixed-scan SCAN")
    for option, given in (
        ("--bonferroni", args.bonferroni),
        ("--snoop-alpha", args.snoop_alpha is not None),
        ("--snoop-removal", args.snoop_removal is not None),
    ):
        refuse_unless(not given or args.snoop, option, "--snoop")
    for option, value in (
        ("--select-candidates", args.select_candidates),
        ("--select-alpha", args.select_alpha),
        ("--max-correlation", args.max_correlation),
    ):
        refuse_unless(value is None or args.select, option, "--select")
    refuse_unless(args.screen_alpha is None or args.screen, "--screen-alpha", "--screen")
    args.given = {k for k in _DEFAULTS if getattr(args, k) is not None}
    for k, v in _DEFAULTS.items():
        if getattr(args, k) is None:
            setattr(args, k, v)


def _warn_ignored_sigmas(args, net) -> None:
    """A --sigma-* option given while every row of the files has its own sigma of that group
    changes nothing: say so (the file's sigmas are used)."""
    from .._io._tables import read_observations

    paths = [p for p in (args.observations, args.planes) if p and p.lower().endswith(".csv")]
    tables = [read_observations(p) for p in paths]
    for col, (option, unit) in enumerate(
        (("sigma_range_mm", "mm"), ("sigma_hz_arcsec", '"'), ("sigma_el_arcsec", '"'))
    ):
        if option not in args.given or not tables:
            continue
        if all(t.sigmas is not None and not np.isnan(t.sigmas[:, col]).any() for t in tables):
            flag = "--" + option.replace("_", "-")
            warn(
                f"{flag} {getattr(args, option):g} {unit} is ignored: every row of "
                f"{', '.join(paths)} has its own {('range', 'hz', 'el')[col]} sigma"
            )


def _read(args):
    from .._io._tables import read_network

    observations, planes = read_tables(
        args.observations, args.planes, args.plane_spacing, args.phases
    )
    net = read_network(
        observations,
        args.scans,
        planes=planes,
        drop_single_targets=args.drop_single_targets,
        sigma_range=args.sigma_range_mm * 1e-3,
        sigma_hz=args.sigma_hz_arcsec * ARCSEC,
        sigma_el=args.sigma_el_arcsec * ARCSEC,
        architecture=args.architecture,
    )
    if args.vce is None:
        args.vce = not net.has_planes
    if net.has_planes and args.vce:
        raise ValueError(
            "--vce is for target networks; with planes the weights are held fixed (SPEC section "
            "5): run without it (plane points are screened for outliers by --screen, the default)"
        )
    if not net.has_planes and not args.vce:
        refuse_unless("screen_alpha" not in args.given, "--screen-alpha", "--vce (or --planes)")
    _warn_ignored_sigmas(args, net)
    if net.dropped:
        print(
            f"dropped {len(net.dropped)} target(s) seen in one scan only: {', '.join(net.dropped)}"
        )
    parts = [f"{len(net.scans)} scans"]
    if net.has_targets:
        parts.append(f"{len(net.targets)} targets, {net.observations.shape[0]} target observations")
    if net.has_planes:
        parts.append(f"{len(net.planes)} planes, {net.plane_observations.shape[0]} plane points")
    print(f"{net.source}: " + ", ".join(parts))
    return net


def _calibrate(args) -> int:
    """Run ``tlsjax calibrate``: check the options and outputs, read, adjust (or adjust and
    test), print and write; one sequence of steps, each a call."""
    from .._adjustment._config import CalibrationModel
    from .._adjustment._network import network_design_warnings
    from .._model._scanner import Scanner
    from ._progress import Phases

    _check_options(args)
    check_outputs(  # before any work: fails in a second
        args.json,
        args.plots,
        args.report,
        inputs=(
            ("observations", args.observations),
            ("--planes", args.planes),
            ("--scans", args.scans),
        ),
        more=[("--targets-out", args.targets_out), ("--tables", args.tables, TABLE_FILES)],
    )
    args.architecture = file_architecture(args.architecture, args.observations, args.planes)
    scanner = Scanner(architecture=args.architecture, aps=args.aps, unit_length=args.unit_length)
    args.phases = Phases(enabled=not args.quiet)
    args.phases.hold()  # shown once the input is accepted
    net = _read(args)
    args.phases.release()
    model = CalibrationModel(
        scanner,
        datum=args.datum,
        fixed_scan=args.fixed_scan,
        correlation_threshold=args.correlation_threshold,
        ap_priors=_ap_priors(args),
    )
    for note in network_design_warnings(net, model):
        warn(note)
    if args.fixed_scan is not None and args.fixed_scan not in net.scans:
        raise ValueError(
            f"--fixed-scan {args.fixed_scan}: no such scan (scans: {', '.join(net.scans)})"
        )
    t0 = time.perf_counter()
    args.phases.start(_adjusting(net, args))
    extra, res, tested, mask, mdb = _run(args, net, model, scanner)
    args.phases.done(f"adjusted: {res.iterations} iterations in the last adjustment, {res.message}")
    print(f"({time.perf_counter() - t0:.2f} s)")
    withheld = None
    if tested is not None and res.ok and not tested.ok:
        withheld = (
            f"the variance components failed ({tested.vce_result.message}); the adjustment with "
            "the last weights that worked converged, but those weights are not estimated, so its "
            "estimates and sigmas are not a calibration"
        )
    report(res, after_vce=tested is not None and tested.weights_fitted, withheld=withheld)
    extra.update(_report_fields(res, scanner, args, mask, mdb))
    failed = not res.ok or withheld is not None or impossible(res)
    extra.update(_table_fields(res, tested, failed))
    write_outputs(
        res, args.json, args.plots, extra=extra, scanner=scanner, mask=mask, withheld=withheld
    )
    if (
        args.targets_out and failed and res.ok
    ):  # no target estimates of a run that is no calibration
        print(f"--targets-out {args.targets_out}: not written (the run is no calibration)")
    elif args.targets_out:
        write_targets(res, args.targets_out)
    if args.tables:
        _write_tables(res, args.tables, tested, failed)
    if args.report:
        _write_report(res, args.report, extra, scanner, mask, withheld)
    return EXIT_FAILED if failed else EXIT_OK


def impossible(res) -> bool:
    """True when an estimated AP has a magnitude no working instrument has (_plausibility):
    the run is then no calibration (exit 1, JSON ``estimates`` says why)."""
    return any(f.level == "impossible" for f in res.plausibility()[0])


def _run(args, net, model, scanner):
    """Selection, then plane screening, testing (VCE, snooping) or a plain calibration."""
    from .._adjustment._calibrate import calibrate
    from .._adjustment._config import SolverOptions

    solver = SolverOptions(max_iterations=args.max_iterations)
    extra, mask, tested, mdb = {}, None, None, None
    if args.select:
        model, scanner = _select(args, net, model, scanner, extra)
    if net.has_planes and args.screen and not args.snoop:
        res = _screen(net, model, solver, extra)
    elif args.vce or args.snoop or args.screen:
        tested = _test(args, net, model, solver)
        res, mask, mdb = tested.calibration, tested.mask, tested.mdb
        extra.update(tested.json_fields())
    else:
        with warnings.catch_warnings():  # the summary names implausible estimates itself
            warnings.simplefilter("ignore", PlausibilityWarning)
            res = calibrate(net, model, solver)
    if tested is None:
        _missing_terms(net, model, solver, res, extra)
    return extra, res, tested, mask, mdb


def _adjusting(net, args) -> str:
    """The progress line of the adjustment phase: what runs, on how many observations."""
    what = "adjusting"
    if net.has_planes and (args.screen or args.snoop):
        what = "screening the plane points (IGG-III reweighting, one adjustment per round)"
    elif args.vce or args.snoop:
        what = "adjusting and testing (screening, VCE, snooping: one adjustment per step)"
    counts = []
    if net.has_targets:
        counts.append(f"{net.observations.shape[0]} target observations")
    if net.has_planes:
        counts.append(f"{net.plane_observations.shape[0]} plane points")
    return f"{what}: {', '.join(counts)} (compiling on the first run of this shape)"


def read_tables(observations, planes, spacing, phases):
    """The observation and plane tables of ``calibrate``, the plane points thinned to
    ``spacing`` (:func:`tlsjax.thin_planes`; a plane CSV given as the observation file counts
    as the planes), with progress lines; target files are read as they are."""
    from .._clouds._thin import thin_planes
    from .._io._tables import read_observations, read_planes

    if observations is not None:
        phases.start(f"reading {observations}")
        observations = read_observations(observations)
        phases.done(f"read {len(observations)} {observations.kind} observation rows")
        if observations.kind == "plane" and planes is None:
            observations, planes = None, observations
    if planes is not None and not hasattr(planes, "kind"):
        phases.start(f"reading {planes}")
        planes = read_planes(planes)
        phases.done(f"read {len(planes)} plane points")
    if planes is not None and spacing != 0:
        phases.start(f"thinning {len(planes)} plane points to one per {spacing:g} m voxel")
        n = len(planes)
        planes = thin_planes(planes, spacing)
        phases.done(f"kept {len(planes)} of {n} plane points")
        if len(planes) < n:
            print(planes.notes[-1])
    return observations, planes


def file_architecture(given, *paths) -> str:
    """``given``, else the architecture recorded in the first observation CSV that records
    one (files tlsjax writes), else hybrid; a mismatch is refused by ``read_network``."""
    from .._io._tables import recorded_architecture

    if given is not None:
        return given
    for p in paths:
        if p is not None and str(p).lower().endswith(".csv") and os.path.isfile(p):
            arch = recorded_architecture(p)
            if arch is not None:
                print(f"{p}: {arch} scanner (recorded in the file)")
                return arch
    return "hybrid"


def write_targets(res, path):
    """The adjusted targets as CSV (``--targets-out``); none for a failed adjustment."""
    from .._report._tables import targets_csv

    if not res.ok:
        print(f"--targets-out {path}: not written (the adjustment failed: no estimates)")
        return
    if not len(res.targets):
        print(f"--targets-out {path}: not written (no targets in this network)")
        return
    targets_csv(res, path)
    print(f"wrote {path}")


def _select(args, net, model, scanner, extra):
    """Stepwise AP selection on the observations the robust start and screening keep (with
    --screen); the chosen set is then weighted and tested."""
    from .._inference._selection import SelectionOptions, select_aps

    sel = select_aps(
        net,
        model,
        start=args.aps,
        candidates=args.select_candidates,
        options=SelectionOptions(
            alpha=args.select_alpha, max_correlation=args.max_correlation, screening=args.screen
        ),
    )
    print(sel.report())
    print()
    scanner = dataclasses.replace(scanner, aps=tuple(sel.aps))
    finite = lambda x: float(x) if x == x and abs(x) != float("inf") else None
    extra["selection"] = {
        "aps": list(sel.aps),
        "n_fits": sel.n_fits,
        "steps": [
            {"action": st.action, "term": st.term, "score": finite(st.score), "reason": st.reason}
            for st in sel.steps
            if st.action != "try"
        ],
        "n_screened": 0 if sel.screened is None else len(sel.screened.outliers),
    }
    return dataclasses.replace(model, scanner=scanner), scanner


def _missing_terms(net, model, solver, res, extra):
    """Score tests of the terms missing from the model (tj.score_tests), printed and in the
    JSON's ``score_tests``; none for a failed adjustment, several instruments or planes."""
    from .._inference._score import score_tests
    from .._model._scanner import Scanner

    if not (res.ok and isinstance(model.scanner, Scanner)) or net.has_planes:
        return
    tests = score_tests(net, model, res, solver=solver)
    print(tests.summary())
    extra["score_tests"] = tests.as_json()


def _screen(net, model, solver, extra):
    """Outlier screening of the plane points (tj.screen_planes); the final adjustment."""
    from .._inference._robust import screen_planes

    screened = screen_planes(net, model, solver)
    print(screened.summary())
    extra.update(screened.json_fields())
    return screened.calibration


def _test(args, net, model, solver):
    from .._inference._testing import TestingOptions, calibrate_and_test

    tested = calibrate_and_test(
        net,
        model,
        solver,
        TestingOptions(
            vce=args.vce,
            screening=args.screen,
            screening_alpha=args.screen_alpha,
            snooping=args.snoop,
            alpha=args.snoop_alpha,
            bonferroni=args.bonferroni,
            removal=args.snoop_removal,
        ),
    )
    print(tested.summary())
    return tested


def report(res, *, after_vce: bool = False, truth=None, withheld=None):
    """Print the summary and the AP table; a failed adjustment prints no estimates (they would
    look plausible and be wrong), nor does a run whose estimates are ``withheld`` (the reason)."""
    from .._report._text import ap_table, summary

    print(summary(res, after_vce=after_vce))
    if withheld:
        print(f"error: {withheld}")
    print()
    print(ap_table(res, truth=truth, withheld=withheld))


def check_outputs(json_path=None, plots_dir=None, report_path=None, *, inputs=(), more=()):
    """Refuse, before any work, output paths that cannot be written, that are one of the
    ``inputs`` ((label, path)) or that two outputs share (one line naming the path)."""
    from .._io._outputs import check_outputs as check

    check(
        [("--json", json_path), ("--plots", plots_dir, PLOT_FILES), ("--report", report_path)]
        + list(more),
        inputs,
    )


def _report_fields(res, scanner, args, mask, mdb) -> dict:
    """JSON fields for ``tlsjax correct`` (scanner settings) and the report (reliability,
    provenance with the input files' SHA-256)."""
    from .._report._html import provenance, reliability_summary, scanner_settings

    fields = {
        "scanner": scanner_settings(scanner),
        "provenance": provenance([args.observations, args.planes, args.scans]),
    }
    if res.network is not None and res.network.has_targets:
        fields["reliability"] = reliability_summary(res, mdb=mdb, mask=mask)
    return fields


def _table_fields(res, tested, failed: bool) -> dict:
    """The per-observation and per-group tables in the JSON (none for a run that is no
    calibration), and the input file's line beside each removal's row."""
    from .._report._tables import table_json, with_lines

    out = {} if failed else table_json(res, tested)
    if tested is not None and tested.outliers:
        out["outliers"] = with_lines(tested.outliers_json(), res)
    return out


def _write_tables(res, folder, tested, failed: bool):
    from .._report._tables import write_tables

    paths = [] if failed else write_tables(res, folder, tested)
    if paths:
        print(f"wrote {len(paths)} tables into {folder}: {', '.join(map(os.path.basename, paths))}")
    else:
        print(f"--tables {folder}: not written (the run is no calibration: no estimates)")


def _write_report(res, path, extra, scanner, mask, withheld=None):
    import base64
    import tempfile

    from .._report._html import write_html_report
    from .._report._json import result_to_dict, withhold_estimates
    from .._report._plots import plot_residuals

    doc = result_to_dict(res)
    doc.update(extra)
    if withheld:
        withhold_estimates(doc, withheld)
    with tempfile.TemporaryDirectory() as tmp:  # the AP correlations are drawn from the JSON
        png = plot_residuals(res, os.path.join(tmp, "residuals.png"), scanner=scanner, mask=mask)
        with open(png, "rb") as fh:
            plots = {"residuals": base64.b64encode(fh.read()).decode("ascii")}
    write_html_report(doc, path, plots=plots)
    print(f"wrote {path}")


def write_outputs(res, json_path, plots_dir, *, extra=None, scanner=None, mask=None, withheld=None):
    """The result JSON (estimates nulled with the reason when ``withheld``) and the plots."""
    from .._io._json import write_json_file
    from .._report._json import result_to_dict, withhold_estimates
    from .._report._plots import plot_ap_correlations, plot_residuals

    if json_path:
        doc = result_to_dict(res)
        doc.update(extra or {})
        if withheld:
            withhold_estimates(doc, withheld)
        write_json_file(json_path, doc, "--json ")
        print(f"wrote {json_path}")
    if plots_dir:
        a, b = (os.path.join(plots_dir, name) for name in PLOT_FILES)
        plot_residuals(res, a, scanner=scanner, mask=mask)
        plot_ap_correlations(res, b)
        print(f"wrote {a} and {b}")
