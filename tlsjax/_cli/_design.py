"""``tlsjax design``: optimise the scan design of the simulated calibration room (SPEC 13)."""

from __future__ import annotations

import numpy as np

from ._checks import non_negative_int, positive_float, positive_int, state_cost
from ._common import EXIT_FAILED, EXIT_OK, scanner_args


def add_design_parser(sub):
    p = sub.add_parser(
        "design",
        help="choose tilts, station positions (and target placements) that minimise a "
        "criterion of the AP covariance of the simulated room",
    )
    p.add_argument("--room", default="14x11x3", help="room L x W x H [m] (default 14x11x3)")
    p.add_argument(
        "--targets", type=positive_int, default=120, help="number of targets (default 120)"
    )
    p.add_argument("--aps", default="A0 B6 B7 C0", help="APs of the model (names or presets)")
    p.add_argument(
        "--criterion", default="max_sigma", choices=("max_sigma", "trace", "max_correlation")
    )
    p.add_argument(
        "--criterion-aps", default=None, help='APs the criterion covers (default: all), e.g. "B6"'
    )
    p.add_argument(
        "--tolerance",
        action="append",
        default=[],
        metavar="AP=VALUE",
        help='tolerance of an AP sigma in mm or " (e.g. B6=1 A0=0.1); default 0.1 mm / 1"',
    )
    p.add_argument(
        "--with-poses",
        action="store_true",
        help="max_correlation: include the correlations with the scan poses (e.g. B6-kappa)",
    )
    p.add_argument(
        "--tilted-scans",
        default="5 6",
        help='scans (1-based) without compensator whose tilts are free (default "5 6"; "" none)',
    )
    p.add_argument("--fixed-stations", action="store_true", help="keep the station positions")
    p.add_argument("--headings", action="store_true", help="also optimise kappa")
    p.add_argument("--move-targets", action="store_true", help="also slide targets on their faces")
    p.add_argument("--tilt-limit-deg", type=positive_float, default=60.0)
    p.add_argument("--clearance", type=positive_float, default=0.5, help="station clearance [m]")
    p.add_argument(
        "--fov-deg", default=None, help='elevation field of view in scanner space, e.g. "-40,90"'
    )
    p.add_argument("--max-incidence-deg", type=positive_float, default=None)
    p.add_argument("--starts", type=positive_int, default=8)
    p.add_argument("--steps", type=positive_int, default=150)
    p.add_argument("--learning-rate", type=positive_float, default=0.1)
    p.add_argument("--seed", type=non_negative_int, default=0)
    p.add_argument(
        "--verify-seed",
        type=non_negative_int,
        default=1,
        help="noise seed of the independent calibrations",
    )
    p.add_argument("--json", default=None, help="write the result as JSON to this file")
    p.add_argument("--no-progress", action="store_true")
    scanner_args(p)
    p.set_defaults(func=cli_design)
    return p


def _tolerances(items, aps):
    from .._model._aps import get_ap
    from .._units import ARCSEC

    out = {}
    for item in items:
        name, _, value = item.partition("=")
        if name not in aps or not value:
            raise ValueError(f"--tolerance {item!r}: expected AP=VALUE with an AP of the model")
        unit = get_ap(name).unit
        out[name] = float(value) * (1e-3 if unit == "m" else ARCSEC if unit == "rad" else 1e-6)
    return out


def _build(args):
    import tlsjax as tj

    from .._units import DEG

    room = tj.Room.parse(args.room, n_targets=args.targets)
    sim = tj.simulate(
        room,
        architecture=args.architecture,
        tilted=False,
        aps=args.aps,
        seed=0,
        noise=False,
        unit_length=args.unit_length,
    )
    tilted = [int(s) - 1 for s in args.tilted_scans.split()]
    n_s = len(sim.true_eops)
    if any(not 0 <= s < n_s for s in tilted):
        raise ValueError(f"--tilted-scans {args.tilted_scans!r}: scans are 1..{n_s}")
    levelled = np.ones(n_s, dtype=bool)
    levelled[tilted] = False
    fov = None
    if args.fov_deg:
        lo, hi = (float(v) * DEG for v in args.fov_deg.split(","))
        fov = (lo, hi)
    inc = None if args.max_incidence_deg is None else args.max_incidence_deg * DEG
    design = tj.TargetDesign.from_simulation(sim)
    dn = tj.DesignProblem.targets(
        design,
        sim.scanner,
        levelled=levelled,
        fov=fov,
        max_incidence=inc,
        smooth_visibility=fov is not None or inc is not None,
    )
    space = tj.DesignSpace(
        room=room,
        stations=not args.fixed_stations,
        tilts="unlevelled",
        headings=args.headings,
        targets=args.move_targets,
        clearance=args.clearance,
        tilt_limit=args.tilt_limit_deg * DEG,
    )
    crit = tj.DesignCriterion(
        args.criterion,
        aps=args.criterion_aps,
        tolerances=_tolerances(args.tolerance, sim.scanner.aps),
        with_poses=args.with_poses,
    )
    return dn, space, crit


def _verify(dn, design, crit, seed):
    """Independent calibrate of a noisy network of ``design``: a priori AP sigmas, criterion."""
    import tlsjax as tj

    res = tj.calibrate(
        dn.network(design, seed=seed), dn.model, tj.SolverOptions(full_covariance=True)
    )
    from .._design._criteria import criterion_of_result

    if not res.ok:
        return res, None, float("nan")
    return res, res.ap_sigmas / res.sigma0, criterion_of_result(crit, res)


def cli_design(args) -> int:
    """CLI handler: optimise, print the design and the independent check, write JSON."""
    import tlsjax as tj

    from .._io._json import write_json_file
    from .._io._outputs import check_outputs
    from .._units import ARCSEC, DEG

    check_outputs([("--json", args.json)])  # before the optimisation runs
    dn, space, crit = _build(args)
    state_cost(  # the optimiser's steps cost about two adjustments' worth each
        "the design optimisation",
        "--steps",
        2 * args.starts * args.steps,
        rows=len(dn.scan_index),
        parameters=6 + len(dn.scanner.aps),
        devices=1,
        result_bytes=0,
        usual="8 starts x 150 steps is usual",
    )
    out = tj.optimize_design(
        dn,
        crit,
        space,
        starts=args.starts,
        steps=args.steps,
        learning_rate=args.learning_rate,
        seed=args.seed,
        progress=not args.no_progress,
    )
    print(f"criterion: {out.criterion}")
    print(f"start design: {out.start_value:.4g}   optimised: {out.value:.4g}")
    print(
        f"compile {out.compile_s:.1f} s, {args.starts} starts x {args.steps} steps in {out.run_s:.1f} s"
    )
    eops = np.asarray(out.design.eops)
    print(
        f"{'scan':>5} {'X [m]':>7} {'Y [m]':>7} {'Z [m]':>7} {'omega':>8} {'phi':>8} {'kappa':>8} [deg]"
    )
    for j, e in enumerate(eops):
        print(
            f"S{j + 1:<4d} {e[0]:7.2f} {e[1]:7.2f} {e[2]:7.2f} "
            f"{e[3] / DEG:8.2f} {e[4] / DEG:8.2f} {e[5] / DEG:8.2f}"
        )
    summary = out.to_dict()
    ok = True
    for label, design in (("start", dn.design), ("optimised", out.design)):
        res, sig, value = _verify(dn, design, crit, args.verify_seed)
        ok &= res.ok
        units = [1e3 if u == "m" else 1 / ARCSEC if u == "rad" else 1e6 for u in res.ap_units]
        shown = (
            ""
            if sig is None
            else "  ".join(f"{n} {s * f:.4g}" for n, s, f in zip(res.ap_names, sig, units))
        )
        print(
            f'independent calibrate ({label}): criterion {value:.4g}; a priori sigmas [mm, ", ppm]: {shown}'
        )
        summary[f"verified_{label}"] = {
            "criterion": value if np.isfinite(value) else None,
            "result": int(res.result),
            "ap_sigmas_apriori": None
            if sig is None
            else {n: (float(s) if np.isfinite(s) else None) for n, s in zip(res.ap_names, sig)},
        }
    if args.json:
        write_json_file(args.json, summary, "--json ")  # strict, atomic
    return EXIT_OK if ok else EXIT_FAILED
