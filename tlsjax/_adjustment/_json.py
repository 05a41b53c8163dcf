"""The JSON of a calibration (:meth:`tlsjax.CalibrationResult.to_dict`, SPEC section 11): SI
units, strict JSON (undefined values are null)."""

from __future__ import annotations

import math

import numpy as np

from .._model._aps import get_ap
from .._stats import ELLIPSOID_95, confidence_scale, global_test
from .._summary import to_json_value
from ._ap_tests import ap_notes
from ._config import scanner_settings
from ._redundancy import redundancy_summary
from ._text import EOP_NAMES, confoundings

#: Result codes whose estimates are numbers (converged, possibly with non-estimable APs held).
_ESTIMATES_VALID = (0, 2)


def _num(x):
    """JSON number or null (NaN and inf are not JSON)."""
    if x is None:
        return None
    x = float(x)
    return x if math.isfinite(x) else None


def principal_axes(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """1-sigma semi-axes (..., k), largest first, and their unit directions (..., k, k), one per
    column, of the k x k covariances ``cov`` (..., k, k): the square roots of the eigenvalues and
    the eigenvectors; NaN where a block is not finite."""
    cov = np.asarray(cov, dtype=np.float64)
    k = cov.shape[-1]
    flat = cov.reshape(-1, k, k)
    ok = np.all(np.isfinite(flat), axis=(1, 2))
    axes = np.full((flat.shape[0], k), np.nan)
    dirs = np.full((flat.shape[0], k, k), np.nan)
    if ok.any():
        w, v = np.linalg.eigh(0.5 * (flat[ok] + np.swapaxes(flat[ok], 1, 2)))
        axes[ok] = np.sqrt(np.clip(w[:, ::-1], 0, None))
        dirs[ok] = v[:, :, ::-1]
    return axes.reshape(cov.shape[:-1]), dirs.reshape(cov.shape)


def target_ellipsoids(cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """1-sigma semi-axes (t, 3), largest first, and their unit directions (t, 3, 3), one per
    column, of the 3 x 3 target covariances ``cov`` (t, 3, 3); NaN where a block is not finite."""
    return principal_axes(np.asarray(cov, dtype=np.float64).reshape(-1, 3, 3))


def plane_ellipsoids(params: np.ndarray, cov: np.ndarray) -> dict:
    """Precision of adjusted planes ``(n, d)`` (k, 4) from their a posteriori covariances
    ``cov`` (k, 4, 4) [1, m], the planes' counterpart of a point's confidence ellipsoid.

    A plane has four parameters and one hard constraint ``|n| = 1``, so its covariance has rank
    three and lives in the tangent space: ``n^T C_nn = 0``, ``n^T C_nd = 0``. JAG3D gives a
    point's ellipsoid; a plane has no point of its own, so tlsjax reports the three rigorous
    measures that together describe its 3 x 3 precision:

    - ``sigma_d = sqrt(C_dd)`` [m]: the plane's offset along its normal at the foot point;
    - ``tilt_sigmas`` [rad] with ``tilt_directions`` (3, 2): the principal axes of the normal's
      covariance in its tangent plane, ``C_t = T^T C_nn T`` with T (3, 2) an orthonormal basis of
      the plane orthogonal to n (eigenvalues, largest first, and the object-space directions
      ``T u_k`` in which the normal tips); a unit vector moved by a small angle e moves by e, so
      these are the sigmas of the two tilt angles;
    - ``foot_point = d n`` [m] (the point of the plane nearest the datum's origin) and its
      covariance ``C_f = J C J^T``, ``J = [d I_3, n]`` (3, 4) (first-order propagation), as
      ellipsoid semi-axes ``foot_axes`` (k, 3) [m], largest first, and ``foot_directions``.
      Along n its variance is ``C_dd``; across n it is ``d^2`` times the tilt's, so it grows with
      the plane's distance from the origin (the datum is part of the statement, as for targets).

    The plane's sigma along its normal at any point X is ``sqrt(a^T C a)``, ``a = (X, -1)``.
    All 1-sigma; the confidence ellipsoids at 95 % are ``tlsjax._stats.confidence_scale(m)``
    times them (m = 1, 2, 3: 1.96, 2.4477, 2.7955). NaN where a block is not finite.
    """
    P = np.asarray(params, dtype=np.float64).reshape(-1, 4)
    C = np.asarray(cov, dtype=np.float64).reshape(-1, 4, 4)
    n, d = P[:, :3] / np.linalg.norm(P[:, :3], axis=1, keepdims=True), P[:, 3]
    # Orthonormal tangent basis: the last two right-singular vectors of n^T (exact for any n;
    # a non-finite plane gets NaN measures through its covariance or d, never an SVD error).
    safe = np.where(np.all(np.isfinite(n), axis=1, keepdims=True), n, [0.0, 0.0, 1.0])
    T = np.linalg.svd(safe[:, None, :])[2][:, 1:, :].transpose(0, 2, 1)  # (k, 3, 2)
    tilt, u = principal_axes(np.einsum("kia,kij,kjb->kab", T, C[:, :3, :3], T))
    bad = ~np.all(np.isfinite(P), axis=1)
    tilt[bad], u[bad] = np.nan, np.nan
    J = np.concatenate([d[:, None, None] * np.eye(3), n[:, :, None]], axis=2)  # (k, 3, 4)
    foot_axes, foot_dirs = principal_axes(J @ C @ np.swapaxes(J, 1, 2))
    return {
        "sigma_d": np.sqrt(np.clip(C[:, 3, 3], 0, None)),
        "tilt_sigmas": tilt,
        "tilt_directions": T @ u,
        "foot_point": d[:, None] * n,
        "foot_axes": foot_axes,
        "foot_directions": foot_dirs,
    }


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
        for key, _ in _PLANE_PRECISION:
            p[key] = to_json_value(np.full(np.shape(p[key]), np.nan).tolist())
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
        "redundancy": redundancy_summary(res),
        # Filled by self_calibrate (data snooping, VCE); a plain calibration has neither.
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
    """Plane parameters with sigmas and the precision measures of :func:`plane_ellipsoids`,
    and the Gauss-Helmert residual summary (plane networks)."""
    if not getattr(res, "planes", ()):
        return {}
    P, S = res.plane_params, res.plane_sigmas
    cov = getattr(res, "plane_covariance", None)
    e = plane_ellipsoids(P, np.full((len(res.planes), 4, 4), np.nan) if cov is None else cov)
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
            **_plane_precision(e, k),
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
        "planes_units": PLANES_UNITS,
        "plane_residual_rms": rms,
        "n_plane_points": int(used.any(axis=1).sum()),
    }


#: What the planes' precision fields are (JSON, SI units; :func:`plane_ellipsoids`).
PLANES_UNITS = (
    "normal 1, d m, sigma a posteriori; tilt_sigmas: 1-sigma principal axes of the normal's "
    "covariance in its tangent plane [rad], largest first (x "
    f"{round(confidence_scale(2), 4)} for the 95 % ellipse), tilt_directions: one unit column "
    "per axis (the object-space direction the normal tips in); foot_point = d n [m] and its "
    "1-sigma ellipsoid semi-axes foot_point_ellipsoid_axes [m], largest first (x "
    f"{round(confidence_scale(3), 4)} for 95 %), foot_point_ellipsoid_directions: one unit "
    "column per axis"
)

_PLANE_PRECISION = (
    ("tilt_sigmas", "tilt_sigmas"),
    ("tilt_directions", "tilt_directions"),
    ("foot_point", "foot_point"),
    ("foot_point_ellipsoid_axes", "foot_axes"),
    ("foot_point_ellipsoid_directions", "foot_directions"),
)


def _plane_precision(e: dict, k: int) -> dict:
    """The JSON fields of plane ``k`` from :func:`plane_ellipsoids` (null where undefined)."""
    return {key: to_json_value(np.asarray(e[src][k]).tolist()) for key, src in _PLANE_PRECISION}
