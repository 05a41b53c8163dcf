"""``tlsjax field-check --s1 FILES... --s2 FILES... --checkerboards --u-t-mm 0.5``: the DVW
guideline's check (DVW-Merkblatt 7-2014) and an ISO 17123-9-style distance comparison from
target scans of two stations. Public API only (``import tlsjax as tj``)."""

from __future__ import annotations

import argparse
import re
import sys

from ._checks import positive_float, positive_int
from ._common import EXIT_FAILED, EXIT_OK

#: A file stem's repeat suffix: "T1.2", "T1_2", "T1-2" are repeats 2 of target T1.
_REPEAT = re.compile(r"^(.*?)[._-]\d+$")


def add_field_check_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "field-check",
        help="DVW / ISO 17123-9-style field check of a scanner from target scans of two stations",
        description="Extract the target centres of the scans (or target patches) of two "
        "stations, average the repeats, and judge the distances between targets seen from "
        "both: the DVW guideline's differences T1T2, T1T4, T3T4 (S1 minus S2) against "
        "U = 4 u_T, and every distance between two targets (ISO 17123-9-style), with a table "
        "and a pass/fail per quantity. Targets are named by the file stem (a patch per file: "
        "T1.1, T1.2 are repeats of T1) or, for scans holding several targets, by matching "
        "them across scans (--min-common, default 3).",
    )
    p.add_argument("--s1", nargs="+", required=True, metavar="FILE", help="scans of station S1")
    p.add_argument("--s2", nargs="+", required=True, metavar="FILE", help="scans of station S2")
    p.add_argument("--spheres", nargs="+", type=positive_float, default=(), metavar="R",
                   help="nominal sphere radii [m]")  # fmt: skip
    p.add_argument("--checkerboards", action="store_true", help="look for 2 x 2 checkerboards")
    p.add_argument("--circles", action="store_true", help="look for white discs on a dark ground")
    p.add_argument("--pattern-size", type=positive_float, default=0.15, metavar="M",
                   help="side of a checkerboard or circle plate [m] (a prior, +-30 %%)")  # fmt: skip
    p.add_argument("--columns", metavar="NAMES", help="columns of text files without a header")
    p.add_argument("--u-t-mm", type=positive_float, default=None,
                   help="type B uncertainty of a target centre [mm] (e.g. the maker's); "
                   "combined with the repeats' scatter (DVW eq. 3)")  # fmt: skip
    p.add_argument("--k", type=positive_float, default=2.0, help="coverage factor (default 2)")
    p.add_argument("--dvw-targets", nargs=4, metavar="NAME",
                   help="names of the guideline's T1 T2 T3 T4 (default: T1 T2 T3 T4)")  # fmt: skip
    p.add_argument("--reference", help="CSV of reference distances: name_a,name_b,distance_m")
    p.add_argument("--min-common", type=positive_int, default=3,
                   help="targets a scan must share with the others to be matched (default 3)")  # fmt: skip
    p.add_argument("--json", help="write the result as JSON here")
    p.set_defaults(func=cli_field_check)
    return p


def _reference(path):
    out = {}
    with open(path, encoding="utf-8") as fh:
        for no, line in enumerate(fh, 1):
            f = [x.strip() for x in line.replace(";", ",").split(",")]
            if len(f) < 3 or not f[0] or line.lstrip().startswith("#"):
                continue
            try:
                out[(f[0], f[1])] = float(f[2])
            except ValueError:
                if no > 1:
                    raise ValueError(
                        f"{path}, line {no}: expected name_a,name_b,distance_m, got {line.strip()!r}"
                    ) from None
    return out


def _named_targets(tj, np, files, opts, args):
    """The targets of one station's files, named by the file stem (one target per file: a
    patch; "T1.2" is repeat 2 of T1) or by matching across its scans."""
    import dataclasses

    found = tj.extract_targets_from_files(files, opts, columns=args.columns)
    for i in np.flatnonzero(~found.accepted):
        print(f"{found.scans[found.scan_index[i]]}: rejected: {found.reason[i]}", file=sys.stderr)
    per_scan = np.bincount(found.scan_index[found.accepted], minlength=len(found.scans))
    if per_scan.max(initial=0) <= 1:
        stems = [(m.group(1) if (m := _REPEAT.match(s)) else s) for s in found.scans]
        names = np.array(
            [stems[j] if ok else "" for j, ok in zip(found.scan_index, found.accepted)],
            dtype=object,
        )
        return dataclasses.replace(found, names=names)
    named = tj.match_targets(found, tj.TargetMatchingOptions(min_common=args.min_common))
    print(named.matching.summary())
    return named


def cli_field_check(args) -> int:
    import numpy as np

    import tlsjax as tj

    if not (args.spheres or args.checkerboards or args.circles):
        raise ValueError(
            "nothing to look for: give --spheres R [R ...], --checkerboards or --circles"
        )
    inputs = [("--s1", p) for p in args.s1] + [("--s2", p) for p in args.s2]
    tj.check_outputs([("--json", args.json)], inputs + [("--reference", args.reference)])
    opts = tj.TargetExtractionOptions(
        spheres=tuple(args.spheres), checkerboards=args.checkerboards, circles=args.circles,
        pattern_size=args.pattern_size,
    )  # fmt: skip
    centres = {}
    for station, files in (("S1", args.s1), ("S2", args.s2)):
        named = _named_targets(tj, np, files, opts, args)
        centres.update(tj.field_check_centres(named, lambda _, s=station: s))
    result = tj.field_check(
        centres,
        tj.FieldCheckOptions(
            u_t=None if args.u_t_mm is None else args.u_t_mm * 1e-3,
            k=args.k,
            dvw_targets=tuple(args.dvw_targets) if args.dvw_targets else None,
            reference=_reference(args.reference) if args.reference else None,
            stations=("S1", "S2"),
        ),
    )
    print(result.summary())
    if args.json:
        tj.write_json(result, args.json)  # strict, atomic; checked before the extraction
    return EXIT_OK if result.passed else EXIT_FAILED
