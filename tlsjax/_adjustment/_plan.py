"""The index plan of one (network, model) pair, built once on the host.

Which observations share a target or plane, which (primitive, scan) pairs exist, which
parameters the datum holds, and the static description (instruments, AP blocks, datum defect)
that the compiled adjustment is specialised on.
"""

from __future__ import annotations

import dataclasses

import jax.numpy as jnp
import numpy as np

from .._model._aps import get_ap
from .._model._scanner import Scanner
from ._approx import approximate_network, approximate_values
from ._config import CalibrationModel
from ._families import Family, Params, Problem, Spec
from ._network import Network

#: Weight of the unit-normal constraint ``|n|^2 - 1`` of a plane, as a pseudo-observation: with
#: it the constraint holds to ~1e-13 while the normal matrix stays well conditioned (a hard
#: constraint in a bordered system gives the same solution, tests/test_plane_adjustment.py).
UNIT_NORMAL_WEIGHT = 1e7
PLANE_PARAMETERS = ("nx", "ny", "nz", "d")


@dataclasses.dataclass(frozen=True, eq=False)
class Plan:
    """Host-built index plan and static spec of one (network, model) pair."""

    spec: Spec
    problem: Problem
    family_targets: tuple  # per family: (n, k) target indices
    ap_labels: tuple
    ap_units: tuple
    parameter_names: tuple
    fixed_scan_index: int | None
    plane_family: int | None = None  # index of the plane family among problem.families


def _scanner_for(model: CalibrationModel, instrument: str) -> Scanner:
    if isinstance(model.scanner, Scanner):
        return model.scanner
    try:
        return model.scanner[instrument]
    except KeyError:
        raise ValueError(
            f"no Scanner configured for instrument {instrument!r}; configured: {sorted(model.scanner)}"
        ) from None


def build_plan(net: Network, model: CalibrationModel) -> Plan:
    """Index plan (which observations share a target, which (target, scan) pairs exist)."""
    scanners = tuple(_scanner_for(model, ins) for ins in net.instruments)
    ap_names, ap_slices, labels, units = [], [], [], []
    off = 0
    for ins, sc in zip(net.instruments, scanners):
        ap_names.append(sc.aps)
        ap_slices.append((off, off + len(sc.aps)))
        off += len(sc.aps)
        for a in sc.aps:
            labels.append(a if len(net.instruments) == 1 else f"{a}[{ins}]")
            units.append(get_ap(a).unit)
    n_s = len(net.scans)
    levelled = net.is_levelled.any()

    datum = model.datum
    if datum == "auto":
        datum = "control" if len(net.control_index) else "inner"
    if datum == "control" and len(net.control_index) == 0:
        raise ValueError(f"{net.source}: datum 'control' needs control points")
    fixed = np.zeros(6 * n_s + off, dtype=bool)
    fixed_idx = None
    if datum == "fixed-scan":
        if model.fixed_scan not in net.scans:
            raise ValueError(
                f"fixed scan {model.fixed_scan!r} is not a scan of {net.source}; scans: {', '.join(net.scans)}"
            )
        fixed_idx = net.scans.index(model.fixed_scan)
        cols = (0, 1, 2, 5) if levelled else tuple(range(6))
        fixed[[6 * fixed_idx + c for c in cols]] = True
    for name in model.fixed_aps:
        if name not in labels:
            raise ValueError(
                f"fixed AP {name!r} is not among the APs of the model: {' '.join(labels)}"
            )
        fixed[6 * n_s + labels.index(name)] = True
    datum_columns = ((0, 1, 2, 5) if levelled else tuple(range(6))) if datum == "inner" else ()

    # Families: free targets (k=1) and scale bars (k=2: both end targets in one block).
    n_t = len(net.targets)
    bars = net.scale_bar_targets
    in_bar = np.zeros(n_t, dtype=bool)
    if len(bars):
        flat = bars.reshape(-1)
        if len(set(flat.tolist())) != len(flat):
            raise ValueError(f"{net.source}: a target may end at most one scale bar")
        in_bar[flat] = True
    fam_of = np.zeros(n_t, dtype=np.int32)
    prim_of = np.zeros(n_t, dtype=np.int32)
    point_of = np.zeros(n_t, dtype=np.int32)
    free = np.flatnonzero(~in_bar)
    prim_of[free] = np.arange(len(free))
    fam_targets = [free[:, None]]
    if len(bars):
        fam_of[bars.reshape(-1)] = 1
        prim_of[bars[:, 0]] = prim_of[bars[:, 1]] = np.arange(len(bars))
        point_of[bars[:, 1]] = 1
        fam_targets.append(bars)
    ctrl_w_t = np.zeros((n_t, 3))
    ctrl_x_t = np.zeros((n_t, 3))
    if datum != "inner" or len(net.control_index):
        ctrl_w_t[net.control_index] = 1.0 / net.control_sigma
        ctrl_x_t[net.control_index] = net.control_xyz
    families = []
    if not net.has_targets:
        fam_targets = []
    for fi, tg in enumerate(fam_targets):
        m = fam_of[net.target_index] == fi
        prim = prim_of[net.target_index[m]]
        scan = net.scan_index[m]
        pairs, pair = np.unique(np.stack([prim, scan], axis=1), axis=0, return_inverse=True)
        k = tg.shape[1]
        blen = np.zeros(len(tg))
        bw = np.zeros(len(tg))
        if k == 2:
            blen[:] = net.scale_bar_length
            bw[:] = 1.0 / net.scale_bar_sigma
        families.append(
            Family(
                obs=jnp.asarray(net.observations[m]),
                weight=jnp.asarray(1.0 / net.sigmas[m]),
                prim=jnp.asarray(prim),
                point=jnp.asarray(point_of[net.target_index[m]]),
                scan=jnp.asarray(scan),
                pair=jnp.asarray(pair.reshape(-1).astype(np.int32)),
                pair_prim=jnp.asarray(pairs[:, 0]),
                pair_scan=jnp.asarray(pairs[:, 1]),
                ctrl_xyz=jnp.asarray(ctrl_x_t[tg]),
                ctrl_weight=jnp.asarray(ctrl_w_t[tg]),
                bar_length=jnp.asarray(blen),
                bar_weight=jnp.asarray(bw),
                k=k,
            )
        )
    kinds = ["point"] * len(families)
    plane_family = None
    if net.has_planes:
        # Planes: one Gauss-Helmert condition per point (SPEC section 4), p = 4 per plane.
        n_k = len(net.planes)
        prim, scan = net.plane_index, net.plane_scan_index
        pairs, pair = np.unique(np.stack([prim, scan], axis=1), axis=0, return_inverse=True)
        plane_family = len(families)
        families.append(
            Family(
                obs=jnp.asarray(net.plane_observations),
                weight=jnp.asarray(1.0 / net.plane_sigmas),
                prim=jnp.asarray(prim),
                point=jnp.zeros(len(prim), dtype=jnp.int32),
                scan=jnp.asarray(scan),
                pair=jnp.asarray(pair.reshape(-1).astype(np.int32)),
                pair_prim=jnp.asarray(pairs[:, 0]),
                pair_scan=jnp.asarray(pairs[:, 1]),
                ctrl_xyz=jnp.zeros((n_k, 1, 3)),
                ctrl_weight=jnp.zeros((n_k, 1, 3)),
                bar_length=jnp.zeros(n_k),
                bar_weight=jnp.full(n_k, UNIT_NORMAL_WEIGHT),
                k=1,
                kind="plane",
            )
        )
        kinds.append("plane")
    spec = Spec(
        scanners,
        tuple(ap_names),
        tuple(ap_slices),
        n_s,
        datum_columns,
        datum == "inner",
        tuple(kinds),
    )
    lw = np.where(np.isfinite(net.levelling_sigma), 1.0 / net.levelling_sigma, 0.0)
    problem = Problem(
        tuple(families),
        jnp.asarray(net.instrument_of_scan),
        jnp.asarray(net.levelling),
        jnp.asarray(lw),
        jnp.asarray(fixed),
    )

    names = []
    for tg in fam_targets:
        for row in tg:
            for t in row:
                names += [f"{c}[{net.targets[t]}]" for c in "XYZ"]
    for k in net.planes:
        names += [f"{c}[{k}]" for c in PLANE_PARAMETERS]
    for s in net.scans:
        names += [f"{c}[{s}]" for c in ("Xs", "Ys", "Zs", "omega", "phi", "kappa")]
    names += labels
    return Plan(
        spec,
        problem,
        tuple(fam_targets),
        tuple(labels),
        tuple(units),
        tuple(names),
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
    prims = [
        jnp.asarray(np.asarray(targets)[tg].reshape(len(tg), -1)) for tg in plan.family_targets
    ]
    if net.has_planes:
        P = np.array(planes, dtype=np.float64).reshape(len(net.planes), 4)
        P /= np.linalg.norm(P[:, :3], axis=1, keepdims=True)[:, [0, 0, 0, 0]]
        prims.append(jnp.asarray(P))
    return Params(tuple(prims), jnp.asarray(eops), jnp.zeros(plan.spec.n_aps))
