"""Target detection in simulated halls at 5-30 m with realistic noise on dark print (issue 38).

Usage::

    python benchmarks/bench_target_rooms.py [--seeds 3] [--out benchmarks/results/target_rooms.json]

Per seed: a 36 x 14 x 5 m hall scanned once from each of four stations along it (levelled
scans, hybrid scanner, APs A0 B6 B7 C0 at SPEC section 8's values); a random field of 14
spheres (72.5 mm), 14 checkerboards and 6 circles (15 cm) (``tj.place_targets``); each target
on a 0.03 deg grid (1.6 mm at 3 m, 16 mm at 30 m: no fine scan), the hall on 3 deg. Noise: 20"
in angle and, in range, ``--sigma-range-mm`` (default 1.0) on white, ``--dark-factor`` (default
4) times that on a target's black print (``CloudDesign.dark_noise_factor``: a phase scanner's
range noise grows as the returned power falls, 3-5 times on black paper), interpolated by the
dark share of the footprint. Every scan's targets are extracted with the defaults
(``tj.extract_targets``: tests from the scan's own noise, the size a prior).

Scored: every (scan, target) at 5-30 m in range. A target is *visible* in a scan when it has
at least 30 points there (the extraction's ``min_points``) and, for planar ones, an incidence
below 70 deg; *well sampled* when it also has at least 150. Per kind and per 5 m range band:
visible, found (an accepted detection within 3 cm of the true centre), false detections
(accepted, no true target within 3 cm), centre errors (median, 95th percentile, largest, mm,
against the noise-free observation of the centre with the APs applied). The worst centres of
each kind are listed with their range, incidence and point count. Wall time of the extraction
per seed. JSON with the date, machine and load average in benchmarks/results/.
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _common import loadavg, write_results  # noqa: E402

DEG = np.pi / 180
BANDS = ((5, 10), (10, 15), (15, 20), (20, 25), (25, 30))
STATIONS = ((3.0, 7.0, 1.6), (12.0, 4.0, 1.6), (24.0, 10.0, 1.6), (33.0, 7.0, 1.6))


def run(seed, sigma_range, dark_factor):
    import tlsjax as tj
    from tlsjax._model._geometry import cartesian_from_spherical, rotation_matrix

    room = tj.Room(length=36.0, width=14.0, height=5.0, stations=STATIONS)
    targets = tj.place_targets(room, spheres=14, checkerboards=14, circles=6, seed=seed)
    scans = tuple((*st, 0.0, 0.0, float(k) * 1.3) for k, st in enumerate(STATIONS))
    design = tj.CloudDesign(
        room=room, scans=scans, angular_step=3 * DEG, target_step=0.03 * DEG,
        sigma_range=sigma_range, dark_noise_factor=dark_factor, **targets,
    )  # fmt: skip
    pc = tj.simulate_point_clouds(design, seed=seed)
    opts = tj.TargetExtractionOptions(spheres=(0.0725,), checkerboards=True, circles=True)
    t0 = time.perf_counter()
    found = tj.extract_targets(pc.observations, opts, intensity=pc.intensity, names=pc.scans)
    wall = time.perf_counter() - t0
    truth = pc.target_observations()
    rows = []
    n_sph = len(design.spheres)
    for j, scan in enumerate(pc.scans):
        ids = pc.target_ids[j]
        counts = np.bincount(ids[ids >= 0], minlength=len(pc.target_names))
        R = rotation_matrix(*pc.eops[j][3:], xp=np)
        acc = np.flatnonzero(found.accepted & (found.scan_index == j))
        used = set()
        for t, name in enumerate(pc.target_names):
            if (scan, name) not in truth:
                continue
            X = cartesian_from_spherical(truth[(scan, name)], xp=np)
            d = [np.linalg.norm(found.centre[i] - X) for i in acc]
            hit = int(acc[int(np.argmin(d))]) if d and min(d) < 0.03 else None
            if hit is not None:
                used.add(hit)
            rng_m = float(np.linalg.norm(X))
            if not 5.0 <= rng_m <= 30.0:
                continue
            kind = pc.target_kinds[t]
            incidence = 0.0
            if kind != "sphere":
                c = R @ (pc.target_centres[t] - pc.eops[j][:3])
                n = R @ np.asarray(design.planar_targets[t - n_sph].normal)
                incidence = float(np.degrees(np.arccos(abs(n @ c) / np.linalg.norm(c))))
            visible = counts[t] >= 30 and incidence < 70.0
            rows.append(dict(
                seed=seed, scan=scan, target=name, kind=kind, range_m=rng_m,
                incidence_deg=incidence, points=int(counts[t]), visible=bool(visible),
                well_sampled=bool(visible and counts[t] >= 150), found=hit is not None,
                error_mm=float(min(d)) * 1e3 if hit is not None else None,
                # The error in units of the extraction's own sigma along it: about 1 (chi,
                # one degree of freedom) when the error is the noise it predicts, not a bias.
                error_sigmas=_sigmas(found, hit, X) if hit is not None else None,
                reason=None if hit is not None else _reason(found, j, X),
            ))  # fmt: skip
        for i in set(acc) - used:
            rows.append(dict(seed=seed, kind=str(found.kind[i]), false=True))
    return rows, wall


def _sigmas(found, i, X):
    e = found.centre[i] - X
    u = e / max(np.linalg.norm(e), 1e-15)
    return float(np.linalg.norm(e) / np.sqrt(u @ found.covariance[i] @ u))


def _reason(found, j, X):
    """Why the nearest rejected candidate of scan j (within 5 cm of X) was rejected."""
    sel = np.flatnonzero((found.scan_index == j) & ~found.accepted)
    if not len(sel):
        return "no candidate"
    d = np.linalg.norm(found.centre[sel] - X, axis=1)
    k = int(np.argmin(d))
    return str(found.reason[sel[k]]) if d[k] < 0.05 else "no candidate"


def _errors(rows):
    err = np.array([r["error_mm"] for r in rows if r["found"]])
    if not len(err):
        return {"error_mm_median": None, "error_mm_p95": None, "error_mm_max": None}
    sig = np.array([r["error_sigmas"] for r in rows if r["found"]])
    return {
        "error_mm_median": round(float(np.median(err)), 3),
        "error_mm_p95": round(float(np.percentile(err, 95)), 3),
        "error_mm_max": round(float(err.max()), 3),
        "error_sigmas_median": round(float(np.median(sig)), 2),
    }


def _summary(rows, kind):
    mine = [r for r in rows if r.get("kind") == kind and not r.get("false")]
    vis = [r for r in mine if r["visible"]]
    well = [r for r in vis if r["well_sampled"]]
    out = {
        "visible": len(vis),
        "found": sum(r["found"] for r in vis),
        "detection_rate": round(sum(r["found"] for r in vis) / len(vis), 4) if vis else None,
        "well_sampled": len(well),
        "found_well_sampled": sum(r["found"] for r in well),
        "detection_rate_well_sampled": (
            round(sum(r["found"] for r in well) / len(well), 4) if well else None
        ),
        "false_detections": sum(1 for r in rows if r.get("kind") == kind and r.get("false")),
        **_errors(vis),
        "bands": {},
    }
    for lo, hi in BANDS:
        band = [r for r in vis if lo <= r["range_m"] < hi or (hi == 30 and r["range_m"] == 30)]
        out["bands"][f"{lo}-{hi} m"] = {
            "visible": len(band),
            "found": sum(r["found"] for r in band),
            "median_points": int(np.median([r["points"] for r in band])) if band else None,
            **_errors(band),
        }
    worst = sorted((r for r in vis if r["found"]), key=lambda r: -r["error_mm"])[:5]
    keys = ("seed", "scan", "target", "range_m", "incidence_deg", "points", "error_mm",
            "error_sigmas")  # fmt: skip
    out["worst"] = [{k: (round(r[k], 2) if isinstance(r[k], float) else r[k]) for k in keys}
                    for r in worst]  # fmt: skip
    missed = [r for r in vis if not r["found"]]
    out["missed"] = [
        {k: (round(r[k], 2) if isinstance(r[k], float) else r[k]) for k in keys[:-2] + ("reason",)}
        for r in missed
    ]
    return out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--sigma-range-mm", type=float, default=1.0)
    ap.add_argument("--dark-factor", type=float, default=4.0)
    ap.add_argument("--out", default=str(Path(__file__).parent / "results" / "target_rooms.json"))
    args = ap.parse_args()
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    load_start = loadavg()
    rows, walls = [], []
    for seed in range(args.seeds):
        r, w = run(seed, args.sigma_range_mm * 1e-3, args.dark_factor)
        rows += r
        walls.append(round(w, 2))
        print(f"seed {seed}: extraction {w:.1f} s", flush=True)
    out = {
        "date": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
        "machine": {
            "platform": platform.platform(),
            "processor": platform.processor() or platform.machine(),
            "cpus": os.cpu_count(),
            "python": platform.python_version(),
        },
        "load_average_start": load_start,
        "load_average_end": loadavg(),
        "seeds": args.seeds,
        "noise": {
            "sigma_range_mm_white": args.sigma_range_mm,
            "dark_factor": args.dark_factor,
            "sigma_angle_arcsec": 20.0,
            "target_step_deg": 0.03,
        },  # fmt: skip
        "extract_wall_s": walls,
        "kinds": {k: _summary(rows, k) for k in ("sphere", "checkerboard", "circle")},
    }
    write_results(out, args.out)
    for k, v in out["kinds"].items():
        print(k, {key: v[key] for key in ("visible", "found", "false_detections")},
              {b: (s["found"], s["visible"], s["error_mm_median"], s["error_mm_max"])
               for b, s in v["bands"].items()})  # fmt: skip


if __name__ == "__main__":
    main()
