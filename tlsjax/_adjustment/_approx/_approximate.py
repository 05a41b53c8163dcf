"""Approximate values from the observations alone (host side, numpy).

The adjustment linearises about these values, so they must be right to centimetres and tenths
of a degree for any plausible network: targets, planes of any orientation (oblique, nearly
parallel, crossing the room and so seen from both sides), stations close to a plane, scans that
see different subsets of the primitives, levelled or tilted scans, hybrid or panoramic scanners,
and gross errors among the correspondences (a target metres off, a swapped name, a wrong plane
match).

1. *Local primitives* per scan (:mod:`._local`): target points and plane fits.
2. *Spanning tree*: the scans are placed one at a time, each the unplaced scan sharing the most
   primitives with those already placed, by one robust closed-form registration against the
   object-space primitives of all placed scans (:mod:`._register`: targets by minimal triples
   screened with their invariant distances, planes by pairs of normals with their signs).
3. *One refinement*: every scan re-registered against the primitives of all the others
   (``ApproxConfig.rounds``), which spreads the error of the first placements over the network.
4. *Consensus* (:mod:`._consistency`): per primitive, the largest group of its (scan,
   primitive) correspondences that agree in object space is kept; the rest are reported
   (:attr:`Approximation.inconsistent`, logged, and the per-observation inlier masks) and left
   out of the object-space primitives. A scan whose consistent correspondences do not fix its
   rotation or position raises a one-line ``ValueError`` naming the scan and its primitives.
5. *Frame* (:mod:`._frame`).
"""

from __future__ import annotations

import dataclasses
import logging

import numpy as np

from .._network import Network, memoised
from ._config import ApproxConfig, Approximation
from ._consistency import check_determined, consensus, inconsistencies, raise_undetermined
from ._frame import orient, to_frame
from ._local import Data, Sums, local_data, scan_prims, target_noise
from ._register import register
from ._targets import all_determined, place_scans, refine_scans

_LOG = logging.getLogger(__name__)


def approximate_values(net: Network, config: ApproxConfig | None = None):
    """Targets (t, 3) and scan poses (s, 6) = (Xs, Ys, Zs, omega, phi, kappa)."""
    a = approximate(net, config)
    return a.targets, a.eops


def approximate_network(net: Network, config: ApproxConfig | None = None):
    """Targets (t, 3), scan poses (s, 6) and planes (k, 4) = (n, d) of any network."""
    a = approximate(net, config)
    return a.targets, a.eops, a.planes


def _shared_counts(data: Data):
    """(s, s) number of primitives each pair of scans shares (targets, and planes twice: a
    plane fixes two rotation angles and one position coordinate)."""
    n_s = data.n_scans
    M = np.zeros((n_s, data.n_targets + data.n_planes))
    M[data.t_scan, data.t_index] = 1.0
    M[data.pair_scan, data.n_targets + data.pair_plane] = 2.0
    C = (M > 0).astype(np.float64) @ M.T
    np.fill_diagonal(C, 0.0)
    return C


def _place_scans(net, data: Data, local, cfg: ApproxConfig, rng):
    """Poses (A, S) with ``X = A_j x + S_j`` (object frame = the first scan's), chained over a
    spanning tree: the next scan is the unplaced one sharing the most primitives with the placed
    ones (its tree parent: the placed scan it shares most with), registered against all of them
    at once. Returns (A, S, tree, registrations)."""
    n_s = data.n_scans
    C = _shared_counts(data)
    A = np.tile(np.eye(3), (n_s, 1, 1))
    S = np.zeros((n_s, 3))
    root = int(np.argmax(C.sum(axis=1)))
    placed = np.zeros(n_s, dtype=bool)
    placed[root] = True
    tree, regs = [(root, None)], []
    all_p = np.ones(len(data.pair_scan), dtype=bool)
    all_t = np.ones(len(data.t_scan), dtype=bool)
    while not placed.all():
        obj = Sums.of(data, A, S, all_p, all_t, placed).prims(cfg)
        shares = np.where(placed, -1.0, C[:, placed].sum(axis=1))
        fit, first = None, None
        for j in np.argsort(-shares, kind="stable")[: int((~placed).sum())]:
            f = register(obj, local[j], cfg, rng)
            first = (int(j), f) if first is None else first
            if f is not None and f.determined:
                fit = f
                break
        if fit is None:
            raise_undetermined(net, *first)
        A[j], S[j] = fit.R, fit.t
        tree.append((int(j), int(np.flatnonzero(placed)[np.argmax(C[j, placed])])))
        regs.append((int(j), fit.n_inliers, fit.shared.size))
        placed[j] = True
    return A, S, tree, regs


def _refine(data: Data, local, A, S, cfg: ApproxConfig, rng):
    """Each scan re-registered from its pose against the primitives of all the others at the
    poses of the round's start (``cfg.rounds`` rounds)."""
    all_p = np.ones(len(data.pair_scan), dtype=bool)
    all_t = np.ones(len(data.t_scan), dtype=bool)
    ones = np.ones(data.n_scans, dtype=bool)
    for _ in range(cfg.rounds):
        A0, S0 = A.copy(), S.copy()
        total = Sums.of(data, A0, S0, all_p, all_t, ones)
        for j in range(data.n_scans):
            own = Sums.of(data, A0, S0, all_p, all_t, np.arange(data.n_scans) == j)
            obj = total.without(own).prims(cfg)
            fit = register(obj, local[j], cfg, rng, current=(A0[j], S0[j]))
            if fit is not None and fit.determined:
                A[j], S[j] = fit.R, fit.t


def _tree_order(C):
    """Scans in the order of a maximum spanning tree of the shared counts ``C`` (Prim), from
    the scan sharing most, each with its parent (the placed scan it shares most with)."""
    n_s = C.shape[0]
    placed = np.zeros(n_s, dtype=bool)
    root = int(np.argmax(C.sum(axis=1)))
    placed[root] = True
    tree = [(root, None)]
    for _ in range(n_s - 1):
        j = int(np.argmax(np.where(placed, -1.0, C[:, placed].max(axis=1))))
        tree.append((j, int(np.flatnonzero(placed)[np.argmax(C[j, placed])])))
        placed[j] = True
    return tree


def _by_targets(data: Data, cfg: ApproxConfig, rng):
    """The vectorised path of a network of targets only (:mod:`._targets`), or None when a scan
    is not fixed (the general path then names it)."""
    tree = _tree_order(_shared_counts(data))
    placed = place_scans(data, cfg, [j for j, _ in tree], rng)
    if placed is None:
        return None
    A, S, _, regs = placed
    data.t_noise = target_noise(data, A, S)
    use_p, use_t = consensus(data, A, S, cfg)
    for _ in range(cfg.rounds):
        refine_scans(data, A, S, use_t, cfg)
        use_p, use_t = consensus(data, A, S, cfg)
    if not all_determined(data, A, S, use_t):
        return None
    return A, S, tree, regs, use_p, use_t


def _general(net, data: Data, cfg: ApproxConfig, rng):
    """Planes, or targets and planes: registrations of :mod:`._register` (module docstring)."""
    local = [scan_prims(data, j, cfg) for j in range(data.n_scans)]
    A, S, tree, regs = _place_scans(net, data, local, cfg, rng)
    data.t_noise = target_noise(data, A, S)
    if data.t_noise:
        local = [scan_prims(data, j, cfg) for j in range(data.n_scans)]
    _refine(data, local, A, S, cfg, rng)
    use_p, use_t = consensus(data, A, S, cfg)
    check_determined(net, data, local, A, S, use_p, use_t, cfg)
    return A, S, tree, regs, use_p, use_t


def approximate(net: Network, config: ApproxConfig | None = None) -> Approximation:
    """Approximate values of any network (targets, planes or both), with the gross errors the
    registration found among the correspondences (see the module docstring).

    Computed once per network's data and config (:func:`.._network.memoised`: a network is
    calibrated many times); every call logs the inconsistencies and returns its own arrays."""
    cfg = config or ApproxConfig()
    a = memoised(net, ("approximate", cfg), lambda: _approximate(net, cfg))
    for item in a.inconsistent:
        _LOG.warning("%s: inconsistent correspondence: %s", net.source, item)
    copy = lambda x: x.copy() if isinstance(x, np.ndarray) else x
    return dataclasses.replace(
        a, **{f.name: copy(getattr(a, f.name)) for f in dataclasses.fields(a)}
    )


def _approximate(net: Network, cfg: ApproxConfig) -> Approximation:
    rng = np.random.default_rng(0)
    data = local_data(net)
    found = _by_targets(data, cfg, rng) if data.n_planes == 0 else None
    if found is None:
        data.t_noise = 0.0
        found = _general(net, data, cfg, rng)
    A, S, tree, regs, use_p, use_t = found
    inconsistent = inconsistencies(net, data, A, S, use_p, use_t, cfg)
    targets, planes = _object_values(data, A, S, use_p, use_t, cfg)
    control = (net.control_index, net.control_xyz) if len(net.control_index) else None
    targets, eops, planes = to_frame(A, S, targets, planes, net.is_levelled, control)
    name = lambda j: None if j is None else net.scans[j]
    return Approximation(
        targets,
        eops,
        planes,
        inconsistent,
        tuple((net.scans[j], name(p)) for j, p in tree),
        target_inlier=use_t,
        plane_inlier=use_p[data.pair_of_row] if len(data.pair_of_row) else np.ones(0, bool),
        registrations=tuple((net.scans[j], n_in, n_sh) for j, n_in, n_sh in regs),
    )


def _object_values(data: Data, A, S, use_p, use_t, cfg: ApproxConfig):
    """Targets (t, 3) and planes (k, 4) from the consistent correspondences of every scan."""
    obj = Sums.of(data, A, S, use_p, use_t, np.ones(data.n_scans, dtype=bool)).prims(cfg)
    targets = np.zeros((data.n_targets, 3))
    targets[obj.target] = obj.x
    planes = np.zeros((data.n_planes, 4))
    planes[obj.plane, :3] = orient(obj, data, A, S, use_p)
    centroids = np.zeros((data.n_planes, 3))
    centroids[obj.plane] = obj.c
    planes[:, 3] = np.einsum("ki,ki->k", planes[:, :3], centroids)
    return targets, planes
