"""``tlsjax montecarlo --aps "A0 B6 B7 C0" --runs 1000``."""

from __future__ import annotations

import tlsjax as tj

from ._checks import non_negative_int, positive_int, state_cost
from ._common import devices_arg


def add_montecarlo_parser(subparsers):
    """``tlsjax montecarlo --aps "A0 B6 B7 C0" --runs 1000`` (wire into the CLI)."""
    p = subparsers.add_parser(
        "montecarlo", help="Monte Carlo self-calibration of the simulated room (SPEC section 9)"
    )
    p.add_argument("--room", default="14x11x3", help="room LxWxH in metres (default 14x11x3)")
    p.add_argument(
        "--targets", type=positive_int, default=120, help="number of targets (default 120)"
    )
    p.add_argument(
        "--aps", default="A0 B6 B7 C0", help="APs in the data and the model (names or presets)"
    )
    p.add_argument("--architecture", default="hybrid", choices=("hybrid", "panoramic"))
    p.add_argument(
        "--levelled", action="store_true", help="all scans levelled (default: tilted variant)"
    )
    p.add_argument("--runs", type=positive_int, default=1000)
    p.add_argument(
        "--chunk-size",
        type=positive_int,
        default=tj.MonteCarloOptions().chunk_size,
        help="realisations per compiled call (default: from the design, about 4 MB of Jacobian rows per device)",
    )
    p.add_argument(
        "--seed",
        type=non_negative_int,
        default=0,
        help="seed of the realisations (the design uses seed 0)",
    )
    p.add_argument("--png", default=None, help="write the plot to this PNG file")
    p.add_argument("--json", default=None, help="write the summary as JSON to this file")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    devices_arg(p)
    p.set_defaults(func=cli_montecarlo)
    return p


def cli_montecarlo(args) -> int:
    """CLI handler: prints the table; exit code 0 when every realisation converged. Failed
    realisations are explained by a plain calibration of the noise-free design (the reason
    ``tlsjax calibrate`` would give, e.g. an AP that needs an independent scale)."""
    tj.check_outputs([("--json", args.json), ("--png", args.png)])  # before the realisations run
    if args.runs < 2:
        raise ValueError(
            f"--runs {args.runs}: an empirical sigma needs at least 2 realisations (1,000 is usual)"
        )
    room = tj.Room.parse(args.room, n_targets=args.targets)
    sim = tj.simulate(
        room, architecture=args.architecture, tilted=not args.levelled, aps=args.aps, seed=0
    )
    a = len(sim.scanner.aps)
    state_cost(
        "the Monte Carlo run",
        "--runs",
        args.runs,
        rows=len(sim.network.observations),
        parameters=6 + a,
        devices=args.devices,
        result_bytes=8.0 * (a * a + 3 * a + 4),  # values, sigmas, truth, covariance, s0^2, code
        usual="1,000 is usual",
    )
    res = tj.monte_carlo(
        sim,
        None,
        tj.MonteCarloOptions(
            runs=args.runs,
            chunk_size=args.chunk_size,
            seed=args.seed,
            progress=not args.no_progress,
        ),
    )
    print(res.table())
    print(f"compile {res.compile_s:.1f} s, {res.runs} realisations in {res.run_s:.2f} s")
    summary = res.to_dict()
    if not res.ok.all():
        summary["diagnosis"] = _diagnose(sim)
        print(f"why realisations fail: {summary['diagnosis']}")
    if args.png:
        tj.plot_monte_carlo(res, args.png)  # atomic; the folder is created if missing
    if args.json:
        tj.write_json(summary, args.json)  # strict: undefined values are null
        print(f"wrote {args.json}")
    return 0 if res.ok.all() else 1


def _diagnose(sim) -> str:
    """The message of a plain calibration of the design's own (noise-free) network."""
    res = tj.calibrate(sim.network, tj.CalibrationModel(sim.scanner))
    if res.result == 0:
        return "the design itself calibrates (converged); the failures depend on the noise draws"
    return res.message
