"""Simulated point clouds of a room of planes, for plane-based self-calibration (SPEC section 8).

Each scan samples an angular grid of directions in scanner space (hybrid convention, step
``angular_step``, elevations inside the scanner's field of view). Every ray is cast from the
station and hits the nearest plane patch: the six faces of the box room (Chow et al. 2013,
section 4) and optional finite boards of other orientations inside it. The true point X on the
patch is then observed with the same fixed-point construction as the target simulation,

    l = F(X, EOP) + Delta(l; AP) + e,

so that a noise-free observation satisfies the plane condition of SPEC section 4 exactly:
``n . (R^T x + S) - d = 0`` with ``x = (rho - Drho)(cos(alpha - Dalpha) cos(theta - Dtheta),
cos(alpha - Dalpha) sin(theta - Dtheta), sin(alpha - Dalpha))`` (Lichti 2007; Chow et al.
2013, eq. 3). Noise: ``sigma_range sec(beta)`` in range (beta = incidence angle between the line
of sight and the plane normal) and ``sigma_angle`` in both angles (SPEC section 5).

Panoramic scanners see directions whose hybrid horizontal direction is >= pi in their second
face: ``theta = theta' - pi``, ``alpha = pi - alpha'`` (SPEC section 1).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import jax.numpy as jnp
import numpy as np

from .._adjustment._network import (
    DEFAULT_SIGMA_ANGLE,
    DEFAULT_SIGMA_LEVELLING,
    DEFAULT_SIGMA_RANGE,
    ObservationTable,
    make_plane_network,
)
from .._model._aps import resolve_aps
from .._model._geometry import TWO_PI, rotation_matrix, second_face, spherical_from_cartesian
from .._model._points import observe_points
from .._model._scanner import Scanner
from .._units import DEG
from ._room import Room, default_true_value, room_scans, simulated_levelling


@dataclasses.dataclass(frozen=True)
class Board:
    """A finite rectangular plane patch [m]: ``X = origin + s edge_u + t edge_v``, s, t in [0, 1].

    The edges need not be orthogonal (a parallelogram); the plane normal is
    ``edge_u x edge_v`` normalised.
    """

    origin: tuple
    edge_u: tuple
    edge_v: tuple

    def __post_init__(self):
        for name in ("origin", "edge_u", "edge_v"):
            v = np.asarray(getattr(self, name), dtype=np.float64)
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise ValueError(
                    f"board {name} must be three finite coordinates in metres, got {getattr(self, name)!r}"
                )
            object.__setattr__(self, name, tuple(float(c) for c in v))
        if np.linalg.norm(np.cross(self.edge_u, self.edge_v)) < 1e-6:
            raise ValueError(
                f"board edges {self.edge_u} and {self.edge_v} are parallel or too short: no plane"
            )

    @classmethod
    def tilted(cls, centre, width: float, height: float, azimuth: float, tilt: float) -> Board:
        """A ``width`` x ``height`` board centred at ``centre`` whose normal has the given
        ``azimuth`` (from +X towards +Y) and ``tilt`` from the horizontal, both in radians."""
        n = np.array([np.cos(tilt) * np.cos(azimuth), np.cos(tilt) * np.sin(azimuth), np.sin(tilt)])
        u = np.array([-np.sin(azimuth), np.cos(azimuth), 0.0])
        v = np.cross(n, u)
        c = np.asarray(centre, dtype=np.float64)
        return cls(
            tuple(c - 0.5 * width * u - 0.5 * height * v), tuple(width * u), tuple(height * v)
        )


#: Three boards of different orientations, placed so that both default stations see them.
DEFAULT_BOARDS = (
    Board.tilted((2.0, 8.5, 1.2), 1.2, 1.0, azimuth=-40.0 * DEG, tilt=25.0 * DEG),
    Board.tilted((12.0, 2.5, 1.0), 1.2, 1.0, azimuth=150.0 * DEG, tilt=-20.0 * DEG),
    Board.tilted((7.0, 9.8, 2.0), 1.5, 1.0, azimuth=-100.0 * DEG, tilt=-50.0 * DEG),
)


@dataclasses.dataclass(frozen=True)
class CloudDesign:
    """Settings of a point-cloud simulation (SPEC section 8).

    ``angular_step`` [rad] of the scanning grid in both angles; ``elevation_limits`` [rad] of the
    field of view in scanner space (hybrid convention). The upper limit stays below the zenith
    because the trunnion and collimation terms (tan alpha, sec alpha) are singular there.
    ``max_incidence`` [rad]: rays that meet their surface more obliquely return nothing.
    ``boards``: finite planes inside the room besides its six faces. ``levelling``: the
    levelled (untilted) scans get dual-axis compensator observations with ``sigma_levelling``
    [rad], as in :func:`~tlsjax.simulate`.
    """

    room: Room = Room()
    boards: tuple = DEFAULT_BOARDS
    architecture: str = "hybrid"
    tilted: bool = True
    aps: tuple = ("A0", "B6", "B7", "C0")
    true_aps: Mapping[str, float] | None = None
    angular_step: float = 0.5 * DEG
    elevation_limits: tuple = (-40.0 * DEG, 85.0 * DEG)
    max_incidence: float = 85.0 * DEG
    noise: bool = True
    sigma_range: float = DEFAULT_SIGMA_RANGE
    sigma_angle: float = DEFAULT_SIGMA_ANGLE
    unit_length: float = 1.2
    levelling: bool = True
    sigma_levelling: float = DEFAULT_SIGMA_LEVELLING

    def __post_init__(self):
        if not (0.0 < self.angular_step <= 10.0 * DEG):
            raise ValueError(
                f"angular_step must be in (0, 10 deg], got {self.angular_step / DEG:g} deg"
            )
        lo, hi = self.elevation_limits
        if not (-np.pi / 2 < lo < hi < np.pi / 2):
            raise ValueError(
                f"elevation_limits must satisfy -90 deg < low < high < 90 deg, got "
                f"({lo / DEG:g}, {hi / DEG:g}) deg"
            )
        if not (0.0 < self.max_incidence < np.pi / 2):
            raise ValueError(
                f"max_incidence must be in (0, 90 deg), got {self.max_incidence / DEG:g} deg"
            )
        for b in self.boards:
            if not isinstance(b, Board):
                raise ValueError(f"boards must be Board instances, got {type(b).__name__}")
        object.__setattr__(self, "aps", resolve_aps(self.aps))
        object.__setattr__(self, "boards", tuple(self.boards))


@dataclasses.dataclass(frozen=True, eq=False)
class PointClouds:
    """Simulated scans with their truth, one entry per scan in each tuple.

    ``observations[j]`` (n_j, 3) = (rho [m], theta [rad], alpha [rad]); ``plane_ids[j]`` the true
    plane of each point (index into ``planes``); ``incidence[j]`` [rad]; ``true_points[j]``
    (n_j, 3) object-space points. ``eops`` (s, 6) = (Xs, Ys, Zs, omega, phi, kappa);
    ``planes`` (k, 4) = (n_x, n_y, n_z, d) with ``n . X = d``, unit normals pointing into the
    room for its faces. ``true_aps``: name -> value (SI). ``levelling``: scan -> compensator
    observation (the mapping :func:`~tlsjax.make_network` takes) of the levelled scans.
    """

    scans: tuple
    observations: tuple
    plane_ids: tuple
    incidence: tuple
    true_points: tuple
    eops: np.ndarray
    planes: np.ndarray
    plane_names: tuple
    scanner: Scanner
    true_aps: dict
    sigma_range: float
    sigma_angle: float
    levelling: dict = dataclasses.field(default_factory=dict)

    def to_table(self, max_points: int | None = None, *, seed: int = 0) -> ObservationTable:
        """The plane observations with the true plane labels, as a plane ``ObservationTable``
        (sigmas at normal incidence plus the incidence angles, as in a plane CSV).

        ``max_points``: keep at most this many points of each plane in each scan, drawn at
        random (``seed``) without replacement; None keeps all.
        """
        scans, prims, obs, inc = [], [], [], []
        for name, ids, o, b, keep in zip(
            self.scans,
            self.plane_ids,
            self.observations,
            self.incidence,
            self._kept(max_points, seed),
        ):
            scans += [name] * len(keep)
            prims += [self.plane_names[i] for i in ids[keep]]
            obs.append(o[keep])
            inc.append(b[keep])
        obs = np.concatenate(obs)
        inc = np.concatenate(inc)
        # The range sigma at normal incidence: readers and make_network scale it by sec(incidence)
        # from the incidence column (SPEC section 5), exactly as the simulation drew the noise.
        sig = np.stack(
            [
                np.full(len(inc), self.sigma_range),
                np.full(len(inc), self.sigma_angle),
                np.full(len(inc), self.sigma_angle),
            ],
            axis=1,
        )
        return ObservationTable(
            kind="plane",
            source="<simulated point clouds>",
            scans=tuple(scans),
            primitives=tuple(prims),
            observations=obs,
            sigmas=sig,
            incidence=inc,
            instruments=None,
            rows=np.arange(2, len(obs) + 2, dtype=np.int64),
        )

    def _kept(self, max_points, seed):
        """Per scan, the indices of the points :meth:`to_table` keeps."""
        rng = np.random.default_rng(seed)
        out = []
        for ids in self.plane_ids:
            keep = np.arange(len(ids))
            if max_points is not None:
                parts = [
                    rng.permutation(np.flatnonzero(ids == k))[:max_points] for k in np.unique(ids)
                ]
                keep = np.sort(np.concatenate(parts)) if parts else keep[:0]
            out.append(keep)
        return out

    def truth(self, max_points: int | None = None, *, seed: int = 0, levelling: bool = True):
        """The plane network of :meth:`to_network` with its truth (true planes, poses and the
        true point of every row), for Monte Carlo (:class:`tlsjax.SimulationTruth`)."""
        from ._truth import SimulationTruth

        net = self.to_network(max_points, seed=seed, levelling=levelling)
        points = np.concatenate(
            [X[k] for X, k in zip(self.true_points, self._kept(max_points, seed))]
        )
        planes = self.planes[[self.plane_names.index(k) for k in net.planes]]
        eops = self.eops[[self.scans.index(s) for s in net.scans]]
        n = len(net.instruments)
        return SimulationTruth(
            net,
            (self.scanner,) * n,
            (dict(self.true_aps),) * n,
            eops,
            planes=planes,
            plane_points=points,
        )

    def to_network(self, max_points: int | None = None, *, seed: int = 0, levelling: bool = True):
        """A plane :class:`~tlsjax.Network` of these scans (see :meth:`to_table`), with the
        compensator observations of the levelled scans unless ``levelling=False``."""
        return make_plane_network(
            self.to_table(max_points, seed=seed),
            sigma_range=self.sigma_range,
            sigma_hz=self.sigma_angle,
            sigma_el=self.sigma_angle,
            levelling=self.levelling if levelling else None,
        )


def room_patches(room: Room, boards=()):
    """Plane patches as arrays: normal (k, 3), d (k,), origin (k, 3), edges (k, 3), (k, 3), names.

    The room's faces come first (x=0, x=L, y=0, y=W, floor, ceiling) with inward normals.
    """
    L, W, H = room.length, room.width, room.height
    faces = [  # origin, edge_u, edge_v, inward normal, name
        ((0, 0, 0), (0, W, 0), (0, 0, H), (1, 0, 0), "wall_x0"),
        ((L, 0, 0), (0, W, 0), (0, 0, H), (-1, 0, 0), "wall_xL"),
        ((0, 0, 0), (L, 0, 0), (0, 0, H), (0, 1, 0), "wall_y0"),
        ((0, W, 0), (L, 0, 0), (0, 0, H), (0, -1, 0), "wall_yW"),
        ((0, 0, 0), (L, 0, 0), (0, W, 0), (0, 0, 1), "floor"),
        ((0, 0, H), (L, 0, 0), (0, W, 0), (0, 0, -1), "ceiling"),
    ]
    origin = [f[0] for f in faces] + [b.origin for b in boards]
    eu = [f[1] for f in faces] + [b.edge_u for b in boards]
    ev = [f[2] for f in faces] + [b.edge_v for b in boards]
    normal = [f[3] for f in faces] + [np.cross(b.edge_u, b.edge_v) for b in boards]
    names = tuple(f[4] for f in faces) + tuple(f"board{i + 1}" for i in range(len(boards)))
    origin, eu, ev = (np.asarray(a, dtype=np.float64) for a in (origin, eu, ev))
    normal = np.asarray(normal, dtype=np.float64)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    d = np.einsum("ki,ki->k", normal, origin)
    return normal, d, origin, eu, ev, names


def cast_rays(station, directions, normal, d, origin, eu, ev):
    """Nearest patch hit by rays ``station + t D`` (object space): (t, patch), t = inf on a miss.

    Intersection with plane k: ``t = (d_k - n_k . S) / (n_k . D)``; the hit lies on the patch
    when its coordinates (s, u) along the edges are in [0, 1], from the 2 x 2 Gram system.
    """
    nD = directions @ normal.T  # (m, k)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (d - normal @ station)[None, :] / nD
        # Rays parallel to a plane give t = inf there; the bounds test below discards them.
        t = np.where(np.isfinite(t), t, np.inf)
        hit = (
            station[None, None, :]
            + np.where(np.isfinite(t), t, 0.0)[..., None] * directions[:, None, :]
            - origin[None]
        )
    guu = np.einsum("ki,ki->k", eu, eu)
    gvv = np.einsum("ki,ki->k", ev, ev)
    guv = np.einsum("ki,ki->k", eu, ev)
    hu = np.einsum("mki,ki->mk", hit, eu)
    hv = np.einsum("mki,ki->mk", hit, ev)
    det = guu * gvv - guv * guv
    s = (gvv * hu - guv * hv) / det
    u = (guu * hv - guv * hu) / det
    # A small tolerance keeps the rays that graze a shared edge of two faces of the box.
    tol = 1e-9
    valid = (
        np.isfinite(t) & (t > 1e-9) & (s >= -tol) & (s <= 1 + tol) & (u >= -tol) & (u <= 1 + tol)
    )
    t = np.where(valid, t, np.inf)
    k = np.argmin(t, axis=1)
    return t[np.arange(len(t)), k], k


def scan_directions(design: CloudDesign) -> np.ndarray:
    """Hybrid scanner-space grid directions (theta, alpha) of one scan, (m, 2).

    Horizontal directions sit half a step off 0 and pi, so that no direction lies exactly on the
    boundary between the two faces of a panoramic scanner (where rounding alone picks the face).
    """
    step = design.angular_step
    theta = step * (np.arange(int(np.floor(TWO_PI / step + 1e-9))) + 0.5)
    lo, hi = design.elevation_limits
    alpha = lo + step * np.arange(int(np.floor((hi - lo) / step + 1e-9)) + 1)
    tt, aa = np.meshgrid(theta, alpha, indexing="ij")
    return np.stack([tt.ravel(), aa.ravel()], axis=1)


_CHUNK = 8192


def _observe_in_chunks(X, E, e, face2, coeffs, scanner, names):
    """The fixed point for all points, in chunks of one compiled size (compiled once per AP set)."""
    n = len(X)
    pad = (-n) % _CHUNK
    # Padding repeats the first point so that every lane stays a valid geometry.
    fill = lambda a: np.concatenate([a, np.repeat(a[:1], pad, axis=0)]) if pad else a
    Xp, Ep, ep, fp = fill(X), fill(E), fill(e), fill(face2)
    out = [
        np.asarray(
            observe_points(
                Xp[i : i + _CHUNK],
                Ep[i : i + _CHUNK],
                ep[i : i + _CHUNK],
                fp[i : i + _CHUNK],
                coeffs,
                scanner,
                names,
            )
        )
        for i in range(0, n + pad, _CHUNK)
    ]
    return np.concatenate(out)[:n]


def simulate_point_clouds(design: CloudDesign | None = None, *, seed: int = 0) -> PointClouds:
    """Simulate the scans of the calibration room as point clouds (SPEC section 8).

    Poses from :func:`tlsjax._simulate.room_scans` (two stations, three scans each; tilted
    variant with omega = -45, +45 deg). ``seed`` fixes the noise. Returns a :class:`PointClouds`
    whose observations satisfy ``l = F + Delta(l; AP) + e`` (see the module docstring).
    """
    design = design or CloudDesign()
    rng = np.random.default_rng(seed)
    values = {n: default_true_value(n) for n in design.aps}
    values.update(design.true_aps or {})
    names = tuple(values)
    scanner = Scanner(architecture=design.architecture, aps=names, unit_length=design.unit_length)
    normal, d, origin, eu, ev, plane_names = room_patches(design.room, design.boards)
    eops = room_scans(design.room, design.tilted)
    grid = scan_directions(design)
    ca = np.cos(grid[:, 1])
    dirs_scanner = np.stack(
        [ca * np.cos(grid[:, 0]), ca * np.sin(grid[:, 0]), np.sin(grid[:, 1])], axis=1
    )

    X_all, eop_all, plane_all, inc_all, scan_all = [], [], [], [], []
    for j, eop in enumerate(eops):
        R = rotation_matrix(*eop[3:], xp=np)
        D = dirs_scanner @ R  # rows R^T d: object-space directions
        t, k = cast_rays(eop[:3], D, normal, d, origin, eu, ev)
        cosb = np.abs(np.einsum("mi,mi->m", D, normal[k]))
        incidence = np.arccos(np.clip(cosb, 0.0, 1.0))
        keep = np.isfinite(t) & (incidence <= design.max_incidence)
        X_all.append(eop[:3] + t[keep, None] * D[keep])
        eop_all.append(np.broadcast_to(eop, (int(keep.sum()), 6)))
        plane_all.append(k[keep])
        inc_all.append(incidence[keep])
        scan_all.append(np.full(int(keep.sum()), j))
    X = np.concatenate(X_all)
    E = np.concatenate(eop_all)
    inc = np.concatenate(inc_all)
    si = np.concatenate(scan_all)

    R_all = np.stack([rotation_matrix(*e[3:], xp=np) for e in eops])
    x = np.einsum("mij,mj->mi", R_all[si], X - E[:, :3])
    hyb = spherical_from_cartesian(x, xp=np)
    face2 = second_face(hyb[:, 1], design.architecture)
    sig = np.stack(
        [
            design.sigma_range / np.cos(inc),
            np.full(len(X), design.sigma_angle),
            np.full(len(X), design.sigma_angle),
        ],
        axis=1,
    )
    e = rng.standard_normal(sig.shape) * sig if design.noise else np.zeros_like(sig)

    coeffs = jnp.asarray([values[n] for n in names], dtype=jnp.float64)
    obs = _observe_in_chunks(X, E, e, face2, coeffs, scanner, names)
    # Full-turn wrap only (a face-2 direction near 0 pushed below zero is near 2 pi, not pi).
    obs[:, 1] = np.mod(obs[:, 1], TWO_PI)
    obs[:, 1] = np.where(obs[:, 1] >= TWO_PI, 0.0, obs[:, 1])

    lev = (
        simulated_levelling(eops, rng, design.sigma_levelling, design.noise)
        if design.levelling
        else {}
    )

    split = np.cumsum([len(p) for p in plane_all])[:-1]
    return PointClouds(
        scans=tuple(f"S{j + 1}" for j in range(len(eops))),
        observations=tuple(np.split(obs, split)),
        plane_ids=tuple(plane_all),
        incidence=tuple(np.split(inc, split)),
        true_points=tuple(np.split(X, split)),
        eops=eops,
        planes=np.concatenate([normal, d[:, None]], axis=1),
        plane_names=plane_names,
        scanner=scanner,
        true_aps=values,
        sigma_range=design.sigma_range,
        sigma_angle=design.sigma_angle,
        levelling=lev,
    )
