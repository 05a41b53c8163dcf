"""The index plan of one (network, model) pair, built once on the host.

Which observations share a target or plane, which (primitive, scan) pairs exist, which
parameters the datum holds, and the static description (instruments, AP blocks, datum defect)
that the compiled adjustment is specialised on.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .._model._aps import get_ap
from .._model._datum import free_motions
from .._model._scanner import Scanner
from ._approx import approximate_network, approximate_values
from ._config import CalibrationModel
from ._families import Params, PlaneFamily, PointFamily, Problem, Spec
from ._network import Network

#: Strength of the unit-normal constraint ``|n|^2 - 1`` of a plane, as a pseudo-observation,
#: relative to what the plane's points say about its normal: its weight is this factor times
#: ``sqrt(sum_i rho_i^2 / sigma_i^2)`` over the plane's points (their information on n), so the
#: constraint holds to ~1e-13 while the normal matrix stays well conditioned, whatever the
#: scale of the sigmas (a hard constraint in a bordered system gives the same solution,
#: tests/test_plane_adjustment.py).
UNIT_NORMAL_STRENGTH = 1e3
PLANE_PARAMETERS = ("nx", "ny", "nz", "d")


@dataclasses.dataclass(frozen=True, eq=False)
class Plan:
    """Host-built index plan and static spec of one (network, model) pair.

    ``family_targets``: per point family, the (n, k) target indices of its primitives;
    ``family_rows``: per family, the rows of the network's observation table it holds (target
    rows for point families, plane rows for the plane family), in the family's order.
    """

    spec: Spec
    problem: Problem
    family_targets: tuple
    family_rows: tuple
    ap_labels: tuple
    ap_units: tuple
    parameter_names: tuple
    datum: str
    fixed_scan_index: int | None
    plane_family: int | None = None  # index of the plane family among problem.families


def _scanner_for(model: CalibrationModel, instrument: str) -> Scanner:
    if isinstance(model.scanner, Scanner):
        return model.scanner
    try:
        return model.scanner[instrument]
    except KeyError:
        raise ValueError(
            f"no Scanner configured for instrument {instrument!r}; "
            f"configured: {sorted(model.scanner)}"
        ) from None


def _ap_blocks(net: Network, model: CalibrationModel):
    """Scanners, AP names and slices per instrument, AP labels and units."""
    # As registered now (Scanner.current): the static spec keys the compiled adjustment.
    scanners = tuple(_scanner_for(model, ins).current() for ins in net.instruments)
    ap_names, ap_slices, labels, units = [], [], [], []
    off = 0
    for ins, sc in zip(net.instruments, scanners):
        ap_names.append(sc.aps)
        ap_slices.append((off, off + len(sc.aps)))
        off += len(sc.aps)
        for a in sc.aps:
            labels.append(a if len(net.instruments) == 1 else f"{a}[{ins}]")
            units.append(get_ap(a).unit)
    return scanners, tuple(ap_names), tuple(ap_slices), tuple(labels), tuple(units)


def _datum(net: Network, model: CalibrationModel, labels, fixed_aps):
    """Datum kind, the parameters it holds (reduced order), the fixed scan, the free motions."""
    n_s = len(net.scans)
    motions = free_motions(bool(net.is_levelled.any()))
    datum = model.datum
    if datum == "auto":
        datum = "control" if len(net.control_index) else "inner"
    if datum == "control" and len(net.control_index) == 0:
        raise ValueError(f"{net.source}: datum 'control' needs control points")
    fixed = np.zeros(6 * n_s + len(labels), dtype=bool)
    fixed_idx = None
    if datum == "fixed-scan":
        if model.fixed_scan not in net.scans:
            raise ValueError(
                f"fixed scan {model.fixed_scan!r} is not a scan of {net.source}; "
                f"scans: {', '.join(net.scans)}"
            )
        fixed_idx = net.scans.index(model.fixed_scan)
        fixed[[6 * fixed_idx + c for c in motions]] = True
    for name in fixed_aps:
        if name not in labels:
            raise ValueError(
                f"fixed AP {name!r} is not among the APs of the model: {' '.join(labels)}"
            )
        fixed[6 * n_s + labels.index(name)] = True
    return datum, fixed, fixed_idx, (motions if datum == "inner" else ())


def _index_pairs(prim, scan):
    n_s = int(scan.max()) + 1 if len(scan) else 1
    keys, pair = np.unique(prim.astype(np.int64) * n_s + scan, return_inverse=True)
    return dict(
        prim=np.asarray(prim),
        scan=np.asarray(scan),
        pair=pair.reshape(-1).astype(np.int32),
        pair_prim=keys // n_s,
        pair_scan=keys % n_s,
    )


def _point_families(net: Network, datum: str):
    """Free targets (k = 1) and scale bars (k = 2: both end targets in one block)."""
    n_t = len(net.targets)
    bars = net.scale_bar_targets
    in_bar = np.zeros(n_t, dtype=bool)
    if len(bars):
        flat = bars.reshape(-1)
        if len(set(flat.tolist())) != len(flat):
            raise ValueError(f"{net.source}: a target may end at most one scale bar")
        in_bar[flat] = True
    fam_of, prim_of, point_of = (np.zeros(n_t, dtype=np.int32) for _ in range(3))
    free = np.flatnonzero(~in_bar)
    prim_of[free] = np.arange(len(free))
    fam_targets = [free[:, None]] if net.has_targets else []
    if len(bars):
        fam_of[bars.reshape(-1)] = 1
        prim_of[bars[:, 0]] = prim_of[bars[:, 1]] = np.arange(len(bars))
        point_of[bars[:, 1]] = 1
        fam_targets.append(bars)
    ctrl_w, ctrl_x = np.zeros((n_t, 3)), np.zeros((n_t, 3))
    if datum != "inner" or len(net.control_index):
        ctrl_w[net.control_index] = 1.0 / net.control_sigma
        ctrl_x[net.control_index] = net.control_xyz
    families, rows = [], []
    for fi, tg in enumerate(fam_targets):
        m = np.flatnonzero(fam_of[net.target_index] == fi)
        k = tg.shape[1]
        bar = k == 2
        families.append(
            PointFamily(
                obs=np.asarray(net.observations[m]),
                weight=np.asarray(1.0 / net.sigmas[m]),
                point=np.asarray(point_of[net.target_index[m]]),
                **_index_pairs(prim_of[net.target_index[m]], net.scan_index[m]),
                ctrl_xyz=np.asarray(ctrl_x[tg]),
                ctrl_weight=np.asarray(ctrl_w[tg]),
                bar_length=np.asarray(net.scale_bar_length if bar else np.zeros(len(tg))),
                bar_weight=np.asarray(1.0 / net.scale_bar_sigma if bar else np.zeros(len(tg))),
                k=k,
            )
        )
        rows.append(m)
    return families, rows, fam_targets


def _plane_family(net: Network):
    """Planes: one Gauss-Helmert condition per point (SPEC section 4), p = 4 per plane."""
    return PlaneFamily(
        obs=np.asarray(net.plane_observations),
        weight=np.asarray(1.0 / net.plane_sigmas),
        point=np.zeros(len(net.plane_index), dtype=np.int32),
        **_index_pairs(net.plane_index, net.plane_scan_index),
        unit_weight=np.asarray(_unit_normal_weight(net)),
    )


def _unit_normal_weight(net: Network):
    """Weight of each plane's unit-normal pseudo-observation (see ``UNIT_NORMAL_STRENGTH``)."""
    info = (net.plane_observations[:, 0] / net.plane_sigmas[:, 0]) ** 2
    total = np.bincount(net.plane_index, weights=info, minlength=len(net.planes))
    return UNIT_NORMAL_STRENGTH * np.sqrt(total)


def _parameter_names(net: Network, fam_targets, labels):
    names = [
        f"{c}[{net.targets[t]}]" for tg in fam_targets for row in tg for t in row for c in "XYZ"
    ]
    names += [f"{c}[{k}]" for k in net.planes for c in PLANE_PARAMETERS]
    eop = ("Xs", "Ys", "Zs", "omega", "phi", "kappa")
    names += [f"{c}[{s}]" for s in net.scans for c in eop]
    return tuple(names) + tuple(labels)


def build_plan(net: Network, model: CalibrationModel, fixed_aps=None) -> Plan:
    """Index plan (which observations share a target or plane, which (primitive, scan) pairs
    exist), the datum and the static spec. ``fixed_aps``: AP labels held at zero (default:
    ``model.fixed_aps``)."""
    scanners, ap_names, ap_slices, labels, units = _ap_blocks(net, model)
    fixed_aps = model.fixed_aps if fixed_aps is None else tuple(fixed_aps)
    datum, fixed, fixed_idx, datum_columns = _datum(net, model, labels, fixed_aps)
    families, rows, fam_targets = _point_families(net, datum)
    plane_family = None
    if net.has_planes:
        plane_family = len(families)
        families.append(_plane_family(net))
        rows.append(np.arange(len(net.plane_index)))
    spec = Spec(scanners, ap_names, ap_slices, len(net.scans), datum_columns, datum == "inner")
    lw = np.where(np.isfinite(net.levelling_sigma), 1.0 / net.levelling_sigma, 0.0)
    problem = Problem(
        tuple(families),
        np.asarray(net.instrument_of_scan),
        np.asarray(net.levelling),
        np.asarray(lw),
        np.asarray(fixed),
    )
    names = _parameter_names(net, fam_targets, labels)
    return Plan(
        spec,
        problem,
        tuple(fam_targets),
        tuple(rows),
        labels,
        units,
        names,
        datum,
        fixed_idx,
        plane_family,
    )


def initial_params(net: Network, plan: Plan, targets=None, eops=None, planes=None) -> Params:
    """Approximate values: computed from the observations (:mod:`._approx`) unless given."""
    if targets is None or eops is None or (net.has_planes and planes is None):
        t0, e0, p0 = (
            approximate_network(net) if net.has_planes else (*approximate_values(net), None)
        )
        targets = t0 if targets is None else np.asarray(targets, dtype=np.float64)
        eops = e0 if eops is None else np.asarray(eops, dtype=np.float64)
        planes = p0 if planes is None else planes
    prims = [np.asarray(np.asarray(targets)[tg].reshape(len(tg), -1)) for tg in plan.family_targets]
    if net.has_planes:
        P = np.array(planes, dtype=np.float64).reshape(len(net.planes), 4)
        P /= np.linalg.norm(P[:, :3], axis=1, keepdims=True)[:, [0, 0, 0, 0]]
        prims.append(np.asarray(P))
    return Params(tuple(prims), np.asarray(eops), np.zeros(plan.spec.n_aps))
