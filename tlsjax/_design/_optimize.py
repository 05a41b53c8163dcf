"""Network design optimisation (SPEC section 13): choose station positions, tilts, headings and
target placements within stated bounds to minimise a criterion of the predicted AP covariance.

The free variables live in a box (the room minus a clearance for the stations, the tilt limit
for omega and phi, the faces minus a margin for the targets) and are reached through
``v = lo + (hi - lo) sigmoid(u)``, so that the outer loop is unconstrained in u: Adam (optax)
on the smooth criterion of :mod:`._criteria`, whose gradient w.r.t. the design is exact
(autodiff through the simulation, the structured normal equations and the Cholesky factor).
The criterion is not convex (the sigma of an AP goes to infinity on whole families of designs,
e.g. every scan levelled for the hybrid B6), so several random starts run side by side as one
vmapped, compiled step; the first start is the given design when it lies inside the bounds.
Field of view and the incidence limit enter through the design network's smooth visibility.
"""

from __future__ import annotations

import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np

from .._jit import jit
from .._simulation._room import Room
from .._summary import to_json_value
from .._units import DEG
from ._criteria import DesignCriterion, predicted_cofactor

TILTS = ("unlevelled", "all", "none")


@dataclasses.dataclass(frozen=True)
class DesignSpace:
    """Which design variables are free, and their bounds.

    ``room``: the box [m] the stations stay in, ``clearance`` [m] from its walls, floor and
    ceiling (station height also within ``height`` [m]). ``stations``: move every station (scans
    that share a position in the start design share a station). ``tilts``: free omega and phi
    of the scans without a compensator (``"unlevelled"``), of every scan (``"all"``; their
    compensator observations then follow the tilt), or none; within +-``tilt_limit`` [rad].
    ``headings``: free kappa. ``targets``: slide every target on its face, ``margin`` [m] from the
    face's edges (target designs only). The number of scans is that of the start design.
    """

    room: Room = Room()
    stations: bool = True
    tilts: str = "unlevelled"
    headings: bool = False
    targets: bool = False
    clearance: float = 0.5
    height: tuple = (0.5, 2.5)
    tilt_limit: float = 60.0 * DEG
    margin: float = 0.3

    def __post_init__(self):
        if self.tilts not in TILTS:
            raise ValueError(f"tilts must be one of {TILTS}, got {self.tilts!r}")
        if not 0 < self.tilt_limit < np.pi / 2:
            raise ValueError(f"tilt_limit must be in (0, 90) deg, got {self.tilt_limit / DEG:g}")
        r = self.room
        if 2 * self.clearance >= min(r.length, r.width) or self.height[0] >= self.height[1]:
            raise ValueError(
                f"no room for stations: clearance {self.clearance} m, height {self.height} m in a "
                f"{r.length} x {r.width} x {r.height} m room"
            )


def _logit(v, lo, hi):
    p = np.clip((np.asarray(v) - lo) / (hi - lo), 1e-3, 1 - 1e-3)
    return np.log(p / (1 - p))


@dataclasses.dataclass(frozen=True, eq=False)
class Parametrisation:
    """The map from unconstrained variables u (a dict of arrays) to a design (host-built)."""

    start: object
    space: DesignSpace
    groups: np.ndarray  # station of every scan
    tilt_scans: np.ndarray
    faces: np.ndarray  # fixed axis of every target

    @classmethod
    def build(cls, dn, space: DesignSpace):
        d = dn.design
        eops = np.asarray(d.eops)
        _, groups = np.unique(np.round(eops[:, :3], 6), axis=0, return_inverse=True)
        tilt = {"unlevelled": ~dn.levelled, "all": np.ones(len(eops), bool), "none": None}
        tilt_scans = (
            np.zeros(0, int) if tilt[space.tilts] is None else np.flatnonzero(tilt[space.tilts])
        )
        faces = np.zeros(0, int)
        if space.targets:
            if dn.is_plane:
                raise ValueError("DesignSpace(targets=True) needs a target design")
            faces = np.argmax(np.abs(np.asarray(d.normals)), axis=1)
        return cls(d, space, groups.reshape(-1), tilt_scans, faces)

    def _station_bounds(self):
        r, s = self.space.room, self.space
        lo = np.array([s.clearance, s.clearance, max(s.height[0], s.clearance)])
        hi = np.array(
            [
                r.length - s.clearance,
                r.width - s.clearance,
                min(s.height[1], r.height - s.clearance),
            ]
        )
        return lo, hi

    def _target_bounds(self):
        r, m = self.space.room, self.space.margin
        return np.full(3, m), np.array([r.length, r.width, r.height]) - m

    def initial(self) -> dict:
        """u of the start design (clipped into the box)."""
        eops = np.asarray(self.start.eops)
        u = {}
        if self.space.stations:
            centres = np.stack(
                [eops[self.groups == g, :3][0] for g in range(self.groups.max() + 1)]
            )
            u["stations"] = _logit(centres, *self._station_bounds())
        if len(self.tilt_scans):
            lim = self.space.tilt_limit
            u["tilts"] = _logit(eops[self.tilt_scans, 3:5], -lim, lim)
        if self.space.headings:
            u["headings"] = np.zeros(len(eops))
        if self.space.targets:
            u["targets"] = _logit(np.asarray(self.start.targets), *self._target_bounds())
        return {k: jnp.asarray(v) for k, v in u.items()}

    def random(self, rng: np.random.Generator, scale: float = 1.5) -> dict:
        return {k: jnp.asarray(rng.normal(0.0, scale, v.shape)) for k, v in self.initial().items()}

    def design(self, u: dict):
        """The design of u (pure)."""
        d = self.start
        eops = d.eops
        if "stations" in u:
            lo, hi = self._station_bounds()
            S = lo + (hi - lo) * jax.nn.sigmoid(u["stations"])
            eops = eops.at[:, :3].set(S[self.groups])
        if "tilts" in u:
            lim = self.space.tilt_limit
            eops = eops.at[self.tilt_scans, 3:5].set(lim * (2 * jax.nn.sigmoid(u["tilts"]) - 1))
        if "headings" in u:
            eops = eops.at[:, 5].add(np.pi * (2 * jax.nn.sigmoid(u["headings"]) - 1))
        d = dataclasses.replace(d, eops=eops)
        if "targets" in u:
            lo, hi = self._target_bounds()
            X = lo + (hi - lo) * jax.nn.sigmoid(u["targets"])
            on_face = jax.nn.one_hot(self.faces, 3, dtype=bool)
            d = dataclasses.replace(d, targets=jnp.where(on_face, d.targets, X))
        return d


@dataclasses.dataclass(frozen=True, eq=False)
class DesignOptimisation:
    """Result of :func:`optimize_design`.

    ``design``: the best design found; ``value``: its exact criterion (hard max); ``start_value``:
    that of the start design; ``values`` (starts,): the best exact value of every start, with
    ``designs`` their designs; ``history`` (steps, starts): the smooth criterion along the
    descent; ``criterion``: what was minimised, in words; timings in seconds.
    """

    design: object
    value: float
    start_value: float
    values: np.ndarray
    designs: tuple
    history: np.ndarray
    criterion: str
    compile_s: float
    run_s: float

    def to_dict(self) -> dict:
        """Strict-JSON data (non-finite values as None): ``criterion``, ``value``,
        ``start_value``, ``values_per_start`` (dimensionless criterion values), ``stations_m``
        (s, 3) [m], ``omega_deg``, ``phi_deg``, ``kappa_deg`` (s,) [deg], ``compile_s``,
        ``run_s`` [s]."""
        eops = np.asarray(self.design.eops)
        return to_json_value(
            {
                "criterion": self.criterion,
                "value": float(self.value),
                "start_value": float(self.start_value),
                "values_per_start": [float(v) for v in self.values],
                "stations_m": eops[:, :3].tolist(),
                "omega_deg": (eops[:, 3] / DEG).tolist(),
                "phi_deg": (eops[:, 4] / DEG).tolist(),
                "kappa_deg": (eops[:, 5] / DEG).tolist(),
                "compile_s": self.compile_s,
                "run_s": self.run_s,
            }
        )

    def summary(self) -> str:
        """Text: the criterion, its value at the start and at the best design, and the best
        design's stations [m] and attitudes [deg]."""
        eops = np.asarray(self.design.eops)
        lines = [
            f"Design optimisation: {self.criterion}",
            f"criterion {self.start_value:.4g} at the start -> {self.value:.4g} at the best of "
            f"{len(self.values)} starts; compile {self.compile_s:.1f} s, run {self.run_s:.1f} s",
            f"{'scan':>5} {'X [m]':>8} {'Y [m]':>8} {'Z [m]':>8} "
            f"{'omega [deg]':>11} {'phi [deg]':>9} {'kappa [deg]':>11}",
        ]
        for j, e in enumerate(eops):
            lines.append(
                f"S{j + 1:<4d} {e[0]:8.3f} {e[1]:8.3f} {e[2]:8.3f} "
                f"{e[3] / DEG:11.2f} {e[4] / DEG:9.2f} {e[5] / DEG:11.2f}"
            )
        return "\n".join(lines)


def optimize_design(
    design_network,
    criterion: DesignCriterion | None = None,
    space: DesignSpace | None = None,
    *,
    starts: int = 8,
    steps: int = 150,
    learning_rate: float = 0.1,
    seed: int = 0,
    progress: bool = True,
) -> DesignOptimisation:
    """Minimise ``criterion`` of the predicted AP covariance over ``space`` (module docstring).

    ``design_network``: a :class:`~tlsjax.DesignProblem` (its design is the start and fixes the
    number of scans and targets; build it with ``smooth_visibility=True`` to honour a field of
    view and an incidence limit). ``starts`` random starts (the first is the start design),
    ``steps`` Adam steps each, all starts in one vmapped compiled step; ``progress`` shows a bar
    with the best value so far. Returns a :class:`DesignOptimisation`; verify its design with an
    independent :func:`tlsjax.calibrate` of ``design_network.network(result.design, seed=...)``.

    (Long because the compiled descent step is defined inside it, closed over the design and the
    criterion, so that it compiles once per call.)
    """
    dn = design_network
    criterion = criterion or DesignCriterion()
    space = space or DesignSpace()
    if starts < 1 or steps < 1:
        raise ValueError(f"starts and steps must be >= 1, got {starts} and {steps}")
    param = Parametrisation.build(dn, space)
    spec, names = dn.template.plan.spec, dn.template.plan.ap_labels
    criterion.smooth(jnp.eye(spec.r), spec.n_scans, names)  # validates the criterion's APs
    rng = np.random.default_rng(seed)
    # The start design, nudged (a start on a singular design, e.g. a hybrid scanner with every
    # scan levelled, has no finite gradient), then random starts.
    u0 = jax.tree.map(lambda a: a + 0.05 * rng.standard_normal(a.shape), param.initial())
    U = [u0] + [param.random(rng) for _ in range(starts - 1)]
    U = jax.tree.map(lambda *a: jnp.stack(a), *U)
    loss = lambda u: criterion.smooth(predicted_cofactor(dn, param.design(u)), spec.n_scans, names)
    import optax  # here, not at import: it takes longer to import than tlsjax's core
    from tqdm.auto import tqdm

    opt = optax.adam(learning_rate)

    @jit
    def step(U, state):
        vals, grads = jax.vmap(jax.value_and_grad(loss))(U)
        ok = jnp.isfinite(vals)
        grads = jax.tree.map(
            lambda g: jnp.where(ok.reshape((-1,) + (1,) * (g.ndim - 1)) & jnp.isfinite(g), g, 0.0),
            grads,
        )
        updates, state = jax.vmap(opt.update)(grads, state, U)
        return jnp.where(ok, vals, jnp.inf), optax.apply_updates(U, updates), state

    state = jax.vmap(opt.init)(U)
    t0 = time.perf_counter()
    step.lower(U, state).compile()
    compile_s = time.perf_counter() - t0
    best_vals = np.full(starts, np.inf)
    best_U = U
    history = []
    t0 = time.perf_counter()
    bar = tqdm(range(steps), disable=not progress, desc="design", leave=False)
    for _ in bar:
        vals, U_next, state = step(U, state)
        vals = np.asarray(vals)
        better = vals < best_vals
        best_U = jax.tree.map(
            lambda b, u, better=better: jnp.where(
                better.reshape((-1,) + (1,) * (u.ndim - 1)), u, b
            ),
            best_U,
            U,
        )
        best_vals = np.where(better, vals, best_vals)
        history.append(vals)
        bar.set_postfix(best=f"{best_vals.min():.4g}")
        U = U_next
    run_s = time.perf_counter() - t0
    designs = tuple(param.design(jax.tree.map(lambda a, k=k: a[k], best_U)) for k in range(starts))
    cofactor = jit(lambda d: predicted_cofactor(dn, d))
    exact = np.array([_exact(cofactor(d), criterion, spec, names) for d in designs])
    k = int(np.nanargmin(np.where(np.isfinite(exact), exact, np.inf)))
    return DesignOptimisation(
        design=designs[k],
        value=float(exact[k]),
        start_value=_exact(cofactor(dn.design), criterion, spec, names),
        values=exact,
        designs=designs,
        history=np.array(history),
        criterion=criterion.describe(names),
        compile_s=compile_s,
        run_s=run_s,
    )


def _exact(Q, criterion, spec, names) -> float:
    v = criterion.exact(Q, spec.n_scans, names)
    return v if np.isfinite(v) else np.inf
