"""The result JSON of SPEC section 11: SI units, strict JSON (undefined values are null),
written atomically (:mod:`tlsjax._io._json`)."""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from .._inference._statistics import ap_notes, global_test
from .._io._json import to_json_value, write_json_file
from .._io._target_lists import ELLIPSOID_95
from .._model._aps import get_ap
from ._text import EOP_NAMES, confoundings

#: Result codes whose estimates are numbers (converged, possibly with non-estimable APs held).
_ESTIMATES_VALID = (0, 2)


def _num(x):
    """JSON number or null (NaN and inf are not JSON)."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def scanner_settings(scanner) -> dict:
    """Architecture, unit lengths and AP names of one :class:`~tlsjax.Scanner`, or of each
    instrument (``{"instruments": {name: settings}}``) for a mapping: what applying the APs
    needs (``tlsjax correct``, :meth:`tlsjax.Calibration.from_json`)."""
    if isinstance(scanner, Mapping):
        per = {str(k): scanner_settings(v) for k, v in scanner.items()}
        archs = {d["architecture"] for d in per.values()}
        out = {"instruments": per}
        if len(archs) == 1:
            out["architecture"] = archs.pop()
        return out
    return {
        "architecture": scanner.architecture,
        "unit_length": scanner.unit_length,
        "unit_length_2": scanner.unit_length_2,
        "aps": list(scanner.aps),
    }


def target_ellipsoids(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """1-sigma semi-axes (t, 3), largest first, and their unit directions (t, 3, 3), one per
    column, of the 3 x 3 target covariances ``cov`` (t, 3, 3); NaN where a block is not finite."""
    cov = np.asarray(cov, dtype=np.float64).reshape(-1, 3, 3)
    ok = np.all(np.isfinite(cov), axis=(1, 2))
    axes = np.full((cov.shape[0], 3), np.nan)
    dirs = np.full((cov.shape[0], 3, 3), np.nan)
    if ok.any():
        w, v = np.linalg.eigh(0.5 * (cov[ok] + np.swapaxes(cov[ok], 1, 2)))
        axes[ok] = np.sqrt(np.clip(w[:, ::-1], 0, None))
        dirs[ok] = v[:, :, ::-1]
    return axes, dirs


def target_scan_counts(res) -> np.ndarray:
    """Number of scans whose used observations include each target (t,)."""
    net = res.network
    used = np.ones(net.observations.shape[0], bool) if res.used is None else res.used.any(axis=1)
    pairs = np.unique(
        np.stack([net.target_index[used], net.scan_index[used]], axis=1).reshape(-1, 2), axis=0
    )
    return np.bincount(pairs[:, 0], minlength=len(res.targets))


def _targets_dict(res) -> dict:
    """Adjusted target coordinates with sigmas and 1-sigma ellipsoid semi-axes [m], in the
    datum of the adjustment (SPEC section 6), with the number of scans that observed each."""
    net = res.network
    if net is None or not len(res.targets):
        return {}
    cov = res.target_covariance
    if cov is None:
        cov = np.full((len(res.targets), 3, 3), np.nan)
    axes, dirs = target_ellipsoids(cov)
    n_scans = target_scan_counts(res)
    targets = {
        name: {
            "xyz": [_num(v) for v in res.target_xyz[t]],
            "sigma": [_num(v) for v in res.target_sigmas[t]],
            "ellipsoid_axes": [_num(v) for v in axes[t]],
            "ellipsoid_directions": [[_num(v) for v in row] for row in dirs[t]],
            "n_scans": int(n_scans[t]),
        }
        for t, name in enumerate(res.targets)
    }
    return {
        "targets": targets,
        "targets_frame": datum_text(res),
        "targets_units": "xyz, sigma and ellipsoid_axes in metres, a posteriori in that frame; "
        f"ellipsoid_axes: 1-sigma semi-axes, largest first (x {ELLIPSOID_95} for 95 %), "
        "ellipsoid_directions: one unit column per axis",
    }


def datum_text(res) -> str:
    """What the target coordinates and sigmas of ``res`` refer to (its datum, SPEC section 6)."""
    datum = str(res.datum)
    if datum.startswith("inner"):
        return (
            "object space of the free network (inner constraints on the targets at their "
            "approximate values)"
        )
    return f"object space of the adjustment's datum ({datum})"


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
    for t in d.get("targets", {}).values():
        t["xyz"], t["sigma"], t["ellipsoid_axes"] = [None] * 3, [None] * 3, [None] * 3
        t["ellipsoid_directions"] = [[None] * 3 for _ in range(3)]
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
    """The result JSON of SPEC section 11, field by field (long because the contract has many
    fields; there is no logic beyond the conversions)."""
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
        "n_conditions": int(res.n_conditions),
        "n_constraints": int(res.n_constraints),
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
        "confoundings": confoundings(res.not_estimable, res.weakly_determined),
        "rank_deficient": list(res.rank_deficient),
        "weighted_constraints": res.weighted_constraints(),
        "estimates": "valid",
        **_scanner_dict(res),
        **_targets_dict(res),
        **_planes_dict(res),
    }


def _scanner_dict(res) -> dict:
    model = getattr(res, "model", None)
    if model is None:
        return {}
    return {"scanner": scanner_settings(model.scanner)}


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
