"""Reports of a calibration: the paper-style AP table, the global test and the result JSON.

Host side only. SI inside the result; the table shows millimetres for lengths, arc seconds (")
for angles and ppm for dimensionless scale terms, with the unit in every label. The JSON keeps
SI units and states them (SPEC section 11).
"""

from __future__ import annotations

import json
import math
import os

import numpy as np
from jax.scipy.special import gammainc

from ._aps import get_ap

ARCSEC = math.pi / 648000.0

#: SI unit of an AP coefficient -> (report unit, factor from SI).
DISPLAY_UNITS = {"m": ("mm", 1e3), "rad": ('"', 1.0 / ARCSEC), "1": ("ppm", 1e6)}
EOP_NAMES = ("Xs", "Ys", "Zs", "omega", "phi", "kappa")


def display(value: float, unit: str) -> tuple[float, str]:
    """A value in SI ``unit`` converted to its report unit: (number, unit label)."""
    label, f = DISPLAY_UNITS[unit]
    return value * f, label


def chi2_cdf(x: float, dof: float) -> float:
    """P(chi^2(dof) <= x), the regularised lower incomplete gamma function."""
    return float(gammainc(0.5 * dof, 0.5 * x))


def chi2_quantile(p: float, dof: float) -> float:
    """Quantile of chi^2(dof) by bisection on :func:`chi2_cdf` (host side, 1e-12 relative)."""
    lo, hi = 0.0, max(1.0, dof)
    while chi2_cdf(hi, dof) < p:
        hi *= 2.0
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        if chi2_cdf(mid, dof) < p:
            lo = mid
        else:
            hi = mid
        if hi - lo <= 1e-12 * hi:
            break
    return 0.5 * (lo + hi)


def global_test(sigma0: float, dof: float, alpha: float = 0.05) -> dict:
    """Global test of the adjustment: ``T = v^T P v = s0^2 r ~ chi^2(r)`` when the a priori
    stochastic model is right (Koch 1999, sec. 4.2.2). Two-sided: the model is accepted when
    ``chi^2_{alpha/2}(r) <= T <= chi^2_{1-alpha/2}(r)``; the p-value is two-sided too."""
    if not (dof > 0 and np.isfinite(sigma0)):
        return {"statistic": None, "dof": dof, "alpha": alpha, "lower": None, "upper": None,
                "p_value": None, "accepted": None}
    T = sigma0**2 * dof
    lo, hi = chi2_quantile(alpha / 2, dof), chi2_quantile(1 - alpha / 2, dof)
    cdf = chi2_cdf(T, dof)
    return {"statistic": T, "dof": dof, "alpha": alpha, "lower": lo, "upper": hi,
            "p_value": 2 * min(cdf, 1 - cdf), "accepted": bool(lo <= T <= hi)}


def _num(x):
    """JSON number or null (NaN and inf are not JSON)."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def result_to_dict(res, *, alpha: float = 0.05) -> dict:
    """The result JSON of SPEC section 11 (SI units), with the global test and the AP covariance.

    Non-estimable APs have ``value`` and ``sigma`` null and are listed in ``not_estimable``
    with the parameter each is confounded with; they are never reported as numbers.
    """
    aps = {}
    for i, name in enumerate(res.ap_names):
        base = name.split("[")[0]
        aps[name] = {
            "value": _num(res.ap_values[i]), "sigma": _num(res.ap_sigmas[i]), "unit": res.ap_units[i],
            "t": _num(res.ap_t[i]), "max_abs_corr": _num(res.ap_max_abs_corr[i]),
            "max_corr_with": res.ap_max_corr_with[i] or None, "description": get_ap(base).description,
        }
    eops = {
        s: {**{k: _num(res.eops[j, c]) for c, k in enumerate(EOP_NAMES)},
            "sigma": {k: _num(res.eop_sigmas[j, c]) for c, k in enumerate(EOP_NAMES)}}
        for j, s in enumerate(res.scans)
    }
    cov = res.ap_covariance
    return {
        "tool": "tlsjax",
        "units": "SI: metres, radians; dimensionless scale terms as plain numbers",
        "source": res.network.source if res.network is not None else None,
        "result": int(res.result),
        "message": res.message,
        "converged": bool(res.converged),
        "iterations": int(res.iterations),
        "datum": res.datum,
        "sigma0": _num(res.sigma0),
        "dof": _num(res.dof),
        "n_observations": int(res.n_observations),
        "n_unknowns": int(res.n_unknowns),
        "global_test": global_test(res.sigma0, res.dof, alpha),
        "aps": aps,
        "ap_covariance_names": list(res.ap_names),
        "ap_covariance": None if cov is None else [[_num(v) for v in row] for row in cov],
        "eops": eops,
        "redundancy": res.redundancy_summary(),
        # Filled by calibrate_and_test (data snooping, VCE); a plain calibration has neither.
        "outliers": [],
        "variance_components": {},
        "not_estimable": [{"name": n, "confounded_with": w, "reason": r} for n, w, r in res.not_estimable],
        "weakly_determined": [{"name": n, "correlated_with": w, "max_abs_corr": c} for n, w, c in res.weakly_determined],
        "rank_deficient": list(res.rank_deficient),
        **_planes_dict(res),
    }


def _planes_dict(res) -> dict:
    """Plane parameters with sigmas and the Gauss-Helmert residual summary (plane networks)."""
    if not getattr(res, "planes", ()):
        return {}
    P, S = res.plane_params, res.plane_sigmas
    net = res.network
    planes = {}
    for k, name in enumerate(res.planes):
        rows = net.plane_index == k
        planes[name] = {
            "normal": [_num(v) for v in P[k, :3]], "d": _num(P[k, 3]),
            "sigma": {"nx": _num(S[k, 0]), "ny": _num(S[k, 1]), "nz": _num(S[k, 2]), "d": _num(S[k, 3])},
            "n_points": int(rows.sum()), "n_scans": int(len(np.unique(net.plane_scan_index[rows]))),
        }
    used = res.plane_used
    v = res.plane_residuals
    rms = {g: _num(np.sqrt(np.mean(v[used[:, c], c] ** 2))) if used[:, c].any() else None
           for c, g in enumerate(("range_m", "hz_rad", "el_rad"))}
    return {"planes": planes, "plane_residual_rms": rms, "n_plane_points": int(used.any(axis=1).sum())}


def write_json(res, path, *, extra: dict | None = None, **kw) -> dict:
    """Write :func:`result_to_dict` (updated with ``extra``, e.g. the ``outliers`` and
    ``variance_components`` of :func:`tlsjax.calibrate_and_test`) as strict JSON."""
    d = result_to_dict(res, **kw)
    d.update(extra or {})
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    with open(path, "w", encoding="utf-8") as fh:
        json.dump(d, fh, indent=2, allow_nan=False)
        fh.write("\n")
    return d


def ap_table(res, truth: dict | None = None) -> str:
    """The papers' AP table (Chow et al. 2013, tables 3-6): estimate, standard deviation,
    t statistic and the largest absolute correlation with the parameter it is with."""
    head = f"{'AP':<8} {'estimate':>12} {'sigma':>10} {'unit':<4} {'|t|':>8} {'max |corr|':>10}  {'with':<14}"
    if truth is not None:
        head += f" {'true':>10}"
    lines = [head, "-" * len(head)]
    not_est = {n: r for n, _, r in res.not_estimable}
    weak = {n for n, _, _ in res.weakly_determined}
    for i, name in enumerate(res.ap_names):
        if name in not_est:
            lines.append(f"{name:<8} not estimable: {not_est[name]}")
            continue
        if name in getattr(res, "ap_fixed", ()):
            lines.append(f"{name:<8} held at 0 (fixed)")
            continue
        v, u = display(res.ap_values[i], res.ap_units[i])
        s, _ = display(res.ap_sigmas[i], res.ap_units[i])
        row = (f"{name:<8} {v:12.4f} {s:10.4f} {u:<4} {abs(res.ap_t[i]):8.1f} {res.ap_max_abs_corr[i]:10.3f}  "
               f"{res.ap_max_corr_with[i]:<14}")
        if truth is not None:
            tv = truth.get(name.split("[")[0])
            row += f" {display(tv, res.ap_units[i])[0]:10.4f}" if tv is not None else f" {'':>10}"
        if name in weak:
            row += "  (weakly determined)"
        lines.append(row)
    return "\n".join(lines)


def summary(res, alpha: float = 0.05) -> str:
    """A few lines: result, sigma0 with the global test, redundancy, flags."""
    gt = global_test(res.sigma0, res.dof, alpha)
    red = res.redundancy_summary()
    out = [
        f"result: {res.result} ({res.message}); {res.iterations} iterations; datum: {res.datum}",
        f"observations n = {res.n_observations}, unknowns u = {res.n_unknowns}, " +
        (f"degrees of freedom r = n - u + d = {res.dof:.0f}" if not getattr(res, "planes", ()) else
         f"degrees of freedom r = conditions + constraints - u + d = {res.dof:.0f} (Gauss-Helmert, "
         f"{len(res.planes)} planes, {int(res.plane_used.any(axis=1).sum())} plane points)"),
    ]
    if gt["statistic"] is not None:
        out.append(
            f"sigma0 = {res.sigma0:.4f} (s0^2 = {res.sigma0**2:.4f}); global test chi^2 = {gt['statistic']:.1f}, "
            f"{100 * (1 - alpha):.0f}% interval [{gt['lower']:.1f}, {gt['upper']:.1f}]: "
            f"{'accepted' if gt['accepted'] else 'REJECTED'} (p = {gt['p_value']:.3f})"
        )
    groups = ", ".join(f"{g} {red[g]['mean']:.3f}" for g in ("range", "hz", "el", "levelling") if g in red)
    if groups:
        out.append(f"mean redundancy numbers: {groups}")
    if "planes" in red:
        pl = red["planes"]
        out.append(f"mean redundancy numbers of plane observations: range {pl['range']['mean']:.3f}, hz {pl['hz']['mean']:.3f}, "
                   f"el {pl['el']['mean']:.3f}; all {pl['all']['mean']:.3f} (at most 1/3: one condition per point)")
    for n, w, c in res.weakly_determined:
        out.append(f"warning: {n} is weakly determined: |corr| = {c:.4f} with {w}")
    for n, w, r in res.not_estimable:
        out.append(f"warning: {n} is not estimable: {r}")
    if res.rank_deficient:
        out.append("error: the network does not determine " + ", ".join(res.rank_deficient))
    return "\n".join(out)
