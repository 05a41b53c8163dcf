"""Batched Monte Carlo self-calibration of one network design (SPEC section 9).

N realisations of a simulated design are drawn and each is adjusted by the engine of
:func:`tlsjax.calibrate` (:func:`tlsjax._adjustment._calibrate.estimate`: the same
Gauss-Newton/Levenberg-Marquardt loop, normal equations, Schur reduction, rank test, datum,
convergence test and result codes), as one compiled computation: ``vmap`` over realisations,
in chunks of a fixed size (one compile per design, never one per chunk), sharded over every JAX
device along the batch axis by :mod:`._batch`. So Monte Carlo works for every design that
``calibrate`` accepts: partial visibility, several instruments, control points and scale bars,
planes, targets and planes combined (:class:`tlsjax.SimulationTruth`).

Realisation k draws from ``fold_in(PRNGKey(seed), k)`` (so its result does not depend on the
chunk size or on the number of devices):

* observations ``l = F + e + Delta(l; AP_true)`` (the fixed point of
  :func:`tlsjax._model._points.distorted_observations`), ``F`` the error-free observation of
  the truth (for a plane row, of the true point on the plane), ``e ~ N(0, Sigma_l)`` with the
  network's sigmas;
* levelling readings, observed kappas, AP priors, control-point coordinates and scale-bar
  lengths: truth plus noise of their sigmas (they are observations too);
* optionally the true APs, drawn ``N(true, sigma^2)`` (``MonteCarloOptions.ap_sigma``).

Each realisation starts from the truth (the standard Monte Carlo choice: the estimator's
sampling distribution does not depend on the start, and 2-3 iterations suffice) and returns
what is estimable and small: the APs, their covariance ``s0^2 Q_aa``, ``s0^2`` and the result
code. A failed realisation returns its code and NaN estimates; it never stops the batch.

Empirical precision (Lichti 2008): from the N estimates, the scatter of each AP, its bias
against the truth, the ratio of empirical to formal sigma, and the power (share of
realisations with ``|t| > t_crit``).
"""

from __future__ import annotations

import dataclasses
import functools
import weakref
from collections.abc import Mapping

import jax
import jax.numpy as jnp
import numpy as np

from .._adjustment._calibrate import Adjustment, estimate, result_code
from .._adjustment._chord import DesignFactorisation, chord_adjust, design_factorisation
from .._adjustment._config import CalibrationModel, SolverOptions
from .._adjustment._families import Params, on_grid
from .._adjustment._quality import Summary
from .._adjustment._result import MAX_ITERATIONS, NOT_ESTIMABLE, RESULT_MESSAGES, SUCCESS
from .._jit import Background, jit
from .._model._aps import ap_corrections, on_reregistration
from .._model._levelling import compensator_reading
from .._model._points import FIXED_POINT_ITERATIONS, distorted_observations
from .._pytree import Module, field
from .._stats import t_critical_value
from .._summary import Settings, to_json_value
from .._units import display_unit
from ._batch import auto_chunk, compile_batched, device_key, round_chunk, run_batched
from ._design import NetworkDesign, simulate_design
from ._truth import SimulationTruth


@dataclasses.dataclass(frozen=True)
class MonteCarloOptions(Settings):
    """Settings of :func:`monte_carlo`.

    ``runs``: number of realisations N. ``chunk_size``: realisations per compiled call
    (rounded up to a multiple of the device count; default None: as many per device as keep
    the Jacobian rows near 4 MB, a measured choice, see :data:`._batch.DEVICE_WORKING_SET`).
    ``seed``: realisation k uses ``fold_in(PRNGKey(seed), k)``. ``ap_sigma``: optional
    {AP name: sigma [SI]}; each realisation's true AP is then drawn ``N(true, sigma^2)`` (for
    every instrument that has the term). ``max_iterations``, ``tolerance``: those of
    :class:`tlsjax.SolverOptions` (the same convergence test as :func:`tlsjax.calibrate`: the
    largest Gauss-Newton update below ``tolerance`` a posteriori sigmas). ``t_test_level``:
    two-sided level of the AP t-test whose power is reported. ``progress``: tqdm bar.
    """

    runs: int = 1000
    chunk_size: int | None = None
    seed: int = 0
    ap_sigma: Mapping[str, float] | None = None
    max_iterations: int = 10
    tolerance: float = 1e-6
    t_test_level: float = 0.05
    progress: bool = True

    def __post_init__(self):
        if int(self.runs) < 1:
            raise ValueError(f"MonteCarloOptions.runs must be >= 1, got {self.runs}")
        if self.chunk_size is not None and int(self.chunk_size) < 1:
            raise ValueError(f"MonteCarloOptions.chunk_size must be >= 1, got {self.chunk_size}")
        if int(self.max_iterations) < 1:
            raise ValueError(
                f"MonteCarloOptions.max_iterations must be >= 1, got {self.max_iterations}"
            )
        if not (self.tolerance > 0):
            raise ValueError(f"MonteCarloOptions.tolerance must be positive, got {self.tolerance}")
        if not (0 < self.t_test_level < 1):
            raise ValueError(
                f"MonteCarloOptions.t_test_level must be in (0, 1), got {self.t_test_level}"
            )

    def solver(self) -> SolverOptions:
        return SolverOptions(
            max_iterations=int(self.max_iterations),
            tolerance=float(self.tolerance),
            full_covariance=False,
        )


# ----------------------------------------------------------------------------------------
# The simulator: host-side constants of one truth, and the draw of one realisation


def _truth_of(simulation) -> SimulationTruth:
    if isinstance(simulation, SimulationTruth):
        return simulation
    if isinstance(simulation, NetworkDesign):  # the one design description: its geometry of seed 0
        return simulate_design(simulation).truth()
    if hasattr(simulation, "truth"):
        return simulation.truth()
    raise ValueError(
        "monte_carlo: give a tlsjax.NetworkDesign, a tlsjax.Simulation, a tlsjax.PointClouds, "
        "a tlsjax.DesignSimulation or a SimulationTruth "
        f"(e.g. clouds.truth(max_points=...)), got {type(simulation).__name__}"
    )


class _Simulator(Module):
    """Everything a realisation is drawn from, as arrays (network row order), and the static
    AP blocks of the instruments that generate the data."""

    F_t: jax.Array  # (n, 3) error-free observations of the target rows
    F_p: jax.Array  # (m, 3) of the plane rows (true points)
    sig_t: jax.Array
    sig_p: jax.Array
    inst_t: jax.Array  # (n,) instrument of each row
    inst_p: jax.Array
    lev_true: jax.Array  # (s, 2) compensator readings of the true poses
    lev_sigma: jax.Array  # (s, 2), 0 where not levelled
    lev_given: jax.Array  # (s, 2) the network's values (kept where not levelled)
    ctrl_true: jax.Array
    ctrl_sigma: jax.Array
    bar_true: jax.Array
    bar_sigma: jax.Array
    true_aps: jax.Array  # all instruments' true APs, concatenated
    draw_sigma: jax.Array
    scanners: tuple = field(static=True)
    slices: tuple = field(static=True)  # per instrument (start, stop) in true_aps
    iterations: int = field(static=True, default=FIXED_POINT_ITERATIONS)

    def draw(self, key):
        """Observations, levelling, control coordinates, bar lengths and true APs of one
        realisation (see the module docstring)."""
        k_t, k_p, k_l, k_c, k_b, k_a = jax.random.split(key, 6)
        true_aps = self.true_aps + jax.random.normal(k_a, self.true_aps.shape) * self.draw_sigma
        l_t = self._observe(self.F_t, self.sig_t, self.inst_t, true_aps, k_t)
        l_p = self._observe(self.F_p, self.sig_p, self.inst_p, true_aps, k_p)
        noise = lambda k, s: jax.random.normal(k, s.shape) * s
        lev = jnp.where(
            self.lev_sigma > 0, self.lev_true + noise(k_l, self.lev_sigma), self.lev_given
        )
        ctrl = self.ctrl_true + noise(k_c, self.ctrl_sigma)
        bar = self.bar_true + noise(k_b, self.bar_sigma)
        return l_t, l_p, lev, ctrl, bar, true_aps

    def expected(self):
        """The noise-free realisation at the true APs: observations with the AP corrections
        applied, levelling readings, control coordinates and bar lengths of the truth (the
        point the design's shared factorisation is linearised at)."""
        l_t = self._observe(self.F_t, self.sig_t, self.inst_t, self.true_aps, None)
        l_p = self._observe(self.F_p, self.sig_p, self.inst_p, self.true_aps, None)
        lev = jnp.where(self.lev_sigma > 0, self.lev_true, self.lev_given)
        return l_t, l_p, lev, self.ctrl_true, self.bar_true, self.true_aps

    def _observe(self, F, sigma, inst, true_aps, key):
        """``l = F + e + Delta(l)``; without a key, e = 0."""
        if F.shape[0] == 0:
            return F

        def correction(l):
            out = jnp.zeros_like(l)
            for i, (sc, (a, b)) in enumerate(zip(self.scanners, self.slices)):
                d = ap_corrections(true_aps[a:b], sc.aps, l, sc) if sc.aps else 0.0
                out = jnp.where((inst == i)[:, None], d, out)
            return out

        base = F if key is None else F + jax.random.normal(key, F.shape) * sigma
        # Stops where the draw has settled: the bound of _fixed_point_iterations is
        # pessimistic (no cancellation between the terms), and this loop runs in every
        # realisation (about a fifth of a Chow-room Monte Carlo's kernel time at the bound's 20;
        # 3 iterations settle it).
        return distorted_observations(base, correction, self.iterations, until_settled=True)


def _simulator(truth: SimulationTruth, ap_sigma) -> _Simulator:
    net = truth.network
    F_t, F_p = truth.error_free()
    slices, off = [], 0
    for sc in truth.scanners:
        slices.append((off, off + len(sc.aps)))
        off += len(sc.aps)
    true_vals = np.concatenate([truth.ap_vector(i) for i in range(len(truth.scanners))] + [[]])
    draw = np.zeros(off)
    names = [a for sc in truth.scanners for a in sc.aps]
    for name, s in dict(ap_sigma or {}).items():
        if name not in names:
            raise ValueError(
                f"MonteCarloOptions.ap_sigma: AP {name!r} is not in the simulated data ({' '.join(dict.fromkeys(names))})"
            )
        if not (np.isfinite(s) and s >= 0):
            raise ValueError(
                f"MonteCarloOptions.ap_sigma[{name!r}] must be a non-negative number, got {s}"
            )
        draw[[k for k, n in enumerate(names) if n == name]] = s
    iterations = _fixed_point_iterations(truth, F_t, F_p, true_vals + 6 * draw, slices)
    levelled = np.isfinite(net.levelling_sigma)
    lev_true = compensator_reading(np.asarray(truth.eops), np)
    X = truth.targets
    bars = net.scale_bar_targets
    return _Simulator(
        F_t=jnp.asarray(F_t),
        F_p=jnp.asarray(F_p),
        sig_t=jnp.asarray(net.sigmas),
        sig_p=jnp.asarray(net.plane_sigmas),
        inst_t=jnp.asarray(net.instrument_of_scan[net.scan_index]),
        inst_p=jnp.asarray(net.instrument_of_scan[net.plane_scan_index]),
        lev_true=jnp.asarray(lev_true),
        lev_sigma=jnp.asarray(np.where(levelled, net.levelling_sigma, 0.0)),
        lev_given=jnp.asarray(net.levelling),
        ctrl_true=jnp.asarray(X[net.control_index].reshape(-1, 3)),
        ctrl_sigma=jnp.asarray(net.control_sigma.reshape(-1, 3)),
        bar_true=jnp.asarray(np.linalg.norm(X[bars[:, 0]] - X[bars[:, 1]], axis=1)),
        bar_sigma=jnp.asarray(net.scale_bar_sigma.reshape(-1)),
        true_aps=jnp.asarray(true_vals),
        draw_sigma=jnp.asarray(draw),
        scanners=tuple(sc.current() for sc in truth.scanners),
        slices=tuple(slices),
        iterations=iterations,
    )


@functools.partial(jit, static_argnums=0)
def _contraction(scanner, aps, rows):
    """``max |d Delta / d l|`` (row sums) over ``rows``: per term, sum_k |a_k| |d basis_k /
    d l| bounds it (no cancellation). Compiled once per scanner (its hash holds the registry's
    tokens) and shape: dispatched eagerly, its Jacobians were a hundred operations per call."""

    def jac(c):
        return jax.vmap(jax.jacfwd(lambda l: ap_corrections(c, scanner.aps, l, scanner)))(rows)

    J = jax.vmap(jac)(jnp.eye(len(scanner.aps)))
    return jnp.max(jnp.einsum("k,kmij->mi", jnp.abs(aps), jnp.abs(J)))


def _fixed_point_iterations(truth, F_t, F_p, aps, slices) -> int:
    """Iterations of the fixed point ``l = base + Delta(l)`` that reach float64 rounding for
    this design: it contracts by ``q = max |d Delta / d l|`` (row sums, at the error-free
    observations, with the APs at their truth plus six draw sigmas), so ``log(eps) / log(q)``
    iterations and two more for the noise. The default 30 covers q up to 0.2 (cyclic range
    terms); the physical terms have q ~ 1e-3 and need 7. The draws stop earlier where they
    have settled (:func:`tlsjax._model._points.distorted_observations`, ``until_settled``):
    the bound takes no cancellation between the terms into account, and is their cap."""
    net = truth.network
    q = 0.0
    for F, scan in ((F_t, net.scan_index), (F_p, net.plane_scan_index)):
        inst = net.instrument_of_scan[scan]
        for i, (sc, (a, b)) in enumerate(zip(truth.scanners, slices)):
            rows = F[inst == i]
            if not len(rows) or not sc.aps:
                continue
            q = max(q, float(_contraction(sc, np.asarray(aps[a:b]), np.asarray(rows))))
    if not 0.0 < q < 0.5:
        return FIXED_POINT_ITERATIONS
    need = int(np.ceil(np.log(np.finfo(np.float64).eps) / np.log(q))) + 2
    return int(min(max(need, 3), FIXED_POINT_ITERATIONS))


# ----------------------------------------------------------------------------------------
# The design: the simulator and the engine's analysed adjustment of the network


@dataclasses.dataclass(frozen=True, eq=False)
class _Design:
    truth: SimulationTruth
    simulator: _Simulator
    adjustment: Adjustment
    start: Params  # the truth, arranged as the engine's parameters (APs set per realisation)
    truth_map: np.ndarray  # (a,) index of each estimated AP into the true APs, -1 when absent


def _default_model(truth: SimulationTruth) -> CalibrationModel:
    net = truth.network
    if len(net.instruments) == 1:
        return CalibrationModel(truth.scanners[0])
    return CalibrationModel(dict(zip(net.instruments, truth.scanners)))


def _design(simulation, model: CalibrationModel | None, ap_sigma) -> _Design:
    truth = _truth_of(simulation)
    net = truth.network
    model = model or _default_model(truth)
    adj = Adjustment(net, model, SolverOptions(full_covariance=False))
    plan = adj.plan
    sim = _simulator(truth, ap_sigma)
    tmap = []
    for i, (ins, names) in enumerate(zip(net.instruments, plan.spec.ap_names)):
        data = truth.scanners[i]
        if plan.spec.scanners[i].architecture != data.architecture:
            raise ValueError(
                f"monte_carlo: the model's scanner of instrument {ins} is "
                f"{plan.spec.scanners[i].architecture!r} but the data are {data.architecture!r}"
            )
        a0 = sim.slices[i][0]
        tmap += [a0 + data.aps.index(a) if a in data.aps else -1 for a in names]
    prims = [jnp.asarray(truth.targets[tg].reshape(len(tg), -1)) for tg in plan.family_targets]
    if net.has_planes:
        prims.append(jnp.asarray(truth.planes))
    start = Params(tuple(prims), jnp.asarray(truth.eops), jnp.zeros(plan.spec.n_aps))
    return _Design(truth, sim, adj, start, np.asarray(tmap, dtype=np.int64))


def _estimated_truth(design: _Design, true_aps):
    """The true value of each estimated AP (0 where the data have no such term)."""
    tmap = design.truth_map
    return jnp.where(tmap >= 0, true_aps[np.maximum(tmap, 0)], 0.0) if len(tmap) else true_aps[:0]


def _problem_and_start(design: _Design, drawn, key=None):
    """The engine's problem of one drawn (or expected) realisation and its start, the truth;
    with ``key`` its observed kappas and AP priors drawn too (:func:`_drawn_constraints`)."""
    l_t, l_p, lev, ctrl, bar, true_aps = drawn
    problem = design.adjustment.with_data(
        observations=l_t, plane_observations=l_p, levelling=lev, control_xyz=ctrl, bar_length=bar
    )
    truth = _estimated_truth(design, true_aps)
    if key is not None:
        problem = _drawn_constraints(problem, design.start.eops, truth, key)
    return problem, Params(design.start.prims, design.start.eops, truth), truth


def _draw(design: _Design, index, seed_key):
    """Realisation ``index``: its problem and start (:func:`_problem_and_start`)."""
    drawn = design.simulator.draw(jax.random.fold_in(seed_key, index))
    key = jax.random.fold_in(jax.random.fold_in(seed_key, index), 1)
    return _problem_and_start(design, drawn, key)


@functools.partial(jit, static_argnums=0)
def _factorise(spec, problem, params, rank_tolerance):
    return design_factorisation(spec, on_grid(problem), params, rank_tolerance)


def _design_factorisation(design: _Design) -> DesignFactorisation:
    """The design's shared factorisation (:mod:`tlsjax._adjustment._chord`): its normal
    matrix at the truth, linearised at the noise-free observations with the true APs applied."""
    problem, params, _ = _problem_and_start(design, design.simulator.expected())
    spec = design.adjustment.plan.spec
    return _factorise(spec, problem, params, SolverOptions().arrays().rank_tolerance)


def _outputs(spec, problem, truth, aps, s, code, iterations):
    """What a realisation returns: estimable and small (module docstring)."""
    s0sq = s.vtpv / s.dof
    good = (code == SUCCESS) | (code == NOT_ESTIMABLE)
    n6 = 6 * spec.n_scans
    keep = good & ~(s.dependent[n6:] & ~problem.fixed[n6:])
    return {
        "true_aps": truth,
        "ap_values": jnp.where(keep, aps, jnp.nan),
        "ap_covariance": jnp.where(keep[:, None] & keep[None, :], s.Qaa * s0sq, jnp.nan),
        "sigma0_sq": jnp.where(good, s0sq, jnp.nan),
        "dof": s.dof,
        "iterations": iterations,
        "result": code,
    }


def _realisation(design: _Design, index, seed_key, options, fact: DesignFactorisation):
    """Draw realisation ``index`` and adjust it from the truth by the chord method on the
    design's factorisation (:mod:`tlsjax._adjustment._chord`)."""
    problem, params0, truth = _draw(design, index, seed_key)
    spec = design.adjustment.plan.spec
    state = chord_adjust(spec, on_grid(problem), params0, fact, options)
    s = Summary(state.cost, fact.dof, fact.Qaa, fact.dependent)
    code = result_code(spec, problem, state, s)
    return _outputs(spec, problem, truth, state.params.aps, s, code, state.iteration)


def _full_realisation(design: _Design, index, seed_key, options):
    """Realisation ``index`` adjusted by the full Gauss-Newton loop of calibrate (for those the
    chord method does not converge on)."""
    problem, params0, truth = _draw(design, index, seed_key)
    spec = design.adjustment.plan.spec
    state, s, code = estimate(spec, problem, params0, options)
    return _outputs(spec, problem, truth, state.params.aps, s, code, state.iteration)


def _drawn_constraints(problem, eops, true_aps, key):
    """The observed kappas and AP priors of one realisation (weighted constraints with observed
    values, SPEC section 6): the truth plus noise of their sigmas (the network's headings, the
    model's priors), so that they are observations like the others."""
    if problem.heading_weight is None or problem.ap_prior_weight is None:
        return problem
    k_h, k_a = jax.random.split(key)
    sigma = lambda w: jnp.where(w > 0, 1.0 / jnp.where(w > 0, w, 1.0), 0.0)
    hw, aw = problem.heading_weight, problem.ap_prior_weight
    heading = eops[:, 5] + jax.random.normal(k_h, hw.shape) * sigma(hw)
    prior = true_aps + jax.random.normal(k_a, aw.shape) * sigma(aw)
    return dataclasses.replace(
        problem,
        heading=jnp.where(hw > 0, heading, problem.heading),
        ap_prior=jnp.where(aw > 0, prior, problem.ap_prior),
    )


# Compiled chunk functions per (simulation, model, AP draw sigmas, chunk, devices): the seed and
# the solver settings are traced arguments, so changing them never recompiles.
_COMPILED: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
# A simulation's own scanner may predate a re-registered AP: empty the cache then.
on_reregistration(_COMPILED.clear)


class _InBackground(Background):
    """``fun()`` computed in the background (:class:`tlsjax._jit.Background`), the shapes of its
    result known at once (``jax.eval_shape``: a trace that the call reuses). The design's
    factorisation is computed this way while the chunk program, which needs only its shapes,
    is compiled: a first Monte Carlo call waits for the two programs' compiles side by side
    with the trace instead of one after the other (the Chow room: about 0.5 of 4.8 s)."""

    def __init__(self, fun):
        self.shapes = jax.eval_shape(fun)
        super().__init__(fun)


def _cached_design(simulation, model, ap_sigma):
    # repr: a model with several instruments holds a dict of scanners (unhashable).
    dkey = (repr(model), tuple(sorted(dict(ap_sigma or {}).items())))
    cache = _COMPILED.setdefault(simulation, {})
    if dkey not in cache:
        design = _design(simulation, model, ap_sigma)
        cache[dkey] = (design, _InBackground(lambda: _design_factorisation(design)))
    return cache, dkey


def _compiled_chunk(simulation, model, ap_sigma, chunk_size: int | None, runs: int, full=False):
    """(design, its factorisation, the compiled chunk function): the chord method, or with
    ``full`` the full Gauss-Newton loop."""
    cache, dkey = _cached_design(simulation, model, ap_sigma)
    design, fact = cache[dkey]
    if chunk_size is None:
        chunk = auto_chunk(_row_bytes(design.adjustment.plan), runs)
    else:
        chunk = round_chunk(chunk_size)
    key = dkey + (chunk, device_key(), full)
    pending = isinstance(fact, _InBackground)
    if key in cache:
        b = dataclasses.replace(cache[key], compile_s=0.0)
    else:
        constants = (jax.random.PRNGKey(0), SolverOptions().arrays())
        if full:
            one = lambda i, k, o: _full_realisation(design, i, k, o)
        else:
            # Compiled on the factorisation's shapes, while it is computed (_InBackground).
            one = lambda i, k, o, f: _realisation(design, i, k, o, f)
            constants += (fact.shapes if pending else fact,)
        b = cache[key] = compile_batched(one, constants, chunk)
    if pending:
        fact = fact.result()
        cache[dkey] = (design, fact)
    return design, fact, b


def _row_bytes(plan) -> float:
    """Bytes of one realisation's whitened Jacobian rows (primitive, pose and AP columns)."""
    cols = 6 + plan.spec.n_aps
    return 8.0 * sum(f.obs.shape[0] * f.rows * (f.p + cols) for f in plan.problem.families)


# ----------------------------------------------------------------------------------------
# Public entry point and result


@dataclasses.dataclass(frozen=True, eq=False)
class MonteCarloResult:
    """Result of :func:`monte_carlo`. SI units (m, rad, dimensionless) in the arrays.

    Per realisation (N rows): ``true_aps`` (N, a) the truth of each estimated AP (0 where the
    data have no such term), ``ap_values`` (N, a), ``ap_sigmas`` (N, a) formal a posteriori
    sigmas (scaled by s0^2), ``ap_covariance`` (N, a, a), ``sigma0_sq`` (N,), ``iterations``,
    ``result`` (result codes, :data:`tlsjax.RESULT_MESSAGES`). Failed realisations keep their
    code and have NaN estimates; the statistics use the successful ones.
    """

    ap_names: tuple
    ap_units: tuple
    true_aps: np.ndarray
    ap_values: np.ndarray
    ap_sigmas: np.ndarray
    ap_covariance: np.ndarray
    sigma0_sq: np.ndarray
    iterations: np.ndarray
    result: np.ndarray
    dof: int
    t_test_level: float
    seed: int
    chunk_size: int
    n_devices: int
    compile_s: float  # 0 when the compiled function was reused
    run_s: float

    @property
    def runs(self) -> int:
        return int(self.result.shape[0])

    @property
    def ok(self) -> np.ndarray:
        return self.result == SUCCESS

    def failures(self) -> dict:
        """{message: count} of the realisations that did not succeed."""
        codes, counts = np.unique(self.result[~self.ok], return_counts=True)
        return {RESULT_MESSAGES[int(c)]: int(n) for c, n in zip(codes, counts)}

    def _statistics(self) -> dict:
        """Empirical precision per AP (Lichti 2008), SI units, NaN where undefined (the data
        of :meth:`to_dict`, of :meth:`table` and of the old ``summary()``)."""
        ok = self.ok
        n = int(ok.sum())
        v = self.ap_values[ok]
        s = self.ap_sigmas[ok]
        t_crit = t_critical_value(self.t_test_level, self.dof)
        out = {
            "runs": self.runs,
            "successful": n,
            "failures": self.failures(),
            "dof": self.dof,
            "sigma0_sq_mean": float(np.mean(self.sigma0_sq[ok])) if n else float("nan"),
            "sigma0_sq_std": float(np.std(self.sigma0_sq[ok], ddof=1)) if n > 1 else float("nan"),
            "t_critical": t_crit,
            "aps": {},
        }
        for k, name in enumerate(self.ap_names):
            emp = float(np.std(v[:, k], ddof=1)) if n > 1 else float("nan")
            formal = float(np.sqrt(np.mean(s[:, k] ** 2))) if n else float("nan")
            out["aps"][name] = {
                "unit": self.ap_units[k],
                "truth_mean": float(np.mean(self.true_aps[ok, k])) if n else float("nan"),
                "mean": float(np.mean(v[:, k])) if n else float("nan"),
                "bias": float(np.mean(v[:, k] - self.true_aps[ok, k])) if n else float("nan"),
                "empirical_sigma": emp,
                "formal_sigma": formal,
                "ratio": emp / formal if formal > 0 else float("nan"),
                "power": float(np.mean(np.abs(v[:, k] / s[:, k]) > t_crit)) if n else float("nan"),
            }
        return out

    def to_dict(self) -> dict:
        """Strict-JSON data (undefined values as None): ``runs``, ``successful``, ``failures``
        ({message: count}), ``dof``, ``sigma0_sq_mean``, ``sigma0_sq_std``, ``t_critical`` and
        per AP in ``aps``: ``unit``, ``truth_mean``, ``mean``, ``bias``, ``empirical_sigma``,
        ``formal_sigma`` (SI units), ``ratio`` (empirical / formal; its own sampling sigma is
        about ``1/sqrt(2 (N - 1))``) and ``power`` (share of realisations with
        ``|t| > t_crit`` at ``t_test_level``). Lichti (2008)."""
        return to_json_value(self._statistics())

    def summary(self) -> str:
        """Text: a header line and :meth:`table`."""
        head = (
            f"Monte Carlo of {self.runs} realisations (seed {self.seed}, t-test level {self.t_test_level:g}); "
            f"compile {self.compile_s:.1f} s, run {self.run_s:.2f} s"
        )
        return head + "\n" + self.table()

    def table(self) -> str:
        """Text table of the empirical precision per AP in mm, arc seconds and ppm."""
        sm = self._statistics()
        lines = [
            f"Monte Carlo: {sm['successful']} of {sm['runs']} realisations converged; dof {sm['dof']}; "
            f"mean s0^2 = {sm['sigma0_sq_mean']:.4f} (std {sm['sigma0_sq_std']:.4f})",
            f"{'AP':5s} {'unit':>4s} {'truth':>10s} {'bias':>10s} {'emp. sigma':>11s} {'formal sigma':>12s} {'emp/formal':>10s} {'power':>6s}",
        ]
        for name, a in sm["aps"].items():
            f, u = display_unit(a["unit"])
            lines.append(
                f"{name:5s} {u:>4s} {a['truth_mean'] * f:10.4f} {a['bias'] * f:10.4f} {a['empirical_sigma'] * f:11.4f} "
                f"{a['formal_sigma'] * f:12.4f} {a['ratio']:10.3f} {a['power']:6.3f}"
            )
        if sm["failures"]:
            lines.append("failures: " + "; ".join(f"{m}: {n}" for m, n in sm["failures"].items()))
        return "\n".join(lines)


def monte_carlo(
    simulation, model: CalibrationModel | None = None, options: MonteCarloOptions | None = None
) -> MonteCarloResult:
    """Simulate and self-calibrate N realisations of one network design as one compiled batch.

    ``simulation``: a :class:`tlsjax.NetworkDesign` (the network :func:`tlsjax.simulate_design`
    draws from it with seed 0; the noise is drawn from its a priori sigmas), a
    :class:`tlsjax.DesignSimulation`, a :class:`tlsjax.Simulation` (targets), a
    :class:`tlsjax.PointClouds` (planes; all its points), or a :class:`tlsjax.SimulationTruth` (any design, e.g.
    ``clouds.truth(max_points=50)`` or a target and a plane truth combined). ``model``: the
    calibration model whose APs are estimated (default: the data's scanners). Realisation k:
    ``l = F(X, EOP) + Delta(l; AP_true) + e``, ``e ~ N(0, Sigma_l)`` drawn from
    ``fold_in(PRNGKey(seed), k)``, then the adjustment of :func:`tlsjax.calibrate` (Chow et al.
    2013, eqs. 1-6; Gauss-Helmert planes) started from the truth, vmapped over realisations. A
    failed realisation returns its result code and NaN estimates; it never stops the batch.
    Lichti (2008) for the empirical-precision analysis.
    """
    options = options or MonteCarloOptions()
    design, fact, b = _compiled_chunk(
        simulation, model, options.ap_sigma, options.chunk_size, int(options.runs)
    )
    chunk = b.chunk
    constants = (jax.random.PRNGKey(int(options.seed)), options.solver().arrays())
    res, run_s = run_batched(
        b,
        int(options.runs),
        constants + (fact,),
        desc="Monte Carlo chunks",
        progress=options.progress,
    )
    compile_s = b.compile_s
    # The realisations the chord method does not converge on: the full loop of calibrate.
    redo = np.flatnonzero(res["result"] == MAX_ITERATIONS)
    if len(redo):
        _, _, bf = _compiled_chunk(simulation, model, options.ap_sigma, chunk, len(redo), full=True)
        more, more_s = run_batched(
            bf, len(redo), constants, desc="full adjustments", progress=False, indices=redo
        )
        for k in res:
            res[k][redo] = more[k]
        run_s, compile_s = run_s + more_s, compile_s + bf.compile_s
    cov = res["ap_covariance"]
    sig = np.sqrt(np.clip(np.diagonal(cov, axis1=1, axis2=2), 0, None))
    plan = design.adjustment.plan
    ok = res["result"] == SUCCESS
    dof = res["dof"][ok] if ok.any() else res["dof"]
    return MonteCarloResult(
        ap_names=plan.ap_labels,
        ap_units=plan.ap_units,
        true_aps=res["true_aps"],
        ap_values=res["ap_values"],
        ap_sigmas=sig,
        ap_covariance=cov,
        sigma0_sq=res["sigma0_sq"],
        iterations=res["iterations"],
        result=res["result"],
        dof=int(round(float(np.median(dof)))),
        t_test_level=float(options.t_test_level),
        seed=int(options.seed),
        chunk_size=chunk,
        n_devices=jax.device_count(),
        compile_s=compile_s,
        run_s=run_s,
    )


@jit
def _draw_many(simulator, seed, indices):
    key = jax.random.PRNGKey(seed)  # in the program: no key made by an eager operation
    return jax.vmap(lambda i: simulator.draw(jax.random.fold_in(key, i)))(indices)


def monte_carlo_network(
    simulation, index, *, seed: int = 0, ap_sigma: Mapping[str, float] | None = None
):
    """The :class:`tlsjax.Network` of realisation ``index`` of :func:`monte_carlo` (same seed):
    the observations, levelling readings, control coordinates and scale-bar lengths it adjusts,
    for checks with :func:`tlsjax.calibrate`. Returns (network, true APs {label: value}, labels
    as the data's AP names, ``name[instrument]`` with several instruments); for a sequence of
    indices, a list of them."""
    truth = _truth_of(simulation)
    sim = _simulator(truth, ap_sigma)
    many = not np.isscalar(index)
    idx = np.atleast_1d(np.asarray(index, dtype=np.int64))
    draws = jax.tree.map(np.asarray, _draw_many(sim, np.int64(seed), idx))
    net = truth.network
    multi = len(net.instruments) > 1
    labels = [
        f"{a}[{ins}]" if multi else a
        for ins, sc in zip(net.instruments, truth.scanners)
        for a in sc.aps
    ]
    out = []
    for k in range(len(idx)):
        l_t, l_p, lev, ctrl, bar, true_aps = (a[k] for a in draws)
        new = dataclasses.replace(
            net.with_observations(l_t, l_p if net.has_planes else None),
            levelling=lev,
            control_xyz=ctrl.reshape(-1, 3),
            scale_bar_length=bar.reshape(-1),
        )
        out.append((new, dict(zip(labels, true_aps.tolist()))))
    return out if many else out[0]
