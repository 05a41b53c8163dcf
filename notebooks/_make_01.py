"""Build and execute notebooks/01_point_based_tilted_scans.ipynb.

Run from the repository root:  python notebooks/_make_01.py
(writes the notebook with its outputs; needs the ``python3`` Jupyter kernel).
"""

from _nbtools import Builder

BUILD = Builder("01_point_based_tilted_scans.ipynb")
md, code = BUILD.md, BUILD.code


md(r"""
# 01 - Point-based self-calibration: scanner architecture and tilted scans

**Question.** How do the scanner architecture (hybrid vs panoramic) and tilted scans change the
precision and the correlation of the additional parameters (APs) in point-based
self-calibration?

This notebook repeats the simulation of Chow et al. (2013), section 4 and 4.1 (Figures 14 and
15), with `tlsjax`:

* a 14 m x 11 m x 3 m room with 120 signalised targets on its six faces, every target seen from
  every scan (no field-of-view limit);
* two stations with three scans each, 60 deg apart in kappa; in the *tilted* design two scans of
  station 2 are rolled by -45 deg and +45 deg (omega); levelled scans carry levelling
  (compensator) observations of 10";
* noise 0.5 mm in range (normal incidence) and 20" in both angles; true APs 10 mm for the range
  terms, 180" (3') for the angular terms, 10 mm for B8 and C6;
* the full 23-term model `chow2013-noscale` (A0, A2-A4, B1-B10, C0-C8; the range scale A1 needs
  an independent scale and is left out), in the same form that generated the data.

The four configurations (hybrid / panoramic x levelled / tilted) use the same seed, so the
targets and the two station positions are the same in all of them.

Units in tables and plots: lengths in mm, angles in arc seconds ("), scale terms (B1, C1) in ppm.
""")

code(r"""
import time

import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

import tlsjax as tj

SEED = 0                      # one explicit seed for all four simulations
APS = "chow2013-noscale"      # A0, A2-A4, B1-B10, C0-C8
OPTIONS = tj.SolverOptions()  # convergence: largest update below 1e-6 of its sigma

RAD_TO_ARCSEC = 206264.806
DISPLAY = {"m": (1e3, "mm"), "rad": (RAD_TO_ARCSEC, '"'), "1": (1e6, "ppm")}  # SI unit -> (factor, label)

CONFIGS = [("hybrid", False), ("hybrid", True), ("panoramic", False), ("panoramic", True)]


def label(arch, tilted):
    return f"{arch}/{'tilted' if tilted else 'levelled'}"
""")

code(r"""
sims, results = {}, {}
for arch, tilted in CONFIGS:
    key = label(arch, tilted)
    t0 = time.perf_counter()
    sims[key] = tj.simulate(seed=SEED, architecture=arch, tilted=tilted, aps=APS, noise=True)
    results[key] = tj.calibrate(sims[key].network, tj.CalibrationModel(sims[key].scanner), OPTIONS)
    r = results[key]
    print(f"{key:20s} {r.message:22s} iterations {r.iterations:3d}  sigma0 {r.sigma0:.4f}  "
          f"dof {r.dof:.0f}  n_obs {r.n_observations}  ({time.perf_counter() - t0:.1f} s)")

names = results["hybrid/levelled"].ap_names
units = results["hybrid/levelled"].ap_units
assert all(r.ap_names == names for r in results.values())
keys = list(results)
scale = np.array([DISPLAY[u][0] for u in units])
unit_label = [DISPLAY[u][1] for u in units]
print("\nAPs:", " ".join(names))
""")

md(r"""
## 1. Are the true APs recovered?

For every AP: (estimate - truth) / sigma, with the a posteriori sigma. A joint check uses the
AP block of the covariance matrix: `d^T C^-1 d` for the 23 differences d, which should be a draw
from chi-square with 23 degrees of freedom (95% quantile 35.2) if the estimates are unbiased and
the covariance is right.
""")

code(r"""
CHI2_23_95 = 35.17

def ap_covariance(res):
    return res.ap_covariance

print(f"{'AP':4s} {'truth':>9s} {'unit':4s} " + " ".join(f"{k:>19s}" for k in keys))
z = {}
for k in keys:
    truth = np.array([sims[k].true_aps[n] for n in names])
    z[k] = (results[k].ap_values - truth) / results[k].ap_sigmas
for i, n in enumerate(names):
    truth = sims[keys[0]].true_aps[n] * scale[i]
    print(f"{n:4s} {truth:9.1f} {unit_label[i]:4s} " + " ".join(f"{z[k][i]:19.2f}" for k in keys))

print()
for k in keys:
    truth = np.array([sims[k].true_aps[n] for n in names])
    d = results[k].ap_values - truth
    chi2 = float(d @ np.linalg.solve(ap_covariance(results[k]), d))
    print(f"{k:20s} max |z| = {np.abs(z[k]).max():.2f}   joint d'C^-1 d = {chi2:6.1f}  (chi2_23, 95%: {CHI2_23_95})")
""")

md(r"""
## 2. Precision and correlation of the APs (the numbers behind Figures 14 and 15)

Sigma in display units for the four configurations, with the change that tilting brings
(negative = tilting reduces the sigma). Then the largest absolute correlation of each AP with
any other unknown (targets, scan poses, other APs) and the unknown it belongs to; the
correlations with poses and targets refer to the inner-constraint datum.
""")

code(r"""
sig = {k: results[k].ap_sigmas * scale for k in keys}
corr = {k: results[k].ap_max_abs_corr for k in keys}
partner = {k: results[k].ap_max_corr_with for k in keys}

def change(a, b):
    return 100.0 * (b - a) / a

hdr = (f"{'AP':4s} {'unit':4s} | {'hyb/lev':>9s} {'hyb/tilt':>9s} {'change':>7s} | "
       f"{'pan/lev':>9s} {'pan/tilt':>9s} {'change':>7s} | {'pan/hyb lev':>11s}")
print("A posteriori standard deviation of the APs")
print(hdr)
print("-" * len(hdr))
for i, n in enumerate(names):
    hl, ht = sig["hybrid/levelled"][i], sig["hybrid/tilted"][i]
    pl, pt = sig["panoramic/levelled"][i], sig["panoramic/tilted"][i]
    print(f"{n:4s} {unit_label[i]:4s} | {hl:9.3g} {ht:9.3g} {change(hl, ht):6.0f}% | "
          f"{pl:9.3g} {pt:9.3g} {change(pl, pt):6.0f}% | {pl / hl:11.2f}")
""")

code(r"""
hdr = f"{'AP':4s} | " + " | ".join(f"{k:^20s}" for k in keys)
print("Largest absolute correlation of each AP (and with which unknown)")
print(hdr)
print("-" * len(hdr))
for i, n in enumerate(names):
    print(f"{n:4s} | " + " | ".join(f"{corr[k][i]:6.3f} {partner[k][i]:>13s}" for k in keys))

print("\nAPs flagged as weakly determined (|corr| > 0.99) and not estimable:")
for k in keys:
    weak = ", ".join(f"{a}~{b} ({c:.4f})" for a, b, c in results[k].weakly_determined) or "none"
    print(f"  {k:20s} weak: {weak}")
    print(f"  {'':20s} not estimable: {results[k].not_estimable or 'none'}")
""")

code(r"""
colors = {"hybrid/levelled": "tab:blue", "hybrid/tilted": "tab:cyan",
          "panoramic/levelled": "tab:red", "panoramic/tilted": "tab:orange"}
x = np.arange(len(names))
w = 0.2
fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(14, 8), sharex=True)
for j, k in enumerate(keys):
    ax1.bar(x + (j - 1.5) * w, sig[k], w, label=k, color=colors[k])
    ax2.bar(x + (j - 1.5) * w, corr[k], w, label=k, color=colors[k])
ax1.set_yscale("log")
ax1.set_ylabel('standard deviation [mm, ", ppm]')
ax1.set_title(f"Standard deviation of the recovered APs (point-based, {APS}, seed {SEED})")
ax1.grid(axis="y", which="both", alpha=0.3)
ax1.legend(ncol=4, fontsize=9)
ax2.set_ylabel("max |correlation|")
ax2.set_ylim(0, 1.02)
ax2.axhline(0.99, color="k", lw=0.8, ls="--")
ax2.set_title("Largest absolute correlation of each AP with any other unknown (dashed: 0.99)")
ax2.grid(axis="y", alpha=0.3)
ax2.set_xticks(x)
ax2.set_xticklabels([f"{n}\n[{u}]" for n, u in zip(names, unit_label)])
fig.tight_layout()
plt.show()
""")

md(r"""
## 3. The hybrid collimation axis error B6

For a hybrid scanner the collimation term is the *reduced* model `B6 (sec(alpha) - 1)`: the
constant part of `B6 sec(alpha)` is a rotation about the vertical axis, which the kappa of
every scan absorbs. The next cell reads B6 from the full-model runs above, then repeats the
calibration of the levelled hybrid design with the small physical set (A0, B6, B7, C0), and
finally registers the un-reduced `sec(alpha)` basis as an empirical term (same design, same
seed) to show what the reduction removes. (Levelled only, to keep the number of compiled
configurations small.)
""")

code(r"""
for k in ("hybrid/levelled", "hybrid/tilted"):
    b6 = results[k].ap("B6")
    print(f"{k:16s} 23-term set: B6 sigma {b6['sigma'] * RAD_TO_ARCSEC:7.1f}\"  "
          f"max|corr| {b6['max_abs_corr']:.3f} with {b6['max_corr_with']:10s} "
          f"flagged: {'B6' in [a for a, _, _ in results[k].weakly_determined]}")
print()


def b6_row(aps, b6_name):
    # Levelled hybrid design with the given AP set: B6's sigma, recovery, largest correlation.
    s = tj.simulate(seed=SEED, architecture="hybrid", tilted=False, aps=aps, noise=True)
    r = tj.calibrate(s.network, tj.CalibrationModel(s.scanner), OPTIONS)
    b6 = r.ap(b6_name)
    zz = (b6["value"] - s.true_aps[b6_name]) / b6["sigma"]
    print(f"levelled {aps:15s} {b6_name:5s}: sigma {b6['sigma'] * RAD_TO_ARCSEC:6.1f}\"  "
          f"(est-truth)/sigma {zz:5.2f}  max|corr| {b6['max_abs_corr']:.4f} with {b6['max_corr_with']}")
    print(f"{'':9s}weakly determined: {[(a, b, round(c, 4)) for a, b, c in r.weakly_determined] or 'none'}; "
          f"not estimable: {r.not_estimable or 'none'}")


b6_row("A0 B6 B7 C0", "B6")     # reduced hybrid model, sec(alpha) - 1

# The un-reduced collimation basis, registered as an empirical term (public API).
if "B6sec" not in tj.registered_aps():
    tj.register_ap("B6sec", "hz", lambda rho, theta, alpha, scanner: 1.0 / jnp.cos(alpha), "rad",
                   "collimation axis error, full sec(alpha) basis (no reduction)")
b6_row("A0 B6sec B7 C0", "B6sec")
""")

md(r"""
## 4. Discussion

All numbers below are from the outputs above (one realisation, seed 0, all 23 APs estimated
together).

**Recovery.** In all four configurations every AP lies within 1.8 sigma of its true value
(largest |z| 1.78, B9 in panoramic/levelled), and the joint statistic d'C^-1 d of the 23
differences is 25.8, 22.1, 18.6 and 11.9 (hybrid levelled, hybrid tilted, panoramic levelled,
panoramic tilted), all below the 95% quantile 35.2 of chi-square(23). sigma0 is 0.99-1.00.
The near-singular hybrid/levelled problem takes a few more Gauss-Newton iterations than the
other three (see the first table); the convergence test measures each update against the
parameter's own sigma, so it does not chase rounding noise along nearly singular directions.

**Hybrid scanners: tilting.** As in the paper, B6 and B10 gain the most precision from the two
rolled scans: sigma(B6) drops from 137" to 11.7" (-91%; paper: -86%) and sigma(B10) from 249"
to 26.1" (-90%; paper: -80%). Their largest correlations fall less: B6 0.907 -> 0.854 (with
B10), and B10 stays high, 1.000 -> 0.988 (with a kappa), which matches the paper's remark
that the maximum correlation of B10 remained high. In this run tilting also cuts the sigmas of
A2 (8.1 mm -> 0.45 mm), B7, B9, C6 and all vertical terms C0-C5 by 88-97%, and the
correlations of A2 (1.000 -> 0.974, with station coordinates), C6 (0.999 -> 0.961) and
B7/B9 (0.981 -> 0.932, with each other) fall below 0.99. The horizontal-circle terms B1-B5,
the range terms A3/A4 and the wobble terms C7/C8 barely change (within +/-15%).

**Vertical-angle terms of hybrid scanners.** The paper reports that tilting plus levelling
improves the correlations of all vertical angular errors except C3. Here, with all 23 terms in
one model, the block C0-C4 stays weakly determined even with tilted scans (C0~C3 0.997,
C1~C2 0.999, C4~C2 0.995; flagged above 0.99), although their sigmas drop by about an order of
magnitude; C5 (0.976) and C6 (0.961) fall just below 0.99. The paper's section 4 tests the
APs one at a time (sinusoidal pairs together), so its correlations are not directly comparable
with a simultaneous 23-term adjustment.

**Panoramic vs hybrid.** With levelled scans the panoramic design determines the axis errors
and the vertical terms far better than the hybrid one: the sigma ratio panoramic/hybrid is
0.00-0.06 for A2, B6, B10, C0-C6 and 0.06-0.16 for B7 and B9, and no vertical term is above
0.99 correlation. The exception is the horizontal-circle group: B1-B5 have 4.6-63 times larger
sigmas for the panoramic scanner, and B1~B3 (0.9996) and B4~B3 (0.993) are flagged in both
panoramic designs, with or without tilted scans. This is consistent with the panoramic
horizontal directions covering only [0, pi), over which theta and cos(theta) are nearly
collinear. So
the paper's "panoramic better than hybrid" holds here for everything except B1-B5.

**Panoramic scanners: tilting.** The paper found significant gains only for B9, C3 and C4
(-50%, -60%, -85%). Here those three drop by 73%, 85% and 87%, but so do C0 (-85%), C1 (-88%),
C5 (-67%), A2 (-53%), C6 (-46%), B6 (-43%), B10 (-39%) and A0 (-35%); the correlations of C0,
C1 and C3-C6 fall to 0.52-0.85 (C2 stays low, 0.23 -> 0.26). B6~B10 remains high
(0.983 -> 0.948), and B1~B3 is unchanged (0.9996).

**Reduced collimation model (B6, hybrid).** With the reduced basis sec(alpha) - 1, B6 is *not*
flagged in levelled hybrid scans: its largest correlation is 0.907 (with B10) in the 23-term set
and 0.941 (with a target coordinate) in the small set A0 B6 B7 C0, where it is recovered at
-2.0 sigma with sigma 42.9". Its weakness shows in the precision (137" with the full set,
11.7" after tilting). The un-reduced basis sec(alpha), registered as `B6sec`, *is* flagged:
max |correlation| 0.999 with kappa of one scan, yet its estimate, sigma (42.9") and recovery
(-2.0 sigma) are identical to those of the reduced term. In this room the constant part of
sec(alpha) is absorbed by the kappas (shifting every kappa and the coefficient together leaves
the observations unchanged); the reduction removes that part and with it the correlation with
kappa, without changing what the data say about B6. Neither basis is reported as not estimable.
""")

if __name__ == "__main__":
    BUILD.run()
