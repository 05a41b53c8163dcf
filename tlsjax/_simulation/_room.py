"""Simulated calibration networks: the room of Chow et al. 2013, section 4 (SPEC section 8).

A 14 x 11 x 3 m room with 120 targets spread evenly over its six faces (20 per face), two
stations with three scans each, 60 deg apart in kappa; in the tilted variant two scans of the
second station are rolled by -45 and +45 deg (omega). Noise 0.5 mm range at normal incidence
(scaled by sec of the incidence angle) and 20" for both angles; levelled scans carry
dual-axis-compensator observations omega = phi = 0 +- 10".
"""

from __future__ import annotations

import dataclasses
import inspect
from collections.abc import Mapping

import jax.numpy as jnp
import numpy as np

from .._adjustment._network import (
    DEFAULT_SIGMA_ANGLE,
    DEFAULT_SIGMA_LEVELLING,
    DEFAULT_SIGMA_RANGE,
    Network,
    make_network,
)
from .._model._aps import get_ap, resolve_aps
from .._model._geometry import TWO_PI, rotation_matrix, second_face, spherical_from_cartesian
from .._model._levelling import compensator_reading
from .._model._points import observe_points
from .._model._scanner import Scanner
from .._units import ARCSEC, DEG


@dataclasses.dataclass(frozen=True)
class Room:
    """Box room [m] with targets on its faces and the scan stations (SPEC section 8)."""

    length: float = 14.0
    width: float = 11.0
    height: float = 3.0
    n_targets: int = 120
    stations: tuple = ((4.5, 4.0, 1.6), (9.5, 7.0, 1.6))
    margin: float = 0.3

    def __post_init__(self):
        if min(self.length, self.width, self.height) <= 2 * self.margin:
            raise ValueError(
                f"room {self.length} x {self.width} x {self.height} m is too small for a {self.margin} m margin"
            )
        if self.n_targets < 12:
            raise ValueError(f"a room needs at least 12 targets, got {self.n_targets}")
        for s in self.stations:
            if not (0 < s[0] < self.length and 0 < s[1] < self.width and 0 < s[2] < self.height):
                raise ValueError(
                    f"station {s} is outside the {self.length} x {self.width} x {self.height} m room"
                )

    @classmethod
    def from_design(cls, design, *, n_targets: int | None = None) -> Room:
        """The room of a :class:`~tlsjax.NetworkDesign`: its box, ``margin`` and the distinct
        stations of its scans (in order of first use); ``n_targets`` (default: the design's
        targets on faces) targets spread over the faces."""
        stations = tuple(dict.fromkeys(tuple(float(c) for c in s[:3]) for s in design.scans))
        L, W, H = design.room
        n = design.n_targets if n_targets is None else n_targets
        return cls(L, W, H, n_targets=n, stations=stations, margin=design.margin)

    @classmethod
    def parse(cls, text: str, **kw) -> Room:
        """``"14x11x3"`` -> Room(14, 11, 3)."""
        try:
            L, W, H = (float(v) for v in text.lower().split("x"))
        except ValueError:
            raise ValueError(
                f"room {text!r} must look like LxWxH in metres, e.g. 14x11x3"
            ) from None
        # Keep the stations at the same relative places in a room of another size.
        st = tuple((x / 14.0 * L, y / 11.0 * W, min(z, 0.6 * H)) for x, y, z in cls.stations)
        return cls(L, W, H, stations=st, **kw)


#: The true APs of the papers' simulations (SPEC section 8): range terms 10 mm, angular 3'
#: (180"), B8 and C6 10 mm; A1 (dimensionless) 1000 ppm, i.e. 10 mm at 10 m.
def default_true_value(name: str) -> float:
    if name in ("B8", "C6"):
        return 0.010
    term = get_ap(name)
    if term.unit == "m":
        return 0.010
    if term.unit == "rad":
        return 180.0 * ARCSEC
    if term.group == "range":
        return 1.0e-3
    return 1.0e-4 if name == "B1" else 5.0e-4


@dataclasses.dataclass(frozen=True, eq=False)
class Simulation:
    """A simulated network with its truth."""

    network: Network
    scanner: Scanner
    true_aps: dict
    true_targets: np.ndarray
    true_eops: np.ndarray
    target_normals: np.ndarray

    def truth(self):
        """The network with its truth, for Monte Carlo (:class:`tlsjax.SimulationTruth`)."""
        from ._truth import SimulationTruth

        net = self.network
        # Targets are named T001, T002, ... after their index in ``true_targets``.
        order = [int(name[1:]) - 1 for name in net.targets]
        return SimulationTruth(
            net,
            (self.scanner,) * len(net.instruments),
            (dict(self.true_aps),) * len(net.instruments),
            self.true_eops[[int(s[1:]) - 1 for s in net.scans]],
            self.true_targets[order],
        )


def simulated_levelling(eops, rng: np.random.Generator, sigma: float, noise: bool) -> dict:
    """Dual-axis compensator observations (the ``levelling`` mapping of :func:`make_network`)
    of the levelled scans (omega = phi = 0): the true zero tilt plus noise of ``sigma`` [rad]."""
    lev = {}
    for j in range(len(eops)):
        if eops[j, 3] == 0.0 and eops[j, 4] == 0.0:
            d = rng.standard_normal(2) * sigma if noise else np.zeros(2)
            lev[f"S{j + 1}"] = {
                "omega": d[0],
                "phi": d[1],
                "sigma_omega": sigma,
                "sigma_phi": sigma,
            }
    return lev


def simulated_orientation(
    eops,
    rng: np.random.Generator,
    noise: bool,
    sigma_tilt: float | None,
    sigma_heading: float | None,
    levelled: dict,
) -> dict:
    """Weighted constraints with observed values (the ``orientation`` mapping of
    :func:`make_network`; Chow et al. 2013, eq. 7): with ``sigma_tilt``, the tilt sensor's
    readings of every scan not in ``levelled`` (the tilted ones: the object-space vertical in
    the scanner frame, :func:`tlsjax._model._levelling.compensator_reading`, plus noise); with
    ``sigma_heading``, an observed kappa of every scan (the true kappa plus noise) [rad]."""
    out = {}
    for j, e in enumerate(np.asarray(eops)):
        scan, d = f"S{j + 1}", {}
        if sigma_tilt is not None and scan not in levelled:
            tilt = compensator_reading(e, np)
            tilt = tilt + (rng.standard_normal(2) * sigma_tilt if noise else 0.0)
            d.update(omega=tilt[0], phi=tilt[1], sigma_omega=sigma_tilt, sigma_phi=sigma_tilt)
        if sigma_heading is not None:
            k = e[5] + (rng.standard_normal() * sigma_heading if noise else 0.0)
            d.update(kappa=float(np.arctan2(np.sin(k), np.cos(k))), sigma_kappa=sigma_heading)
        if d:
            out[scan] = {k: float(v) for k, v in d.items()}
    return out


def room_targets(room: Room, rng: np.random.Generator):
    """Targets spread evenly over the six faces, with the faces' inward normals."""
    L, W, H, m = room.length, room.width, room.height, room.margin
    per = np.full(6, room.n_targets // 6)
    per[: room.n_targets % 6] += 1
    faces = [  # (fixed axis, value, inward normal)
        (0, 0.0, (1, 0, 0)),
        (0, L, (-1, 0, 0)),
        (1, 0.0, (0, 1, 0)),
        (1, W, (0, -1, 0)),
        (2, 0.0, (0, 0, 1)),
        (2, H, (0, 0, -1)),
    ]
    size = np.array([L, W, H])
    pts, nrm = [], []
    for (ax, val, n), k in zip(faces, per):
        u = rng.uniform(m, size - m, size=(k, 3))
        u[:, ax] = val
        pts.append(u)
        nrm.append(np.tile(n, (k, 1)))
    return np.concatenate(pts).astype(np.float64), np.concatenate(nrm).astype(np.float64)


def room_scans(room: Room, tilted: bool) -> np.ndarray:
    """Scan poses (s, 6): three scans per station, 60 deg apart in kappa; tilted variant rolls
    scans 2 and 3 of the second station by -45 and +45 deg."""
    eops = []
    for si, st in enumerate(room.stations):
        for k in range(3):
            omega = 0.0
            if tilted and si == 1 and k > 0:
                omega = (-45.0 if k == 1 else 45.0) * DEG
            eops.append([*st, omega, 0.0, (20.0 * si + 60.0 * k) * DEG])
    return np.array(eops, dtype=np.float64)


#: The settings of :func:`simulate` that a NetworkDesign carries itself.
_DESIGN_SETTINGS = (
    "architecture", "tilted", "aps", "true_aps", "noise", "sigma_range", "sigma_angle",
    "sigma_levelling", "levelling", "unit_length", "two_face",
)  # fmt: skip


def _from_network_design(design, given: dict) -> dict:
    """The room, scans and settings of :func:`simulate` from a NetworkDesign (the one design
    description): its box and stations, its scans, scanner, APs, sigmas and levelling; noise
    on or off (``noise_scale`` 1 or 0). Refuses what this simulation cannot reproduce and a
    setting given beside the design (it belongs on the design)."""
    defaults = inspect.signature(simulate).parameters
    for name in _DESIGN_SETTINGS:
        if given[name] != defaults[name].default:
            raise ValueError(
                f"simulate(NetworkDesign): {name} comes from the design; set it there "
                "(dataclasses.replace(design, ...)) or give a Room"
            )
    if design.n_free_targets or design.planes or design.faces_as_planes:
        raise ValueError(
            "simulate(NetworkDesign) simulates targets on the room's faces only: free-standing "
            "targets and planes need tlsjax.simulate_design (or simulate_point_clouds)"
        )
    return dict(
        room=Room.from_design(design),
        scans=np.asarray(design.scans, dtype=np.float64),
        **design_scanner_settings(design, "simulate(NetworkDesign)"),
    )


def design_scanner_settings(design, who: str) -> dict:
    """The scanner, APs and true APs, sigmas, levelling and noise switch of a NetworkDesign, as
    the settings of :func:`simulate` and :class:`~tlsjax.CloudDesign` (which draw the nominal
    noise or none: a ``noise_scale`` other than 1 or 0, or a ``sigma_scale`` other than 1, is
    refused, naming ``who``)."""
    if design.sigma_scale != 1.0 or design.noise_scale not in (0.0, 1.0):
        raise ValueError(
            f"{who} draws the nominal noise or none (noise_scale 1 or 0, sigma_scale 1): use "
            "tlsjax.simulate_design for other scales"
        )
    return dict(
        architecture=design.architecture,
        aps=design.aps,
        true_aps=design.true_aps,
        noise=design.noise_scale > 0,
        sigma_range=design.sigma_range,
        sigma_angle=design.sigma_angle,
        sigma_levelling=design.sigma_levelling,
        levelling=design.levelling,
        unit_length=design.unit_length,
    )


def simulate(
    room: Room | None = None,
    *,
    architecture: str = "hybrid",
    tilted: bool = True,
    aps="A0 B6 B7 C0",
    true_aps: Mapping[str, float] | None = None,
    seed: int = 0,
    noise: bool = True,
    sigma_range: float = DEFAULT_SIGMA_RANGE,
    sigma_angle: float = DEFAULT_SIGMA_ANGLE,
    sigma_levelling: float = DEFAULT_SIGMA_LEVELLING,
    levelling: bool = True,
    scale_bars: int = 0,
    unit_length: float = 1.2,
    two_face: bool = False,
    sigma_tilt: float | None = None,
    sigma_heading: float | None = None,
) -> Simulation:
    """Simulate the Chow et al. 2013 calibration room (SPEC section 8).

    ``aps`` are the terms that are present in the data (with ``true_aps`` values, default per
    :func:`default_true_value`). Levelled scans get compensator observations when
    ``levelling``. ``sigma_tilt`` [rad]: the tilted scans carry a tilt sensor's readings
    (omega, phi; the paper's eq. 7) with this noise; ``sigma_heading`` [rad]: every scan
    carries an observed kappa (a known heading) with this noise (their noise is drawn from a
    generator of its own, so the other observations of a seed stay the same).
    ``scale_bars`` > 0 adds that many scale bars between pairs of floor targets.
    Every target is visible from every scan (the paper's design; no field-of-view limit).

    ``two_face``: the NIST two-face design (Muralikrishnan et al. 2015; Wang et al. 2017) of a
    panoramic scanner: the room's first station, two levelled scans with the head turned by 180
    deg (kappa 0 and 180 deg), so that every target is observed once in each face, ``(theta,
    alpha)`` in one scan and ``(theta, pi - alpha)`` in the other (SPEC section 1: hz in [0, 180)
    deg in both faces). The terms whose sign flips between the faces (collimation, trunnion,
    index, mirror tilt) are then seen without a second station.

    ``room`` may be a :class:`~tlsjax.NetworkDesign` (the one design description): its box,
    stations and scans, scanner, APs, sigmas, levelling and noise on or off are taken from it
    (``Room.from_design``); the settings above that it carries must then be left at their
    defaults. Its ``n_targets`` are spread over the faces as here, all seen from every scan
    (this simulation's design: no field-of-view, range or incidence limit).
    """
    scans = None
    if room is not None and not isinstance(room, Room):  # a NetworkDesign
        d = _from_network_design(room, locals())
        room, scans, architecture, aps = d["room"], d["scans"], d["architecture"], d["aps"]
        true_aps, noise, unit_length, levelling = (
            d["true_aps"], d["noise"], d["unit_length"], d["levelling"]
        )  # fmt: skip
        sigma_range, sigma_angle, sigma_levelling = (
            d["sigma_range"], d["sigma_angle"], d["sigma_levelling"]
        )  # fmt: skip
    room = room or Room()
    rng = np.random.default_rng(seed)
    names = resolve_aps(aps)
    values = {n: default_true_value(n) for n in names}
    values.update(true_aps or {})
    names = tuple(values)
    scanner = Scanner(architecture=architecture, aps=names, unit_length=unit_length)
    X, normals = room_targets(room, rng)
    if scans is not None:
        eops = scans
    elif two_face:
        if architecture != "panoramic":
            raise ValueError("the two-face design needs a panoramic scanner (architecture)")
        eops = np.array([[*room.stations[0], 0.0, 0.0, 0.0], [*room.stations[0], 0.0, 0.0, np.pi]])
    else:
        eops = room_scans(room, tilted)
    n_t, n_s = len(X), len(eops)
    ti, si = np.meshgrid(np.arange(n_t), np.arange(n_s), indexing="xy")
    ti, si = ti.reshape(-1), si.reshape(-1)

    # Geometry first: line of sight, incidence angle, face of a panoramic scanner.
    R = np.stack([rotation_matrix(*e[3:], xp=np) for e in eops])
    x = np.einsum("mij,mj->mi", R[si], X[ti] - eops[si, :3])
    los = X[ti] - eops[si, :3]
    cosb = np.abs(np.sum(los * normals[ti], axis=1)) / np.linalg.norm(los, axis=1)
    incidence = np.arccos(np.clip(cosb, 0.0, 1.0))
    hyb = spherical_from_cartesian(x, xp=np)
    face2 = second_face(hyb[:, 1], architecture)
    sig = np.stack(
        [
            sigma_range / np.cos(incidence),
            np.full(len(ti), sigma_angle),
            np.full(len(ti), sigma_angle),
        ],
        axis=1,
    )
    e = rng.standard_normal((len(ti), 3)) * sig if noise else np.zeros((len(ti), 3))

    coeffs = jnp.asarray([values[n] for n in names])
    obs = np.array(
        observe_points(
            jnp.asarray(X[ti]),
            jnp.asarray(eops[si]),
            jnp.asarray(e),
            jnp.asarray(face2),
            coeffs,
            scanner,
            names,
        )
    )
    # Wrap by a full turn only: a panoramic direction near theta = 0 that the APs push below
    # zero is the same direction at 2 pi, not at pi.
    obs[:, 1] = np.mod(obs[:, 1], TWO_PI)

    lev = simulated_levelling(eops, rng, sigma_levelling, noise) if levelling else {}
    orientation = simulated_orientation(
        eops, np.random.default_rng([seed, 7]), noise, sigma_tilt, sigma_heading, lev
    )
    bars = []
    if scale_bars:
        floor = np.flatnonzero(normals[:, 2] > 0.5)
        for b in range(scale_bars):
            a, c = floor[2 * b], floor[2 * b + 1]
            d = np.linalg.norm(X[a] - X[c]) + (rng.standard_normal() * 0.05e-3 if noise else 0.0)
            bars.append((f"T{a + 1:03d}", f"T{c + 1:03d}", d, 0.05e-3))
    net = make_network(
        [f"S{j + 1}" for j in si],
        [f"T{t + 1:03d}" for t in ti],
        obs,
        sigma_range=sigma_range,
        sigma_hz=sigma_angle,
        sigma_el=sigma_angle,
        incidence=incidence,
        levelling=lev,
        orientation=orientation,
        scale_bars=bars,
        source="<simulated room>",
    )
    return Simulation(net, scanner, values, X, eops, normals)
