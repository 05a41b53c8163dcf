"""Build and execute notebooks/04_compatibility.ipynb.

Run from the repository root:  python notebooks/_make_04.py
(writes the notebook with its outputs; needs the ``python3`` Jupyter kernel).
"""

from _nbtools import Builder

BUILD = Builder("04_compatibility.ipynb")
md, code = BUILD.md, BUILD.code


md(r"""
# 04 - Are two AP sets of one scanner compatible? The 1,000-simulation test

**Question.** Two calibrations of the same instrument give two sets of additional parameters
(APs) with their covariance matrices. Do they describe the same instrument?

Comparing the APs one by one misleads: the sets may differ in which terms are significant, and
the APs are correlated with the scan poses and with each other (Habib & Morgan 2005). Lichti
(2008) and Chow et al. (2013, section 4.3) compare their *joint effect in object space* by
simulation: 1,000 simulated scans of targets in a room of the real data's size, corrected with
each set, fitted onto each other on control points, compared at check points (SPEC section 9;
the statistic is written out in the docstring of `tj.compatibility_test`).

The paper compares point-based with plane-based AP sets. Plane-based self-calibration is not
built in tlsjax yet, so this notebook uses **two point-based sessions** of one simulated
instrument:

* sessions A and B: the Chow room (14 m x 11 m x 3 m, 120 targets, 6 scans, tilted variant,
  hybrid scanner, APs A0 B6 B7 C0) simulated twice with independent noise and target layouts:
  the same instrument, so the sets should be compatible;
* session C: the same instrument after a realistic change, the collimation error B6 larger by
  several sigma: the test should call A and C incompatible.

First, a Monte Carlo check of the design itself: do the formal sigmas of the APs describe their
scatter? Units: mm, arc seconds ("), ppm.
""")

code(r"""
import time

import numpy as np
import matplotlib.pyplot as plt

import tlsjax as tj

ARCSEC = np.pi / (180 * 3600)
APS = "A0 B6 B7 C0"
MODEL = tj.CalibrationModel(tj.Scanner(aps=APS))
""")

md(r"""
## 1. Monte Carlo of the calibration design (1,000 realisations)

Every realisation draws new observation noise (0.5 mm, 20") and levelling readings (10") from
its own key, `fold_in(PRNGKey(seed), k)`, and is self-calibrated from the simulated truth
(the standard Monte Carlo choice). All 1,000 run as one compiled, vmapped computation in chunks.
""")

code(r"""
design = tj.simulate(seed=0, aps=APS)
mc = tj.monte_carlo(design, MODEL, tj.MonteCarloOptions(runs=1000, seed=1, progress=False))
print(f"compile {mc.compile_s:.1f} s, 1,000 self-calibrations {mc.run_s:.2f} s "
      f"({mc.runs / mc.run_s:.0f} per second), iterations {np.bincount(mc.iterations).tolist()}")
print(mc.table())
fig = tj.plot_monte_carlo(mc)
plt.show()
""")

md(r"""
The ratio of empirical to formal sigma should be 1 within its sampling sigma
`1/sqrt(2 (N - 1)) = 0.022` for N = 1,000, and the mean of s0^2 within `sqrt(2 / r / N)`.
""")

md(r"""
## 2. Two sessions of one instrument

Each session is a separate simulation of the room (its own seed: new target layout and noise)
calibrated with `tj.calibrate`; the AP set with its full covariance comes from the result.
""")

code(r"""
def session(seed, true_aps=None):
    sim = tj.simulate(seed=seed, aps=APS, true_aps=true_aps)
    res = tj.calibrate(sim.network, MODEL)
    assert res.ok, res.message
    return tj.APSet.from_result(res)

set_a = session(seed=11)
set_b = session(seed=12)
for name, s in (("A", set_a), ("B", set_b)):
    print(name, "  ".join(f"{n} {v / ARCSEC if n != 'A0' else v * 1e3:8.2f} +- {np.sqrt(c) / ARCSEC if n != 'A0' else np.sqrt(c) * 1e3:.2f}"
                         for n, v, c in zip(s.names, s.values, np.diag(s.covariance))), '(A0 in mm, others in ")')
""")

code(r"""
t0 = time.perf_counter()
same = tj.compatibility_test(set_a, set_b, tj.Room(), options=tj.CompatibilityOptions(runs=1000, seed=2, progress=False))
print(f"1,000-run compatibility test: {time.perf_counter() - t0:.1f} s "
      f"(compile {same.compile_s:.1f} s, simulations {same.run_s:.2f} s)\n")
print(same.table())
""")

md(r"""
## 3. A changed instrument: collimation B6 larger by several sigma

Session C simulates the same instrument with B6 increased by 10 sigma of the A - C difference
(about 100" here), everything else equal.
""")

code(r"""
sd_b6 = np.sqrt(2) * np.sqrt(set_a.covariance[1, 1])
b6_c = 180 * ARCSEC + 10 * sd_b6
set_c = session(seed=13, true_aps={"B6": b6_c})
print(f'true B6 of session C: {b6_c / ARCSEC:.1f}" (sessions A and B: 180.0")')
t0 = time.perf_counter()
changed = tj.compatibility_test(set_a, set_c, tj.Room(), options=tj.CompatibilityOptions(runs=1000, seed=2, progress=False))
print(f"1,000-run compatibility test: {time.perf_counter() - t0:.1f} s\n")
print(changed.table())
""")

code(r"""
fig, ax = plt.subplots(1, 2, figsize=(10, 3.5), sharey=True)
for a, r, title in ((ax[0], same, "sessions A, B (same instrument)"), (ax[1], changed, "sessions A, C (B6 changed)")):
    bins = np.linspace(0, 100, 41)
    a.hist(100 * r.null_shares, bins=bins, color="0.8", label="null distribution")
    a.hist(100 * r.shares, bins=bins, histtype="step", color="k", label="observed")
    a.axvline(100 * r.null_quantile, color="r", ls="--", label=f"null {100 * (1 - r.alpha):g}% quantile")
    a.axvline(100 * r.median_share, color="k", lw=2, label="observed median")
    a.set_title(f"{title}: p = {r.p_value:.3f}", fontsize=10)
    a.set_xlabel("significant check points per simulation [%]")
ax[0].set_ylabel("simulations")
ax[1].legend(fontsize=8)
fig.tight_layout()
plt.show()
""")

md(r"""
## What this shows

* The formal AP sigmas of the Chow room describe the Monte Carlo scatter (ratios within a few
  percent of 1, mean s0^2 = 1), so the covariances that enter the test are right.
* The two sessions of one instrument are compatible: the median share of significant check
  points stays below the null distribution's 95% quantile. After a 10-sigma change of the
  collimation error the sets are incompatible, and the check-point differences (mm) show how
  much that change moves points in the room.
* The null distribution of the share is wide: when the AP difference is drawn, all check
  points move together, so a simulation has either few or many significant points. The group
  test keeps its level (about 5% rejections with both sets drawn from one truth) but needs a
  larger difference than the naive chi-square test of the AP differences to reject. The naive
  test, printed beside it, ignores that the APs are correlated with the scan poses; the group
  test asks whether the difference matters in object space.
* Timing: the 1,000 simulations with both AP sets and the null draws, including the autodiff
  covariance propagation through correction, conversion and the control-point fit, are one
  compiled, vmapped computation (times above; the machine is shared, so they vary).
""")

if __name__ == "__main__":
    BUILD.run()
