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
of sight and the plane normal) and ``sigma_angle`` in both angles (SPEC section 5), each point's
independent of the others'. ``correlated_sigma_range`` adds a range error that neighbouring
points share (footprint overlap, surface texture: the correlated noise of dense scans that Chow
et al. 2013, section 3.2, warn of), ``sec(beta)`` times a stationary Gaussian random field over
object space, new for every scan, with covariance ``sigma_c^2 exp(-|X - Y|^2 / (2 L^2))``
(``L = correlation_length``). It is drawn as random Fourier features (Rahimi & Recht 2007),
``sigma_c sqrt(2 / K) sum_k cos(w_k . X + b_k)`` with ``w_k ~ N(0, I / L^2)``, ``b_k ~ U(0, 2
pi)``, whose covariance over realisations is that Gaussian function exactly, at a cost linear in
the points. The a priori range sigma of such clouds is the total, ``sqrt(sigma_range^2 +
sigma_c^2)``, as a user would state it from the scatter of points about a plane.

Panoramic scanners see directions whose hybrid horizontal direction is >= pi in their second
face: ``theta = theta' - pi``, ``alpha = pi - alpha'`` (SPEC section 1).

Signalised targets (issue 33): spheres (:class:`SphereTarget`) and planar contrast targets
(:class:`PlanarTarget`: a 2 x 2 checkerboard, or a white disc on a dark square) are rendered in
the same ray cast, geometry and intensity. Every point carries an intensity
``reflectance (0.25 + 0.75 cos beta) exp(-rho / 40 m) + e_I``; on a planar target the
reflectance is the printed pattern blurred by the laser footprint (``_model/_targets.py``), of
standard deviation ``beam_width + beam_divergence rho``. ``dark_range_bias`` adds a range
offset on the dark share of a target's footprint (the intensity-dependent range error that
makes a contrast centroid sit off the target's plane, Lichti & Licht 2006, section 5.3).
``target_step`` scans a finer angular grid in a window around each target (as scanners
fine-scan their targets), so that a room of thousands of points holds targets of hundreds.
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
from .._model._targets import (
    PATTERNS,
    checkerboard_white,
    disc_white,
    plane_frame,
    sphere_ray_distance,
)
from .._units import DEG
from ._room import (
    Room,
    default_true_value,
    design_scanner_settings,
    room_scans,
    simulated_levelling,
)


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


def _point3(value, what: str) -> tuple:
    v = np.asarray(value, dtype=np.float64)
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ValueError(f"{what} must be three finite coordinates in metres, got {value!r}")
    return tuple(float(c) for c in v)


def _share(value, what: str) -> float:
    if not (np.isfinite(value) and 0.0 <= value <= 1.0):
        raise ValueError(f"{what} must be in [0, 1], got {value}")
    return float(value)


@dataclasses.dataclass(frozen=True)
class SphereTarget:
    """A sphere target: ``centre`` (3,) [m] in object space, ``radius`` [m], ``reflectance``
    in [0, 1] (a matt white sphere: 0.85)."""

    centre: tuple
    radius: float = 0.0725
    reflectance: float = 0.85

    def __post_init__(self):
        object.__setattr__(self, "centre", _point3(self.centre, "sphere centre"))
        if not (np.isfinite(self.radius) and 0.0 < self.radius < 2.0):
            raise ValueError(f"sphere radius must be in (0, 2) m, got {self.radius}")
        object.__setattr__(self, "reflectance", _share(self.reflectance, "sphere reflectance"))


@dataclasses.dataclass(frozen=True)
class PlanarTarget:
    """A planar contrast target: a square plate of side ``size`` [m] centred at ``centre`` (3,)
    [m], facing ``normal`` (towards the scanners), its pattern turned by ``rotation`` [rad]
    about the normal from the plate's horizontal axis (:func:`~tlsjax._model._targets.plane_frame`).

    ``pattern``: "checkerboard" (2 x 2 squares of side size / 2, white where ``u v > 0``) or
    "circle" (a white disc of ``circle_radius``, default 0.3 size, on a dark plate).
    ``dark``/``bright``: reflectances of the print.
    """

    centre: tuple
    normal: tuple
    pattern: str = "checkerboard"
    size: float = 0.15
    rotation: float = 0.0
    circle_radius: float | None = None
    dark: float = 0.05
    bright: float = 0.85

    def __post_init__(self):
        object.__setattr__(self, "centre", _point3(self.centre, "planar target centre"))
        n = np.asarray(_point3(self.normal, "planar target normal"))
        if np.linalg.norm(n) < 1e-9:
            raise ValueError("planar target normal must not be zero")
        object.__setattr__(self, "normal", tuple(float(c) for c in n / np.linalg.norm(n)))
        if self.pattern not in PATTERNS:
            raise ValueError(f"planar target pattern {self.pattern!r} is not one of {PATTERNS}")
        if not (np.isfinite(self.size) and 0.0 < self.size < 5.0):
            raise ValueError(f"planar target size must be in (0, 5) m, got {self.size}")
        r = 0.3 * self.size if self.circle_radius is None else float(self.circle_radius)
        if not 0.0 < r < 0.5 * self.size:
            raise ValueError(f"circle radius {r} m must be in (0, size / 2 = {self.size / 2} m)")
        object.__setattr__(self, "circle_radius", r)
        object.__setattr__(self, "dark", _share(self.dark, "planar target dark reflectance"))
        object.__setattr__(self, "bright", _share(self.bright, "planar target bright reflectance"))

    def frame(self) -> np.ndarray:
        """In-plane axes (u, v) (2, 3) of the pattern."""
        return plane_frame(self.normal, self.rotation)

    def board(self) -> Board:
        """The plate as a :class:`Board` (for the ray cast)."""
        u, v = self.frame() * self.size
        c = np.asarray(self.centre)
        return Board(tuple(c - 0.5 * (u + v)), tuple(u), tuple(v))


def place_targets(
    room: Room | None = None,
    *,
    spheres: int = 8,
    checkerboards: int = 8,
    circles: int = 0,
    radius: float = 0.0725,
    size: float = 0.15,
    seed: int = 0,
    clearance: float = 0.6,
) -> dict:
    """A random field of targets in ``room``: ``spheres`` free-standing spheres of ``radius``
    (0.5 to 2.5 m high, at least ``clearance`` from the walls, the stations and each other) and
    planar targets of ``size`` on the room's faces (facing into the room, 2 mm off the face,
    turned at random in their plane), as keyword arguments of :class:`CloudDesign`
    (``spheres=``, ``planar_targets=``)."""
    room = room or Room()
    rng = np.random.default_rng(seed)
    L, W, H = room.length, room.width, room.height
    st = np.asarray(room.stations, dtype=np.float64)
    sph = []
    for _ in range(10000):
        if len(sph) == spheres:
            break
        c = rng.uniform(
            [clearance, clearance, 0.5], [L - clearance, W - clearance, min(2.5, H - 0.3)]
        )
        if np.min(np.linalg.norm(st - c, axis=1)) < 1.5 or any(
            np.linalg.norm(c - np.asarray(t.centre)) < clearance for t in sph
        ):
            continue
        sph.append(SphereTarget(tuple(c), radius))
    faces = [(0, 0.0, 1), (0, L, -1), (1, 0.0, 1), (1, W, -1), (2, 0.0, 1), (2, H, -1)]
    size3 = np.array([L, W, H])
    planar = []
    kinds = ["checkerboard"] * checkerboards + ["circle"] * circles
    for kind in kinds:
        for _ in range(10000):
            ax, val, sign = faces[rng.integers(6)]
            c = rng.uniform(room.margin, size3 - room.margin)
            c[ax] = val + sign * 0.002
            if all(np.linalg.norm(c - np.asarray(t.centre)) > 4 * size for t in planar):
                break
        n = np.zeros(3)
        n[ax] = sign
        planar.append(
            PlanarTarget(tuple(c), tuple(n), kind, size, rotation=rng.uniform(0, np.pi / 2))
        )
    return {"spheres": tuple(sph), "planar_targets": tuple(planar)}


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

    Targets (module docstring): ``spheres`` (:class:`SphereTarget`), ``planar_targets``
    (:class:`PlanarTarget`), ``target_step`` [rad] the finer grid in a window around each
    target (None: the room grid only). Intensity: ``reflectance`` of the room's faces and
    boards, the footprint ``beam_width`` [m] + ``beam_divergence`` [rad] x range (standard
    deviation of the spot), ``intensity_noise`` (standard deviation, in reflectance units),
    ``dark_range_bias`` [m] added to the range of the dark share of a target's footprint;
    ``dark_noise_factor``: the range noise of a footprint wholly on a target's dark print is
    this many times ``sigma_range`` (a phase scanner's range noise grows as the returned power
    falls: 3-5 times on black paper), interpolated by the dark share.
    ``correlated_sigma_range`` [m] and ``correlation_length`` [m]: the spatially correlated
    range noise of the module docstring (0: independent noise only).
    ``scans`` (s, 6): the scan poses (X, Y, Z [m], omega, phi, kappa [rad]); None: those of
    :func:`~tlsjax.simulate`'s room (three scans at each of ``room.stations``, ``tilted``).
    :meth:`from_design` builds one from a :class:`~tlsjax.NetworkDesign`.
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
    spheres: tuple = ()
    planar_targets: tuple = ()
    target_step: float | None = None
    reflectance: float = 0.5
    beam_width: float = 1.0e-3
    beam_divergence: float = 0.2e-3
    intensity_noise: float = 0.01
    dark_range_bias: float = 0.0
    dark_noise_factor: float = 1.0
    correlated_sigma_range: float = 0.0
    correlation_length: float = 0.02
    scans: tuple | None = None

    @classmethod
    def from_design(cls, design, **cloud_settings) -> CloudDesign:
        """The point-cloud view of a :class:`~tlsjax.NetworkDesign` (the one design
        description): its room (:meth:`Room.from_design`), scans, the planes that are
        :class:`Board` s, scanner, APs and true APs, sigmas, levelling, field of view and
        largest incidence; noise on when ``noise_scale`` > 0. ``cloud_settings``: the fields
        of the scanning itself (``angular_step``, targets, intensity, ...). The design's
        infinite planes (:class:`~tlsjax.RoomPlane`) and its targets have no point-cloud
        counterpart and are refused; a ``noise_scale`` or ``sigma_scale`` other than 1 (or 0)
        too (the clouds draw the nominal noise)."""
        if any(not isinstance(p, Board) for p in design.planes) or design.n_free_targets:
            raise ValueError(
                "CloudDesign.from_design: only Board planes have a point-cloud counterpart "
                "(no RoomPlane, no free-standing targets)"
            )
        settings = dict(
            room=Room.from_design(design, n_targets=max(design.n_targets, 12)),
            boards=tuple(design.planes),
            elevation_limits=design.elevation_limits,
            max_incidence=design.max_incidence,
            scans=design.scans,
            **design_scanner_settings(design, "CloudDesign.from_design"),
        )
        return cls(**(settings | cloud_settings))

    def scan_poses(self) -> np.ndarray:
        """(s, 6) scan poses: ``scans``, or the room's (:func:`tlsjax._simulation._room.room_scans`)."""
        if self.scans is None:
            return room_scans(self.room, self.tilted)
        return np.asarray(self.scans, dtype=np.float64)

    def __post_init__(self):
        for t in self.spheres:
            if not isinstance(t, SphereTarget):
                raise ValueError(f"spheres must be SphereTarget instances, got {type(t).__name__}")
        for t in self.planar_targets:
            if not isinstance(t, PlanarTarget):
                raise ValueError(
                    f"planar_targets must be PlanarTarget instances, got {type(t).__name__}"
                )
        object.__setattr__(self, "spheres", tuple(self.spheres))
        object.__setattr__(self, "planar_targets", tuple(self.planar_targets))
        if self.target_step is not None and not (0.0 < self.target_step <= self.angular_step):
            raise ValueError(
                f"target_step must be None or in (0, angular_step], got {self.target_step}"
            )
        _share(self.reflectance, "reflectance")
        for name in ("beam_width", "beam_divergence", "intensity_noise"):
            if not (np.isfinite(getattr(self, name)) and getattr(self, name) >= 0.0):
                raise ValueError(f"CloudDesign.{name} must be >= 0, got {getattr(self, name)}")
        if self.beam_width + self.beam_divergence <= 0.0:
            raise ValueError("CloudDesign.beam_width and beam_divergence must not both be 0")
        if not (np.isfinite(self.correlated_sigma_range) and self.correlated_sigma_range >= 0.0):
            raise ValueError(
                f"correlated_sigma_range must be >= 0, got {self.correlated_sigma_range}"
            )
        if not (np.isfinite(self.correlation_length) and self.correlation_length > 0.0):
            raise ValueError(f"correlation_length must be > 0, got {self.correlation_length}")
        if not np.isfinite(self.dark_range_bias):
            raise ValueError(f"dark_range_bias must be finite, got {self.dark_range_bias}")
        if not (np.isfinite(self.dark_noise_factor) and self.dark_noise_factor >= 1.0):
            raise ValueError(f"dark_noise_factor must be >= 1, got {self.dark_noise_factor}")
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
        if self.scans is not None:
            scans = np.asarray(self.scans, dtype=np.float64)
            size = np.array([self.room.length, self.room.width, self.room.height])
            if scans.ndim != 2 or scans.shape[1] != 6 or not np.all(np.isfinite(scans)):
                raise ValueError(f"CloudDesign.scans must be (s, 6) finite, got {scans.shape}")
            for j, s in enumerate(scans):
                if not np.all((s[:3] > 0) & (s[:3] < size)):
                    raise ValueError(f"scan {j + 1}: station {tuple(s[:3])} is outside the room")
            object.__setattr__(self, "scans", tuple(tuple(float(c) for c in s) for s in scans))


@dataclasses.dataclass(frozen=True, eq=False)
class PointClouds:
    """Simulated scans with their truth, one entry per scan in each tuple.

    ``observations[j]`` (n_j, 3) = (rho [m], theta [rad], alpha [rad]); ``plane_ids[j]`` the true
    plane of each point (index into ``planes``); ``incidence[j]`` [rad]; ``true_points[j]``
    (n_j, 3) object-space points. ``eops`` (s, 6) = (Xs, Ys, Zs, omega, phi, kappa);
    ``planes`` (k, 4) = (n_x, n_y, n_z, d) with ``n . X = d``, unit normals pointing into the
    room for its faces. ``true_aps``: name -> value (SI). ``levelling``: scan -> compensator
    observation (the mapping :func:`~tlsjax.make_network` takes) of the levelled scans.

    Targets: ``intensity[j]`` (n_j,) of every point; ``target_ids[j]`` (n_j,) the target hit
    (index into ``target_names``, -1 elsewhere; a sphere's points have plane id -1, a planar
    target's plate is a plane ``plate1``, ``plate2``, ...); ``target_kinds`` ("sphere",
    "checkerboard", "circle"), ``target_centres`` (t, 3) in object space, ``target_sizes``
    (t,) the sphere radius or the plate's side [m].
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
    intensity: tuple = ()
    target_ids: tuple = ()
    target_names: tuple = ()
    target_kinds: tuple = ()
    target_centres: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3)))
    target_sizes: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0))

    def target_observations(self, min_points: int = 1) -> dict:
        """The noise-free observation of every target centre in every scan that has at least
        ``min_points`` points on it: ``{(scan, target): (rho, theta, alpha)}``, the fixed point
        ``l = F(X_c, EOP) + Delta(l; AP)`` of the centre (for a panoramic scanner in the face of
        its direction), i.e. what a perfect extraction of the centre from the APs-distorted
        cloud observes."""
        keys, X, E = [], [], []
        for j, ids in enumerate(self.target_ids):
            counts = np.bincount(ids[ids >= 0], minlength=len(self.target_names))
            for t in np.flatnonzero(counts >= min_points):
                keys.append((self.scans[j], self.target_names[t]))
                X.append(self.target_centres[t])
                E.append(self.eops[j])
        if not keys:
            return {}
        X, E = np.asarray(X), np.asarray(E)
        R = np.stack([rotation_matrix(*e[3:], xp=np) for e in E])
        hyb = spherical_from_cartesian(np.einsum("mij,mj->mi", R, X - E[:, :3]), xp=np)
        face2 = second_face(hyb[:, 1], self.scanner.architecture)
        names = self.scanner.aps
        coeffs = jnp.asarray([self.true_aps[n] for n in names], dtype=jnp.float64)
        obs = _observe_in_chunks(X, E, np.zeros_like(X), face2, coeffs, self.scanner, names)
        obs[:, 1] = np.mod(obs[:, 1], TWO_PI)
        return dict(zip(keys, obs))

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
            keep = np.flatnonzero(ids >= 0)  # -1: a point on a sphere target
            if max_points is not None:
                parts = [
                    rng.permutation(np.flatnonzero(ids == k))[:max_points]
                    for k in np.unique(ids[keep])
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


@dataclasses.dataclass(frozen=True, eq=False)
class _Scene:
    """Everything a ray can hit: plane patches (the room's faces, boards, target plates; arrays
    of :func:`room_patches`), spheres, and the targets' truth."""

    patches: tuple  # normal, d, origin, edge_u, edge_v
    plane_names: tuple
    plate_target: np.ndarray  # (k,) target index of a plate, -1 for other patches
    sphere_centres: np.ndarray  # (q, 3)
    sphere_radii: np.ndarray
    sphere_reflectance: np.ndarray
    n_spheres: int
    planar: tuple  # PlanarTarget per planar target (targets n_spheres, n_spheres + 1, ...)
    frames: np.ndarray  # (p, 2, 3) pattern axes of the planar targets
    names: tuple
    kinds: tuple
    centres: np.ndarray  # (t, 3)
    sizes: np.ndarray  # (t,)
    extents: np.ndarray  # (t,) radius of the fine window around a target [m]


def _scene(design: CloudDesign) -> _Scene:
    plates = tuple(t.board() for t in design.planar_targets)
    normal, d, origin, eu, ev, names = room_patches(design.room, design.boards + plates)
    n_other = len(names) - len(plates)
    names = names[:n_other] + tuple(f"plate{i + 1}" for i in range(len(plates)))
    q = len(design.spheres)
    plate_target = np.full(len(names), -1, dtype=np.int64)
    plate_target[n_other:] = q + np.arange(len(plates))
    kinds = ("sphere",) * q + tuple(t.pattern for t in design.planar_targets)
    counter: dict[str, int] = {}
    tnames = []
    for k in kinds:
        counter[k] = counter.get(k, 0) + 1
        tnames.append(f"{k}{counter[k]}")
    sph = design.spheres
    return _Scene(
        (normal, d, origin, eu, ev),
        names,
        plate_target,
        np.array([t.centre for t in sph], dtype=np.float64).reshape(-1, 3),
        np.array([t.radius for t in sph], dtype=np.float64),
        np.array([t.reflectance for t in sph], dtype=np.float64),
        q,
        design.planar_targets,
        np.array([t.frame() for t in design.planar_targets]).reshape(-1, 2, 3),
        tuple(tnames),
        kinds,
        np.array(
            [t.centre for t in sph] + [t.centre for t in design.planar_targets], dtype=np.float64
        ).reshape(-1, 3),
        np.array([t.radius for t in sph] + [t.size for t in design.planar_targets]),
        np.array(
            [1.6 * t.radius + 0.03 for t in sph]
            + [0.75 * t.size + 0.03 for t in design.planar_targets]
        ),
    )


def _window_directions(design: CloudDesign, scene: _Scene, eop):
    """Fine-grid directions (theta, alpha) (m, 2) around the targets seen from ``eop``, and the
    windows as unit axes (t, 3) and cosines of their angular radii (t,)."""
    step = design.target_step
    lo, hi = design.elevation_limits
    R = rotation_matrix(*eop[3:], xp=np)
    c = (scene.centres - eop[:3]) @ R.T
    dist = np.linalg.norm(c, axis=1)
    gamma = np.arcsin(np.minimum(1.0, scene.extents / dist)) + 2.0 * step
    axes = c / dist[:, None]
    hyb = spherical_from_cartesian(c, xp=np)
    n_theta = int(np.floor(TWO_PI / step + 1e-9))
    cells = []
    for (_, th, al), g, a in zip(hyb, gamma, axes):
        j = np.arange(
            np.ceil((max(lo, al - g) - lo) / step), np.floor((min(hi, al + g) - lo) / step) + 1
        )
        cos_band = np.cos(min(np.pi / 2, abs(al) + g))
        half = np.pi if cos_band < np.sin(g) else np.arcsin(np.sin(g) / cos_band) + step
        i = np.arange(np.floor((th - half) / step - 0.5), np.ceil((th + half) / step - 0.5) + 1)
        ii, jj = np.meshgrid(np.mod(i, n_theta), j, indexing="ij")
        ii, jj = ii.ravel().astype(np.int64), jj.ravel().astype(np.int64)
        t, e = step * (ii + 0.5), lo + step * jj
        u = np.stack([np.cos(e) * np.cos(t), np.cos(e) * np.sin(t), np.sin(e)], axis=1)
        inside = u @ a >= np.cos(g)
        cells.append(np.stack([ii[inside], jj[inside]], axis=1))
    cells = np.unique(np.concatenate(cells), axis=0) if cells else np.zeros((0, 2), np.int64)
    dirs = np.stack([step * (cells[:, 0] + 0.5), lo + step * cells[:, 1]], axis=1)
    return dirs, axes, np.cos(gamma)


def _unit(grid):
    ca = np.cos(grid[:, 1])
    return np.stack([ca * np.cos(grid[:, 0]), ca * np.sin(grid[:, 0]), np.sin(grid[:, 1])], axis=1)


def scan_grid(design: CloudDesign, scene: _Scene, eop) -> np.ndarray:
    """All directions (theta, alpha) (m, 2) of one scan: the room grid of
    :func:`scan_directions`, its directions inside a target's window replaced by the window's
    finer grid (``target_step``)."""
    grid = scan_directions(design)
    if design.target_step is None or len(scene.names) == 0:
        return grid
    fine, axes, cos_g = _window_directions(design, scene, eop)
    u = _unit(grid)
    outside = np.ones(len(grid), dtype=bool)
    for a, cg in zip(axes, cos_g):
        outside &= u @ a < cg
    return np.concatenate([grid[outside], fine])


_RAYS = 1 << 16


def render_rays(design: CloudDesign, scene: _Scene, eop, grid) -> dict:
    """Cast the scanner-space directions ``grid`` (theta, alpha) of the scan at ``eop`` into the
    scene. Returns, for the directions that hit something within ``max_incidence``: ``X``
    (object space), ``plane`` (patch index, -1 on a sphere), ``target`` (-1 off targets),
    ``incidence``, ``white`` (white share of the footprint on a plate, 1 elsewhere) and
    ``reflectance``. Chunked, so that memory does not grow with the patches times the rays."""
    normal, d, origin, eu, ev = scene.patches
    R = rotation_matrix(*eop[3:], xp=np)
    S = eop[:3]
    parts = []
    for a in range(0, len(grid), _RAYS):
        D = _unit(grid[a : a + _RAYS]) @ R  # rows R^T u: object-space directions
        t, k = cast_rays(S, D, normal, d, origin, eu, ev)
        sphere = np.full(len(D), -1, dtype=np.int64)
        for q, (C, r) in enumerate(zip(scene.sphere_centres, scene.sphere_radii)):
            ts = sphere_ray_distance(D, C - S, r)
            nearer = ts < t
            t = np.where(nearer, ts, t)
            sphere[nearer] = q
        X = S + np.where(np.isfinite(t), t, 0.0)[:, None] * D
        on_sphere = sphere >= 0
        nrm = normal[k]
        if on_sphere.any():
            c = scene.sphere_centres[sphere[on_sphere]]
            nrm[on_sphere] = (X[on_sphere] - c) / scene.sphere_radii[sphere[on_sphere], None]
        inc = np.arccos(np.clip(np.abs(np.einsum("mi,mi->m", D, nrm)), 0.0, 1.0))
        keep = np.isfinite(t) & (inc <= design.max_incidence)
        plane = np.where(on_sphere, -1, k)[keep]
        target = np.where(on_sphere, sphere, scene.plate_target[k])[keep]
        refl = np.full(len(D), design.reflectance)
        refl[on_sphere] = scene.sphere_reflectance[sphere[on_sphere]]
        refl = refl[keep]
        parts.append(
            {"X": X[keep], "plane": plane, "target": target, "incidence": inc[keep], "refl": refl}
        )
    out = {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}
    _paint_plates(design, scene, out, S)
    return out


def _paint_plates(design: CloudDesign, scene: _Scene, hits: dict, station) -> None:
    """The white share and reflectance of the points on the target plates (in place)."""
    X, target = hits["X"], hits["target"]
    white = np.ones(len(X))
    for p, tgt in enumerate(scene.planar):
        on = target == scene.n_spheres + p
        if not on.any():
            continue
        rho = np.linalg.norm(X[on] - station, axis=1)
        uv = (X[on] - np.asarray(tgt.centre)) @ scene.frames[p].T
        blur = design.beam_width + design.beam_divergence * rho
        if tgt.pattern == "checkerboard":
            w = checkerboard_white(uv[:, 0], uv[:, 1], blur, xp=np)
        else:
            w = disc_white(uv[:, 0], uv[:, 1], tgt.circle_radius, blur, xp=np)
        white[on] = w
        hits["refl"][on] = tgt.dark + (tgt.bright - tgt.dark) * w
    hits["white"] = white


def correlated_field(X, length: float, rng, features: int = 64, chunk: int = 250_000):
    """A unit-variance stationary random field at the points ``X`` (m, 3) with Gaussian
    covariance of correlation length ``length`` [m] (random Fourier features, module
    docstring); in chunks, so that memory stays linear in the points."""
    w = rng.standard_normal((features, 3)) / length
    b = rng.uniform(0.0, 2.0 * np.pi, features)
    out = np.empty(len(X))
    for i in range(0, len(X), chunk):
        out[i : i + chunk] = np.cos(X[i : i + chunk] @ w.T + b).sum(axis=1)
    return out * np.sqrt(2.0 / features)


def _observe_scan(design, eop, hits, rng, coeffs, scanner, names, rng_c=None):
    """Observations ``l = F + Delta(l; AP) + e`` of one scan's hit points (module docstring):
    range noise ``sigma_range sec(beta)`` plus the correlated range noise (drawn from ``rng_c``)
    and the dark share's range bias, angular noise."""
    X = hits["X"]
    m = len(X)
    R = rotation_matrix(*eop[3:], xp=np)
    hyb = spherical_from_cartesian((X - eop[:3]) @ R.T, xp=np)
    face2 = second_face(hyb[:, 1], design.architecture)
    sig = np.stack(
        [
            design.sigma_range
            * (1.0 + (design.dark_noise_factor - 1.0) * (1.0 - hits["white"]))
            / np.cos(hits["incidence"]),
            np.full(m, design.sigma_angle),
            np.full(m, design.sigma_angle),
        ],
        axis=1,
    )
    e = rng.standard_normal(sig.shape) * sig if design.noise else np.zeros_like(sig)
    if design.noise and design.correlated_sigma_range > 0.0:
        field = correlated_field(X, design.correlation_length, rng_c)
        e[:, 0] += design.correlated_sigma_range * field / np.cos(hits["incidence"])
    e[:, 0] += design.dark_range_bias * (1.0 - hits["white"])
    E = np.broadcast_to(eop, (m, 6))
    obs = _observe_in_chunks(X, E, e, face2, coeffs, scanner, names)
    # Full-turn wrap only (a face-2 direction near 0 pushed below zero is near 2 pi, not pi).
    obs[:, 1] = np.mod(obs[:, 1], TWO_PI)
    obs[:, 1] = np.where(obs[:, 1] >= TWO_PI, 0.0, obs[:, 1])
    return obs


def simulate_point_clouds(design: CloudDesign | None = None, *, seed: int = 0) -> PointClouds:
    """Simulate the scans of the calibration room as point clouds (SPEC section 8).

    ``design``: a :class:`CloudDesign`, or a :class:`~tlsjax.NetworkDesign` (the one design
    description; :meth:`CloudDesign.from_design` with the default scanning settings). Poses
    from ``design.scans``, else :func:`tlsjax._simulation._room.room_scans` (two stations,
    three scans each; tilted variant with omega = -45, +45 deg). ``seed`` fixes the noise. Returns a :class:`PointClouds`
    whose observations satisfy ``l = F + Delta(l; AP) + e`` (see the module docstring), with
    the intensity of every point and the targets' truth.
    """
    design = design or CloudDesign()
    if not isinstance(design, CloudDesign):  # a NetworkDesign
        design = CloudDesign.from_design(design)
    rng = np.random.default_rng(seed)
    values = {n: default_true_value(n) for n in design.aps}
    values.update(design.true_aps or {})
    names = tuple(values)
    scanner = Scanner(architecture=design.architecture, aps=names, unit_length=design.unit_length)
    scene = _scene(design)
    eops = design.scan_poses()

    coeffs = jnp.asarray([values[n] for n in names], dtype=jnp.float64)
    hits = [render_rays(design, scene, eop, scan_grid(design, scene, eop)) for eop in eops]
    # One scan at a time, so that memory follows the largest scan; the noise is drawn in the
    # same order as for all points at once.
    # The correlated noise from its own stream: the independent noise of a seed is unchanged.
    rng_c = np.random.default_rng([seed, 27])
    for eop, h in zip(eops, hits):
        h["obs"] = _observe_scan(design, eop, h, rng, coeffs, scanner, names, rng_c)
    obs = np.concatenate([h["obs"] for h in hits])
    inc = np.concatenate([h["incidence"] for h in hits])
    X = np.concatenate([h["X"] for h in hits])
    rho = np.concatenate([np.linalg.norm(h["X"] - e[:3], axis=1) for e, h in zip(eops, hits)])

    lev = (
        simulated_levelling(eops, rng, design.sigma_levelling, design.noise)
        if design.levelling
        else {}
    )
    # Intensity from its own stream, so that the geometry of a seed does not depend on it.
    rng_i = np.random.default_rng([seed, 33])
    refl = np.concatenate([h["refl"] for h in hits])
    intensity = refl * (0.25 + 0.75 * np.cos(inc)) * np.exp(-rho / 40.0)
    if design.noise:
        intensity = intensity + rng_i.standard_normal(len(X)) * design.intensity_noise

    split = np.cumsum([len(h["X"]) for h in hits])[:-1]
    return PointClouds(
        scans=tuple(f"S{j + 1}" for j in range(len(eops))),
        observations=tuple(np.split(obs, split)),
        plane_ids=tuple(h["plane"] for h in hits),
        incidence=tuple(np.split(inc, split)),
        true_points=tuple(np.split(X, split)),
        eops=eops,
        planes=np.concatenate([scene.patches[0], scene.patches[1][:, None]], axis=1),
        plane_names=scene.plane_names,
        scanner=scanner,
        true_aps=values,
        sigma_range=float(np.hypot(design.sigma_range, design.correlated_sigma_range)),
        sigma_angle=design.sigma_angle,
        levelling=lev,
        intensity=tuple(np.split(intensity, split)),
        target_ids=tuple(h["target"] for h in hits),
        target_names=scene.names,
        target_kinds=scene.kinds,
        target_centres=scene.centres,
        target_sizes=scene.sizes,
    )
