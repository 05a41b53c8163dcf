"""``tlsjax correct CAL.json SCANS... --out DIR``: apply a calibration to point-cloud files."""

from __future__ import annotations

import os
import sys

from ._checks import warn
from ._common import EXIT_OK


def add_correct_parser(sub):
    p = sub.add_parser(
        "correct",
        help="apply a calibration (result JSON) to point clouds",
        description="Correct every point of each scan by l - Delta(l) with the calibration's APs "
        "(SPEC section 11) and write the corrected file, same format and attributes, into --out.",
    )
    p.add_argument("calibration", help="result JSON of `tlsjax calibrate` (SPEC section 11)")
    p.add_argument("scans", nargs="+", help="point-cloud files (E57, PTX, PLY, LAS/LAZ, XYZ)")
    p.add_argument("--out", required=True, help="folder for the corrected files (same names)")
    p.add_argument(
        "--poses",
        help="scan poses CSV for LAS/LAZ files without a stored pose (their coordinates are "
        "object space; the correction is applied in scanner space)",
    )
    p.add_argument(
        "--architecture",
        choices=("hybrid", "panoramic"),
        help="scanner architecture (default: the one stored in the calibration JSON)",
    )
    p.add_argument(
        "--instrument", help="instrument whose AP block to apply (multi-instrument JSON)"
    )
    p.add_argument(
        "--precision",
        action="store_true",
        help="also propagate each point's sigma from the AP covariance (LAS: extra dimension "
        "calibration_sigma; PLY: vertex property; PTX/XYZ/E57: <file>.sigma_mm.txt)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=cli_correct)
    return p


def cli_correct(args) -> int:
    import tlsjax as tj

    names = [os.path.basename(p) for p in args.scans]
    if len(set(names)) != len(names):
        raise ValueError(f"scan files with the same name would overwrite each other in {args.out}")
    written = names + [n + ".sigma_mm.txt" for n in names] if args.precision else names
    tj.check_outputs(  # before any work: never over an input, every file writable
        [("--out", args.out, written)],
        [("calibration", args.calibration), ("--poses", args.poses)]
        + [("scan", p) for p in args.scans],
    )
    for path in args.scans:  # refuse unknown formats and missing files before writing anything
        tj.point_cloud_format(path)
        if not os.path.isfile(path):
            raise FileNotFoundError(2, "No such file or directory", path)
    cal = tj.Calibration.from_json(
        args.calibration, architecture=args.architecture, instrument=args.instrument
    )
    poses = tj.read_poses(args.poses) if args.poses else None
    print(f"{args.calibration}: {cal.scanner.architecture} scanner; applying {cal.describe()}")
    for note in cal.notes:
        warn(note)
    for path in args.scans:
        out = os.path.join(args.out, os.path.basename(path))
        try:
            scans = tj.correct_point_cloud(
                path,
                cal,
                out,
                poses=poses,
                precision=args.precision,
                progress=not args.no_progress and sys.stderr.isatty(),
            )
        except (FileNotFoundError, ValueError, ImportError):
            raise
        except OSError as err:  # an unwritable folder, a full disk: one line
            raise ValueError(f"{out}: cannot write ({err.strerror or err})") from None
        for scan in scans:
            print(scan.line())
            for note in scan.notes:
                warn(note)
    return EXIT_OK
