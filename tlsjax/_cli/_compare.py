"""``tlsjax compare A.json B.json``: the AP-set compatibility test of SPEC section 9.

Each file is an AP-set JSON (:func:`tlsjax.write_json` of an ``APSet``) or the result JSON of
``tlsjax calibrate
--json`` (values, full AP covariance and scanner settings). Exit code 0: compatible, 1: not
compatible, 2: bad input.
"""

from __future__ import annotations

import numpy as np

import tlsjax as tj

from ._checks import (
    non_negative_float,
    non_negative_int,
    positive_float,
    positive_int,
    probability,
    state_cost,
)
from ._common import devices_arg


def add_compare_parser(subparsers):
    """``tlsjax compare A.json B.json --room 14x11x3 --runs 1000`` (wire into the CLI)."""
    p = subparsers.add_parser(
        "compare", help="AP-set compatibility test by simulation (SPEC section 9)"
    )
    p.add_argument("set1", help="AP-set JSON or result JSON (calibrate --json) of calibration 1")
    p.add_argument("set2", help="AP-set JSON or result JSON (calibrate --json) of calibration 2")
    p.add_argument("--room", default="14x11x3", help="room LxWxH in metres (default 14x11x3)")
    p.add_argument(
        "--runs", type=positive_int, default=1000, help="number of simulations N (default 1000)"
    )
    p.add_argument(
        "--alpha", type=probability, default=0.05, help="significance level (default 0.05)"
    )
    p.add_argument(
        "--targets", type=positive_int, default=100, help="targets per simulation (default 100)"
    )
    p.add_argument(
        "--control", type=non_negative_int, default=10, help="control points (default 10)"
    )
    p.add_argument(
        "--architecture",
        default=None,
        choices=("hybrid", "panoramic"),
        help="override both files' scanner architecture (default: each file's own)",
    )
    p.add_argument(
        "--unit-length",
        type=positive_float,
        default=None,
        help="override the unit length U [m] of A3/A4 (default: each file's own)",
    )
    p.add_argument(
        "--instrument", default=None, help="AP block of one instrument (multi-instrument files)"
    )
    p.add_argument(
        "--sigma-range-mm",
        type=non_negative_float,
        default=None,
        help="range noise at normal incidence [mm] (default: the files' data noise, else 0.5)",
    )
    p.add_argument(
        "--sigma-angle-arcsec",
        type=non_negative_float,
        default=None,
        help="angle noise [\"] (default: the files' data noise, else 20); 0 with "
        "--sigma-range-mm 0 gives the pure object-space test",
    )
    p.add_argument("--seed", type=non_negative_int, default=0)
    p.add_argument(
        "--draws", type=positive_int, default=100_000, help="draws of the null (default 100000)"
    )
    p.add_argument("--json", default=None, help="write the result as strict JSON to this file")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    devices_arg(p)
    p.set_defaults(func=cli_compare)
    return p


def _scanner_override(args, s: tj.APSet):
    if args.architecture is None and args.unit_length is None:
        return s
    sc = s.scanner
    return tj.APSet(
        s.names,
        s.values,
        s.covariance,
        s.source,
        tj.Scanner(
            architecture=args.architecture or sc.architecture,
            aps=s.names,
            unit_length=args.unit_length or sc.unit_length,
            unit_length_2=sc.unit_length_2,
        ),
        s.noise,
        s.notes,
    )


def cli_compare(args) -> int:
    """CLI handler: prints the report; exit code 0 compatible, 1 not compatible."""
    tj.check_outputs([("--json", args.json)], [("set1", args.set1), ("set2", args.set2)])
    sets = [
        _scanner_override(args, tj.APSet.from_json(f, instrument=args.instrument))
        for f in (args.set1, args.set2)
    ]
    a = len(set(sets[0].names) | set(sets[1].names))
    state_cost(  # each simulation: two scans of --targets targets, Jacobians at the targets
        "the compatibility test",
        "--runs",
        args.runs,
        rows=2 * args.targets,
        parameters=6 + 2 * a,
        devices=args.devices,
        result_bytes=8.0 * args.targets * 3 * (2 + 2 * a),
        usual="1,000 is usual",
    )
    room = tj.Room.parse(args.room)
    options = tj.CompatibilityOptions(
        runs=args.runs,
        level=args.alpha,
        n_targets=args.targets,
        n_control=args.control,
        seed=args.seed,
        progress=not args.no_progress,
        null_draws=args.draws,
    )
    res = tj.compatibility_test(
        *sets,
        room,
        options=options,
        sigma_range=None if args.sigma_range_mm is None else args.sigma_range_mm * 1e-3,
        sigma_angle=None
        if args.sigma_angle_arcsec is None
        else np.deg2rad(args.sigma_angle_arcsec / 3600.0),
    )
    print(res.summary())
    if args.json:
        doc = res.to_dict()
        doc["files"] = [args.set1, args.set2]
        doc["room_m"] = [room.length, room.width, room.height]
        tj.write_json(doc, args.json)  # strict: undefined values are null
    return 0 if res.compatible else 1
