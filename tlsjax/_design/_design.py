"""Differentiable network designs (SPEC section 13): a design is a pytree of arrays that a pure
simulation turns into the inputs of an analysed adjustment.

* :class:`TargetDesign`: scan poses (station positions and orientations, tilts included), target
  positions and the normals of the surfaces they sit on, the true APs and the instrument noise.
  Observations of target i from scan j: ``l = F(X_i, EOP_j) + Delta(l; AP) + sigma z`` (the
  fixed point of :func:`tlsjax._model._points.simulate_point_observations`), range sigma
  ``sigma_range sec(beta)`` with beta the incidence angle (SPEC section 5).
* :class:`PlaneDesign`: scan poses and planes ``(n, d)``; each point is the intersection of a
  fixed scanner-space direction ``u(theta, alpha)`` with its plane,
  ``rho = (d - n . S) / (n . R^T u)`` (Chow et al. 2013, eq. 3 read backwards), so a point
  slides on its plane when the station, the tilt or the plane moves.

A :class:`DesignProblem` holds what is static (which rows exist, which scans carry a
compensator, the scanner, the calibration model; built once on the host as a template network
and analysed adjustment) and maps a design to :class:`~tlsjax.NetworkInputs` and to the true
parameters, both pure functions: ``jax.grad`` of anything computed from them w.r.t. the design
works (the implicit adjustment of :mod:`tlsjax._adjustment._implicit` for estimates of noisy
data; a linearisation at the truth for predicted covariances, :mod:`._criteria`).

Visibility (field of view in elevation, largest incidence angle) is hard in :meth:`network`
(rows outside it are dropped) and smooth in :meth:`DesignProblem.inputs` when
``smooth_visibility`` is set: the information of an observation is multiplied by
``sigmoid((alpha - alpha_min) / tau) sigmoid((alpha_max - alpha) / tau) sigmoid((beta_max -
beta) / tau)`` (floored at 1e-6 so that every target stays determined), which lets an optimiser
move scans across the edge of the field of view.
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from .._adjustment._calibrate import Adjustment
from .._adjustment._config import CalibrationModel
from .._adjustment._families import Params
from .._adjustment._implicit import NetworkInputs
from .._adjustment._network import ObservationTable, make_network, make_plane_network
from .._jit import jit
from .._model._aps import ap_corrections
from .._model._geometry import TWO_PI, rotation_matrix, second_face, spherical_from_cartesian
from .._model._levelling import compensator_reading
from .._model._points import distorted_observations
from .._model._scanner import Scanner
from .._pytree import Module
from .._simulation._design import DesignSimulation, NetworkDesign, simulate_design
from .._simulation._room import Simulation
from .._units import DEG

#: Width of the smooth visibility edges [rad] and the information floor of a hidden observation.
VISIBILITY_EDGE = 1.0 * DEG
VISIBILITY_FLOOR = 1e-6


class TargetDesign(Module):
    """A target-based calibration design (SPEC section 13); all SI units, all arrays.

    ``eops`` (s, 6) = (Xs, Ys, Zs, omega, phi, kappa); ``targets`` (t, 3); ``normals`` (t, 3) unit
    normals of the surfaces the targets sit on (for the incidence angle); ``aps`` (a,) true AP
    values in the order of the scanner's APs; ``sigma_range`` [m] at normal incidence,
    ``sigma_angle`` [rad] of both angles, ``sigma_levelling`` [rad] of the compensator.
    """

    eops: Float[Array, "s 6"]
    targets: Float[Array, "t 3"]
    normals: Float[Array, "t 3"]
    aps: Float[Array, " a"]
    sigma_range: Float[Array, ""]
    sigma_angle: Float[Array, ""]
    sigma_levelling: Float[Array, ""]

    @classmethod
    def from_simulation(
        cls, sim: Simulation, *, sigma_range=None, sigma_angle=None, sigma_levelling=None
    ):
        """The design of a :func:`tlsjax.simulate` room (its sigmas unless given)."""
        from .._adjustment._network import (
            DEFAULT_SIGMA_ANGLE,
            DEFAULT_SIGMA_LEVELLING,
            DEFAULT_SIGMA_RANGE,
        )

        f = lambda v, d: jnp.asarray(d if v is None else v, dtype=jnp.float64)
        return cls(
            jnp.asarray(sim.true_eops),
            jnp.asarray(sim.true_targets),
            jnp.asarray(sim.target_normals),
            jnp.asarray([sim.true_aps[n] for n in sim.scanner.aps], dtype=jnp.float64),
            f(sigma_range, DEFAULT_SIGMA_RANGE),
            f(sigma_angle, DEFAULT_SIGMA_ANGLE),
            f(sigma_levelling, DEFAULT_SIGMA_LEVELLING),
        )

    @classmethod
    def from_design(cls, design: NetworkDesign, *, seed: int = 0) -> TargetDesign:
        """The targets of a :class:`~tlsjax.NetworkDesign` (the one design description), as
        :func:`tlsjax.simulate_design` places them with ``seed``: its scans, the targets of
        its network with their faces' normals, its true APs (in the order of
        ``simulate_design(design).scanner.aps``) and its a priori sigmas (``sigma_scale`` x
        nominal). :meth:`DesignProblem.targets` observes every target from every scan: build
        the design with ``common_targets=True`` for the same rows as ``simulate_design``."""
        sim = simulate_design(design, seed=seed)
        if len(sim.true_targets) == 0 or np.isnan(sim.target_normals).any():
            raise ValueError(
                "TargetDesign.from_design needs targets on the room's faces (n_targets > 0; "
                "free-standing targets have no surface normal for the incidence angle)"
            )
        return cls(
            jnp.asarray(sim.true_eops),
            jnp.asarray(sim.true_targets),
            jnp.asarray(sim.target_normals),
            *_aps_and_sigmas(sim),
        )


class PlaneDesign(Module):
    """A plane-based calibration design: ``eops`` (s, 6), ``planes`` (k, 4) = (n, d) with
    ``n . X = d``, true ``aps``, and the sigmas as in :class:`TargetDesign`."""

    eops: Float[Array, "s 6"]
    planes: Float[Array, "k 4"]
    aps: Float[Array, " a"]
    sigma_range: Float[Array, ""]
    sigma_angle: Float[Array, ""]
    sigma_levelling: Float[Array, ""]

    @classmethod
    def from_design(cls, design: NetworkDesign, *, seed: int = 0) -> PlaneDesign:
        """The planes of a :class:`~tlsjax.NetworkDesign` (the one design description), as
        :func:`tlsjax.simulate_design` observes them with ``seed``: its scans, the planes of
        its network (faces with inward normals, clipped planes, boards), its true APs and its
        a priori sigmas (``sigma_scale`` x nominal)."""
        sim = simulate_design(design, seed=seed)
        if len(sim.true_planes) == 0:
            raise ValueError("PlaneDesign.from_design: the design observes no plane")
        return cls(jnp.asarray(sim.true_eops), jnp.asarray(sim.true_planes), *_aps_and_sigmas(sim))


def _aps_and_sigmas(sim: DesignSimulation) -> tuple:
    """True APs (in the scanner's order) and a priori sigmas of a design's simulation."""
    d = sim.design
    return (
        jnp.asarray([sim.true_aps[n] for n in sim.scanner.aps], dtype=jnp.float64),
        jnp.asarray(d.sigma_scale * d.sigma_range),
        jnp.asarray(d.sigma_scale * d.sigma_angle),
        jnp.asarray(d.sigma_scale * d.sigma_levelling),
    )


def _sigmoid_edge(x):
    return jax.nn.sigmoid(x / VISIBILITY_EDGE)


@functools.partial(jit, static_argnums=0)
def _network_arrays(dn, design, noise, levelling_noise):
    """What :meth:`DesignProblem.network` reads of a design: its inputs without the smooth
    visibility (the sigmas of the drawn network are the design's) and the rows' incidence
    cosines and elevations; one compiled program per problem (run eagerly, their operations
    compiled and dispatched one by one: about 90 small XLA compiles per problem)."""
    _, cosb, alpha = dn._geometry(design)
    inputs = dataclasses.replace(dn, smooth_visibility=False).inputs(design, noise, levelling_noise)
    return inputs, cosb, alpha


def _observe(X, eop, aps, noise, scanner: Scanner):
    """``l = F(X, EOP) + Delta(l) + noise`` for one point (the simulation's fixed point)."""
    x = rotation_matrix(eop[3], eop[4], eop[5]) @ (X - eop[:3])
    face2 = None
    if scanner.architecture == "panoramic":
        face2 = second_face(spherical_from_cartesian(jax.lax.stop_gradient(x))[1])
    base = spherical_from_cartesian(x, face2) + noise
    return distorted_observations(base, lambda l: ap_corrections(aps, scanner.aps, l, scanner))


@dataclasses.dataclass(frozen=True, eq=False)
class DesignProblem:
    """The design problem that :func:`tlsjax.optimize_design` and :func:`tlsjax.design_criterion`
    work on: the static part of a design (rows (scan, primitive), compensator scans, scanner,
    model, visibility limits) and the pure maps from the design arrays (:class:`TargetDesign`,
    :class:`PlaneDesign`) to inputs and truth (module docstring). (A :class:`tlsjax.NetworkDesign`
    describes a network to simulate; this is what optimisation varies.)

    ``levelled`` (s,): scans with compensator observations (default: those with omega = phi =
    0 in the design). ``fov`` (alpha_min, alpha_max) [rad] in scanner space and
    ``max_incidence`` [rad]: observations outside are dropped from :meth:`network` and, with
    ``smooth_visibility``, faded out smoothly in :meth:`inputs`.
    """

    design: TargetDesign | PlaneDesign
    scanner: Scanner
    model: CalibrationModel
    levelled: np.ndarray
    scan_index: np.ndarray  # (n,) per row
    prim_index: np.ndarray  # (n,) target or plane per row
    directions: np.ndarray | None  # (n, 2) scanner-space (theta, alpha) of plane rows
    fov: tuple | None
    max_incidence: float | None
    smooth_visibility: bool
    template: object  # the analysed adjustment of the template network

    @classmethod
    def targets(
        cls,
        design: TargetDesign,
        scanner: Scanner,
        model: CalibrationModel | None = None,
        *,
        levelled=None,
        fov=None,
        max_incidence=None,
        smooth_visibility: bool = False,
    ) -> DesignProblem:
        """Every target observed from every scan (rows scan-major, as :func:`tlsjax.simulate`)."""
        s, t = design.eops.shape[0], design.targets.shape[0]
        si, ti = np.repeat(np.arange(s), t), np.tile(np.arange(t), s)
        return cls._build(
            design, scanner, model, levelled, si, ti, None, fov, max_incidence, smooth_visibility
        )

    @classmethod
    def planes(
        cls,
        design: PlaneDesign,
        scanner: Scanner,
        scan_index,
        plane_index,
        directions,
        model: CalibrationModel | None = None,
        *,
        levelled=None,
    ) -> DesignProblem:
        """Plane rows: scan, plane and the scanner-space direction (theta, alpha) of each point."""
        return cls._build(
            design,
            scanner,
            model,
            levelled,
            np.asarray(scan_index),
            np.asarray(plane_index),
            np.asarray(directions, dtype=np.float64),
            None,
            None,
            False,
        )

    @classmethod
    def from_point_clouds(
        cls, clouds, *, max_points: int = 20, seed: int = 0, model=None
    ) -> DesignProblem:
        """The plane design of simulated point clouds (:func:`tlsjax.simulate_point_clouds`):
        at most ``max_points`` random points of each plane in each scan (``seed``), each a fixed
        scanner-space direction of its true point; planes, poses, APs and sigmas of the clouds."""
        rng = np.random.default_rng(seed)
        si, pi, dirs = [], [], []
        for j, (ids, X) in enumerate(zip(clouds.plane_ids, clouds.true_points)):
            e = clouds.eops[j]
            x = (rotation_matrix(*e[3:], xp=np) @ (X - e[:3]).T).T
            sph = spherical_from_cartesian(x, xp=np)
            for k in np.unique(ids[ids >= 0]):  # -1: a sphere target, not a plane
                rows = np.sort(rng.permutation(np.flatnonzero(ids == k))[:max_points])
                si += [j] * len(rows)
                pi += [int(k)] * len(rows)
                dirs.append(sph[rows, 1:])
        from .._adjustment._network import DEFAULT_SIGMA_LEVELLING

        design = PlaneDesign(
            jnp.asarray(clouds.eops),
            jnp.asarray(clouds.planes),
            jnp.asarray([clouds.true_aps[n] for n in clouds.scanner.aps], dtype=jnp.float64),
            jnp.asarray(clouds.sigma_range),
            jnp.asarray(clouds.sigma_angle),
            jnp.asarray(DEFAULT_SIGMA_LEVELLING),
        )
        levelled = np.array([f"S{j + 1}" in clouds.levelling for j in range(len(clouds.eops))])
        names = [f"S{j + 1}" for j in range(len(clouds.eops))]
        if tuple(names) != tuple(clouds.scans):
            levelled = np.array([s in clouds.levelling for s in clouds.scans])
        return cls.planes(
            design, clouds.scanner, si, pi, np.concatenate(dirs), model, levelled=levelled
        )

    @classmethod
    def _build(cls, design, scanner, model, levelled, si, pi, dirs, fov, max_inc, smooth):
        eops = np.asarray(design.eops)
        if levelled is None:
            levelled = np.all(eops[:, 3:5] == 0.0, axis=1)
        model = model or CalibrationModel(scanner, datum="inner")
        dn = cls(
            design,
            scanner,
            model,
            np.asarray(levelled, dtype=bool),
            si,
            pi,
            dirs,
            fov,
            max_inc,
            smooth,
            None,
        )
        # The template sees every row: what the limits hide is faded out, never dropped, so
        # the shapes (and the compiled code) do not change while an optimiser moves the design.
        object.__setattr__(dn, "template", Adjustment(dn.network(design, cut=False), model))
        return dn

    @property
    def is_plane(self) -> bool:
        return self.directions is not None

    # --- pure maps ---------------------------------------------------------------------------

    def _geometry(self, design):
        """Per row: object-space point X, incidence cosine, scanner-space elevation."""
        E = design.eops[self.scan_index]
        R = jax.vmap(lambda e: rotation_matrix(e[3], e[4], e[5]))(E)
        if self.is_plane:
            th, al = self.directions[:, 0], self.directions[:, 1]
            u = jnp.stack([jnp.cos(al) * jnp.cos(th), jnp.cos(al) * jnp.sin(th), jnp.sin(al)], -1)
            D = jnp.einsum("nji,nj->ni", R, u)  # object-space direction R^T u
            P = design.planes[self.prim_index]
            nD = jnp.sum(P[:, :3] * D, axis=1)
            rho = (P[:, 3] - jnp.sum(P[:, :3] * E[:, :3], axis=1)) / nD
            X = E[:, :3] + rho[:, None] * D
            return X, jnp.abs(nD), al
        X = design.targets[self.prim_index]
        los = X - E[:, :3]
        dist = jnp.linalg.norm(los, axis=1)
        cosb = jnp.abs(jnp.sum(los * design.normals[self.prim_index], axis=1)) / dist
        x = jnp.einsum("nij,nj->ni", R, los)
        return X, cosb, spherical_from_cartesian(x)[:, 2]

    def visibility(self, design):
        """Smooth visibility weight of every row (1 without limits)."""
        _, cosb, alpha = self._geometry(design)
        v = jnp.ones_like(cosb)
        if self.fov is not None:
            v = v * _sigmoid_edge(alpha - self.fov[0]) * _sigmoid_edge(self.fov[1] - alpha)
        if self.max_incidence is not None:
            beta = jnp.arccos(jnp.clip(cosb, 0.0, 1.0))
            v = v * _sigmoid_edge(self.max_incidence - beta)
        return jnp.maximum(v, VISIBILITY_FLOOR)

    def inputs(self, design, noise=None, levelling_noise=None) -> NetworkInputs:
        """The adjustment's inputs for ``design``: observations with ``sigma * noise`` added
        (``noise`` (n, 3) standard normal draws, ``levelling_noise`` (s, 2); None = error-free)."""
        X, cosb, _ = self._geometry(design)
        n = X.shape[0]
        sig = jnp.stack(
            [
                design.sigma_range / cosb,
                jnp.full(n, design.sigma_angle),
                jnp.full(n, design.sigma_angle),
            ],
            axis=1,
        )
        e = jnp.zeros((n, 3)) if noise is None else noise * sig
        E = design.eops[self.scan_index]
        obs = jax.vmap(lambda X_, E_, e_: _observe(X_, E_, design.aps, e_, self.scanner))(X, E, e)
        obs = obs.at[:, 1].set(jnp.mod(obs[:, 1], TWO_PI))
        if self.smooth_visibility:
            sig = sig / jnp.sqrt(self.visibility(design))[:, None]
        lev = jax.vmap(compensator_reading)(design.eops)
        if levelling_noise is not None:
            lev = lev + levelling_noise * design.sigma_levelling
        lev_sig = jnp.where(jnp.asarray(self.levelled)[:, None], design.sigma_levelling, jnp.inf)
        lev_sig = jnp.broadcast_to(lev_sig, lev.shape)
        empty = jnp.zeros((0, 3))
        if self.is_plane:
            return NetworkInputs(empty, empty, obs, sig, lev, lev_sig)
        return NetworkInputs(obs, sig, empty, empty, lev, lev_sig)

    def truth(self, design) -> Params:
        """The true parameters in the template's layout (primitives per family, EOPs, APs)."""
        plan, net = self.template.plan, self.template.network
        scans = np.array([int(n[1:]) - 1 for n in net.scans])
        if self.is_plane:
            prims = (design.planes[np.array([int(n[1:]) - 1 for n in net.planes])],)
        else:
            X = design.targets[np.array([int(n[1:]) - 1 for n in net.targets])]
            prims = tuple(X[tg].reshape(len(tg), -1) for tg in plan.family_targets)
        return Params(prims, design.eops[scans], design.aps)

    # --- host side ---------------------------------------------------------------------------

    def hard_visibility(self, design) -> np.ndarray:
        """Rows inside the field of view and the incidence limit (hard cut)."""
        _, cosb, alpha = (np.asarray(a) for a in self._geometry(design))
        return self._hard_cut(cosb, alpha)

    def _hard_cut(self, cosb: np.ndarray, alpha: np.ndarray) -> np.ndarray:
        keep = np.ones(len(cosb), dtype=bool)
        if self.fov is not None:
            keep &= (alpha >= self.fov[0]) & (alpha <= self.fov[1])
        if self.max_incidence is not None:
            keep &= np.arccos(np.clip(cosb, 0.0, 1.0)) <= self.max_incidence
        return keep

    def network(self, design, *, seed: int | None = None, cut: bool = True, rows=None):
        """A :class:`~tlsjax.Network` of ``design`` for an independent :func:`tlsjax.calibrate`:
        rows outside the visibility limits dropped; with ``seed`` the observations and the
        compensator readings carry noise drawn from the design's sigmas; ``rows`` (n,) bool:
        keep only these rows (e.g. leave a board out)."""
        n, s = len(self.scan_index), self.levelled.shape[0]
        noise = lev_noise = None
        if seed is not None:
            rng = np.random.default_rng(seed)
            noise = rng.standard_normal((n, 3))
            lev_noise = rng.standard_normal((s, 2))
        th, cosb, alpha = jax.device_get(_network_arrays(self, design, noise, lev_noise))
        keep = self._hard_cut(cosb, alpha) if cut else np.ones(n, dtype=bool)
        if rows is not None:
            keep = keep & np.asarray(rows, dtype=bool)
        scans = [f"S{j + 1}" for j in range(s)]
        lev = {
            scans[j]: {
                "omega": float(th.levelling[j, 0]),
                "phi": float(th.levelling[j, 1]),
                "sigma_omega": float(th.levelling_sigmas[j, 0]),
                "sigma_phi": float(th.levelling_sigmas[j, 1]),
            }
            for j in range(s)
            if self.levelled[j]
        }
        si, pi = self.scan_index[keep], self.prim_index[keep]
        if self.is_plane:
            table = ObservationTable(
                kind="plane",
                source="<design>",
                scans=tuple(scans[j] for j in si),
                primitives=tuple(f"P{k + 1}" for k in pi),
                observations=np.asarray(th.plane_observations)[keep],
                sigmas=np.asarray(th.plane_sigmas)[keep],
                incidence=np.zeros(int(keep.sum())),
                instruments=None,
                rows=np.arange(2, int(keep.sum()) + 2),
            )
            return make_plane_network(table, levelling=lev)
        return make_network(
            [scans[j] for j in si],
            [f"T{t + 1:03d}" for t in pi],
            np.asarray(th.observations)[keep],
            sigmas=np.asarray(th.sigmas)[keep],
            levelling=lev,
            drop_single_targets=True,
            source="<design>",
        )
