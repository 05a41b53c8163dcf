"""Simulated networks from a general design (SPEC sections 8 and 13).

A :class:`NetworkDesign` is a box room of any size, targets on its faces and free-standing
inside it, planes (the room's faces, infinite planes clipped to the room, finite boards),
stations anywhere inside, scans of any orientation (tilts up to 90 deg), a hybrid or panoramic
scanner with a field of view, a largest incidence angle and a largest range, and a noise model.
:func:`simulate_design` turns it into a :class:`~tlsjax.Network` of targets, planes or both,
together with its truth.

Visibility: a target or a sampled plane point is observed from a scan when its elevation angle
in scanner space (hybrid convention) is inside ``elevation_limits``, its range at most
``max_range``, its incidence angle (line of sight against the surface normal) at most
``max_incidence``, and no patch (face, plane or board) lies in front of it on the line of sight.
Plane points are drawn uniformly on the visible part of each patch, ``points_per_plane`` per
(scan, plane); a pair with fewer than ``min_plane_points`` visible points is left out.

Observations come from the library's one fixed point
(:func:`tlsjax._model._points.observe_points`), ``l = F(X, EOP) + Delta(l; AP) + e``, so a
noise-free observation satisfies the point and plane models exactly. Noise: ``e ~ N(0,
(noise_scale sigma)^2)`` per observation, with ``sigma = (sigma_range sec(beta), sigma_angle,
sigma_angle)`` (SPEC section 5); the network's a priori sigmas are ``sigma_scale sigma``. The
expected a posteriori sigma0 is therefore ``noise_scale / sigma_scale``.
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
    Network,
    ObservationTable,
    make_network,
)
from .._model._aps import resolve_aps
from .._model._geometry import TWO_PI, rotation_matrix, second_face, spherical_from_cartesian
from .._model._scanner import ARCHITECTURES, Scanner
from .._units import DEG
from ._point_clouds import Board, _observe_in_chunks
from ._room import default_true_value
from ._truth import SimulationTruth


@dataclasses.dataclass(frozen=True)
class RoomPlane:
    """A plane of a :class:`NetworkDesign`'s room: the infinite plane through ``point`` with
    normal ``normal`` [m], clipped to the room."""

    normal: tuple
    point: tuple

    def __post_init__(self):
        n = np.asarray(self.normal, dtype=np.float64)
        p = np.asarray(self.point, dtype=np.float64)
        if n.shape != (3,) or p.shape != (3,) or not np.all(np.isfinite(np.r_[n, p])):
            raise ValueError(
                f"RoomPlane needs a finite normal and point (3 coordinates each), got {self.normal!r}, {self.point!r}"
            )
        if np.linalg.norm(n) < 1e-9:
            raise ValueError("RoomPlane normal must not be zero")
        object.__setattr__(self, "normal", tuple(float(c) for c in n / np.linalg.norm(n)))
        object.__setattr__(self, "point", tuple(float(c) for c in p))


@dataclasses.dataclass(frozen=True)
class NetworkDesign:
    """A simulated network's design (SPEC sections 8, 13). Lengths in metres, angles in radians.

    ``room``: (length, width, height) of the box [0, L] x [0, W] x [0, H].
    ``scans`` (s, 6): (X, Y, Z, omega, phi, kappa) of each scan, ``x = R (X - S)`` (SPEC 1).
    ``n_targets`` on the room's faces (spread evenly, ``margin`` from the edges) and
    ``n_free_targets`` free-standing inside the room (seen from every side);
    ``common_targets``: only targets that every scan sees (the papers' design).
    ``faces_as_planes``: the six faces are observed as planes; ``planes``: further planes
    (:class:`RoomPlane`, clipped to the room, or :class:`~tlsjax.Board`), always observed.
    ``levelling``: scans with omega = phi = 0 carry compensator observations.
    ``noise_scale`` x the nominal sigmas is the noise drawn (0: noise-free);
    ``sigma_scale`` x the nominal sigmas are the network's a priori sigmas.
    """

    room: tuple = (14.0, 11.0, 3.0)
    scans: tuple = ((4.5, 4.0, 1.6, 0.0, 0.0, 0.0), (9.5, 7.0, 1.6, 0.0, 0.0, 0.5))
    n_targets: int = 0
    n_free_targets: int = 0
    common_targets: bool = False
    faces_as_planes: bool = False
    planes: tuple = ()
    points_per_plane: int = 20
    min_plane_points: int = 6
    architecture: str = "hybrid"
    aps: tuple = ("A0", "B6", "B7", "C0")
    true_aps: Mapping[str, float] | None = None
    unit_length: float = 1.2
    elevation_limits: tuple = (-60.0 * DEG, 85.0 * DEG)
    max_incidence: float = 80.0 * DEG
    max_range: float = np.inf
    sigma_range: float = DEFAULT_SIGMA_RANGE
    sigma_angle: float = DEFAULT_SIGMA_ANGLE
    sigma_levelling: float = DEFAULT_SIGMA_LEVELLING
    noise_scale: float = 1.0
    sigma_scale: float = 1.0
    levelling: bool = True
    margin: float = 0.3

    def __post_init__(self):
        room = tuple(float(v) for v in self.room)
        if len(room) != 3 or not all(np.isfinite(v) and v > 2 * self.margin for v in room):
            raise ValueError(
                f"room must be (length, width, height) above 2 x margin, got {self.room}"
            )
        object.__setattr__(self, "room", room)
        scans = np.asarray(self.scans, dtype=np.float64)
        if scans.ndim != 2 or scans.shape[1] != 6 or not np.all(np.isfinite(scans)):
            raise ValueError(
                f"scans must be (s, 6) finite (X, Y, Z, omega, phi, kappa), got {scans.shape}"
            )
        for j, s in enumerate(scans):
            if not np.all((s[:3] > 0) & (s[:3] < room)):
                raise ValueError(f"scan {j + 1}: station {tuple(s[:3])} is outside the room {room}")
        object.__setattr__(self, "scans", tuple(tuple(s) for s in scans))
        for p in self.planes:
            if not isinstance(p, RoomPlane | Board):
                raise ValueError(f"planes must be RoomPlane or Board, got {type(p).__name__}")
        object.__setattr__(self, "planes", tuple(self.planes))
        if self.architecture not in ARCHITECTURES:
            raise ValueError(f"architecture {self.architecture!r} is not one of {ARCHITECTURES}")
        object.__setattr__(self, "aps", resolve_aps(self.aps))
        lo, hi = self.elevation_limits
        if not (-np.pi / 2 < lo < hi < np.pi / 2):
            raise ValueError("elevation_limits must satisfy -90 deg < low < high < 90 deg")
        if not (0 < self.max_incidence < np.pi / 2) or not self.max_range > 0:
            raise ValueError("max_incidence must be in (0, 90 deg) and max_range positive")
        if self.noise_scale < 0 or not self.sigma_scale > 0:
            raise ValueError("noise_scale must be >= 0 and sigma_scale > 0")
        if self.min_plane_points < 4 or self.points_per_plane < self.min_plane_points:
            raise ValueError("need points_per_plane >= min_plane_points >= 4")

    @property
    def expected_sigma0(self) -> float:
        """The a posteriori sigma0 the noise model implies: noise_scale / sigma_scale."""
        return self.noise_scale / self.sigma_scale


@dataclasses.dataclass(frozen=True, eq=False)
class DesignSimulation:
    """A network simulated from a :class:`NetworkDesign`, with its truth and noise model.

    Truth in the network's order: ``true_targets`` (t, 3) for ``network.targets``,
    ``true_planes`` (k, 4) = (n, d) with ``n . X = d`` for ``network.planes`` (room faces with
    inward normals), ``true_eops`` (s, 6) for ``network.scans``, ``true_aps`` name -> value.
    ``noise_sigmas`` (n, 3) and ``plane_noise_sigmas`` (m, 3): the standard deviations the noise
    was drawn with (incidence applied), in the network's row order. ``target_normals`` (t, 3):
    the inward normals of the faces the targets sit on (NaN: a free-standing target);
    ``plane_points`` (m, 3): the true point of every plane row. :meth:`truth` hands all of it
    to :func:`tlsjax.monte_carlo`.
    """

    network: Network
    scanner: Scanner
    design: NetworkDesign
    true_aps: dict
    true_eops: np.ndarray
    true_targets: np.ndarray
    true_planes: np.ndarray
    noise_sigmas: np.ndarray
    plane_noise_sigmas: np.ndarray
    target_normals: np.ndarray | None = None
    plane_points: np.ndarray | None = None

    @property
    def expected_sigma0(self) -> float:
        return self.design.expected_sigma0

    def truth(self) -> SimulationTruth:
        """The network with its truth, for :func:`tlsjax.monte_carlo` (which draws its noise
        from the network's a priori sigmas, i.e. as if ``noise_scale = sigma_scale``)."""
        n = len(self.network.instruments)
        return SimulationTruth(
            self.network,
            (self.scanner,) * n,
            (dict(self.true_aps),) * n,
            self.true_eops,
            self.true_targets,
            self.true_planes,
            np.zeros((0, 3)) if self.plane_points is None else self.plane_points,
        )


# ---------------------------------------------------------------------------------------------
# Patches: convex polygons (faces, clipped planes, boards) with their planes


@dataclasses.dataclass(frozen=True, eq=False)
class _Patches:
    """K convex polygons: unit normal (K, 3), d (K,), vertices (K, V, 3) counter-clockwise about
    the normal (padded by repeating the last), the number of real vertices, names."""

    normal: np.ndarray
    d: np.ndarray
    vertices: np.ndarray
    n_vertices: np.ndarray
    names: tuple


_FACES = (  # origin, edge_u, edge_v (fractions of L, W, H), inward normal, name
    ((0, 0, 0), (0, 1, 0), (0, 0, 1), (1, 0, 0), "wall_x0"),
    ((1, 0, 0), (0, 1, 0), (0, 0, 1), (-1, 0, 0), "wall_xL"),
    ((0, 0, 0), (1, 0, 0), (0, 0, 1), (0, 1, 0), "wall_y0"),
    ((0, 1, 0), (1, 0, 0), (0, 0, 1), (0, -1, 0), "wall_yW"),
    ((0, 0, 0), (1, 0, 0), (0, 1, 0), (0, 0, 1), "floor"),
    ((0, 0, 1), (1, 0, 0), (0, 1, 0), (0, 0, -1), "ceiling"),
)


def _parallelogram(o, eu, ev, n):
    o, eu, ev, n = (np.asarray(a, dtype=np.float64) for a in (o, eu, ev, n))
    v = np.stack([o, o + eu, o + eu + ev, o + ev])
    return v if np.cross(eu, ev) @ n > 0 else v[::-1]


def _clip_to_box(plane: RoomPlane, size):
    """The convex polygon where an infinite plane meets the box [0, size]: the plane's
    crossings of the 12 edges, ordered by angle about the normal."""
    n, p = np.asarray(plane.normal), np.asarray(plane.point)
    d = n @ p
    corners = np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)], float) * size
    pts = []
    for a in range(8):
        for b in range(a + 1, 8):
            if np.count_nonzero(corners[a] != corners[b]) != 1:
                continue
            fa, fb = n @ corners[a] - d, n @ corners[b] - d
            if fa * fb <= 0 and fa != fb:
                pts.append(corners[a] + fa / (fa - fb) * (corners[b] - corners[a]))
    uniq = []
    for q in pts:
        if all(np.linalg.norm(q - u) > 1e-9 for u in uniq):
            uniq.append(q)
    if len(uniq) < 3:
        raise ValueError(f"plane through {plane.point} with normal {plane.normal} misses the room")
    P = np.array(uniq)
    c = P.mean(0)
    u = P[0] - c
    u /= np.linalg.norm(u)
    w = np.cross(n, u)
    return P[np.argsort(np.arctan2((P - c) @ w, (P - c) @ u))]


def _patches(design: NetworkDesign) -> _Patches:
    size = np.asarray(design.room)
    polys, normals, names = [], [], []
    for o, eu, ev, n, name in _FACES:
        polys.append(
            _parallelogram(np.multiply(o, size), np.multiply(eu, size), np.multiply(ev, size), n)
        )
        normals.append(np.asarray(n, dtype=np.float64))
        names.append(name)
    for i, p in enumerate(design.planes):
        if isinstance(p, Board):
            n = np.cross(p.edge_u, p.edge_v)
            n /= np.linalg.norm(n)
            polys.append(_parallelogram(p.origin, p.edge_u, p.edge_v, n))
            names.append(f"board{i + 1}")
        else:
            n = np.asarray(p.normal)
            polys.append(_clip_to_box(p, size))
            names.append(f"plane{i + 1}")
        normals.append(n)
    V = max(len(v) for v in polys)
    verts = np.stack([np.concatenate([v, np.repeat(v[-1:], V - len(v), 0)]) for v in polys])
    normal = np.stack(normals)
    d = np.einsum("ki,ki->k", normal, verts[:, 0])
    return _Patches(normal, d, verts, np.array([len(v) for v in polys]), tuple(names))


def _first_hits(S, D, patches: _Patches):
    """Distance along unit rays ``S + t D`` (m, 3) to the nearest patch, and which one."""
    nD = D @ patches.normal.T
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (patches.d - patches.normal @ S)[None, :] / nD
    t = np.where(np.isfinite(t) & (t > 1e-9), t, np.inf)
    hit = S + np.where(np.isfinite(t), t, 0.0)[..., None] * D[:, None, :]  # (m, K, 3)
    v = patches.vertices
    edge = np.roll(v, -1, axis=1) - v  # (K, V, 3); padded vertices give zero edges
    rel = hit[:, :, None, :] - v[None]  # (m, K, V, 3)
    side = np.einsum("kvi,mkvi->mkv", np.cross(edge, patches.normal[:, None, :]), rel)
    # side <= 0 inside (edge x n points outwards for counter-clockwise vertices).
    inside = np.all(side <= 1e-9 * (1 + np.linalg.norm(edge, axis=-1)), axis=-1)
    t = np.where(inside, t, np.inf)
    k = np.argmin(t, axis=1)
    return t[np.arange(len(t)), k], k


def _visible(S, R, X, normals, own, patches, design):
    """Which points X (m, 3) scan (S, R) observes (field of view, range, incidence, occlusion),
    and their incidence angles. ``own`` (m,) is the patch each point lies on (-1: none)."""
    los = X - S
    r = np.linalg.norm(los, axis=1)
    D = los / r[:, None]
    x = los @ R.T
    alpha = np.arctan2(x[:, 2], np.hypot(x[:, 0], x[:, 1]))
    lo, hi = design.elevation_limits
    cosb = np.where(
        np.isnan(normals[:, 0]), 1.0, np.abs(np.einsum("mi,mi->m", D, np.nan_to_num(normals)))
    )
    inc = np.arccos(np.clip(cosb, 0.0, 1.0))
    t, k = _first_hits(S, D, patches)
    free = (t >= r * (1 - 1e-9) - 1e-9) | (k == own)
    ok = (alpha >= lo) & (alpha <= hi) & (r <= design.max_range) & (inc <= design.max_incidence)
    return ok & free & (r > 0.1), inc


def _sample_polygon(v, nv, m, rng):
    """m points uniform on the convex polygon with vertices v[:nv] (fan triangulation)."""
    v = v[:nv]
    a, b, c = v[0], v[1:-1], v[2:]
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    tri = rng.choice(len(area), size=m, p=area / area.sum())
    r1, r2 = np.sqrt(rng.uniform(size=m)), rng.uniform(size=m)
    return (1 - r1)[:, None] * a + (r1 * (1 - r2))[:, None] * b[tri] + (r1 * r2)[:, None] * c[tri]


def _plane_points(design, S, R, k, patches, rng):
    """Up to ``points_per_plane`` points of patch k visible from (S, R), drawn uniformly on the
    patch (in batches until enough are visible), with their incidence angles; none when fewer
    than ``min_plane_points`` are visible."""
    want, got = design.points_per_plane, []
    for _ in range(8):
        cand = _sample_polygon(patches.vertices[k], patches.n_vertices[k], 25 * want, rng)
        nk = np.broadcast_to(patches.normal[k], cand.shape)
        ok, inc = _visible(S, R, cand, nk, np.full(len(cand), k), patches, design)
        got += [(cand[i], inc[i]) for i in np.flatnonzero(ok)]
        if len(got) >= want:
            break
    return got[:want] if len(got) >= design.min_plane_points else []


def _targets(design: NetworkDesign, eops, R, patches, rng):
    """Targets, their normals and patches. With ``common_targets`` only targets that every scan
    sees are kept (drawn in rounds over the faces until there are ``n_targets``)."""
    if not design.common_targets:
        return _face_targets(design, rng, 1)
    X, n, own = _face_targets(design, rng, 40)
    ok = np.ones(len(X), dtype=bool)
    for e, Rj in zip(eops, R):
        ok &= _visible(e[:3], Rj, X, n, own, patches, design)[0]
    # Round robin over the faces (and the free targets), so that the kept ones stay spread.
    idx = np.flatnonzero(ok)
    rank = np.zeros(len(X))
    for g in np.unique(own[idx]):
        m = idx[own[idx] == g]
        rank[m] = np.arange(len(m))
    idx = idx[np.argsort(rank[idx], kind="stable")]
    wanted = design.n_targets + design.n_free_targets
    if len(idx) < wanted:
        raise ValueError(
            f"only {len(idx)} of the {wanted} targets of the design can be seen from every scan"
        )
    idx = np.sort(idx[:wanted])
    return X[idx], n[idx], own[idx]


def _face_targets(design: NetworkDesign, rng, oversample: int):
    """Targets spread evenly over the six faces (``margin`` from their edges), with the faces'
    inward normals, then free-standing ones (no normal: NaN) inside the room."""
    size, m = np.asarray(design.room), design.margin
    n_face, n_free = oversample * design.n_targets, oversample * design.n_free_targets
    per = np.full(6, n_face // 6)
    per[: n_face % 6] += 1
    pts, nrm, own = [], [], []
    for f, ((o, _, _, n, _), k) in enumerate(zip(_FACES, per)):
        ax = int(np.flatnonzero(n)[0])
        u = rng.uniform(m, size - m, size=(k, 3))
        u[:, ax] = o[ax] * size[ax]
        pts.append(u)
        nrm.append(np.tile(np.asarray(n, float), (k, 1)))
        own.append(np.full(k, f))
    pts.append(rng.uniform(0.5, size - 0.5, size=(n_free, 3)))
    nrm.append(np.full((n_free, 3), np.nan))
    own.append(np.full(n_free, -1))
    return np.concatenate(pts), np.concatenate(nrm), np.concatenate(own)


# ---------------------------------------------------------------------------------------------
# Simulation


def simulate_design(
    design: NetworkDesign, *, seed: int = 0, noise_seed: int | None = None
) -> DesignSimulation:
    """Simulate the network of ``design`` (see the module docstring): the geometry (target
    layout, sampled plane points) from ``seed``, the noise from ``noise_seed`` (default
    ``seed``), so that Monte Carlo can redraw the noise on one geometry.

    Targets seen in one scan only are dropped (they give no redundancy); a design that leaves a
    scan with too few primitives raises the ``ValueError`` of :func:`~tlsjax.make_network`.
    """
    rng = np.random.default_rng(seed)
    values = {n: default_true_value(n) for n in design.aps}
    values.update(design.true_aps or {})
    names = tuple(values)
    scanner = Scanner(architecture=design.architecture, aps=names, unit_length=design.unit_length)
    patches = _patches(design)
    eops = np.asarray(design.scans, dtype=np.float64)
    R = np.stack([rotation_matrix(*e[3:], xp=np) for e in eops])
    observed = [k for k in range(len(patches.names)) if k >= 6 or design.faces_as_planes]

    X_t, n_t, own_t = _targets(design, eops, R, patches, rng)
    rows_t, rows_p = [], []  # (scan, index, point, incidence)
    for j, (e, Rj) in enumerate(zip(eops, R)):
        if len(X_t):
            ok, inc = _visible(e[:3], Rj, X_t, n_t, own_t, patches, design)
            rows_t += [(j, i, X_t[i], inc[i]) for i in np.flatnonzero(ok)]
        for k in observed:
            rows_p += [(j, k, x, b) for x, b in _plane_points(design, e[:3], Rj, k, patches, rng)]

    unseen = sorted(set(range(len(eops))) - {r[0] for r in rows_t + rows_p})
    if unseen:
        raise ValueError(f"scan S{unseen[0] + 1} of the design observes no target and no plane")
    coeffs = jnp.asarray([values[n] for n in names], dtype=jnp.float64)
    noise_seed = seed if noise_seed is None else noise_seed
    obs_t, obs_p, sig_t, sig_p, lev = _observe(
        design, eops, rows_t, rows_p, scanner, coeffs, names, noise_seed
    )
    net = _make_network(design, len(eops), patches, rows_t, rows_p, obs_t, obs_p, lev)
    return _with_truth(
        net, scanner, design, values, eops, X_t, n_t, patches, rows_t, rows_p, sig_t, sig_p
    )


def _make_network(design, n_scans, patches, rows_t, rows_p, obs_t, obs_p, lev):
    """The network of the observed rows, with the a priori sigmas ``sigma_scale`` x nominal
    (range sigma x sec(incidence), applied by make_network)."""
    s_names = [f"S{j + 1}" for j in range(n_scans)]
    table = None
    if rows_p:
        table = ObservationTable(
            kind="plane",
            source="<simulated design>",
            scans=tuple(s_names[r[0]] for r in rows_p),
            primitives=tuple(patches.names[r[1]] for r in rows_p),
            observations=obs_p,
            sigmas=np.tile(design.sigma_scale * _nominal(design), (len(rows_p), 1)),
            incidence=np.array([r[3] for r in rows_p]),
            instruments=None,
            rows=np.arange(2, len(rows_p) + 2),
        )
    scale = design.sigma_scale
    return make_network(
        [s_names[r[0]] for r in rows_t],
        [f"T{r[1] + 1:03d}" for r in rows_t],
        obs_t.reshape(-1, 3),
        sigma_range=scale * design.sigma_range,
        sigma_hz=scale * design.sigma_angle,
        sigma_el=scale * design.sigma_angle,
        incidence=np.array([r[3] for r in rows_t]) if rows_t else None,
        levelling=lev,
        drop_single_targets=True,
        planes=table,
        source="<simulated design>",
    )


def _nominal(design: NetworkDesign) -> np.ndarray:
    return np.array([design.sigma_range, design.sigma_angle, design.sigma_angle])


def _observe(design, eops, rows_t, rows_p, scanner, coeffs, names, noise_seed):
    """Observations of all target and plane rows through the fixed point, with noise of
    ``noise_scale`` x the nominal sigmas (range sigma x sec(incidence)), and the compensator
    observations of the levelled scans."""
    rng = np.random.default_rng(noise_seed)
    rows = rows_t + rows_p
    if not rows:
        raise ValueError("the design observes nothing: no target or plane point is visible")
    si = np.array([r[0] for r in rows])
    X = np.stack([r[2] for r in rows])
    inc = np.array([r[3] for r in rows])
    sig = np.tile(_nominal(design), (len(rows), 1))
    sig[:, 0] /= np.cos(inc)
    e = rng.standard_normal(sig.shape) * sig * design.noise_scale
    R = np.stack([rotation_matrix(*p[3:], xp=np) for p in eops])
    x = np.einsum("mij,mj->mi", R[si], X - eops[si, :3])
    hyb = spherical_from_cartesian(x, xp=np)
    face2 = second_face(hyb[:, 1], design.architecture)
    obs = _observe_in_chunks(X, eops[si], e, face2, coeffs, scanner, names)
    # Full-turn wrap only (a face-2 direction near 0 pushed below zero is near 2 pi, not pi).
    obs[:, 1] = np.mod(obs[:, 1], TWO_PI)
    obs[:, 1] = np.where(obs[:, 1] >= TWO_PI, 0.0, obs[:, 1])
    lev = {}
    if design.levelling:
        s_lev = design.sigma_levelling
        for j, p in enumerate(eops):
            if p[3] == 0.0 and p[4] == 0.0:
                dn = rng.standard_normal(2) * s_lev * design.noise_scale
                lev[f"S{j + 1}"] = {
                    "omega": dn[0],
                    "phi": dn[1],
                    "sigma_omega": design.sigma_scale * s_lev,
                    "sigma_phi": design.sigma_scale * s_lev,
                }
    n_t = len(rows_t)
    sig = sig * design.noise_scale
    return obs[:n_t], obs[n_t:], sig[:n_t], sig[n_t:], lev


def _with_truth(
    net, scanner, design, values, eops, X_t, n_t, patches, rows_t, rows_p, sig_t, sig_p
):
    """The truth and the noise sigmas in the network's order (scans in order of appearance,
    targets seen in one scan dropped)."""
    scan_of = {f"S{j + 1}": j for j in range(len(eops))}
    keep = np.array([f"T{r[1] + 1:03d}" not in set(net.dropped) for r in rows_t], dtype=bool)
    k_of = {name: k for k, name in enumerate(patches.names)}
    planes = np.concatenate([patches.normal, patches.d[:, None]], axis=1)
    targets = [int(t[1:]) - 1 for t in net.targets]
    return DesignSimulation(
        network=net,
        scanner=scanner,
        design=design,
        true_aps=dict(values),
        true_eops=eops[[scan_of[s] for s in net.scans]],
        true_targets=X_t[targets].reshape(-1, 3),
        true_planes=planes[[k_of[k] for k in net.planes]].reshape(-1, 4),
        noise_sigmas=sig_t[keep] if len(rows_t) else np.zeros((0, 3)),
        plane_noise_sigmas=sig_p.reshape(-1, 3),
        target_normals=n_t[targets].reshape(-1, 3),
        plane_points=np.array([r[2] for r in rows_p]).reshape(-1, 3),
    )
