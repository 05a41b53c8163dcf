"""``tlsjax extract-targets SCANS... --spheres 0.0725 --checkerboards --out targets.csv``."""

from __future__ import annotations

import argparse
import os
import sys

import numpy as np

from .._clouds._target_match import TargetMatchingOptions
from .._clouds._targets import TargetExtractionOptions
from .._units import DEG
from ._checks import fraction, non_negative_int, positive_float, positive_int
from ._common import EXIT_FAILED, EXIT_OK


def add_targets_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``extract-targets`` sub-command to an argparse ``subparsers`` object."""
    p = subparsers.add_parser(
        "extract-targets",
        help="extract sphere and checkerboard/circle target centres from point clouds",
        description="Find sphere targets of the given radii and planar contrast targets "
        "(2 x 2 checkerboards, white circles on a dark ground) in scans (E57, PTX, LAS/LAZ, "
        "PLY, PCD, XYZ; streamed), match them across scans (by a target list, or by the "
        "distances between them), and write the target observation CSV that `tlsjax "
        "calibrate` reads, a per-target table and a picture per scan.",
    )
    p.add_argument(
        "scans", nargs="+", help="point-cloud files (PTX/E57 files may hold several scans)"
    )
    p.add_argument("--out", required=True, help="target observation CSV (SPEC section 11)")
    p.add_argument("--spheres", nargs="+", type=positive_float, default=(), metavar="R",
                   help="nominal sphere radii [m], e.g. 0.0725 0.1")  # fmt: skip
    p.add_argument("--checkerboards", action="store_true", help="look for 2 x 2 checkerboards")
    p.add_argument("--circles", action="store_true", help="look for white discs on a dark ground")
    p.add_argument("--pattern-size", type=positive_float, default=TargetExtractionOptions.pattern_size,
                   metavar="M", help="side of a checkerboard or circle plate [m] (default 0.15)")  # fmt: skip
    p.add_argument("--circle-radius", type=positive_float, default=None, metavar="M",
                   help="radius of the white disc [m] (default: any from 0.1 to 0.45 of the size)")  # fmt: skip
    p.add_argument("--sphere-model", choices=("offset", "known", "free"), default="offset",
                   help="sphere fit whose centre is written (default offset: radius known plus a "
                   "range offset, unbiased by an uncalibrated rangefinder offset)")  # fmt: skip
    p.add_argument("--architecture", choices=("hybrid", "panoramic"), default="hybrid",
                   help="panoramic: observations in the two-face form (SPEC section 1)")  # fmt: skip
    p.add_argument("--poses", help="scan poses CSV replacing the files' (LAS needs one)")
    p.add_argument("--columns", metavar="NAMES",
                   help="columns of text point files without a header naming them, e.g. "
                   "x,y,z,r,g,b,intensity (other names are skipped; default: the header's "
                   "names, else x y z [intensity] by the column count)")  # fmt: skip
    p.add_argument(
        "--target-list",
        help="name the targets by this list of approximate coordinates in any one frame (a "
        "survey: any point list `check-targets --reference` reads, or a result JSON's targets)",
    )
    p.add_argument("--table", help="per-target table CSV (default: <out>_table.csv)")
    p.add_argument("--plots", help="folder for one PNG per scan of what was found")
    p.add_argument("--min-points", type=positive_int, default=TargetExtractionOptions.min_points)
    p.add_argument("--min-coverage", type=fraction, default=TargetExtractionOptions.min_coverage)
    p.add_argument("--max-rms-mm", type=positive_float, default=None,
                   help="fixed limit on a sphere's fit RMS and a plate's plane scale [mm] "
                   "(default: 3 x the scan's own noise there, from the points)")  # fmt: skip
    p.add_argument("--max-radius-misfit-mm", type=positive_float, default=None,
                   help="test a sphere's fitted radius against the nominal one to this [mm] "
                   "(default: only against --size-tolerance, to tell sphere sizes apart)")  # fmt: skip
    p.add_argument("--size-tolerance", type=fraction, default=TargetExtractionOptions.size_tolerance,
                   help="how far (relative) a target's real size may be from --pattern-size or "
                   "the radius given (default 0.3)")  # fmt: skip
    p.add_argument("--max-incidence-deg", type=positive_float,
                   default=TargetExtractionOptions.max_incidence / DEG)  # fmt: skip
    p.add_argument(
        "--sigma-range-mm", type=positive_float, default=TargetExtractionOptions.sigma_range * 1e3
    )
    p.add_argument("--tolerance-mm", type=positive_float, default=TargetMatchingOptions.tolerance * 1e3,
                   help="matching tolerance of distances between targets [mm] (default 20)")  # fmt: skip
    p.add_argument("--min-common", type=positive_int, default=TargetMatchingOptions.min_common,
                   help="targets a scan must share with the others to be named (at least 3; "
                   f"default {TargetMatchingOptions.min_common}). A scan placed on exactly 3 "
                   "is named only when their distances agree within 5 mm + 0.5 mm/m and a "
                   "chance match of 3 is improbable among the centres; else it is reported "
                   "as undecided")  # fmt: skip
    p.add_argument("--length-unit", choices=("m", "mm"), default="m")
    p.add_argument("--angle-unit", choices=("rad", "deg", "gon", "arcsec"), default="deg")
    p.add_argument("--seed", type=non_negative_int, default=0)
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=cli_targets)
    return p


def _options(args) -> tuple[TargetExtractionOptions, TargetMatchingOptions]:
    if not (args.spheres or args.checkerboards or args.circles):
        raise ValueError(
            "nothing to look for: give --spheres R [R ...], --checkerboards or --circles"
        )
    return (
        TargetExtractionOptions(
            spheres=tuple(args.spheres),
            checkerboards=args.checkerboards,
            circles=args.circles,
            sphere_model=args.sphere_model,
            pattern_size=args.pattern_size,
            circle_radius=args.circle_radius,
            min_points=args.min_points,
            min_coverage=args.min_coverage,
            max_rms=None if args.max_rms_mm is None else args.max_rms_mm * 1e-3,
            max_radius_misfit=(
                None if args.max_radius_misfit_mm is None else args.max_radius_misfit_mm * 1e-3
            ),
            size_tolerance=args.size_tolerance,
            max_incidence=args.max_incidence_deg * DEG,
            sigma_range=args.sigma_range_mm * 1e-3,
            seed=args.seed,
        ),
        TargetMatchingOptions(
            tolerance=args.tolerance_mm * 1e-3, min_common=args.min_common, seed=args.seed
        ),
    )


def _print_summary(targets, out) -> None:
    print("scan       kind           found  accepted", file=out)
    for j, scan in enumerate(targets.scans):
        for kind in ("sphere", "checkerboard", "circle"):
            sel = (targets.scan_index == j) & (targets.kind == kind)
            if sel.any():
                print(
                    f"{scan:10s} {kind:13s} {int(sel.sum()):6d} {int(targets.accepted[sel].sum()):9d}",
                    file=out,
                )
    reasons = {}
    for r in targets.reason[~targets.accepted]:
        key = str(r).split(" (")[0].split(" ")[0:2]
        reasons[" ".join(key)] = reasons.get(" ".join(key), 0) + 1
    if reasons:
        print("rejected: " + ", ".join(f"{n} x {k}" for k, n in sorted(reasons.items())), file=out)
    if targets.matching is not None:
        print(targets.matching.summary(), file=out)


def cli_targets(args) -> int:
    """Run ``tlsjax extract-targets``; returns the exit code."""
    from .._clouds._target_match import match_targets
    from .._clouds._targets import extract_targets_from_files
    from .._io._outputs import check_outputs
    from .._io._plane_files import read_poses
    from .._io._tables import write_observations
    from .._io._target_files import write_target_table
    from .._io._target_lists import read_reference
    from .._report._target_plots import picture_name, plot_all_targets

    options, matching = _options(args)
    table_path = args.table or os.path.splitext(args.out)[0] + "_table.csv"
    inputs = [("scan", p) for p in args.scans]
    inputs += [("--poses", args.poses), ("--target-list", args.target_list)]
    outputs = [("--out", args.out), ("--table", table_path)]
    check_outputs(outputs + [("--plots", args.plots, ())], inputs)  # before the extraction
    target_list = read_reference(args.target_list) if args.target_list else None
    poses = read_poses(args.poses) if args.poses else None
    progress = not args.no_progress and sys.stderr.isatty()
    found = extract_targets_from_files(
        args.scans, options, architecture=args.architecture, poses=poses, columns=args.columns,
        progress=progress,
    )  # fmt: skip
    for note in found.notes:
        print(f"warning: {note}", file=sys.stderr)
    targets = match_targets(found, matching, target_list=target_list)
    if args.plots:  # the picture names come from the scans: checked once they are known
        names = [picture_name(s) for s in targets.scans]
        check_outputs(outputs + [("--plots", args.plots, names)], inputs)
    write_target_table(table_path, targets)
    if args.plots:
        plot_all_targets(targets, args.plots)
    _print_summary(targets, sys.stdout)
    named = targets.accepted & (targets.names != "")
    if not named.any():
        print(
            f"tlsjax extract-targets: no accepted target matched across scans; see {table_path}",
            file=sys.stderr,
        )
        return EXIT_FAILED
    write_observations(
        args.out, targets.to_table(), length_unit=args.length_unit, angle_unit=args.angle_unit
    )
    n_t = len(set(targets.names[named]))
    print(
        f"{int(named.sum())} observations of {n_t} targets in "
        f"{len(np.unique(targets.scan_index[named]))} scans -> {args.out} (table: {table_path})"
    )
    return EXIT_OK
