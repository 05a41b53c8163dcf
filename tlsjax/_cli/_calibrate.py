"""``tlsjax calibrate``: self-calibration from target and/or plane observation files."""

from __future__ import annotations

import argparse
import dataclasses
import os
import time

from .._units import ARCSEC
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
    c.add_argument("--scans", help="scans CSV with levelling observations")
    c.add_argument(
        "--aps",
        default="physical",
        help='APs to estimate, e.g. "A0 B6 B7 C0" or a preset (default: physical)',
    )
    c.add_argument("--datum", choices=("auto", "inner", "fixed-scan"), default="auto")
    c.add_argument("--fixed-scan", help="scan held fixed with --datum fixed-scan")
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
        type=float,
        default=0.5,
        help="a priori range sigma [mm] where the file has none",
    )
    c.add_argument(
        "--sigma-hz-arcsec",
        type=float,
        default=20.0,
        help='a priori hz sigma ["] where the file has none',
    )
    c.add_argument(
        "--sigma-el-arcsec",
        type=float,
        default=20.0,
        help='a priori el sigma ["] where the file has none',
    )
    c.add_argument("--max-iterations", type=int, default=30)
    c.add_argument(
        "--correlation-threshold",
        type=float,
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
        help="with VCE, remove gross errors before it (robust group scales, family-wise level "
        "--screen-alpha); default on: VCE on data with blunders inflates the factors until the "
        "blunders look normal. With planes: screen the plane points (IGG-III reweighting, "
        "family-wise removal, then the a priori weights)",
    )
    c.add_argument(
        "--screen-alpha",
        type=float,
        default=0.001,
        help="family-wise significance level of the screening before VCE (default 0.001)",
    )
    c.add_argument(
        "--snoop",
        action="store_true",
        help="Baarda data snooping: remove rejected observations, re-adjust",
    )
    c.add_argument(
        "--snoop-alpha",
        type=float,
        default=0.001,
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
        default="observation",
        help="remove one scalar observation or all three of the target in that scan",
    )
    c.add_argument(
        "--select",
        action="store_true",
        help="stepwise AP selection starting from --aps, adding from --select-candidates",
    )
    c.add_argument(
        "--select-candidates", default="chow2013-noscale", help="candidate terms (names or presets)"
    )
    c.add_argument(
        "--select-alpha",
        type=float,
        default=0.01,
        help="significance level of the selection t-tests",
    )
    c.add_argument(
        "--max-correlation",
        type=float,
        default=0.9,
        help="a candidate more correlated than this with the model is not added (default 0.9)",
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


def _calibrate(args) -> int:
    """Run ``tlsjax calibrate``: read, adjust (or adjust and test), print and write. A little over
    60 lines: one sequence of steps of the command, each a call."""
    from .._adjustment._calibrate import calibrate
    from .._adjustment._config import CalibrationModel, SolverOptions
    from .._io._json import check_output_dir, check_output_file
    from .._io._tables import read_network
    from .._model._scanner import Scanner

    if args.observations is None and args.planes is None:
        raise ValueError("give an observation CSV, --planes FILE, or both")
    check_outputs(args.json, args.plots, args.report)  # before any work: fails in a second
    check_output_file(args.targets_out, "--targets-out ")
    check_output_dir(args.tables, "--tables ")
    args.architecture = file_architecture(args.architecture, args.observations, args.planes)
    scanner = Scanner(architecture=args.architecture, aps=args.aps, unit_length=args.unit_length)
    net = read_network(
        args.observations,
        args.scans,
        planes=args.planes,
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
    if net.has_planes and net.has_targets and args.snoop:
        raise ValueError(
            "--snoop of a combined network is not supported: the plane points are screened "
            "(--screen); snoop the targets in a target-only calibration"
        )
    if net.dropped:
        print(
            f"dropped {len(net.dropped)} target(s) seen in one scan only: {', '.join(net.dropped)}"
        )
    model = CalibrationModel(
        scanner,
        datum=args.datum,
        fixed_scan=args.fixed_scan,
        correlation_threshold=args.correlation_threshold,
    )
    solver = SolverOptions(max_iterations=args.max_iterations)
    t0 = time.perf_counter()
    parts = [f"{len(net.scans)} scans"]
    if net.has_targets:
        parts.append(f"{len(net.targets)} targets, {net.observations.shape[0]} target observations")
    if net.has_planes:
        parts.append(f"{len(net.planes)} planes, {net.plane_observations.shape[0]} plane points")
    print(f"{net.source}: " + ", ".join(parts))
    extra, mask, tested, mdb = {}, None, None, None
    if args.select:
        model, scanner = _select(args, net, model, scanner, extra)
    if net.has_planes and (args.screen or args.snoop):
        res = _screen(net, model, solver, extra)
    elif args.vce or args.snoop:
        tested = _test(args, net, model, solver)
        res, mask, mdb = tested.calibration, tested.mask, tested.mdb
        extra.update(tested.json_fields())
    else:
        res = calibrate(net, model, solver)
    print(f"({time.perf_counter() - t0:.2f} s)")
    report(res, after_vce=tested is not None and tested.weights_fitted)
    extra.update(_report_fields(res, scanner, args, mask, mdb))
    extra.update(_table_fields(res, tested))
    if extra.get("outliers"):
        from .._report._tables import with_lines

        extra["outliers"] = with_lines(extra["outliers"], res)
    write_outputs(res, args.json, args.plots, extra=extra, scanner=scanner, mask=mask)
    if args.targets_out:
        write_targets(res, args.targets_out)
    if args.tables:
        _write_tables(res, args.tables, tested)
    if args.report:
        _write_report(res, args.report, extra, scanner, mask)
    ok = res.ok and (tested is None or tested.ok)
    return EXIT_OK if ok else EXIT_FAILED


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
    """Stepwise AP selection on the a priori weights; the chosen set is then weighted and
    tested."""
    from .._inference._selection import SelectionOptions, select_aps

    sel = select_aps(
        net,
        model,
        start=args.aps,
        candidates=args.select_candidates,
        options=SelectionOptions(alpha=args.select_alpha, max_correlation=args.max_correlation),
    )
    print(sel.report())
    print()
    scanner = dataclasses.replace(scanner, aps=tuple(sel.aps))
    extra["selection"] = {"aps": list(sel.aps), "n_fits": sel.n_fits}
    return dataclasses.replace(model, scanner=scanner), scanner


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


def report(res, *, after_vce: bool = False, truth=None):
    """Print the summary and the AP table; a failed adjustment prints no estimates (they would
    look plausible and be wrong)."""
    from .._report._text import ap_table, summary

    print(summary(res, after_vce=after_vce))
    print()
    print(ap_table(res, truth=truth))


def check_outputs(json_path=None, plots_dir=None, report_path=None):
    """Refuse unwritable output paths before any work (one line naming the path)."""
    from .._io._json import check_output_dir, check_output_file

    check_output_file(json_path, "--json ")
    check_output_dir(plots_dir, "--plots ")
    check_output_file(report_path, "--report ")


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


def _table_fields(res, tested) -> dict:
    """The per-observation and per-group tables in the JSON (none for a failed adjustment)."""
    from .._report._tables import table_json

    return table_json(res, tested) if res.ok else {}


def _write_tables(res, folder, tested):
    from .._report._tables import write_tables

    paths = write_tables(res, folder, tested)
    if paths:
        print(f"wrote {len(paths)} tables into {folder}: {', '.join(map(os.path.basename, paths))}")
    else:
        print(f"--tables {folder}: not written (the adjustment failed: no estimates)")


def _write_report(res, path, extra, scanner, mask):
    import base64
    import tempfile

    from .._report._html import write_html_report
    from .._report._json import result_to_dict
    from .._report._plots import plot_residuals

    doc = result_to_dict(res)
    doc.update(extra)
    with tempfile.TemporaryDirectory() as tmp:  # the AP correlations are drawn from the JSON
        png = plot_residuals(res, os.path.join(tmp, "residuals.png"), scanner=scanner, mask=mask)
        with open(png, "rb") as fh:
            plots = {"residuals": base64.b64encode(fh.read()).decode("ascii")}
    write_html_report(doc, path, plots=plots)
    print(f"wrote {path}")


def write_outputs(res, json_path, plots_dir, *, extra=None, scanner=None, mask=None):
    from .._report._json import write_json
    from .._report._plots import plot_ap_correlations, plot_residuals

    if json_path:
        write_json(res, json_path, extra=extra)
        print(f"wrote {json_path}")
    if plots_dir:
        try:
            a = plot_residuals(
                res, os.path.join(plots_dir, "residuals.png"), scanner=scanner, mask=mask
            )
            b = plot_ap_correlations(res, os.path.join(plots_dir, "ap_correlations.png"))
        except OSError as err:
            raise ValueError(
                f"--plots {plots_dir}: cannot be written ({err.strerror or err})"
            ) from None
        print(f"wrote {a} and {b}")
