"""The redundancy numbers of a calibration summarised: per observation group, per scan, for
the plane points and the weighted constraints, and in total (SPEC section 7: their sum is the
degrees of freedom)."""

from __future__ import annotations

import numpy as np

#: The groups of a target observation's three components.
GROUP_NAMES = ("range", "hz", "el")


def redundancy_summary(result) -> dict:
    """Mean and sum of the redundancy numbers of ``result`` (a :class:`tlsjax.CalibrationResult`)
    per group, per scan and in total (``redundancy`` of its JSON); the total's sum is the
    degrees of freedom."""
    net = result.network
    r = result.redundancy
    used = np.ones(r.shape, dtype=bool) if result.used is None else result.used
    rp = np.zeros((0, 3)) if result.plane_redundancy is None else result.plane_redundancy
    up = np.ones(rp.shape, dtype=bool) if result.plane_used is None else result.plane_used
    # Means over the observations in the adjustment: a removed one has redundancy 0 by
    # construction and would pull the mean down.
    mean = lambda a, keep: float(a[keep].mean()) if keep.any() else float("nan")
    out = {}
    if r.shape[0] or not rp.shape[0]:
        for g, name in enumerate(GROUP_NAMES):
            out[name] = {"mean": mean(r[:, g], used[:, g]), "sum": float(r[:, g].sum())}
    if rp.shape[0]:
        # Plane points (Gauss-Helmert): a point's three numbers share one condition's
        # redundancy, so the mean over plane observations never exceeds 1/3 (SPEC 4).
        pl = {
            name: {"mean": mean(rp[:, g], up[:, g]), "sum": float(rp[:, g].sum())}
            for g, name in enumerate(GROUP_NAMES)
        }
        pl["all"] = {"mean": mean(rp, up), "sum": float(rp.sum())}
        pl["per_point"] = {"mean": mean(rp.sum(axis=1), up.any(axis=1))}
        out["planes"] = pl
    lev = result.redundancy_levelling
    active = net.is_levelled
    if active.any():
        out["levelling"] = {"mean": float(lev[active].mean()), "sum": float(lev[active].sum())}
    extra = 0.0
    for key, r_ in (
        (
            "heading",
            None if result.redundancy_orientation is None else result.redundancy_orientation[:, 2],
        ),
        ("ap_priors", result.redundancy_ap_prior),
    ):
        if r_ is not None and np.isfinite(r_).any():
            a = r_[np.isfinite(r_)]
            out[key] = {"mean": float(a.mean()), "sum": float(a.sum())}
            extra += float(a.sum())
    per_scan = {}
    for j, s in enumerate(result.scans):
        a = np.concatenate(
            [
                r[net.scan_index == j][used[net.scan_index == j]],
                rp[net.plane_scan_index == j][up[net.plane_scan_index == j]],
            ]
        )
        per_scan[s] = {"mean": float(a.mean()) if a.size else float("nan")}
    out["per_scan"] = per_scan
    total = float(r.sum() + rp.sum() + lev.sum() + result.redundancy_prior_sum + extra)
    out["total"] = {"mean": total / max(result.n_observations, 1), "sum": total}
    return out
