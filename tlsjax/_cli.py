"""Command line: ``tlsjax demo | simulate | calibrate | extract-planes | montecarlo | compare``.

Every subcommand is a thin layer over the public API. Bad input is reported as one line
naming the file, line, scan, target or parameter (exit code 2); a calibration that fails
(non-convergence, rank defect) exits with 1 after writing what it has.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import sys
import time

import numpy as np

EXIT_OK, EXIT_FAILED, EXIT_BAD_INPUT = 0, 1, 2


def _enable_compilation_cache():
    # Compiling the adjustment costs seconds; the CLI is run again and again on the same
    # shapes, so JAX's persistent cache pays (PERFORMANCE.md).
    import jax

    path = os.environ.get("TLSJAX_CACHE_DIR", os.path.join(os.path.expanduser("~"), ".cache", "tlsjax", "jax"))
    if path.lower() in ("", "0", "off", "none"):
        return
    try:
        os.makedirs(path, exist_ok=True)
        jax.config.update("jax_compilation_cache_dir", path)
    except OSError:
        pass


def _scanner_args(p):
    p.add_argument("--architecture", choices=("hybrid", "panoramic"), default="hybrid",
                   help="scanner architecture (default: hybrid)")
    p.add_argument("--unit-length", type=float, default=1.2, metavar="M",
                   help="unit length U [m] of the cyclic range terms A3/A4 (default 1.2)")


def build_parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(prog="tlsjax", description="Terrestrial laser scanner self-calibration in JAX.")
    sub = ap.add_subparsers(dest="command", required=True)

    d = sub.add_parser("demo", help="simulate the Chow et al. 2013 room and self-calibrate it (hybrid, tilted scans)")
    d.add_argument("--out", default="out/demo", help="output folder for report.json, plots and the simulated data")
    d.add_argument("--aps", default="chow2013-noscale",
                   help="APs present in the data and estimated (default: chow2013-noscale, 23 terms)")
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--levelled", action="store_true", help="levelled scans only (default: two scans tilted by +-45 deg)")
    _scanner_args(d)

    s = sub.add_parser("simulate", help="simulate a calibration room and write the observation CSVs")
    s.add_argument("--out", required=True, help="target observation CSV to write")
    s.add_argument("--scans-out", help="scans CSV with the levelling observations (default: <out>_scans.csv)")
    s.add_argument("--truth", help="JSON with the true APs, targets and scan poses")
    s.add_argument("--room", default="14x11x3", help="room L x W x H [m] (default 14x11x3)")
    s.add_argument("--targets", type=int, default=120, help="number of targets (default 120)")
    s.add_argument("--aps", default="A0 B6 B7 C0", help="APs present in the data (names or presets)")
    s.add_argument("--seed", type=int, default=0)
    s.add_argument("--levelled", action="store_true", help="levelled scans only (default: tilted)")
    s.add_argument("--no-noise", action="store_true", help="noiseless observations")
    s.add_argument("--scale-bars", type=int, default=0, help=argparse.SUPPRESS)
    s.add_argument("--length-unit", default="m", choices=("m", "mm"))
    s.add_argument("--angle-unit", default="deg", choices=("rad", "deg", "gon", "arcsec"))
    _scanner_args(s)

    c = sub.add_parser("calibrate", help="self-calibrate from target and/or plane observations")
    c.add_argument("observations", nargs="?",
                   help="target or plane observation CSV (SPEC section 11; units from the header suffixes)")
    c.add_argument("--planes", help="plane observations: a plane CSV or the .npz of `tlsjax extract-planes`; "
                                    "alone (plane-based) or with a target CSV (combined network)")
    c.add_argument("--scans", help="scans CSV with levelling observations")
    c.add_argument("--aps", default="physical", help='APs to estimate, e.g. "A0 B6 B7 C0" or a preset (default: physical)')
    c.add_argument("--datum", choices=("auto", "inner", "fixed-scan"), default="auto")
    c.add_argument("--fixed-scan", help="scan held fixed with --datum fixed-scan")
    c.add_argument("--json", help="write the result JSON here")
    c.add_argument("--plots", help="write residual and correlation plots into this folder")
    c.add_argument("--drop-single-targets", action="store_true", help="drop targets seen in one scan only (reported)")
    c.add_argument("--sigma-range-mm", type=float, default=0.5, help="a priori range sigma [mm] where the file has none")
    c.add_argument("--sigma-hz-arcsec", type=float, default=20.0, help='a priori hz sigma ["] where the file has none')
    c.add_argument("--sigma-el-arcsec", type=float, default=20.0, help='a priori el sigma ["] where the file has none')
    c.add_argument("--max-iterations", type=int, default=30)
    c.add_argument("--correlation-threshold", type=float, default=0.99,
                   help="flag APs whose max |correlation| exceeds this (default 0.99)")
    c.add_argument("--vce", action=argparse.BooleanOptionalAction, default=None,
                   help="variance component estimation per group (range, hz, el, levelling); default on for "
                        "target networks, off with planes (SPEC section 5: the near-zero angular residuals of "
                        "plane points bias it)")
    c.add_argument("--snoop", action="store_true", help="Baarda data snooping: remove rejected observations, re-adjust")
    c.add_argument("--snoop-alpha", type=float, default=0.001,
                   help="significance level of each w-test (default 0.001: critical value 3.29)")
    c.add_argument("--bonferroni", action="store_true",
                   help="divide --snoop-alpha by the number of tests (family-wise level; no clean observation "
                        "removed with probability 1 - alpha)")
    c.add_argument("--snoop-removal", choices=("observation", "target"), default="observation",
                   help="remove one scalar observation or all three of the target in that scan")
    c.add_argument("--select", action="store_true",
                   help="stepwise AP selection starting from --aps, adding from --select-candidates")
    c.add_argument("--select-candidates", default="chow2013-noscale", help="candidate terms (names or presets)")
    c.add_argument("--select-alpha", type=float, default=0.01, help="significance level of the selection t-tests")
    c.add_argument("--max-correlation", type=float, default=0.9,
                   help="a candidate more correlated than this with the model is not added (default 0.9)")
    _scanner_args(c)

    d.set_defaults(func=_demo)
    s.set_defaults(func=_simulate)
    c.set_defaults(func=_calibrate)
    # Subcommands that live with their library code register themselves (func set there).
    from ._compat import add_compare_parser
    from ._extract import add_extract_parser
    from ._montecarlo import add_montecarlo_parser

    add_extract_parser(sub)
    add_montecarlo_parser(sub)
    add_compare_parser(sub)
    return ap


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    _enable_compilation_cache()
    try:
        return args.func(args)
    except ValueError as exc:
        print(f"tlsjax {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except FileNotFoundError as exc:
        print(f"tlsjax {args.command}: error: {exc.filename}: no such file", file=sys.stderr)
        return EXIT_BAD_INPUT
    except ImportError as exc:
        # Optional dependencies (open3d, pye57) are named in the message.
        print(f"tlsjax {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT


def _write_simulation(sim, obs_path, scans_path, truth_path=None, length_unit="m", angle_unit="deg"):
    from ._io import levelling_of_network, table_from_network, write_observations, write_scans

    for p in (obs_path, scans_path, truth_path):
        if p:
            os.makedirs(os.path.dirname(os.path.abspath(p)), exist_ok=True)
    write_observations(obs_path, table_from_network(sim.network), length_unit=length_unit, angle_unit=angle_unit)
    write_scans(scans_path, levelling_of_network(sim.network))
    if truth_path:
        net = sim.network
        with open(truth_path, "w", encoding="utf-8") as fh:
            json.dump({
                "units": "SI: metres, radians",
                "architecture": sim.scanner.architecture,
                "aps": {k: float(v) for k, v in sim.true_aps.items()},
                "targets": {t: sim.true_targets[i].tolist() for i, t in enumerate(net.targets)},
                "eops": {s: sim.true_eops[j].tolist() for j, s in enumerate(net.scans)},
            }, fh, indent=2)


def _simulate(args) -> int:
    from ._simulate import Room, simulate

    if args.scale_bars:
        raise ValueError("--scale-bars: the target CSV contract has no scale-bar columns yet; use the Python API")
    room = Room.parse(args.room, n_targets=args.targets)
    sim = simulate(room, architecture=args.architecture, tilted=not args.levelled, aps=args.aps, seed=args.seed,
                   noise=not args.no_noise, unit_length=args.unit_length)
    scans_path = args.scans_out or os.path.splitext(args.out)[0] + "_scans.csv"
    _write_simulation(sim, args.out, scans_path, args.truth, args.length_unit, args.angle_unit)
    net = sim.network
    print(f"wrote {args.out} ({net.observations.shape[0]} target observations, {len(net.scans)} scans, "
          f"{len(net.targets)} targets) and {scans_path}" + (f" and {args.truth}" if args.truth else ""))
    return EXIT_OK


def _calibrate(args) -> int:
    from ._adjust import CalibrationModel, SolverOptions, calibrate
    from ._io import read_network
    from ._models import Scanner
    from ._report import ap_table, summary

    ARC = np.pi / 648000.0
    if args.observations is None and args.planes is None:
        raise ValueError("give an observation CSV, --planes FILE, or both")
    net = read_network(args.observations, args.scans, planes=args.planes, drop_single_targets=args.drop_single_targets,
                       sigma_range=args.sigma_range_mm * 1e-3, sigma_hz=args.sigma_hz_arcsec * ARC,
                       sigma_el=args.sigma_el_arcsec * ARC)
    if args.vce is None:
        args.vce = not net.has_planes
    if net.has_planes and (args.vce or args.snoop):
        raise ValueError("--vce and --snoop are for target networks; with planes the weights are held fixed "
                         "(SPEC section 5): run without them")
    if net.dropped:
        print(f"dropped {len(net.dropped)} target(s) seen in one scan only: {', '.join(net.dropped)}")
    scanner = Scanner(architecture=args.architecture, aps=args.aps, unit_length=args.unit_length)
    model = CalibrationModel(scanner, datum=args.datum, fixed_scan=args.fixed_scan,
                             correlation_threshold=args.correlation_threshold)
    solver = SolverOptions(max_iterations=args.max_iterations)
    t0 = time.perf_counter()
    parts = [f"{len(net.scans)} scans"]
    if net.has_targets:
        parts.append(f"{len(net.targets)} targets, {net.observations.shape[0]} target observations")
    if net.has_planes:
        parts.append(f"{len(net.planes)} planes, {net.plane_observations.shape[0]} plane points")
    print(f"{net.source}: " + ", ".join(parts))
    extra, mask = {}, None
    if args.select:
        from ._selection import SelectionOptions, select_aps

        # Selection runs on the a priori weights; the chosen set is then weighted and tested.
        sel = select_aps(net, model, start=args.aps, candidates=args.select_candidates,
                         options=SelectionOptions(alpha=args.select_alpha, max_correlation=args.max_correlation))
        print(sel.report())
        print()
        scanner = dataclasses.replace(scanner, aps=tuple(sel.aps))
        model = dataclasses.replace(model, scanner=scanner)
        extra["selection"] = {"aps": list(sel.aps), "n_fits": sel.n_fits}
    if args.vce or args.snoop:
        from ._statistics import TestingOptions, calibrate_and_test

        tested = calibrate_and_test(net, model, solver, TestingOptions(
            vce=args.vce, snooping=args.snoop, alpha=args.snoop_alpha, bonferroni=args.bonferroni,
            removal=args.snoop_removal))
        res, mask = tested.calibration, tested.mask
        extra.update(tested.json_fields())
        print(tested.summary())
    else:
        res = calibrate(net, model, solver)
    print(f"({time.perf_counter() - t0:.2f} s)")
    print(summary(res))
    print()
    print(ap_table(res))
    _write_outputs(res, args.json, args.plots, extra=extra, scanner=scanner, mask=mask)
    return EXIT_OK if res.ok else EXIT_FAILED


def _write_outputs(res, json_path, plots_dir, *, extra=None, scanner=None, mask=None):
    from ._plots import plot_ap_correlations, plot_residuals
    from ._report import write_json

    if json_path:
        write_json(res, json_path, extra=extra)
        print(f"wrote {json_path}")
    if plots_dir:
        a = plot_residuals(res, os.path.join(plots_dir, "residuals.png"), scanner=scanner, mask=mask)
        b = plot_ap_correlations(res, os.path.join(plots_dir, "ap_correlations.png"))
        print(f"wrote {a} and {b}")


def _demo(args) -> int:
    from ._adjust import CalibrationModel, calibrate
    from ._report import ap_table, summary
    from ._simulate import simulate

    t0 = time.perf_counter()
    sim = simulate(architecture=args.architecture, tilted=not args.levelled, aps=args.aps, seed=args.seed,
                   unit_length=args.unit_length)
    net = sim.network
    design = "levelled" if args.levelled else "tilted (two scans rolled by -45 and +45 deg)"
    print(f"Simulated Chow et al. (2013) room 14 x 11 x 3 m: {len(net.targets)} targets, {len(net.scans)} scans, "
          f"{args.architecture} scanner, {design}, seed {args.seed}; noise 0.5 mm range, 20\" angles.")
    res = calibrate(net, CalibrationModel(sim.scanner))
    print(f"self-calibration: {time.perf_counter() - t0:.1f} s including compilation")
    print(summary(res))
    print()
    print(ap_table(res, truth=sim.true_aps))
    os.makedirs(args.out, exist_ok=True)
    _write_simulation(sim, os.path.join(args.out, "observations.csv"), os.path.join(args.out, "scans.csv"),
                      os.path.join(args.out, "truth.json"))
    _write_outputs(res, os.path.join(args.out, "report.json"), args.out, scanner=sim.scanner)
    print(f"simulated data in {args.out}/observations.csv and scans.csv; rerun with "
          f"`tlsjax calibrate {args.out}/observations.csv --scans {args.out}/scans.csv --aps {args.aps}`")
    return EXIT_OK if res.ok else EXIT_FAILED


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
