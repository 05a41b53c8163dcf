"""The result JSON of SPEC section 11: SI units, strict JSON (undefined values are null),
written atomically (:mod:`tlsjax._io._json`)."""

from __future__ import annotations

import math

import numpy as np

from .._inference._statistics import ap_notes, global_test
from .._io._json import to_json_value, write_json_file
from .._model._aps import get_ap
from ._text import EOP_NAMES

#: Result codes whose estimates are numbers (converged, possibly with non-estimable APs held).
_ESTIMATES_VALID = (0, 2)


def _num(x):
    """JSON number or null (NaN and inf are not JSON)."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def result_to_dict(res, *, alpha: float = 0.05) -> dict:
    """The result JSON of SPEC section 11 (SI units), with the global test and the AP covariance.

    Non-estimable APs have ``value`` and ``sigma`` null and are listed in ``not_estimable``
    with the parameter each is confounded with; they are never reported as numbers. Scan
    parameters the network does not determine (``rank_deficient``) are null too, and a failed
    adjustment (no convergence, rank defect, non-finite values) reports no estimates at all:
    its numbers would look plausible and be wrong (``estimates`` says why).
    """
    d = _result_dict(res, alpha)
    if int(res.result) not in _ESTIMATES_VALID:
        _withhold_estimates(d, res.message)
    else:
        _judge_plausibility(d, res)
    return to_json_value(d)


def _judge_plausibility(d: dict, res) -> None:
    """``plausibility``: the AP magnitudes beyond what instruments have (the rules of
    :mod:`tlsjax._model._plausibility`); an impossible one makes ``estimates`` say so, and
    ``tlsjax correct`` then refuses to apply them."""
    findings, summary = res.plausibility()
    d["plausibility"] = [{"ap": f.name, "level": f.level, "text": f.text} for f in findings]
    if any(f.level == "impossible" for f in findings):
        d["estimates"] = f"implausible: {summary}"


def _withhold_estimates(d: dict, reason: str) -> None:
    """Null every estimate and sigma of a failed adjustment, in place."""
    for a in d["aps"].values():
        for k in ("value", "sigma", "t", "max_abs_corr", "max_corr_with"):
            a[k] = None
        a["note"] = "withheld: the adjustment failed"
    for e in d["eops"].values():
        for k in EOP_NAMES:
            e[k] = None
            e["sigma"][k] = None
    d["ap_covariance"] = None
    d["sigma0"] = None
    d["global_test"] = global_test(float("nan"), d["dof"] or 0.0)
    for p in d.get("planes", {}).values():
        p["normal"], p["d"] = [None, None, None], None
        p["sigma"] = {k: None for k in p["sigma"]}
    d["estimates"] = f"withheld: the adjustment failed ({reason})"


def _undetermined(res) -> set:
    """(scan, EOP name) pairs of the scan parameters named in ``res.rank_deficient``."""
    out = set()
    for name in res.rank_deficient:
        head, _, scan = str(name).partition("[")
        out.add((scan.rstrip("]"), head))
    return out


def withhold_estimates(d: dict, reason: str) -> None:
    """Null every estimate of a result JSON dict in place, ``estimates`` saying why (e.g. a
    run whose variance components failed: its numbers are not a calibration)."""
    _withhold_estimates(d, reason)
    d["estimates"] = f"withheld: {reason}"
    for a in d["aps"].values():
        a["note"] = f"withheld: {reason}"


def _result_dict(res, alpha: float) -> dict:
    notes = ap_notes(res)
    aps = {}
    for i, name in enumerate(res.ap_names):
        base = name.split("[")[0]
        aps[name] = {
            "value": _num(res.ap_values[i]),
            "sigma": _num(res.ap_sigmas[i]),
            "unit": res.ap_units[i],
            "t": _num(res.ap_t[i]),
            "max_abs_corr": _num(res.ap_max_abs_corr[i]),
            "max_corr_with": res.ap_max_corr_with[i] or None,
            "description": get_ap(base).description,
            # Why a quantity is null or its t is no verdict (not estimable, fixed, weakly
            # determined); null when the AP has an ordinary estimate and t-test.
            "note": notes.get(name) or None,
        }
    undetermined = _undetermined(res)
    eops = {
        s: {
            **{
                k: None if (s, k) in undetermined else _num(res.eops[j, c])
                for c, k in enumerate(EOP_NAMES)
            },
            "sigma": {
                k: None if (s, k) in undetermined else _num(res.eop_sigmas[j, c])
                for c, k in enumerate(EOP_NAMES)
            },
        }
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
        "not_estimable": [
            {"name": n, "confounded_with": w, "reason": r} for n, w, r in res.not_estimable
        ],
        "weakly_determined": [
            {"name": n, "correlated_with": w, "max_abs_corr": c}
            for n, w, c in res.weakly_determined
        ],
        "rank_deficient": list(res.rank_deficient),
        "estimates": "valid",
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
            "normal": [_num(v) for v in P[k, :3]],
            "d": _num(P[k, 3]),
            "sigma": {
                "nx": _num(S[k, 0]),
                "ny": _num(S[k, 1]),
                "nz": _num(S[k, 2]),
                "d": _num(S[k, 3]),
            },
            "n_points": int(rows.sum()),
            "n_scans": int(len(np.unique(net.plane_scan_index[rows]))),
        }
    used = res.plane_used
    v = res.plane_residuals
    rms = {
        g: _num(np.sqrt(np.mean(v[used[:, c], c] ** 2))) if used[:, c].any() else None
        for c, g in enumerate(("range_m", "hz_rad", "el_rad"))
    }
    return {
        "planes": planes,
        "plane_residual_rms": rms,
        "n_plane_points": int(used.any(axis=1).sum()),
    }


def write_json(res, path, *, extra: dict | None = None, **kw) -> dict:
    """Write :func:`result_to_dict` (updated with ``extra``, e.g. the ``outliers`` and
    ``variance_components`` of :func:`tlsjax.calibrate_and_test`) as strict JSON (NaN and
    infinities are null), atomically: the file is complete or not written. A path that cannot
    be written is a one-line ValueError naming it."""
    d = result_to_dict(res, **kw)
    d.update(extra or {})
    return write_json_file(path, d)
