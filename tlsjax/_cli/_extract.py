"""``tlsjax extract-planes SCANS... --out planes.npz``."""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np

from .._clouds._extract import ExtractionOptions
from ._checks import non_negative_int, positive_float, positive_int
from ._common import EXIT_FAILED
from ._progress import Phases


def add_extract_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``extract-planes`` sub-command to an argparse ``subparsers`` object."""
    p = subparsers.add_parser(
        "extract-planes",
        help="extract and match planes from point clouds",
        description="Extract planes from scans (E57, PTX, LAS/LAZ, PLY, PCD, XYZ), match "
        "them across scans with the scan poses, write them as .npz and optionally as a plane "
        "observation CSV.",
    )
    p.add_argument(
        "scans", nargs="+", help="point-cloud files, one scan each (PTX/E57 files may hold several)"
    )
    p.add_argument("--out", required=True, help="output .npz of the extracted planes")
    p.add_argument(
        "--poses",
        help="scan poses CSV (scan, x_m, y_m, z_m, omega_deg, phi_deg, kappa_deg); "
        "default: the poses stored in the files",
    )
    p.add_argument("--architecture", choices=("hybrid", "panoramic"), default="hybrid")
    p.add_argument("--seed", type=non_negative_int, default=0)
    p.add_argument(
        "--budget", type=positive_int, default=None, help="most points kept per plane patch"
    )
    p.add_argument(
        "--distance-threshold",
        type=positive_float,
        default=ExtractionOptions.distance_threshold,
        help="RANSAC inlier distance [m]",
    )
    p.add_argument("--min-points", type=positive_int, default=ExtractionOptions.min_points)
    p.add_argument("--csv", help="also write the plane observations CSV (SPEC section 11)")
    p.add_argument(
        "--no-progress",
        action="store_true",
        help="no progress bar or phase lines on stderr",
    )
    p.set_defaults(func=cli_extract)
    return p


def read_scan_files(paths, architecture, poses_path=None, *, out=None):
    """Read point-cloud files for a subcommand: one line per scan (points kept of stored, pose)
    and one ``warning:`` line per note (dropped points, map-scale coordinates) on stderr."""
    import sys
    import warnings

    from .._io._plane_files import read_poses
    from .._io._point_clouds import PointCloudWarning, read_point_clouds

    out = out or sys.stdout
    poses = read_poses(poses_path) if poses_path else None
    clouds = []
    for path in paths:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PointCloudWarning)  # printed below, once
            scans = read_point_clouds(path, architecture=architecture, poses=poses)
        for c in scans:
            pose = "no pose" if c.pose is None else "pose " + " ".join(f"{v:.6g}" for v in c.pose)
            print(
                f"{path}: scan {c.name}: {len(c.points)} of {c.n_stored} points, {pose}", file=out
            )
            for note in c.notes:
                print(f"warning: {note}", file=sys.stderr)
        clouds.extend(scans)
    return clouds, poses


def _scan_line(phases):
    """A progress line per extracted scan (where no progress bar is drawn)."""

    def line(name, n_patches, n_on, n):
        phases.note(f"scan {name}: {n_patches} patches, {n_on} of {n} points on them")

    return line


def cli_extract(args) -> int:
    """Run ``tlsjax extract-planes``; returns the exit code.

    (A little over 60 lines: one sequence of steps of the command, each a call.)
    """
    import sys

    from .._clouds._extract import ExtractionOptions, extract_planes
    from .._clouds._match import match_planes
    from .._io._outputs import check_outputs
    from .._io._plane_files import write_extracted_planes
    from .._io._tables import write_observations

    check_outputs(  # before the extraction runs
        [("--out", args.out), ("--csv", args.csv)],
        [("scan", p) for p in args.scans] + [("--poses", args.poses)],
    )
    phases = Phases(enabled=not args.no_progress)
    phases.hold()  # shown once the input is accepted (a refusal is one line on stderr)
    phases.start(f"reading {len(args.scans)} file(s)")
    clouds, table = read_scan_files(args.scans, args.architecture, args.poses)
    phases.done(f"read {len(clouds)} scan(s), {sum(len(c.points) for c in clouds)} points")
    names = [c.name for c in clouds]
    if len(set(names)) != len(names):
        raise ValueError(f"scan names are not unique: {names}")
    if table is not None:
        missing = [n for n in names if n not in table]
        if missing:
            raise ValueError(f"{args.poses}: no pose for scan(s) {', '.join(missing)}")
        poses = np.stack([table[n] for n in names])
    elif all(c.pose is not None for c in clouds):
        poses = np.stack([c.pose for c in clouds])
    elif len(clouds) == 1:
        poses = np.zeros((1, 6))  # one scan: its own frame is object space
    else:
        poses = None
    if poses is None and args.csv:
        raise ValueError("matching planes across scans needs scan poses: give --poses poses.csv")
    config = ExtractionOptions(
        distance_threshold=args.distance_threshold, min_points=args.min_points, budget=args.budget
    )
    phases.release()
    bar = not args.no_progress and sys.stderr.isatty()
    phases.start("extracting planes (RANSAC, DBSCAN, least-squares refit per scan)")
    planes = extract_planes(
        [c.observations for c in clouds],
        config,
        names=names,
        seed=args.seed,
        progress=bar,
        on_scan=None if bar else _scan_line(phases),
    )
    phases.done(f"extracted {len(planes.patch_scan)} patches")
    if len(planes.patch_scan) == 0:  # a non-result: no file, exit 1, the likely causes
        print(
            f"tlsjax extract-planes: no plane found in {len(names)} scan(s) ("
            f"{sum(len(c.points) for c in clouds)} points): no patch of --min-points "
            f"{args.min_points} points within --distance-threshold {args.distance_threshold} m. "
            "Likely: clouds too sparse or not in metres, or a threshold too tight for the noise; "
            f"nothing written to {args.out}",
            file=sys.stderr,
        )
        return EXIT_FAILED
    if poses is not None:
        phases.start("matching the patches across scans")
        planes = match_planes(planes, poses)
        phases.done(f"matched {len(planes.planes)} planes")
    write_extracted_planes(args.out, planes)
    if args.csv:
        table = dataclasses.replace(planes.to_table(), architecture=args.architecture)
        write_observations(args.csv, table)
    matched = (
        "not matched (no scan poses: give --poses)"
        if planes.planes is None
        else f"{len(planes.planes)} planes"
    )
    print(
        f"{len(names)} scan(s), {len(planes.patch_scan)} patches, {matched}, "
        f"{len(planes.point_patch)} points -> {args.out}"
    )
    if planes.planes is not None:
        print(planes.summary().split("\n", 1)[1])  # the per-plane lines (counts printed above)
    return 0
