"""``tlsjax report CAL.json --html report.html``: the calibration report of a result JSON."""

from __future__ import annotations

import tlsjax as tj

from ._common import EXIT_OK


def add_report_parser(sub):
    p = sub.add_parser(
        "report",
        help="write the HTML calibration report of a result JSON",
        description="One self-contained HTML file (plots embedded) from the result JSON of "
        "`tlsjax calibrate --json`: design, global test, AP table, variance components, "
        "redundancy, reliability, outliers, plots and what produced it.",
    )
    p.add_argument("calibration", help="result JSON (SPEC section 11)")
    p.add_argument("--html", required=True, help="output HTML file")
    p.add_argument(
        "--plots", help="folder of PNG plots to embed (e.g. the --plots folder of calibrate)"
    )
    p.set_defaults(func=cli_report)
    return p


def cli_report(args) -> int:
    import os

    pngs = []
    if args.plots and os.path.isdir(args.plots):
        pngs = [("--plots", os.path.join(args.plots, n)) for n in os.listdir(args.plots)]
    tj.check_outputs([("--html", args.html)], [("calibration", args.calibration)] + pngs)
    print(f"wrote {tj.report_from_json(args.calibration, args.html, plots_dir=args.plots)}")
    return EXIT_OK
