"""Detection rates of the statistical tests over many simulated networks (issue #3).

Usage::

    JAX_PLATFORMS=cpu python benchmarks/stats_rates.py snoop --seeds 30
    JAX_PLATFORMS=cpu python benchmarks/stats_rates.py vce --seeds 30
    JAX_PLATFORMS=cpu python benchmarks/stats_rates.py select --seeds 20

``snoop``: the Chow et al. 2013 room (120 targets, 6 scans, tilted, hybrid, true APs A0 B6 B7
C0; 720 target observations = 2,160 observations), five 20-sigma blunders in five random
observations (random sign, distinct target observations); data snooping with VCE at two
levels: the per-test 3.29 (alpha = 0.1 %) and Bonferroni (family-wise alpha = 5 %, i.e. no clean
observation removed in 95 % of networks). Counts found blunders and false removals.

``vce``: the same room without blunders, analysed with deliberately wrong a priori sigmas
(range 1.0 mm instead of 0.5 mm, hz 10" instead of 20", el 30" instead of 20", levelling 20"
instead of 10"); reports the re-estimated sigmas against the simulated ones.

``select``: stepwise AP selection starting from no APs, candidates A0 A2 B6 B7 B8 C0 C6 C7,
truth A0 B6 B7 C0; confusion counts per term.

Writes JSON to ``benchmarks/results/stats_<what>.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import tlsjax as tj  # noqa: E402

TRUE_APS = ("A0", "B6", "B7", "C0")


def inject_blunders(net, rng, k=5, size=20.0):
    obs = net.observations.copy()
    rows = rng.choice(len(obs), k, replace=False)
    cols = rng.integers(0, 3, k)
    for i, c in zip(rows, cols):
        obs[i, c] += size * net.sigmas[i, c] * rng.choice([-1.0, 1.0])
    return net.with_observations(obs), set(zip(rows.tolist(), cols.tolist()))


def run_snoop(seeds):
    model = tj.CalibrationModel(tj.Scanner(aps=TRUE_APS))
    levels = {
        "alpha=0.001 (k=3.29)": tj.SnoopingOptions(w_test_level=0.001),
        "bonferroni family alpha=0.05": tj.SnoopingOptions(w_test_level=0.05, bonferroni=True),
        "target removal, bonferroni 0.05": tj.SnoopingOptions(
            w_test_level=0.05, bonferroni=True, removal="target"
        ),
    }
    out = {
        name: {
            "found": 0,
            "injected": 0,
            "false_removals": 0,
            "networks_with_false_removal": 0,
            "networks_all_found": 0,
            "per_seed": [],
        }
        for name in levels
    }
    for seed in seeds:
        sim = tj.simulate(seed=seed, aps=" ".join(TRUE_APS))
        rng = np.random.default_rng(1000 + seed)
        net, truth = inject_blunders(sim.network, rng)
        for name, opt in levels.items():
            t = time.perf_counter()
            r = tj.self_calibrate(net, model, tj.CalibrationOptions(snooping=opt))
            dt = time.perf_counter() - t
            removed = {(o.row, ("range", "hz", "el").index(o.group)) for o in r.outliers}
            if opt.removal == "target":
                hit_rows = {o.row for o in r.outliers}
                found = sum(1 for (i, c) in truth if i in hit_rows)
                false = len({o.row for o in r.outliers} - {i for i, _ in truth})
            else:
                found = len(truth & removed)
                false = len(removed - truth)
            d = out[name]
            d["found"] += found
            d["injected"] += len(truth)
            d["false_removals"] += false
            d["networks_with_false_removal"] += int(false > 0)
            d["networks_all_found"] += int(found == len(truth))
            d["per_seed"].append(
                {
                    "seed": seed,
                    "found": found,
                    "false": false,
                    "n_adjustments": r.n_adjustments,
                    "critical": r.critical_value,
                    "seconds": round(dt, 3),
                    "result": r.calibration.result,
                }
            )
        print(
            seed,
            {k: (v["per_seed"][-1]["found"], v["per_seed"][-1]["false"]) for k, v in out.items()},
            flush=True,
        )
    for d in out.values():
        d["detection_rate"] = d["found"] / max(d["injected"], 1)
    return {
        "n_seeds": len(seeds),
        "n_observations": int(sim.network.n_observations),
        "blunders_per_network": 5,
        "blunder_size_sigma": 20.0,
        "levels": out,
    }


def run_vce(seeds):
    model = tj.CalibrationModel(tj.Scanner(aps=TRUE_APS))
    wrong = np.array([2.0, 0.5, 1.5])  # a priori sigma / true sigma per group
    wrong_lev = 2.0
    true = {
        "range": 0.5,
        "hz": 20.0,
        "el": 20.0,
        "levelling": 10.0,
    }  # mm, arcsec (at normal incidence)
    rows = []
    for seed in seeds:
        sim = tj.simulate(seed=seed, aps=" ".join(TRUE_APS))
        net = dataclasses.replace(
            sim.network,
            sigmas=sim.network.sigmas * wrong[None, :],
            levelling_sigma=sim.network.levelling_sigma * wrong_lev,
        )
        r = tj.self_calibrate(net, model)
        est = {}
        for vc in r.variance_components:
            # Estimated true sigma = a priori (wrong) sigma x sqrt(factor), in the nominal units.
            w = {"range": wrong[0], "hz": wrong[1], "el": wrong[2], "levelling": wrong_lev}[
                vc.group
            ]
            est[vc.group] = true[vc.group] * w * vc.sigma_factor
        rows.append(
            {
                "seed": seed,
                "estimated_sigma": est,
                "n_adjustments": r.n_adjustments,
                "group_redundancy": {vc.group: vc.redundancy for vc in r.variance_components},
            }
        )
        print(seed, {k: round(v, 3) for k, v in est.items()}, flush=True)
    summary = {}
    for g in true:
        v = np.array([row["estimated_sigma"][g] for row in rows])
        ratio = v / true[g]
        summary[g] = {
            "true": true[g],
            "a_priori_given": true[g]
            * {"range": wrong[0], "hz": wrong[1], "el": wrong[2], "levelling": wrong_lev}[g],
            "mean_estimate": float(v.mean()),
            "mean_ratio": float(ratio.mean()),
            "sd_ratio": float(ratio.std(ddof=1)),
            "max_abs_dev_percent": float(np.abs(ratio - 1).max() * 100),
            "unit": "mm" if g == "range" else "arcsec",
        }
    return {"n_seeds": len(seeds), "summary": summary, "per_seed": rows}


def run_select(seeds):
    candidates = ("A0", "A2", "B6", "B7", "B8", "C0", "C6", "C7")
    conf = {c: {"tp": 0, "fp": 0, "fn": 0, "tn": 0} for c in candidates}
    exact = 0
    rows = []
    for seed in seeds:
        sim = tj.simulate(seed=seed, aps=" ".join(TRUE_APS))
        t = time.perf_counter()
        selection = tj.SelectionOptions(candidates=candidates)
        sel = tj.self_calibrate(
            sim.network,
            tj.CalibrationModel(tj.Scanner(aps=())),
            tj.CalibrationOptions(vce=None, selection=selection),
        ).selection
        dt = time.perf_counter() - t
        chosen = set(sel.aps)
        for c in candidates:
            key = (
                ("tp" if c in chosen else "fn")
                if c in TRUE_APS
                else ("fp" if c in chosen else "tn")
            )
            conf[c][key] += 1
        exact += int(chosen == set(TRUE_APS))
        rows.append(
            {"seed": seed, "chosen": sorted(chosen), "n_fits": sel.n_fits, "seconds": round(dt, 2)}
        )
        print(seed, sorted(chosen), sel.n_fits, round(dt, 1), flush=True)
    return {
        "n_seeds": len(seeds),
        "true": list(TRUE_APS),
        "candidates": list(candidates),
        "exact_matches": exact,
        "confusion": conf,
        "per_seed": rows,
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("what", choices=("snoop", "vce", "select"))
    ap.add_argument("--seeds", type=int, default=30)
    ap.add_argument("--first-seed", type=int, default=0)
    ap.add_argument("--out", default=None)
    a = ap.parse_args(argv)
    seeds = list(range(a.first_seed, a.first_seed + a.seeds))
    t = time.perf_counter()
    res = {"snoop": run_snoop, "vce": run_vce, "select": run_select}[a.what](seeds)
    res["wall_seconds"] = round(time.perf_counter() - t, 1)
    res["machine"] = platform.platform()
    res["command"] = "python benchmarks/stats_rates.py " + " ".join(
        argv if argv is not None else sys.argv[1:]
    )
    out = Path(a.out or Path(__file__).parent / "results" / f"stats_{a.what}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(res, indent=1, default=float))
    print("wrote", out)


if __name__ == "__main__":
    main()
