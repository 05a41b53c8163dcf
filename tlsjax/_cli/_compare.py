"""``tlsjax compare A.json B.json --room 14x11x3 --runs 1000``."""

from __future__ import annotations

from .._adjustment._network import DEFAULT_SIGMA_RANGE
from .._inference._compat import APSet, CompatibilityOptions, compatibility_test
from .._model._scanner import Scanner
from .._simulation._room import Room
from .._units import ARCSEC
from ._common import devices_arg


def add_compare_parser(subparsers):
    """``tlsjax compare A.json B.json --room 14x11x3 --runs 1000`` (wire into the CLI)."""
    p = subparsers.add_parser(
        "compare", help="AP-set compatibility test by simulation (SPEC section 9)"
    )
    p.add_argument("set1", help="tlsjax result JSON of the first calibration")
    p.add_argument("set2", help="tlsjax result JSON of the second calibration")
    p.add_argument("--room", default="14x11x3", help="room LxWxH in metres (default 14x11x3)")
    p.add_argument("--runs", type=int, default=1000, help="number of simulations N (default 1000)")
    p.add_argument("--alpha", type=float, default=0.05, help="significance level (default 0.05)")
    p.add_argument(
        "--architecture",
        default=None,
        choices=("hybrid", "panoramic"),
        help="scanner architecture (default: the one stored in the JSONs, else hybrid)",
    )
    p.add_argument("--unit-length", type=float, default=1.2, help="unit length U of A3/A4 [m]")
    p.add_argument("--sigma-range-mm", type=float, default=DEFAULT_SIGMA_RANGE * 1e3)
    p.add_argument("--sigma-angle-arcsec", type=float, default=20.0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--json", default=None, help="write the result as JSON to this file")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    devices_arg(p)
    p.set_defaults(func=cli_compare)
    return p


def _stored_architecture(args) -> str:
    """``--architecture``, else the architecture both JSONs store (their ``scanner``
    section), else hybrid; two sets of different architectures are refused."""
    from .._io._json import read_result_json

    if args.architecture is not None:
        return args.architecture
    found = {}
    for path in (args.set1, args.set2):
        sc = read_result_json(path).get("scanner")
        if isinstance(sc, dict) and sc.get("architecture"):
            found[path] = sc["architecture"]
    if len(set(found.values())) > 1:
        raise ValueError(
            f"the AP sets calibrate different architectures ({found}); give --architecture"
        )
    return next(iter(found.values()), "hybrid")


def cli_compare(args) -> int:
    """CLI handler: prints the report; exit code 0 compatible, 1 not compatible."""
    from .._io._json import check_output_file, write_json_file

    check_output_file(args.json, "--json ")  # before the simulations run
    s1, s2 = APSet.from_json(args.set1), APSet.from_json(args.set2)
    args.architecture = _stored_architecture(args)
    room = Room.parse(args.room)
    sc = Scanner(architecture=args.architecture, aps=(), unit_length=args.unit_length)
    res = compatibility_test(
        s1,
        s2,
        room,
        sc,
        CompatibilityOptions(
            runs=args.runs, alpha=args.alpha, seed=args.seed, progress=not args.no_progress
        ),
        sigma_range=args.sigma_range_mm * 1e-3,
        sigma_angle=args.sigma_angle_arcsec * ARCSEC,
    )
    print(res.table())
    if args.json:
        out = {
            "ap_names": list(res.ap_names),
            "median_share": res.median_share,
            "null_quantile": res.null_quantile,
            "p_value": res.p_value,
            "compatible": res.compatible,
            "rms_mm": dict(zip(("X", "Y", "Z", "3D"), res.rms_mm.tolist())),
            "naive_chi2_test": {
                "chi2": res.naive_chi2,
                "dof": res.naive_dof,
                "p_value": res.naive_p_value,
                "compatible": res.naive_compatible,
            },
            "runs": res.runs,
            "alpha": res.alpha,
            "n_failed": res.n_failed,
        }
        write_json_file(args.json, out, "--json ")  # strict: undefined values are null
    return 0 if res.compatible else 1
