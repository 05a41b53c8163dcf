"""Outlier screening of plane networks: robust reweighting of the Gauss-Helmert conditions,
then an adjustment with the a priori weights of the points kept (SPEC sections 4 and 7).

Points extracted from real scans carry edges, clutter and neighbouring surfaces. Removing one
point at a time by data snooping costs one adjustment per removal, far too many for 10^5
points, so plane networks use the IGG-III scheme (Yang 1999; Yang, Song & Xu 2002) on the
conditions, one condition per point:

* the normalised residual of point i is the w-test of its condition,
  ``w_i = e_i / (s sqrt(r_i))``, with ``e_i = g_i / sqrt(m_i)`` the whitened condition,
  ``r_i = 1 - (a Q a^T)_i`` its redundancy number (the sum of its three observations' shares)
  and ``s`` a robust scale of the w's (``median |w| / 0.6745``, :func:`tlsjax._stats.robust_scale`), so that a
  priori sigmas that are too large or too small by any factor neither hide nor invent outliers;
* the point's weight is multiplied by the IGG-III factor ``1`` for ``|w| <= k0``,
  ``(k0 / |w|) ((k1 - |w|) / (k1 - k0))^2`` for ``k0 < |w| <= k1`` and ``0`` beyond ``k1``,
  and the network re-adjusted, until no factor changes by more than 1e-3;
* the points with ``|w| > k1`` are removed and the network adjusted once more with the a priori
  weights of all other points: that final adjustment gives the estimates, sigmas and tests.

``k0`` is the per-test critical value of Baarda's w-test (3.29 for ``point_level`` = 0.1 %),
``k1`` the family-wise (Bonferroni) critical value for all points at ``family_level`` = 5 %, so that a clean
network of 10^5 points loses no point with probability 95 %. Every reweighting is a new weight
vector for the same compiled adjustment (:class:`tlsjax.Adjustment`): nothing recompiles.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .._adjustment._network import Network
from .._adjustment._quality import MIN_TESTABLE_REDUNDANCY
from .._adjustment._result import CalibrationResult, assemble
from .._stats import normal_critical_value, robust_scale
from .._summary import Settings, to_json_value


@dataclasses.dataclass(frozen=True)
class PlaneScreeningOptions(Settings):
    """IGG-III screening of plane points (module docstring): ``point_level``, the level of one
    point's w-test below which it keeps its full weight (k0); ``family_level``, the family-wise
    level of the final removal (k1, Bonferroni over the points); ``max_iterations`` of the
    reweighting."""

    point_level: float = 0.001
    family_level: float = 0.05
    max_iterations: int = 10

    def __post_init__(self):
        for name in ("point_level", "family_level"):
            v = getattr(self, name)
            if not 0 < v < 1:
                raise ValueError(f"PlaneScreeningOptions.{name} must be in (0, 1), got {v}")
        if int(self.max_iterations) < 1:
            raise ValueError(
                f"PlaneScreeningOptions.max_iterations must be >= 1, got {self.max_iterations}"
            )


@dataclasses.dataclass(frozen=True, eq=False)
class PlaneScreening:
    """What the IGG-III screening of the plane points found (``result.plane_screening`` of
    :func:`tlsjax.self_calibrate`): ``removed`` (row indices into the network's plane rows),
    ``w`` (the normalised residuals of the last reweighting; NaN where untestable), ``scale``
    (the robust scale of the w's), ``k0``, ``k1``, ``iterations``, and ``per_pair`` (scan,
    plane) -> {"points", "removed"} counts."""

    removed: np.ndarray
    w: np.ndarray
    scale: float
    k0: float
    k1: float
    iterations: int
    per_pair: dict

    def summary(self) -> str:
        lines = [
            f"plane outlier screening (IGG-III, k0 = {self.k0:.2f}, k1 = {self.k1:.2f}, robust scale "
            f"{self.scale:.3g}, {self.iterations} reweightings): {len(self.removed)} point(s) removed"
        ]
        for (scan, plane), c in sorted(self.per_pair.items(), key=lambda kv: -kv[1]["removed"]):
            if c["removed"]:
                lines.append(
                    f"  scan {scan}, plane {plane}: {c['removed']} of {c['points']} points removed"
                )
        return "\n".join(lines)

    def to_dict(self) -> dict:
        pairs = [
            {"scan": s, "plane": p, **c} for (s, p), c in self.per_pair.items() if c["removed"]
        ]
        return to_json_value(
            {
                "method": "IGG-III reweighting of the Gauss-Helmert conditions, then a priori weights",
                "k0": self.k0,
                "k1": self.k1,
                "robust_scale": self.scale,
                "iterations": self.iterations,
                "n_removed": int(len(self.removed)),
                "removed_per_scan_and_plane": pairs,
            }
        )


def igg3(w, k0: float, k1: float):
    """IGG-III weight factor of normalised residuals ``w`` (Yang 1999)."""
    a = np.abs(w)
    mid = (k0 / np.maximum(a, k0)) * ((k1 - a) / (k1 - k0)) ** 2
    return np.where(a <= k0, 1.0, np.where(a <= k1, mid, 0.0))


def _normalised(res: CalibrationResult, q_e, active):
    r = res.plane_redundancy.sum(axis=1)
    ok = active & (r > MIN_TESTABLE_REDUNDANCY)
    w = np.full(len(r), np.nan)
    w[ok] = q_e[ok] / np.sqrt(r[ok])
    return w


def screen_planes(adjustment, options: PlaneScreeningOptions):
    """Robust outlier screening of the plane points of an analysed adjustment (a
    :class:`tlsjax.Adjustment` of a network with planes; module docstring): the
    :class:`PlaneScreening` and the estimates of the last reweighting (a warm start for the
    final adjustment with the a priori weights of the points kept, which the pipeline of
    :func:`tlsjax.self_calibrate` runs)."""
    network = adjustment.network
    base = 1.0 / network.plane_sigmas
    n = base.shape[0]
    k0 = normal_critical_value(options.point_level)
    k1 = max(normal_critical_value(options.family_level / n), k0 + 0.5)
    factor = np.ones(n)
    params, scale, w, iterations = None, 1.0, np.full(n, np.nan), 0
    for _ in range(int(options.max_iterations)):
        iterations += 1
        res, q, params = _solve(adjustment, base * np.sqrt(factor)[:, None], params)
        if not res.ok:
            break
        e = np.asarray(q.misclosure[adjustment.plan.plane_family])[:, 0]
        w = _normalised(res, e / np.sqrt(np.maximum(factor, 1e-300)), factor > 0)
        good = np.isfinite(w)
        scale = robust_scale(w, good, 1) if good.any() else 1.0
        new = np.where(good, igg3(w / max(scale, 1e-300), k0, k1), factor)
        done = np.max(np.abs(new - factor)) < 1e-3
        factor = new
        if done:
            break
    removed = np.flatnonzero(factor == 0)
    screening = PlaneScreening(
        removed, w, scale, float(k0), float(k1), iterations, _per_pair(network, removed)
    )
    return screening, params


def _solve(adj, plane_weights, params):
    """One adjustment with other plane weights: the result, the quality arrays and the
    estimates (a warm start for the next)."""
    problem = adj.problem(plane_weights=plane_weights)
    state, q = adj.run(problem, params)
    plan = dataclasses.replace(adj.plan, problem=problem)
    return assemble(adj.network, adj.model, plan, state, q), q, state.params


def _per_pair(net: Network, removed):
    out = {}
    cnt = {}
    for j, k in zip(net.plane_scan_index, net.plane_index):
        key = (net.scans[j], net.planes[k])
        cnt[key] = cnt.get(key, 0) + 1
    rem = {}
    for i in removed:
        key = (net.scans[net.plane_scan_index[i]], net.planes[net.plane_index[i]])
        rem[key] = rem.get(key, 0) + 1
    for key, c in cnt.items():
        out[key] = {"points": int(c), "removed": int(rem.get(key, 0))}
    return out
