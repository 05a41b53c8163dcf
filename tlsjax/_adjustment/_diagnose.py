"""Naming what a non-estimable AP is confounded with (SPEC section 7).

The rank-revealing Cholesky of :mod:`._linalg` finds *that* an AP column depends on the others;
this module says *on what*. A dependency is a null vector of the reduced normal matrix K, but
it is defined only up to the rigid-motion null space of the free network, so the partner one
reads off it depends on the datum. The papers' tables report correlations in the
inner-constraint datum on the object-space primitives (SPEC section 6), so the dependency is
expressed in that datum too:

* the AP gets a vanishing ridge ``eps K_jj`` so that its cofactor exists, the other dependent
  columns are held fixed;
* the datum is closed by the inner constraints on the targets written in the reduced unknowns:
  a reduced update ``z`` moves the targets by ``dp = -N_pp^-1 N_pz z`` (homogeneous part of the
  back-substitution), so ``G^T dp = 0`` reads ``C z = 0`` with ``C = sum_i H_p,i^T N_pp,i^-1
  N_pz,i``;
* the bordered system ``[[K + eps e_j e_j^T, C^T], [C, 0]]`` is inverted; the AP's largest
  absolute correlation in that cofactor matrix names its partner (it tends to 1 as eps -> 0).

A dependency that is a change of network scale (A1 without scale bars or control) is reported
as such: the AP's null vector then moves every scan position radially. A dependency on the
primitives alone (A0 with every scan at one station: a range offset moves every target
radially, no pose changes) is found from ``diag(K) / diag(N_zz)``, the share of the AP's column
that the eliminated primitives do not explain, and reported as such.

:func:`failure_diagnosis` says where an adjustment that failed went wrong.
"""

from __future__ import annotations

import functools

import jax.numpy as jnp
import numpy as np

from .._jit import jit
from ._families import on_grid, settled_state
from ._normal import linearise, null_space, reduce

RIDGE = 1e-9


@functools.partial(jit, static_argnums=0)
def _reduced_system(spec, problem, params):
    """Raw reduced normal matrix K, target-datum constraint C (d, r) and the datum columns Hz,
    from the engine's linearisation and Schur reduction (:func:`._normal.reduce`)."""
    grid = on_grid(problem)
    blocks = linearise(spec, grid, params, state=settled_state(spec, grid, params))
    Hp, Hz = null_space(spec, grid.families, params)
    red = reduce(spec, grid, blocks, Hz, jnp.asarray(0.0), jnp.asarray(0.0))
    C = jnp.zeros((Hz.shape[1], spec.r))
    for H, Y in zip(Hp, red.Y):
        C = C + jnp.einsum("npd,npr->dr", H, Y)
    return red.K, C, Hz


#: An AP whose column the primitives explain to within this share is absorbed by them.
ABSORBED = 1e-4


def confounded_partners(
    spec, problem, params, dependent: np.ndarray, fixed: np.ndarray, columns, k_over_n=None
) -> dict:
    """For each reduced column j in ``columns``: (partner index, |corr|, kind) with kind
    "scale", "primitives" or "parameter"."""
    K, C, Hz = (np.asarray(a) for a in _reduced_system(spec, problem, params))
    r = K.shape[0]
    d = np.sqrt(np.clip(np.diag(K), 0.0, None))
    d = np.where(d > 0, d, 1.0)
    Ks = K / np.outer(d, d)
    Cs = C / d[None, :]
    ns = spec.n_scans
    out = {}
    for j in columns:
        keep = ~(dependent | fixed)
        keep[j] = True
        idx = np.flatnonzero(keep)
        A = Ks[np.ix_(idx, idx)].copy()
        jj = int(np.flatnonzero(idx == j)[0])
        A[jj, jj] += RIDGE
        B = Cs[:, idx] if Hz.shape[1] else np.zeros((0, len(idx)))
        M = np.block([[A, B.T], [B, np.zeros((B.shape[0], B.shape[0]))]])
        Q = np.linalg.pinv(M, hermitian=True)[: len(idx), : len(idx)]
        s = np.sqrt(np.clip(np.diag(Q), 1e-300, None))
        corr = Q[jj] / (s[jj] * s)
        corr[jj] = 0.0
        k = int(np.argmax(np.abs(corr)))
        # The AP's own uncertainty direction, back in unscaled reduced coordinates.
        v = np.zeros(r)
        v[idx] = Q[jj] / d[idx]
        if k_over_n is not None and k_over_n[j] < ABSORBED:
            kind = "primitives"
        elif is_scale(v, params, ns):
            kind = "scale"
        else:
            kind = "parameter"
        out[j] = (int(idx[k]), float(abs(corr[k])), kind)
    return out


def is_scale(v, params, ns) -> bool:
    """True when the scan-position part of the null direction is a radial expansion."""
    S = np.asarray(params.eops)[:, :3]
    radial = (S - S.mean(axis=0)).reshape(-1)
    pos = v[: 6 * ns].reshape(ns, 6)[:, :3].reshape(-1)
    pos = pos - np.tile(pos.reshape(ns, 3).mean(axis=0), ns)
    den = np.linalg.norm(pos) * np.linalg.norm(radial)
    return bool(den > 0 and abs(pos @ radial) / den > 0.9)


#: Scan positions closer than this [m] are one station of the design.
STATION_TOLERANCE = 0.05


def station_of_scans(eops, tolerance: float = STATION_TOLERANCE) -> np.ndarray:
    """Station index of every scan (s,): scans whose positions are within ``tolerance`` of a
    station's first scan share it (two scans of one set-up differ by the noise of their
    estimated positions, which separates nothing that the design does not)."""
    out, centres = np.zeros(len(eops), dtype=int), []
    for j, x in enumerate(np.asarray(eops)[:, :3]):
        for k, c in enumerate(centres):
            if np.linalg.norm(x - c) < tolerance:
                out[j] = k
                break
        else:
            out[j] = len(centres)
            centres.append(x)
    return out


def station_positions(eops, tolerance: float = STATION_TOLERANCE) -> np.ndarray:
    """Every scan's position replaced by the mean position of its station (s, 3): the design
    as set up, for estimability judged from the design rather than from noise."""
    pos = np.asarray(eops)[:, :3]
    st = station_of_scans(pos, tolerance)
    means = np.stack([pos[st == k].mean(axis=0) for k in range(st.max() + 1)])
    return means[st]


#: Plane points of one scan whose mean distance from the adjusted plane exceeds this [m], and
#: this many times its standard error, suggest a wrong match of that scan's patch.
PLANE_OFFSET = 0.01
PLANE_OFFSET_SIGMAS = 5.0


def _group_rms(e2, rows, group, n_groups):
    """RMS of whitened residuals and counts per group (e.g. per scan)."""
    cnt = np.bincount(group[rows], minlength=n_groups)
    ss = np.bincount(group[rows], weights=e2[rows], minlength=n_groups)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.sqrt(ss / cnt), cnt


def failure_diagnosis(net, plan, q) -> dict:
    """Where the misfit of an adjustment sits, in words and numbers a person can act on.

    From the whitened residuals at the last estimate: sigma0 per scan and per target or plane
    (RMS of the whitened residuals, 1 when the data fit their sigmas), the largest normalised
    misclosures with their scan, primitive and observation, and plane matches that look wrong
    (a scan's points on a plane sitting centimetres off the adjusted plane on average).
    Host side; strict-JSON friendly (no NaN).
    """
    GROUPS = ("range", "hz", "el")
    scan_ss, scan_n = np.zeros(len(net.scans)), np.zeros(len(net.scans))
    worst, per_prim, planes_off = [], {}, []
    for fi, fam in enumerate(plan.problem.families):
        e = np.asarray(q.misclosure[fi])
        active = fam.active_rows(np)
        e2 = np.where(active, e**2, 0.0)
        scan, prim = np.asarray(fam.scan), np.asarray(fam.prim)
        np.add.at(scan_ss, scan, e2.sum(axis=1))
        np.add.at(scan_n, scan, active.sum(axis=1))
        is_plane = fi == plan.plane_family
        names = (
            net.planes
            if is_plane
            else ["-".join(net.targets[t] for t in tg) for tg in plan.family_targets[fi]]
        )
        rms, cnt = _group_rms(e2.sum(axis=1), active.any(axis=1), prim, len(names))
        for k in np.argsort(-np.nan_to_num(rms))[:5]:
            if cnt[k]:
                per_prim[names[k]] = round(float(rms[k] / np.sqrt(max(e.shape[1], 1))), 3)
        flat = np.abs(np.where(active, e, 0.0))
        for i in np.argsort(-flat.max(axis=1))[:5]:
            c = int(np.argmax(flat[i]))
            worst.append(
                {
                    "scan": net.scans[scan[i]],
                    "primitive": names[prim[i]],
                    "observation": "condition" if is_plane else GROUPS[c],
                    "normalised_misclosure": round(float(e[i, c]), 2),
                }
            )
        if is_plane:
            planes_off = _plane_offsets(net, fam, q, fi)
    with np.errstate(invalid="ignore", divide="ignore"):
        s0_scan = np.sqrt(scan_ss / scan_n)
    worst = sorted(worst, key=lambda w: -abs(w["normalised_misclosure"]))[:5]
    out = {
        "sigma0_per_scan": {
            s: round(float(v), 3) for s, v in zip(net.scans, s0_scan) if np.isfinite(v)
        },
        "worst_primitives": per_prim,
        "largest_misclosures": worst,
        "suspicious_plane_matches": planes_off,
    }
    out["summary"] = _summary(out)
    return out


def _plane_offsets(net, fam, q, fi):
    """Mean distance of each scan's points from the adjusted plane, flagged when large."""
    g = np.asarray(q.misclosure[fi])[:, 0]  # whitened condition g / sqrt(m)
    m_sigma = 1.0 / np.where(np.asarray(fam.weight)[:, 0] > 0, np.asarray(fam.weight)[:, 0], np.inf)
    dist = g * m_sigma  # approximately the point's distance [m] (m ~ range variance)
    active = fam.active_rows(np)[:, 0]
    out = []
    pair = np.asarray(fam.pair)
    n_pairs = int(np.asarray(fam.pair_prim).shape[0])
    cnt = np.bincount(pair[active], minlength=n_pairs)
    mean = np.bincount(pair[active], weights=dist[active], minlength=n_pairs) / np.maximum(cnt, 1)
    sd = np.sqrt(
        np.bincount(pair[active], weights=dist[active] ** 2, minlength=n_pairs) / np.maximum(cnt, 1)
        - mean**2
    )
    se = sd / np.sqrt(np.maximum(cnt, 1))
    bad = (cnt > 0) & (np.abs(mean) > PLANE_OFFSET) & (np.abs(mean) > PLANE_OFFSET_SIGMAS * se)
    pp, ps = np.asarray(fam.pair_prim), np.asarray(fam.pair_scan)
    for k in np.flatnonzero(bad)[np.argsort(-np.abs(mean[bad]))][:10]:
        out.append(
            {
                "scan": net.scans[ps[k]],
                "plane": net.planes[pp[k]],
                "points": int(cnt[k]),
                "mean_offset_mm": round(float(mean[k] * 1e3), 1),
            }
        )
    return out


def _summary(d) -> str:
    parts = []
    s0 = d["sigma0_per_scan"]
    if s0:
        worst = max(s0, key=s0.get)
        parts.append(
            f"largest misfit in scan {worst} (sigma0 {s0[worst]:.3g}; all scans: "
            + ", ".join(f"{k} {v:.3g}" for k, v in s0.items())
            + ")"
        )
    if d["largest_misclosures"]:
        w = d["largest_misclosures"][0]
        parts.append(
            f"largest normalised misclosure {w['normalised_misclosure']:.3g} ({w['observation']} of "
            f"{w['primitive']} in scan {w['scan']})"
        )
    for p in d["suspicious_plane_matches"][:3]:
        parts.append(
            f"the points of scan {p['scan']} on plane {p['plane']} sit {p['mean_offset_mm']:.0f} mm off "
            "the adjusted plane (wrong match?)"
        )
    return "; ".join(parts)
