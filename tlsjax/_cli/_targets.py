"""``tlsjax import-targets`` (vendor target lists -> the observation CSV) and ``tlsjax
check-targets`` (targets without and with a calibration against a reference survey).

``import-targets`` is its own command rather than an option of ``calibrate``: the conversion is
done once, its decisions (layout, units and the rule that chose them, the scan of each file, the
panoramic fold) are printed for the user to check, and its result is the one observation
contract (SPEC section 11, with the architecture recorded) that ``calibrate``, ``check-targets``
and every later run read without vendor options of their own.
"""

from __future__ import annotations

import tlsjax as tj

from ._checks import positive_int, warn
from ._common import EXIT_FAILED, EXIT_OK


def add_import_targets_parser(sub):
    p = sub.add_parser(
        "import-targets",
        help="convert vendor target lists (name, x, y, z per scan) to an observation CSV",
        description="Read Cartesian target lists in each scanner's frame (one file per scan, "
        "named by the file, or files with a scan column; comma, semicolon, tab or space "
        "separated, with or without a header; metres or millimetres) and write range, "
        "horizontal direction and elevation angle (SPEC sections 1 and 11). For a panoramic "
        "scanner the back half (hz >= 180 deg) is folded into the second face.",
    )
    p.add_argument("lists", nargs="+", help="target list files")
    p.add_argument("--out", required=True, help="observation CSV to write")
    p.add_argument(
        "--architecture",
        required=True,
        choices=("hybrid", "panoramic"),
        help="scanner architecture (required: it decides the panoramic fold, and is recorded)",
    )
    p.add_argument(
        "--length-unit",
        choices=("m", "cm", "mm"),
        help="unit of the coordinates (default: from the header, or detected: median range up "
        "to 300 file units -> m, from 3000 -> mm, between refused)",
    )
    p.add_argument("--scan", help="scan name of a single file without a scan column")
    p.add_argument(
        "--columns",
        help="column roles when the layout is not detected, e.g. 'name,x,y,z' or "
        "'scan,name,x,y,z,-,sigma' ('-' ignores a column)",
    )
    p.add_argument(
        "--angle-unit",
        default="deg",
        choices=("rad", "deg", "gon", "arcsec"),
        help="angle unit of the written CSV (default deg; 17 significant digits)",
    )
    p.set_defaults(func=_import_targets)
    return p


def _import_targets(args) -> int:
    tj.check_outputs([("--out", args.out)], [("list", p) for p in args.lists])
    table = tj.read_target_list(
        args.lists,
        args.architecture,
        length_unit=args.length_unit,
        scan=args.scan,
        columns=args.columns,
    )
    for note in table.notes:
        print(note)
    tj.write_observations(args.out, table, length_unit="m", angle_unit=args.angle_unit)
    n_scans = len(set(table.scans))
    face2 = int((table.observations[:, 2] > 1.5707963267948966).sum())
    fold = (
        f"; {face2} observation(s) folded into the second face (hz >= 180 deg)"
        if args.architecture == "panoramic"
        else ""
    )
    print(
        f"wrote {args.out}: {len(table)} target observations, {n_scans} scans, "
        f"{len(set(table.primitives))} targets, {args.architecture} scanner{fold}"
    )
    return EXIT_OK


def add_check_targets_parser(sub):
    p = sub.add_parser(
        "check-targets",
        help="compare targets placed from scans, without and with a calibration, with a "
        "reference survey (RMS per axis; Lichti & Licht 2006, tables 3 and 4)",
        description="Correct the target observations with the calibration, place the targets "
        "by adjusting all scans together (APs held at zero, raw and corrected), fit them onto "
        "the reference on the common names and print the RMS of the differences in X, Y, Z "
        "and 3D, and per scan in range, direction and elevation, without and with the "
        "calibration. A result JSON with targets as --reference is the cross-validation of "
        "held-out scans.",
    )
    p.add_argument(
        "calibration", help="calibration JSON (tlsjax calibrate --json, or a truth JSON)"
    )
    p.add_argument("observations", help="target observation CSV (SPEC section 11)")
    p.add_argument(
        "--reference",
        required=True,
        help="reference coordinates: a point list (name, X, Y, Z; any layout import-targets "
        "reads) or a tlsjax result JSON with targets",
    )
    p.add_argument("--scans", help="scans CSV with levelling observations")
    p.add_argument(
        "--transform",
        default="rigid",
        choices=("rigid", "similarity", "7-parameter"),
        help="fit onto the reference: rigid body (default) or 7-parameter Helmert",
    )
    p.add_argument(
        "--length-unit",
        choices=("m", "cm", "mm"),
        help="unit of the reference list (default: header, or detected from its spread)",
    )
    p.add_argument(
        "--columns",
        help="columns of the reference list in order, e.g. 'name,x,y,z' or 'name,-,x,y,z' "
        "('-' a column to ignore; default: from its header or its numbers)",
    )
    p.add_argument(
        "--exclude", nargs="+", default=(), metavar="TARGET", help="targets to leave out"
    )
    p.add_argument(
        "--min-points", type=positive_int, default=4, help="check points per scan (default 4)"
    )
    p.add_argument("--instrument", help="AP block of a calibration with several instruments")
    p.add_argument("--json", help="write the comparison as JSON")
    p.set_defaults(func=_check_targets)
    return p


def _check_targets(args) -> int:
    tj.check_outputs(
        [("--json", args.json)],
        [
            ("calibration", args.calibration),
            ("observations", args.observations),
            ("--reference", args.reference),
            ("--scans", args.scans),
        ],
    )
    cal = tj.Calibration.from_json(args.calibration, instrument=args.instrument)
    for note in cal.notes:
        warn(note)
    table = tj.read_observations(args.observations)
    if table.kind != "target":
        raise ValueError(f"{args.observations}: a {table.kind} file; check-targets needs targets")
    arch = cal.scanner.architecture
    if table.architecture not in (None, arch):
        raise ValueError(
            f"{args.observations}: recorded for a {table.architecture} scanner, but "
            f"{args.calibration} calibrates a {arch} scanner"
        )
    reference = tj.read_reference(
        args.reference, length_unit=args.length_unit, columns=args.columns
    )
    levelling = tj.read_scans(args.scans) if args.scans else None
    chk = tj.check_targets(
        table,
        cal,
        reference,
        transform=args.transform,
        exclude=args.exclude,
        levelling=levelling,
        min_points=args.min_points,
    )
    aps = ", ".join(cal.scanner.aps) or "none"
    print(f"{args.calibration}: {arch} scanner, APs {aps}; reference {args.reference}")
    print(chk.summary())
    worst = chk.worst()
    if worst:
        print(
            "largest 3D differences with calibration: "
            + ", ".join(f"{n} {d * 1e3:.2f} mm" for n, d in worst)
        )
    if args.json:
        tj.write_json(
            {
                "tool": "tlsjax",
                "kind": "target check",
                "units": "RMS in mm and arc seconds (keys say which), differences in metres",
                "calibration": args.calibration,
                "observations": args.observations,
                "reference": args.reference,
                "scanner": tj.scanner_settings(cal.scanner),
                "aps": {n: {"value": float(v)} for n, v in zip(cal.scanner.aps, cal.values)},
                **chk.to_dict(),
            },
            args.json,
        )
        print(f"wrote {args.json}")
    # A placement that was tried and failed, or nothing compared at all, is not a result.
    failed = any(chk.network[c]["rms"] is None and chk.network[c]["message"] for c in chk.network)
    return EXIT_FAILED if failed or (not chk.names) else EXIT_OK
