"""``tlsjax calibrate``: self-calibration from target and/or plane observation files.

A thin layer over the public API: parse the options, read the files
(:func:`tlsjax.read_network`), build the model and the :class:`tlsjax.CalibrationOptions`, call
:func:`tlsjax.self_calibrate`, print its ``summary()`` and write its ``to_dict()`` and the
other files. Everything it prints and writes of the calibration comes from that one result.
"""

from __future__ import annotations

import argparse
import base64
import hashlib
import os
import shlex
import tempfile

import numpy as np

import tlsjax as tj

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
        default=tj.DEFAULT_PLANE_SPACING,
        metavar="M",
        help="thin the plane points to one per voxel of this side [m] per scan and plane "
        f"(default {tj.DEFAULT_PLANE_SPACING:g}: noise of points closer than about a third of it is "
        "correlated, and the sigmas of all points would be too small; 0 keeps all points)",
    )
    c.add_argument(
        "--from-json",
        metavar="RESULT_JSON",
        help="re-run the calibration a result JSON of tlsjax calibrate records (its input files, "
        "how they were read, the model and every option): give only output options with it; an "
        "input file that changed since is named",
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
        "tlsjax.self_calibrate, then snooping, plane points and targets alike",
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
    c.set_defaults(func=_calibrate, defaults=_parser_defaults(c))
    return c


#: The options that may be given with --from-json: where the files go, and how the run talks.
_RERUN_OPTIONS = ("from_json", "json", "plots", "report", "targets_out", "tables", "quiet")


def _parser_defaults(parser) -> dict:
    return {a.dest: a.default for a in parser._actions if a.dest != "help"}


def _ap_priors(args) -> dict:
    """The AP priors of ``--ap-priors FILE`` and ``--ap-prior`` (SI units)."""
    priors = tj.read_ap_priors(args.ap_priors) if args.ap_priors else {}
    for text in args.ap_prior:
        name, value, sigma = tj.parse_ap_prior(text)
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
#: Radians per arc second.
ARCSEC = np.pi / (180.0 * 3600.0)


def _recorded(args) -> dict:
    """``--from-json``: the settings a result JSON records (``settings``: the inputs and how
    they were read, the model, the options), put in ``args`` as if given; any other option
    given is refused (the run takes its settings from the file), and an input whose SHA-256
    differs from the one recorded is named (the re-run then reproduces nothing)."""
    for dest, default in args.defaults.items():
        if dest not in _RERUN_OPTIONS and getattr(args, dest) != default:
            flag = dest if dest == "observations" else "--" + dest.replace("_", "-")
            raise ValueError(
                f"{flag}: not with --from-json (the run takes its inputs and settings from "
                f"{args.from_json}); give only output options with it"
            )
    doc = tj.read_result_json(args.from_json)
    settings = doc.get("settings") or {}
    inputs = settings.get("inputs") or {}
    if not {"model", "options"} <= set(settings) or not inputs:
        raise ValueError(
            f"{args.from_json}: records no settings to re-run (written by an earlier tlsjax, or "
            "by tj.self_calibrate without with_inputs()); run tlsjax calibrate with the options"
        )
    for key in _INPUTS:
        value = inputs.get(key, getattr(args, key))
        if _DEFAULTS.get(key, object()) != value:  # a default stays "not given"
            setattr(args, key, value)
    version = settings.get("tlsjax_version")
    if version != tj.__version__:
        warn(f"{args.from_json} was made by tlsjax {version}; this is {tj.__version__}")
    for f in (doc.get("provenance") or {}).get("inputs", []):
        if not os.path.isfile(f["path"]) or _sha256(f["path"]) != f["sha256"]:
            warn(
                f"{f['path']} is not the file {args.from_json} was made from (its SHA-256 "
                "differs or it is gone): the re-run does not reproduce that result"
            )
    return settings


#: What ``settings.inputs`` records of how the network was read (``--from-json`` reads it back).
_INPUTS = (
    "observations",
    "planes",
    "scans",
    "plane_spacing",
    "drop_single_targets",
    "sigma_range_mm",
    "sigma_hz_arcsec",
    "sigma_el_arcsec",
    "architecture",
)


def _sha256(path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while chunk := fh.read(1 << 20):
            h.update(chunk)
    return h.hexdigest()


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


def _warn_ignored_sigmas(args, tables) -> None:
    """A --sigma-* option given while every row of the files has its own sigma of that group
    changes nothing: say so (the file's sigmas are used)."""
    tables = [t for t in tables if t is not None and str(t.source).lower().endswith(".csv")]
    for col, (option, unit) in enumerate(
        (("sigma_range_mm", "mm"), ("sigma_hz_arcsec", '"'), ("sigma_el_arcsec", '"'))
    ):
        if option not in args.given or not tables:
            continue
        if all(t.sigmas is not None and not np.isnan(t.sigmas[:, col]).any() for t in tables):
            flag = "--" + option.replace("_", "-")
            warn(
                f"{flag} {getattr(args, option):g} {unit} is ignored: every row of "
                f"{', '.join(t.source for t in tables)} has its own {('range', 'hz', 'el')[col]} sigma"
            )


def _read(args):
    """The network of the files, with what reading decided printed (single targets dropped,
    the architecture a file records, the counts)."""
    observations, planes = read_tables(
        args.observations, args.planes, args.plane_spacing, args.phases
    )
    args.architecture = _architecture(args.architecture, observations, planes)
    net = tj.read_network(
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
    _warn_ignored_sigmas(args, (observations, planes))
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


def _architecture(given, *tables) -> str:
    """``given``, else the architecture recorded in the first table whose file records one
    (files tlsjax writes), else hybrid; a mismatch is refused by ``read_network``."""
    if given is not None:
        return given
    for t in tables:
        if t is not None and t.architecture is not None:
            print(f"{t.source}: {t.architecture} scanner (recorded in the file)")
            return t.architecture
    return "hybrid"


def _model(args, net) -> tj.CalibrationModel:
    if args.fixed_scan is not None and args.fixed_scan not in net.scans:
        raise ValueError(
            f"--fixed-scan {args.fixed_scan}: no such scan (scans: {', '.join(net.scans)})"
        )
    return tj.CalibrationModel(
        tj.Scanner(architecture=args.architecture, aps=args.aps, unit_length=args.unit_length),
        datum=args.datum,
        fixed_scan=args.fixed_scan,
        correlation_threshold=args.correlation_threshold,
        ap_priors=_ap_priors(args),
    )


def _options(args) -> tj.CalibrationOptions:
    """The :class:`tlsjax.CalibrationOptions` of the command's options (one concern each)."""
    return tj.CalibrationOptions(
        solver=tj.SolverOptions(max_iterations=args.max_iterations),
        screening=tj.ScreeningOptions(family_level=args.screen_alpha) if args.screen else None,
        plane_screening=tj.PlaneScreeningOptions() if args.screen else None,
        vce=tj.VCEOptions() if args.vce else None,
        snooping=(
            tj.SnoopingOptions(
                w_test_level=args.snoop_alpha,
                bonferroni=args.bonferroni,
                removal=args.snoop_removal,
            )
            if args.snoop
            else None
        ),
        selection=(
            tj.SelectionOptions(
                candidates=args.select_candidates,
                test_level=args.select_alpha,
                max_correlation=args.max_correlation,
            )
            if args.select
            else None
        ),
    )


def _inputs(args, argv) -> dict:
    """How the network was read, recorded in the result (``settings.inputs`` of the JSON), so
    that ``--from-json`` reads it again the same way, and the command line."""
    inputs = {key: getattr(args, key) for key in _INPUTS}
    return {**inputs, "command": " ".join(shlex.quote(a) for a in argv)}


def _calibrate(args) -> int:
    """Run ``tlsjax calibrate``: check the options and outputs, read, build the model and the
    options, self-calibrate, print and write; one sequence of steps, each a call."""
    from ._progress import Phases

    recorded = _recorded(args) if args.from_json else None
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
    args.phases = Phases(enabled=not args.quiet)
    args.phases.hold()  # shown once the input is accepted
    net = _read(args)
    args.phases.release()
    if recorded is None:
        model, options = _model(args, net), _options(args)
    else:
        model = tj.CalibrationModel.from_dict(recorded["model"])
        options = tj.CalibrationOptions.from_dict(recorded["options"])
    args.phases.start(_adjusting(net, options))
    result = tj.self_calibrate(net, model, options)
    result = result.with_inputs(**_inputs(args, ["tlsjax", *args.argv]))
    args.phases.done(
        f"adjusted: {result.calibration.iterations} iterations in the last adjustment, "
        f"{result.calibration.message}"
    )
    for note in result.design_warnings:
        warn(note)
    print(result.summary())
    _write(result, args)
    return EXIT_OK if result.ok else EXIT_FAILED


def _adjusting(net, options) -> str:
    """The progress line of the adjustment phase: what runs, on how many observations."""
    what = "adjusting"
    if net.has_planes and options.plane_screening is not None and options.snooping is None:
        what = "screening the plane points (IGG-III reweighting, one adjustment per round)"
    elif options.vce is not None or options.snooping is not None:
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
    if observations is not None:
        phases.start(f"reading {observations}")
        observations = tj.read_observations(observations)
        phases.done(f"read {len(observations)} {observations.kind} observation rows")
        if observations.kind == "plane" and planes is None:
            observations, planes = None, observations
    if planes is not None and not hasattr(planes, "kind"):
        phases.start(f"reading {planes}")
        planes = tj.read_planes(planes)
        phases.done(f"read {len(planes)} plane points")
    if planes is not None and spacing != 0:
        phases.start(f"thinning {len(planes)} plane points to one per {spacing:g} m voxel")
        n = len(planes)
        planes = tj.thin_planes(planes, spacing)
        phases.done(f"kept {len(planes)} of {n} plane points")
        if len(planes) < n:
            print(planes.notes[-1])
    return observations, planes


def _write(result, args) -> None:
    """The files of the run: the JSON (``result.to_dict()``), the plots, the adjusted targets,
    the tables and the HTML report; the targets and tables only of a run that is a
    calibration."""
    res = result.calibration
    if args.json:
        tj.write_json(result, args.json)
        print(f"wrote {args.json}")
    if args.plots:
        a, b = (os.path.join(args.plots, name) for name in PLOT_FILES)
        tj.plot_residuals(res, a, scanner=result.model.scanner, mask=result.mask)
        tj.plot_ap_correlations(res, b)
        print(f"wrote {a} and {b}")
    if args.targets_out:
        _write_targets(result, args.targets_out)
    if args.tables:
        paths = tj.write_tables(res, args.tables, result) if result.ok else []
        if paths:
            names = ", ".join(map(os.path.basename, paths))
            print(f"wrote {len(paths)} tables into {args.tables}: {names}")
        else:
            print(f"--tables {args.tables}: not written (the run is no calibration: no estimates)")
    if args.report:
        _write_report(result, args.report)


def _write_targets(result, path) -> None:
    """The adjusted targets as CSV (``--targets-out``); none of a run that is no calibration."""
    res = result.calibration
    if not res.ok:
        print(f"--targets-out {path}: not written (the adjustment failed: no estimates)")
    elif not result.ok:
        print(f"--targets-out {path}: not written (the run is no calibration)")
    elif not len(res.targets):
        print(f"--targets-out {path}: not written (no targets in this network)")
    else:
        tj.write_adjusted_targets(res, path)
        print(f"wrote {path}")


def check_outputs(json_path=None, plots_dir=None, report_path=None, *, inputs=(), more=()):
    """Refuse, before any work, output paths that cannot be written, that are one of the
    ``inputs`` ((label, path)) or that two outputs share (one line naming the path)."""
    tj.check_outputs(
        [("--json", json_path), ("--plots", plots_dir, PLOT_FILES), ("--report", report_path)]
        + list(more),
        inputs,
    )


def _write_report(result, path) -> None:
    """The HTML report of ``result.to_dict()``, with the residual plot embedded."""
    with tempfile.TemporaryDirectory() as tmp:  # the AP correlations are drawn from the JSON
        png = tj.plot_residuals(
            result.calibration,
            os.path.join(tmp, "residuals.png"),
            scanner=result.model.scanner,
            mask=result.mask,
        )
        with open(png, "rb") as fh:
            plots = {"residuals": base64.b64encode(fh.read()).decode("ascii")}
    tj.write_html_report(result.to_dict(), path, plots=plots)
    print(f"wrote {path}")
