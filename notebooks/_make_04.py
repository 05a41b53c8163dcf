"""Build and execute notebooks/04_compatibility.ipynb.

Run from the repository root:  python notebooks/_make_04.py
(writes the notebook with its outputs; needs the ``python3`` Jupyter kernel).
"""

from _nbtools import Builder

BUILD = Builder("04_compatibility.ipynb")
md, code = BUILD.md, BUILD.code


md(r"""
# 04 - Point-based against plane-based AP sets: Chow et al. (2013), section 5.2, re-tested

**Question.** Chow, Lichti, Glennie & Hartzell (2013) calibrated two scanners from the same
point clouds twice, once with signalised targets (point-based) and once with planes
(plane-based), and compared each pair of AP sets "as a group through simulation" (Lichti 2008):
1,000 simulations in a room of the real data's size and noise, 100 targets, 10 of them control.
They found four of the five pairs of their Tables 2-5 compatible (Table 3, Table 4 datasets 1
and 2, Tables 2/5 with tilted scans) and one not (Tables 2/5, levelled scans only).
With the values and sigmas as printed, what does tlsjax's compatibility test say about the
same five pairs, and where and why does it differ?

**The test** (SPEC section 9, written out in the docstring of `tj.compatibility_test`): each
set corrects its own simulated noisy scan, the scans are fitted onto each other on the control
points, and at every check point the difference `d` is judged by its covariance
`C = J1 C1 J1^T + J2 C2 J2^T + N` (both sets' AP covariances and both scans' noise, propagated
by autodiff through correction, conversion and the fit). The statistic is the mean of
`d^T C^-1 d` over all simulations and check points; its null is exact (a quadratic form in the
two sets' errors over the same simulations). The share of check points whose distance exceeds
the chi-square(3) quantile is reported beside it, as the papers report it.

**Inputs and assumptions.**
* Values and sigmas as printed (A0 in mm; C0, B6, B7 in arc seconds). The tables print no
  correlations, so each set's covariance is diagonal.
* Rooms: the HDS6100 data (Tables 3, 4) were captured in a 14 m x 11 m x 3 m room in Calgary,
  the Imager 5003 data (Tables 2, 5) in a 30 m x 33 m x 5 m room in Houston (section 5.1).
* Architecture: the HDS6100 in hybrid mode for Table 3 (B6 is then the reduced collimation
  `sec(alpha) - 1`) and in panoramic mode for Table 4; the Imager 5003 is panoramic (its
  elevation angles reach 235 deg).
* Noise: the paper does not print the data's observation noise. We take 0.5 mm (at normal
  incidence) and 20" for both angles, the values of the paper's own simulations (section 4),
  and show below how little the verdicts depend on that choice.
* 1,000 simulations (seed 1), alpha = 5 %. Units: mm and arc seconds (").
""")

code(r"""
import time

import numpy as np
import matplotlib.pyplot as plt

import tlsjax as tj

T_START = time.perf_counter()
ARCSEC = np.pi / 648000
NAMES = ("A0", "C0", "B6", "B7")            # the order of the paper's tables
UNITS = np.array([1e-3, ARCSEC, ARCSEC, ARCSEC])  # mm, ", ", " -> SI

# (values, sigmas) as printed; "paper": the paper's verdict (compatible or not)
PAIRS = {
    "Table 3, HDS6100 hybrid": dict(
        room="14x11x3", architecture="hybrid", paper=True,
        point=([-0.6, -87.3, -24.2, 20.3], [0.05, 3.2, 5.8, 4.6]),
        plane=([-0.5, -77.5, -27.6, 40.0], [0.02, 1.5, 12.8, 2.4])),
    "Table 4, HDS6100 panoramic, ds 1": dict(
        room="14x11x3", architecture="panoramic", paper=True,
        point=([-0.8, 10.7, -2.5, -48.6], [0.05, 1.3, 0.7, 1.9]),
        plane=([-0.5, 3.8, 1.8, -57.0], [0.02, 0.5, 0.2, 1.8])),
    "Table 4, HDS6100 panoramic, ds 2": dict(
        room="14x11x3", architecture="panoramic", paper=True,
        point=([-1.7, 10.7, -19.4, -84.8], [0.1, 2.0, 1.4, 2.1]),
        plane=([-0.4, 8.1, -4.5, -69.4], [0.1, 1.5, 0.5, 4.0])),
    "Tables 2/5, Imager 5003 levelled": dict(
        room="30x33x5", architecture="panoramic", paper=False,
        point=([3.6, 40.5, 3.5, 79.7], [1.1, 8.3, 3.6, 35.4]),
        plane=([0.8, 18.6, 1.8, 22.9], [0.1, 1.8, 0.8, 7.5])),
    "Tables 2/5, Imager 5003 tilted": dict(
        room="30x33x5", architecture="panoramic", paper=True,
        point=([-0.6, 36.9, -6.0, -19.7], [0.5, 5.3, 2.5, 9.5]),
        plane=([-1.0, -0.3, -3.3, -19.1], [0.1, 1.4, 0.6, 2.0])),
}


def ap_set(pair, which, scale=1.0, same_a0=False):
    # One AP set of a table, sigmas times `scale`; `same_a0`: A0 of the point-based set.
    values, sigmas = (np.asarray(x, float) * UNITS for x in PAIRS[pair][which])
    if same_a0:
        values[0] = PAIRS[pair]["point"][0][0] * UNITS[0]
    scanner = tj.Scanner(architecture=PAIRS[pair]["architecture"])
    return tj.APSet.from_values(NAMES, values, sigmas=scale * sigmas,
                                source=f"{pair}, {which}-based", scanner=scanner)


def compare(pair, runs=1000, scale=1.0, same_a0=False, **noise):
    options = tj.CompatibilityOptions(runs=runs, seed=1, progress=False)
    return tj.compatibility_test(ap_set(pair, "point", scale), ap_set(pair, "plane", scale, same_a0),
                                 tj.Room.parse(PAIRS[pair]["room"]), options=options, **noise)


def yes_no(flag):
    return "compatible" if flag else "NOT"


labels = [f"{n} [mm]" if n == "A0" else f'{n} ["]' for n in NAMES]
print(f"{'':34s} {'':>6s}" + "".join(f"{label:>22s}" for label in labels))
for pair, p in PAIRS.items():
    for which in ("point", "plane"):
        v, s = p[which]
        print(f"{pair if which == 'point' else '':34s} {which:>6s}"
              + "".join(f"{a:>13.2f} +- {b:<6.2f}" for a, b in zip(v, s)))
""")

md(r"""
## 1. The five verdicts

One test per pair, 1,000 simulations each. `T` is the mean distance (3 when the difference is
what the sets' uncertainty and the noise explain); `p` its p-value under the exact null. The
naive chi-square test of the AP differences and the median share of significant check points
are printed beside it, as the test reports them.
""")

code(r"""
t0 = time.perf_counter()
results = {pair: compare(pair) for pair in PAIRS}
print(f"5 tests of 1,000 simulations: {time.perf_counter() - t0:.1f} s (compiling included)\n")
print(f"{'pair':34s} {'paper':>11s} {'tlsjax':>11s} {'T':>7s} {'p':>9s} {'naive p':>9s} "
      f"{'median share':>13s}  least visible direction")
for pair, r in results.items():
    print(f"{pair:34s} {yes_no(PAIRS[pair]['paper']):>11s} {yes_no(r.compatible):>11s} "
          f"{r.statistic:7.3f} {r.p_value:9.2g} {r.naive_p_value:9.2g} "
          f"{100 * r.median_share:12.1f}%  {r.least_visible}")
agree = sum(PAIRS[p]["paper"] == r.compatible for p, r in results.items())
print(f"\nthe test agrees with the paper on {agree} of 5 pairs")
""")

md(r"""
The test agrees with the paper only where the paper found a difference (levelled Imager 5003).
Its four other verdicts differ: with the printed sigmas, each pair differs by more than the two
sets' uncertainty and the scanner's noise explain. The median share of significant check points
stays near 5 % for the three pairs the paper's rule accepts: at each check point the difference
(a fraction of a millimetre) is smaller than the noise of two scans, so few points are
significant one by one. The mean distance adds up 90,000 check points, and a systematic
difference that no single point shows moves it far outside its null.

## 2. The paper's kind of decision: thresholding each point and taking the median share

To see that the two readings differ in the decision rule and not in the data, the median share
is given its own null: 80 pairs drawn from one instrument (both sets around their weighted mean,
with their own sigmas), 20 simulations each, the same noise; the rule says "compatible" when the
observed median share is at most the null's 95 % quantile. (A rough quantile from 80 pairs:
enough to show the rule's verdicts, not to tune it.)
""")

code(r"""
rng = np.random.default_rng(2)
t0 = time.perf_counter()
share_rule = {}
for pair in PAIRS:
    s1, s2 = ap_set(pair, "point"), ap_set(pair, "plane")
    C1, C2 = s1.covariance, s2.covariance
    mean = s1.values + C1 @ np.linalg.solve(C1 + C2, s2.values - s1.values)
    V1 = np.vstack([s1.values, mean + rng.standard_normal((80, 4)) * s1.sigmas])
    V2 = np.vstack([s2.values, mean + rng.standard_normal((80, 4)) * s2.sigmas])
    batch = tj.compatibility_batch(s1, s2, V1, V2, tj.Room.parse(PAIRS[pair]["room"]),
                                   options=tj.CompatibilityOptions(runs=20, null_draws=2000, seed=3,
                                                                   progress=False))
    q95 = np.quantile(batch["median_share"][1:], 0.95)
    share_rule[pair] = batch["median_share"][0] <= q95
    print(f"{pair:34s} median share {100 * batch['median_share'][0]:5.1f}% against its null's 95% "
          f"quantile {100 * q95:4.1f}%: {yes_no(share_rule[pair]):>10s}   paper: "
          f"{yes_no(PAIRS[pair]['paper'])}")
agree = sum(PAIRS[p]["paper"] == share_rule[p] for p in PAIRS)
print(f"\nthe median-share rule agrees with the paper on {agree} of 5 pairs "
      f"({time.perf_counter() - t0:.1f} s)")
""")

md(r"""
Thresholding each check point at the noise and counting reproduces the paper's verdicts where
the differences hide below the noise of single points. It is the weaker rule: the tests of
`tests/test_compat.py` hold the mean distance to at least its power in every direction, and
the rule's null has an atom and a quantile that moves with the seed (SPEC section 9).

## 3. Why the exact test rejects: the sigmas, A0, the noise

**The printed sigmas.** The tables print sigmas without correlations, so every set here is
uncorrelated; and the plane-based sigmas come from about 100,000 point-to-plane conditions
(e.g. A0 +- 0.02 mm), whose residual statistics the paper itself calls biased (section 5.2:
"statistics computed from the residuals are biased because of the large amount of zero
residuals"). How much larger would both sets' sigmas have to be for the differences to be
explained? (200 simulations per test: a p-value near 0.05 does not need 1,000.)
""")

code(r"""
scales = (1, 2, 3, 5)
t0 = time.perf_counter()
p_scaled = {pair: [results[pair].p_value] + [compare(pair, runs=200, scale=k).p_value for k in scales[1:]]
            for pair in PAIRS}
print(f"{'p-value with all sigmas times k':34s}" + "".join(f"{'k = ' + str(k):>10s}" for k in scales))
for pair, ps in p_scaled.items():
    print(f"{pair:34s}" + "".join(f"{p:10.2g}" for p in ps))
print(f"({time.perf_counter() - t0:.1f} s)")

fig, ax = plt.subplots(figsize=(7, 3.5))
for pair, ps in p_scaled.items():
    ax.semilogy(scales, np.maximum(ps, 1e-6), "o-", label=pair)
ax.axhline(0.05, color="k", ls="--", lw=1, label="alpha = 5 %")
ax.set_xlabel("factor k on both sets' printed sigmas")
ax.set_ylabel("p-value (floor 1e-6 drawn)")
ax.legend(fontsize=7)
fig.tight_layout()
plt.show()
""")

md(r"""
**A0.** The paper expects the rangefinder offset to differ between targets and planes ("a
function of the scanner, target fitting algorithm, and properties of the target"), so the two
A0 do not estimate one quantity. Setting the plane-based A0 to the point-based value (sigmas
kept) takes the A0 difference out of the comparison.

**The noise.** Zero noise is the pure object-space test of the AP difference; twice the
assumed noise (1 mm, 40") stands for a noisier scanner.
""")

code(r"""
t0 = time.perf_counter()
same_a0 = {pair: compare(pair, runs=200, same_a0=True) for pair in PAIRS}
zero = {pair: compare(pair, runs=200, sigma_range=0.0, sigma_angle=0.0) for pair in PAIRS}
double = {pair: compare(pair, runs=200, sigma_range=1e-3, sigma_angle=40 * ARCSEC) for pair in PAIRS}
print(f"{'p-value':34s} {'as printed':>11s} {'same A0':>11s} {'zero noise':>11s} {'2x noise':>11s}")
for pair in PAIRS:
    print(f"{pair:34s} {results[pair].p_value:11.2g} {same_a0[pair].p_value:11.2g} "
          f"{zero[pair].p_value:11.2g} {double[pair].p_value:11.2g}")
print(f"({time.perf_counter() - t0:.1f} s)")
print(f"\nnotebook ran in {time.perf_counter() - T_START:.0f} s")
""")

md(r"""
## What this shows

* **Verdicts.** With the values and sigmas as printed, the exact test finds all five pairs
  incompatible; it agrees with the paper on one pair (Tables 2/5 levelled, which both call
  incompatible). The median share of significant check points, judged against its own null,
  agrees with the paper on four of the five (all but Table 4, dataset 2).
* **What differs is the decision rule.** Each point's difference is below the noise of two
  scans, so a rule that thresholds points one by one sees little; the mean distance over all
  simulations and check points, with its exact null, sees a systematic difference of that size.
  The noise changes the p-values but not the verdicts (zero and twice the assumed noise give the
  same five): it enters every point's covariance and is known in the simulations, so it neither
  hides nor creates a difference.
* **Why the differences are significant.** Both sets' sigmas would have to be about twice as
  large (Table 3, both Imager 5003 pairs) or five times and more (Table 4) to explain the
  differences. The printed sigmas are the likely cause: the plane-based ones are often several
  times smaller than the point-based ones (A0 0.02 against 0.05 mm, B6 0.2" against 0.7" in
  Table 4) and come from residual statistics the paper calls biased, and the tables give no
  correlations (only each AP's largest, e.g. 0.48 between B6 and B7 in Table 3's plane-based
  set). A0, which targets and planes measure differently, explains the levelled Imager 5003
  pair (p 0.4 once the A0 difference is taken out) but none of the others.
* **Visibility.** The least visible direction is B6 or a B6/B7 mix in every pair: a collimation
  difference moves the points least in object space relative to its uncertainty, so it is where
  a group test is weakest and a one-by-one comparison of B6 most misleading.
""")

if __name__ == "__main__":
    BUILD.run()
