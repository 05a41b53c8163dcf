"""The truth of a simulated network: what a Monte Carlo realisation is drawn from.

A :class:`SimulationTruth` holds a network (its design: which primitive is seen in which scan,
the sigmas, levelling, control points, scale bars, instruments) and the true values behind it:
targets, planes, scan poses and, per instrument, the scanner that generated the data with its
true APs. From them it gives, for every observation row, the error-free observation
``F(X, EOP)`` (for a plane row, of the true point on the plane). A realisation is then
``l = F + e + Delta(l; AP_true)`` (the fixed point :func:`tlsjax._model._points.distorted_observations`),
so any design that :func:`tlsjax.calibrate` accepts can be simulated: partial visibility,
several instruments, control points and scale bars, planes, or targets and planes combined.

:meth:`tlsjax.Simulation.truth` (targets) and :meth:`tlsjax.PointClouds.truth` (planes) make
one; :meth:`SimulationTruth.combine` joins a target and a plane truth of the same scans into a
combined network.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from .._adjustment._network import Network, ObservationTable, make_network
from .._jit import jit
from .._model._geometry import is_face2, spherical_from_cartesian
from .._model._points import point_geometry
from .._model._scanner import Scanner


@dataclasses.dataclass(frozen=True, eq=False)
class SimulationTruth:
    """A network with the truth behind it (SI units).

    ``scanners`` (one per instrument of the network, in ``network.instruments`` order): the
    scanner that generates that instrument's data, its ``aps`` the terms present in the data;
    ``true_aps``: per instrument, {name: value}. ``eops`` (s, 6) in ``network.scans`` order,
    ``targets`` (t, 3) in ``network.targets`` order, ``planes`` (k, 4) = (n, d) in
    ``network.planes`` order, ``plane_points`` (m, 3) the true point of each plane row.
    """

    network: Network
    scanners: tuple
    true_aps: tuple
    eops: np.ndarray
    targets: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3)))
    planes: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 4)))
    plane_points: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3)))

    def __post_init__(self):
        net = self.network
        if not isinstance(net, Network):
            raise ValueError("SimulationTruth.network must be a tlsjax.Network")
        if len(self.scanners) != len(net.instruments) or len(self.true_aps) != len(net.instruments):
            raise ValueError(
                f"SimulationTruth: one scanner and one true-AP mapping per instrument "
                f"({len(net.instruments)}: {', '.join(net.instruments)})"
            )
        for sc, aps in zip(self.scanners, self.true_aps):
            if not isinstance(sc, Scanner):
                raise ValueError("SimulationTruth.scanners must be tlsjax.Scanner objects")
            missing = [a for a in sc.aps if a not in aps]
            if missing:
                raise ValueError(f"SimulationTruth: no true value for AP {missing[0]}")
        shapes = {
            "eops": (self.eops, (len(net.scans), 6)),
            "targets": (self.targets, (len(net.targets), 3)),
            "planes": (self.planes, (len(net.planes), 4)),
            "plane_points": (self.plane_points, (net.plane_observations.shape[0], 3)),
        }
        for name, (a, shape) in shapes.items():
            a = np.asarray(a, dtype=np.float64).reshape(shape)
            if not np.all(np.isfinite(a)):
                raise ValueError(f"SimulationTruth.{name} must be finite")
            object.__setattr__(self, name, a)

    def ap_vector(self, instrument: int) -> np.ndarray:
        """True AP values of one instrument, in its scanner's ``aps`` order."""
        sc = self.scanners[instrument]
        return np.array([self.true_aps[instrument][a] for a in sc.aps], dtype=np.float64)

    def error_free(self):
        """Error-free observations ``F(X, EOP)`` of the target rows (n, 3) and of the true
        points of the plane rows (m, 3), each in the face of the network's observation (a
        panoramic scanner sees a direction in the face it was observed in)."""
        net = self.network
        F_t = _spherical(
            self.targets[net.target_index],
            self.eops[net.scan_index],
            net.observations,
            self._panoramic(net.scan_index),
        )
        F_p = _spherical(
            self.plane_points,
            self.eops[net.plane_scan_index],
            net.plane_observations,
            self._panoramic(net.plane_scan_index),
        )
        return F_t, F_p

    def _panoramic(self, scan_index):
        pano = np.array([sc.architecture == "panoramic" for sc in self.scanners], dtype=bool)
        return pano[self.network.instrument_of_scan[scan_index]]

    def combine(self, other: SimulationTruth) -> SimulationTruth:
        """A combined network: the target rows of one truth and the plane rows of the other,
        scanned from the same poses by the same instruments (SPEC section 11)."""
        t, p = (self, other) if other.network.has_planes else (other, self)
        if t.network.has_planes or not p.network.has_planes or not t.network.has_targets:
            raise ValueError("combine: give one target truth and one plane truth")
        if t.network.scans != p.network.scans or not np.allclose(t.eops, p.eops, atol=1e-12):
            raise ValueError("combine: the two truths must share their scans and poses")
        if t.network.instruments != p.network.instruments or t.scanners != p.scanners:
            raise ValueError("combine: the two truths must share their instruments and scanners")
        if t.true_aps != p.true_aps:
            raise ValueError("combine: the two truths must have the same true APs")
        net = _combined_network(t.network, p.network)
        eops = t.eops[[t.network.scans.index(s) for s in net.scans]]
        return SimulationTruth(
            net, t.scanners, t.true_aps, eops, t.targets, p.planes, p.plane_points
        )


# One compiled program per shape: an un-jitted vmap dispatched a hundred operations one by one
# on every call (each Monte Carlo check network, every error-free evaluation).
_scanner_coordinates = jit(jax.vmap(point_geometry))


def _spherical(X, E, l_obs, panoramic):
    if len(X) == 0:
        return np.zeros((0, 3))
    x = np.asarray(_scanner_coordinates(jnp.asarray(X), jnp.asarray(E)))
    face2 = panoramic & np.asarray(is_face2(l_obs[:, 2], xp=np))
    return np.asarray(spherical_from_cartesian(x, face2, xp=np))


def _combined_network(tn: Network, pn: Network) -> Network:
    """The rows of a target network and of a plane network as one network."""
    inst = lambda net, scan_index: [net.instruments[net.instrument_of_scan[j]] for j in scan_index]
    table = ObservationTable(
        kind="plane",
        source=pn.source,
        scans=tuple(pn.scans[j] for j in pn.plane_scan_index),
        primitives=tuple(pn.planes[k] for k in pn.plane_index),
        observations=pn.plane_observations,
        sigmas=pn.plane_sigmas,
        incidence=None,
        instruments=tuple(inst(pn, pn.plane_scan_index)),
        rows=np.arange(2, len(pn.plane_index) + 2),
    )
    levelling = {
        s: {
            "omega": tn.levelling[j, 0],
            "phi": tn.levelling[j, 1],
            "sigma_omega": tn.levelling_sigma[j, 0],
            "sigma_phi": tn.levelling_sigma[j, 1],
        }
        for j, s in enumerate(tn.scans)
        if np.isfinite(tn.levelling_sigma[j]).all()
    }
    control = {
        tn.targets[t]: (xyz, sg)
        for t, xyz, sg in zip(tn.control_index, tn.control_xyz, tn.control_sigma)
    }
    bars = [
        (tn.targets[a], tn.targets[b], length, sg)
        for (a, b), length, sg in zip(tn.scale_bar_targets, tn.scale_bar_length, tn.scale_bar_sigma)
    ]
    return make_network(
        [tn.scans[j] for j in tn.scan_index],
        [tn.targets[t] for t in tn.target_index],
        tn.observations,
        sigmas=tn.sigmas,
        instruments=inst(tn, tn.scan_index),
        levelling=levelling,
        control=control,
        scale_bars=bars,
        source=f"{tn.source} + {pn.source}",
        planes=table,
    )
