"""``tlsjax demo`` and ``tlsjax simulate``: the simulated Chow et al. (2013) room."""

from __future__ import annotations

import argparse
import os
import time

from .._units import ARCSEC
from ._calibrate import PLOT_FILES, check_outputs
from ._checks import non_negative_int, positive_int
from ._common import EXIT_FAILED, EXIT_OK, scanner_args

#: The files demo writes into --out.
_DEMO_FILES = (
    "report.json",
    "residuals.png",
    "ap_correlations.png",
    "observations.csv",
    "scans.csv",
    "truth.json",
)


def add_demo_parser(sub):
    d = sub.add_parser(
        "demo",
        help="simulate the Chow et al. 2013 room and self-calibrate it (hybrid, tilted scans)",
    )
    d.add_argument(
        "--out",
        default="out/demo",
        help="output folder for report.json, plots and the simulated data",
    )
    d.add_argument(
        "--aps",
        default="chow2013-noscale",
        help="APs present in the data and estimated (default: chow2013-noscale, 23 terms)",
    )
    d.add_argument("--seed", type=non_negative_int, default=0)
    d.add_argument(
        "--levelled",
        action="store_true",
        help="levelled scans only (default: two scans tilted by +-45 deg)",
    )
    scanner_args(d)
    d.set_defaults(func=_demo)
    return d


def add_simulate_parser(sub):
    s = sub.add_parser(
        "simulate", help="simulate a calibration room and write the observation CSVs"
    )
    s.add_argument("--out", required=True, help="target observation CSV to write")
    s.add_argument(
        "--scans-out", help="scans CSV with the levelling observations (default: <out>_scans.csv)"
    )
    s.add_argument("--truth", help="JSON with the true APs, targets and scan poses")
    s.add_argument("--room", default="14x11x3", help="room L x W x H [m] (default 14x11x3)")
    s.add_argument(
        "--targets", type=positive_int, default=120, help="number of targets (default 120)"
    )
    s.add_argument(
        "--aps", default="A0 B6 B7 C0", help="APs present in the data (names or presets)"
    )
    s.add_argument("--seed", type=non_negative_int, default=0)
    s.add_argument("--levelled", action="store_true", help="levelled scans only (default: tilted)")
    s.add_argument("--no-noise", action="store_true", help="noiseless observations")
    s.add_argument(
        "--sigma-tilt-arcsec",
        type=float,
        help="tilted scans carry a tilt sensor's readings (omega, phi) with this sigma [\"] "
        "(eq. 7 of Chow et al. 2013; written to the scans CSV)",
    )
    s.add_argument(
        "--sigma-heading-arcsec",
        type=float,
        help='every scan carries an observed kappa (a known heading) with this sigma ["]',
    )
    s.add_argument("--scale-bars", type=int, default=0, help=argparse.SUPPRESS)
    s.add_argument("--length-unit", default="m", choices=("m", "mm"))
    s.add_argument("--angle-unit", default="deg", choices=("rad", "deg", "gon", "arcsec"))
    scanner_args(s)
    s.set_defaults(func=_simulate)
    return s


def _write_simulation(
    sim, obs_path, scans_path, truth_path=None, length_unit="m", angle_unit="deg"
):
    from .._io._json import write_json_file
    from .._io._tables import write_network

    write_network(
        obs_path,
        sim.network,
        scans_path=scans_path,
        architecture=sim.scanner.architecture,
        length_unit=length_unit,
        angle_unit=angle_unit,
    )
    if truth_path:
        from .._adjustment._config import scanner_settings

        net = sim.network
        write_json_file(
            truth_path,
            {
                "units": "SI: metres, radians",
                "architecture": sim.scanner.architecture,
                "scanner": scanner_settings(sim.scanner),
                "aps": {k: float(v) for k, v in sim.true_aps.items()},
                "targets": {t: sim.true_targets[i].tolist() for i, t in enumerate(net.targets)},
                "eops": {s: sim.true_eops[j].tolist() for j, s in enumerate(net.scans)},
            },
            "--truth ",
        )


def _simulate(args) -> int:
    from .._io._outputs import check_outputs
    from .._simulation._room import Room, simulate

    if args.scale_bars:
        raise ValueError(
            "--scale-bars: the target CSV contract has no scale-bar columns yet; use the Python API"
        )
    scans_path = args.scans_out or os.path.splitext(args.out)[0] + "_scans.csv"
    check_outputs([("--out", args.out), ("--scans-out", scans_path), ("--truth", args.truth)])
    room = Room.parse(args.room, n_targets=args.targets)
    sim = simulate(
        room,
        architecture=args.architecture,
        tilted=not args.levelled,
        aps=args.aps,
        seed=args.seed,
        noise=not args.no_noise,
        unit_length=args.unit_length,
        sigma_tilt=None if args.sigma_tilt_arcsec is None else args.sigma_tilt_arcsec * ARCSEC,
        sigma_heading=(
            None if args.sigma_heading_arcsec is None else args.sigma_heading_arcsec * ARCSEC
        ),
    )
    _write_simulation(sim, args.out, scans_path, args.truth, args.length_unit, args.angle_unit)
    net = sim.network
    print(
        f"wrote {args.out} ({net.observations.shape[0]} target observations, {len(net.scans)} scans, "
        f"{len(net.targets)} targets) and {scans_path}"
        + (f" and {args.truth}" if args.truth else "")
    )
    return EXIT_OK


def _demo(args) -> int:
    from .._adjustment._calibrate import calibrate
    from .._adjustment._config import CalibrationModel
    from .._simulation._room import simulate

    check_outputs(more=[("--out", args.out, _DEMO_FILES)])
    t0 = time.perf_counter()
    sim = simulate(
        architecture=args.architecture,
        tilted=not args.levelled,
        aps=args.aps,
        seed=args.seed,
        unit_length=args.unit_length,
    )
    net = sim.network
    design = "levelled" if args.levelled else "tilted (two scans rolled by -45 and +45 deg)"
    print(
        f"Simulated Chow et al. (2013) room 14 x 11 x 3 m: {len(net.targets)} targets, {len(net.scans)} scans, "
        f'{args.architecture} scanner, {design}, seed {args.seed}; noise 0.5 mm range, 20" angles.'
    )
    res = calibrate(net, CalibrationModel(sim.scanner))
    print(f"self-calibration: {time.perf_counter() - t0:.1f} s including compilation")
    report(res, truth=sim.true_aps)
    _write_simulation(
        sim,
        os.path.join(args.out, "observations.csv"),
        os.path.join(args.out, "scans.csv"),
        os.path.join(args.out, "truth.json"),
    )
    write_outputs(res, os.path.join(args.out, "report.json"), args.out, scanner=sim.scanner)
    print(
        f"simulated data in {args.out}/observations.csv and scans.csv; rerun with "
        f"`tlsjax calibrate {args.out}/observations.csv --scans {args.out}/scans.csv --aps {args.aps}`"
    )
    return EXIT_OK if res.ok else EXIT_FAILED


def report(res, *, truth=None):
    """Print the summary and the AP table with the true values beside the estimates; a failed
    adjustment prints no estimates (they would look plausible and be wrong)."""
    from .._adjustment._text import ap_table, summary

    print(summary(res))
    print()
    print(ap_table(res, truth=truth))


def write_outputs(res, json_path, plots_dir, *, scanner=None):
    """The result JSON and the plots of the demo's calibration."""
    from .._io._json import write_json
    from .._report._plots import plot_ap_correlations, plot_residuals

    write_json(res, json_path)
    print(f"wrote {json_path}")
    a, b = (os.path.join(plots_dir, name) for name in PLOT_FILES)
    plot_residuals(res, a, scanner=scanner)
    plot_ap_correlations(res, b)
    print(f"wrote {a} and {b}")
