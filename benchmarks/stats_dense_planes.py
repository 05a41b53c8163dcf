"""Reported AP sigmas against Monte Carlo scatter on clouds with spatially correlated noise, with
and without the default thinning, at two densities (issue 27 item 7).

Usage::

    python benchmarks/stats_dense_planes.py [--runs 60] [--raw-runs 10]
                                            [--out benchmarks/results/stats_dense_planes.json]

Clouds: a 6 x 5 x 3 m room with two boards, two stations with three scans each (two rolled),
hybrid scanner, APs A0 B6 B7 C0; range noise 0.5 mm independent plus 0.5 mm correlated over
object space with a Gaussian correlation function of length L = 0.25 m (``CloudDesign.
correlated_sigma_range``), 20" in the angles. Thinning at 0.8 m = 3.2 L: the ratio of the
default 0.1 m to a 3 cm correlation length, scaled up so that the room stays small (the
statistics depend on spacing / L only). Densities: 4 and 2 deg steps (17,000 and 68,000
points). Per AP and pooled: ``sigma / scatter``, with scatter the RMS of (estimate - truth) over
the runs (bias included), and its Monte Carlo standard error ``ratio / sqrt(2 runs)`` per AP.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import loadavg, write_results  # noqa: E402

HERE = Path(__file__).resolve().parent
DEG = np.pi / 180
L_CORR, SPACING = 0.25, 0.8


def design(step):
    import tlsjax as tj

    return tj.CloudDesign(
        room=tj.Room(6.0, 5.0, 3.0, n_targets=12, stations=((2.0, 2.0, 1.5), (4.0, 3.2, 1.5))),
        boards=(
            tj.Board.tilted((1.0, 4.0, 1.2), 1.0, 0.8, azimuth=-40 * DEG, tilt=25 * DEG),
            tj.Board.tilted((5.0, 1.0, 1.0), 1.0, 0.8, azimuth=150 * DEG, tilt=-20 * DEG),
        ),
        angular_step=step,
        correlated_sigma_range=0.5e-3,
        correlation_length=L_CORR,
    )


def sigma_over_scatter(step, spacing, runs) -> dict:
    """One thinned design (the rows thinning keeps in the first realisation; the geometry is
    the same in all), ``runs`` noise realisations."""
    import tlsjax as tj
    from tlsjax._clouds._thin import take_rows, thin_indices

    d, keep, err, sig, names = design(step), None, [], [], None
    t0 = time.perf_counter()
    for seed in range(runs):
        pc = tj.simulate_point_clouds(d, seed=seed)
        table = pc.to_table()
        if keep is None:
            keep, n_all = thin_indices(table, spacing), len(table)
        net = tj.make_plane_network(
            take_rows(table, keep),
            sigma_range=pc.sigma_range,
            sigma_hz=pc.sigma_angle,
            sigma_el=pc.sigma_angle,
            levelling=pc.levelling,
        )
        res = tj.calibrate(net, tj.CalibrationModel(pc.scanner))
        names = res.ap_names
        err.append(res.ap_values - np.array([pc.true_aps[a] for a in names]))
        sig.append(res.ap_sigmas)
    err, sig = np.array(err), np.array(sig)
    ratio = np.mean(sig, axis=0) / np.sqrt(np.mean(err**2, axis=0))
    pooled = 1.0 / np.sqrt(np.mean((err / sig) ** 2))
    return {
        "angular_step_deg": step / DEG,
        "spacing_m": spacing,
        "points": int(n_all),
        "kept": int(len(keep)),
        "runs": runs,
        "sigma_over_scatter": dict(zip(names, np.round(ratio, 4).tolist())),
        "standard_error_per_ap": round(1.0 / np.sqrt(2 * runs), 4),
        "pooled": round(float(pooled), 4),
        "mean_error_over_sigma": dict(zip(names, np.round(np.mean(err / sig, 0), 3).tolist())),
        "wall_s": round(time.perf_counter() - t0, 1),
    }


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--runs", type=int, default=60)
    p.add_argument("--raw-runs", type=int, default=10)
    p.add_argument("--out", default=str(HERE / "results" / "stats_dense_planes.json"))
    args = p.parse_args(argv)
    cases = [(4 * DEG, SPACING, args.runs), (2 * DEG, SPACING, args.runs)]
    if args.raw_runs > 0:
        cases += [(4 * DEG, 0.0, args.raw_runs), (2 * DEG, 0.0, args.raw_runs)]
    results = {
        "benchmark": "dense plane sigmas against Monte Carlo scatter (issue 27 item 7)",
        "date": time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime()),
        "correlation_length_m": L_CORR,
        "loadavg_before": loadavg(),
        "cases": [],
    }
    for step, spacing, runs in cases:
        r = sigma_over_scatter(step, spacing, runs)
        print(
            f"step {r['angular_step_deg']:g} deg, spacing {spacing:g} m: {r['kept']} of "
            f"{r['points']} points, pooled sigma/scatter {r['pooled']:.3f}, per AP "
            f"{r['sigma_over_scatter']} (+-{r['standard_error_per_ap']:.3f} each)",
            flush=True,
        )
        results["cases"].append(r)
    results["loadavg_after"] = loadavg()
    write_results(results, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
