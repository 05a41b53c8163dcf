"""Build and execute notebooks/05_design_optimisation.ipynb.

Run from the repository root:  python notebooks/_make_05.py
(writes the notebook with its outputs; needs the ``python3`` Jupyter kernel). With
``TLSJAX_NOTEBOOK_FAST=1`` the optimiser runs 2 starts x 20 steps instead of 8 x 150 (the test
suite's mode; the conclusions in the last cell are from the full run).
"""

from _nbtools import Builder

BUILD = Builder("05_design_optimisation.ipynb")
md, code = BUILD.md, BUILD.code

md(r"""
# 05 - Design optimisation: which tilts, stations and boards?

**Question.** Chow, Lichti, Glennie and Hartzell (2013, section 4.1) show by simulation that
rolling two of the six scans of the calibration room by -45 and +45 deg decorrelates the
collimation axis error B6 from the scans' kappa for a hybrid scanner: sigma(B6) drops by 86 %
against the all-levelled design. That design was chosen by hand. With a differentiable
adjustment the question becomes: starting from the levelled room, **which tilts and station
positions minimise sigma(B6)**, how much better than the paper's hand-chosen design is that,
what does it do to the B6-kappa correlation, and, for a plane-based room, **which extra boards
help most**?

**Set-up.** The room of notebooks 01-03: 14 m x 11 m x 3 m, 120 targets on the six faces, two
stations with three scans each 60 deg apart in kappa; noise 0.5 mm (range, at normal incidence)
and 20" (both angles); compensator observations of 10" on the levelled scans; hybrid scanner
with the four physical APs A0, B6, B7, C0. The design variables: the two stations (X, Y, Z, at
least 0.5 m from the walls, 0.5-2.5 m high) and the roll and pitch of scans 5 and 6 (the
paper's tilted scans; no compensator; within +-60 deg). Four scans stay levelled.

**Criterion.** sigma(B6) in units of a 1" tolerance, a priori (sigma0 = 1), from the
linearisation at the true parameters: it needs no noise and is a differentiable function of the
design (`tj.design_criterion`). The optimiser is Adam (optax) on the box-constrained variables,
several random starts at once (`tj.optimize_design`). Every number in the comparison tables
comes from an **independent** `tj.calibrate` of a noisy simulated network of each design (a
priori sigmas = a posteriori sigmas / sigma0), not from the optimiser.
""")

code(r"""
import os
import time

import matplotlib.pyplot as plt
import numpy as np

import tlsjax as tj

T_START = time.perf_counter()
FAST = os.environ.get("TLSJAX_NOTEBOOK_FAST") == "1"
STARTS, STEPS = (2, 20) if FAST else (8, 150)
SEED = 0
ARCSEC = np.pi / 648000
DEG = np.pi / 180
APS = "A0 B6 B7 C0"
B6_TOL = {"B6": 1 * ARCSEC}

levelled = tj.simulate(seed=SEED, architecture="hybrid", tilted=False, aps=APS)
paper = tj.simulate(seed=SEED, architecture="hybrid", tilted=True, aps=APS)
mask = np.array([True, True, True, True, False, False])      # scans 5 and 6 may tilt
start = tj.TargetDesign.from_simulation(levelled)
paper_design = tj.TargetDesign.from_simulation(paper)
dn = tj.DesignProblem.targets(start, levelled.scanner, levelled=mask)
space = tj.DesignSpace()                                       # the Chow room, clearance 0.5 m
sigma_b6 = tj.DesignCriterion("max_sigma", aps="B6", tolerances=B6_TOL)
print(f"fast mode: {FAST}; optimiser: {STARTS} starts x {STEPS} steps")
""")

md(r"""
## 1. The optimiser

`tj.optimize_design` descends the criterion from the levelled room (nudged, since the levelled
design itself has no finite gradient) and from random designs inside the bounds. The curves show
the criterion of every start along the descent.
""")

code(r"""
t0 = time.perf_counter()
opt = tj.optimize_design(dn, sigma_b6, space, starts=STARTS, steps=STEPS, seed=SEED, progress=False)
print(f"optimiser: {time.perf_counter() - t0:.1f} s wall ({opt.compile_s:.1f} s compile, {opt.run_s:.1f} s descent)")
print(f"sigma(B6) / 1\": levelled start {opt.start_value:.2f}, optimised {opt.value:.3f} (best of {STARTS} starts)")
print("best of every start:", np.round(opt.values, 3))

fig, ax = plt.subplots(figsize=(6, 3.2))
ax.semilogy(opt.history)
ax.set_xlabel("Adam step")
ax.set_ylabel('smooth sigma(B6) / 1" [-]')
ax.set_title("descent of every start")
fig.tight_layout()
""")

code(r"""
def show(design, title):
    e = np.asarray(design.eops)
    print(title)
    print(f"{'scan':>5} {'X [m]':>7} {'Y [m]':>7} {'Z [m]':>7} {'omega [deg]':>12} {'phi [deg]':>10} {'kappa [deg]':>12}")
    for j, r in enumerate(e):
        print(f"S{j + 1:<4d} {r[0]:7.2f} {r[1]:7.2f} {r[2]:7.2f} {r[3] / DEG:12.1f} {r[4] / DEG:10.1f} {r[5] / DEG:12.1f}")


show(paper_design, "the paper's tilted design (Chow et al. 2013)")
show(opt.design, "\nthe optimised design")
""")

md(r"""
## 2. Independent check: `tj.calibrate` of each design

A noisy network of each design (seed 1), self-calibrated by `tj.calibrate` with the full
covariance matrix; a priori sigmas (a posteriori / sigma0) in mm and ", and the largest
|correlation| of B6 with the kappa of any scan (inner-constraint datum).
""")

code(r"""
def check(design, label, seed=1):
    res = tj.calibrate(dn.network(design, seed=seed), dn.model, tj.SolverOptions(full_covariance=True))
    sig = res.ap_sigmas / res.sigma0
    C = np.abs(res.correlation())
    names = res.parameter_names
    b6 = names.index("B6")
    kappas = [i for i, n in enumerate(names) if n.startswith("kappa[")]
    return {
        "design": label,
        "result": res.message,
        "A0 [mm]": sig[0] * 1e3,
        'B6 ["]': sig[1] / ARCSEC,
        'B7 ["]': sig[2] / ARCSEC,
        'C0 ["]': sig[3] / ARCSEC,
        "B6-kappa": C[b6, kappas].max() if np.isfinite(sig[1]) else np.nan,
    }


rows = [check(start, "levelled"), check(paper_design, "paper: rolls -45/+45"), check(opt.design, "optimised")]
keys = list(rows[0])[2:]
print(f"{'design':22s}" + "".join(f"{k:>11s}" for k in keys))
for r in rows:
    print(f"{r['design']:22s}" + "".join(f"{r[k]:11.3f}" for k in keys) + "   " + r["result"][:40])
lv, pp, op = (r['B6 ["]'] for r in rows)
print(f"\nsigma(B6): paper vs levelled {100 * (pp / lv - 1):+.0f} %, optimised vs levelled {100 * (op / lv - 1):+.0f} %, "
      f"optimised vs paper {100 * (op / pp - 1):+.0f} %")
print(f"B6-kappa |corr|: levelled {rows[0]['B6-kappa']:.3f}, paper {rows[1]['B6-kappa']:.3f}, optimised {rows[2]['B6-kappa']:.3f}")
print(f"optimiser's own prediction for the optimised design: {opt.value:.3f}\" (calibrate: {op:.3f}\")")
""")

md(r"""
## 3. Decorrelating B6 from kappa

The same search with the criterion "largest |correlation| of B6 with the other APs and the scan
poses" (smooth p-norm), i.e. the B6-kappa correlation of the paper's Table 5.
""")

code(r"""
corr_b6 = tj.DesignCriterion("max_correlation", aps="B6", with_poses=True)
opt_c = tj.optimize_design(dn, corr_b6, space, starts=STARTS, steps=STEPS, seed=SEED, progress=False)
print(f"max |corr(B6, .)|: start {opt_c.start_value:.3f}, paper {tj.design_criterion(dn, paper_design, corr_b6, smooth=False):.3f}, "
      f"optimised {opt_c.value:.3f}")
r = check(opt_c.design, "optimised for |corr|")
b6 = r['B6 ["]']
print(f"independent calibrate: B6-kappa {r['B6-kappa']:.3f}, sigma(B6) {b6:.3f} arcsec")
show(opt_c.design, "design")
""")

md(r"""
## 4. Plane-based room: which extra boards help most?

Point clouds of the same room (tilted design of the paper, hybrid scanner), sampled on a 2 deg
grid, at most 25 points per plane and scan. Candidate boards of different orientations are all
in the simulation; a board "left out" has its rows' information scaled by 1e-6 (sigmas x 1000), so that one
compiled criterion compares every subset. Criterion: the largest AP sigma in units of
0.05 mm (A0) and 1" (angles). Boards are added greedily, best first; the final choice is checked
by an independent `tj.calibrate` of the network with and without the chosen boards.
""")

code(r"""
import jax

CANDIDATES = tuple(tj.CloudDesign().boards) + (
    tj.Board.tilted((4.0, 2.0, 0.8), 1.2, 1.0, azimuth=60 * DEG, tilt=45 * DEG),
    tj.Board.tilted((10.0, 9.0, 2.2), 1.2, 1.0, azimuth=-120 * DEG, tilt=-45 * DEG),
    tj.Board.tilted((12.5, 8.0, 1.5), 1.2, 1.0, azimuth=200 * DEG, tilt=0.0),
)
STEP, MAX_POINTS = (3 * DEG, 12) if FAST else (2 * DEG, 25)
clouds = tj.simulate_point_clouds(tj.CloudDesign(angular_step=STEP, boards=CANDIDATES, aps=APS), seed=SEED)
pdn = tj.DesignProblem.from_point_clouds(clouds, max_points=MAX_POINTS, seed=SEED)
tol = {"A0": 0.05e-3, "B6": ARCSEC, "B7": ARCSEC, "C0": ARCSEC}
crit = tj.DesignCriterion("max_sigma", tolerances=tol)
plane_of_row = pdn.prim_index
n_faces = 6
value = jax.jit(lambda info: tj.predicted_cofactor(pdn, pdn.design, info))


def criterion(boards):
    keep = (plane_of_row < n_faces) | np.isin(plane_of_row - n_faces, list(boards))
    Q = value(np.where(keep, 1.0, 1e-6))
    return crit.exact(Q, len(clouds.scans), clouds.scanner.aps), np.sqrt(np.diag(np.asarray(Q)))[-4:]


base, base_sig = criterion([])
print(f"faces only: criterion {base:.3f}")
for b in range(len(CANDIDATES)):
    v, s = criterion([b])
    print(f"+ board {b + 1}: criterion {v:.3f} ({100 * (v / base - 1):+.0f} %)")
chosen, current = [], base
for _ in range(3):
    best = min((b for b in range(len(CANDIDATES)) if b not in chosen), key=lambda b: criterion(chosen + [b])[0])
    chosen.append(best)
    current = criterion(chosen)[0]
    print(f"greedy: boards {[c + 1 for c in chosen]} -> criterion {current:.3f}")
""")

code(r"""
def plane_check(boards, seed=1):
    keep = (plane_of_row < n_faces) | np.isin(plane_of_row - n_faces, list(boards))
    net = pdn.network(pdn.design, seed=seed, rows=keep)
    res = tj.calibrate(net, pdn.model, tj.SolverOptions(full_covariance=True))
    return res, res.ap_sigmas / res.sigma0


for label, boards in (("faces only", []), ("faces + greedy boards", chosen)):
    res, sig = plane_check(boards)
    print(f"{label:24s} calibrate: A0 {sig[0] * 1e3:.4f} mm, B6 {sig[1] / ARCSEC:.3f}\", B7 {sig[2] / ARCSEC:.3f}\", "
          f"C0 {sig[3] / ARCSEC:.3f}\"  ({res.message})")
print(f"\nnotebook run time {time.perf_counter() - T_START:.0f} s")
""")

md(r"""
## Conclusions (full run: 8 starts x 150 steps, measured 2026-11-23 on 2 shared CPU cores)

| design | sigma(B6) ["] | B6-kappa abs(corr) | A0 [mm] | B7 ["] | C0 ["] |
|---|---|---|---|---|---|
| levelled (start) | 43.35 | 0.333 | 0.107 | 13.34 | 8.44 |
| paper: scans 5, 6 rolled -45/+45 deg | 5.72 | 0.193 | 0.106 | 2.42 | 2.94 |
| optimised for sigma(B6) | 0.99 | 0.138 | 0.118 | 0.83 | 2.43 |

(a priori sigmas from an independent `tj.calibrate` of a noisy network of each design)

* The paper's tilted design cuts sigma(B6) by 87 % against the levelled room (the paper: 86 %).
* The optimiser (65 s wall, of which 25 s compilation) tilts scans 5 and 6 in roll **and** pitch
  to the +-60 deg limit (omega 59 deg, phi 54-58 deg) and moves the stations to (4.8, 8.5, 1.8) m
  and (8.3, 6.3, 1.5) m: sigma(B6) 0.99", 98 % below the levelled room and **83 % below the
  paper's design**; the B6-kappa correlation drops from 0.193 to 0.138; B7 and C0 also improve,
  A0 loses 0.012 mm. The optimiser's own prediction (0.991") and the independent calibrate
  (0.990") agree. The tilts sit on their bound: a larger tilt limit would help further.
* Minimising the largest abs(correlation) of B6 instead gives 0.097 (paper 0.193) at a sigma(B6)
  of 3.4": decorrelation and precision are different optima.
* Plane-based room: the extra boards help little here (each at most -4 % on the largest
  sigma/tolerance, which is B6 at 25"); board 1 (the default board facing azimuth -40 deg,
  tilted 25 deg) helps most, and three boards chosen greedily (1, 5, 4) give -8 % (calibrate:
  sigma(B6) 25.1" -> 23.2", C0 4.13" -> 3.60"). The scan geometry, not the boards, dominates.
""")

if __name__ == "__main__":
    BUILD.run()
