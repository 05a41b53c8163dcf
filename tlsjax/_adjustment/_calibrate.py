"""The entry points: ``calibrate(network, model, options)`` and the two-phase
``analyze(network, model, options).solve(...)``.

Host side: validate the configuration, build the index plan and the approximate values once
(:class:`Adjustment`), call the compiled adjustment (:mod:`._solver`) and quality
(:mod:`._quality`), and turn the arrays into a result with names, units and result codes
(:mod:`._result`). Variance component estimation, data snooping, AP selection and Monte Carlo
re-solve one analysed adjustment with other weights, masks, fixed APs or observations: the
compiled function is specialised on the plan's static spec and shapes only, so none of them
recompiles.
"""

from __future__ import annotations

import dataclasses
import functools
import warnings

import jax
import jax.numpy as jnp
import numpy as np

from .._jit import StoredProgram, jit
from .._model._aps import get_ap
from .._model._plausibility import PlausibilityWarning
from .._pytree import kept
from ._config import CalibrationModel, SolverOptions
from ._families import Params, grid_layout, on_grid
from ._network import Network, check_calibration_arguments, memoised, network_design_warnings
from ._plan import build_plan, initial_params
from ._quality import quality_from, summary_from
from ._result import CalibrationResult, _on_host, assemble, not_estimable_aps, result_code_of
from ._solver import adjust_linearised


@functools.partial(jit, static_argnums=(0, 4))
def _run(spec, problem, params0, options, full_covariance):
    """The compiled adjustment and its quality; pure in (problem, params0, options)."""
    grid = on_grid(problem)
    state, lin = adjust_linearised(spec, grid, params0, options)
    return state, quality_from(spec, problem, grid, state.params, lin, full_covariance)


@functools.cache
def _flat_run(spec, treedef, full_covariance: bool):
    """:func:`_run` as a compiled function of the flattened (problem, params0, options): a call
    then flattens no pytree of modules in Python (the dispatch of a compiled call with
    a few dozen arguments costs about 20 us instead of about 1 ms)."""

    def run(*leaves):
        problem, params0, options = jax.tree.unflatten(treedef, leaves)
        return _run(spec, problem, params0, options, full_covariance)

    # Stored traced (a re-run in a new process neither traces nor compiles it), keyed on what
    # it closes over: the spec with its AP terms, the arguments' structure, full_covariance;
    # its outputs come to the host in one transfer per dtype (``host``).
    key = ("adjustment", spec_key(spec), treedef, full_covariance)
    return StoredProgram(run, key, host=True)


def spec_key(spec) -> tuple:
    """What a program specialised on ``spec`` closes over besides tlsjax's code: the spec and
    its AP terms (a user's own term has no stable description: such a program is not stored,
    :class:`tlsjax._jit.StoredProgram`)."""
    return spec, tuple(get_ap(n) for names in spec.ap_names for n in names)


def estimate(spec, problem, params0, options):
    """The adjustment of :func:`_run` with only its estimable summary (:func:`._quality.summary`)
    and its result code, computed in the graph: what a batch of realisations (Monte Carlo)
    needs of each. Pure, so it can be vmapped; the codes are those of :func:`calibrate`."""
    grid = on_grid(problem)
    state, lin = adjust_linearised(spec, grid, params0, options)
    s = summary_from(spec, grid, state.params, lin, state.cost)
    return state, s, result_code(spec, problem, state, s)


def result_code(spec, problem, state, s):
    """:class:`ResultCode` of an adjustment as a traced integer (:func:`._result.result_code_of`,
    the one order of precedence of the codes)."""
    n6 = 6 * spec.n_scans
    free_dep = s.dependent & ~problem.fixed
    return result_code_of(
        finite=state.finite & jnp.isfinite(s.vtpv),
        rank_deficient=jnp.any(free_dep[:n6]),
        converged=state.converged,
        not_estimable=jnp.any(free_dep[n6:]),
    )


def _to_device(a: np.ndarray):
    """A host array on the device by a transfer (``jnp.asarray`` of a numpy array runs a small
    program of its own: an operation dispatched eagerly)."""
    return jax.device_put(a)


def _support(problem) -> bytes:
    """Which observations and constraints take part (nonzero weight) and which parameters are
    held: what decides estimability, as bytes to key on."""
    parts = [np.asarray(problem.fixed)]
    for family in problem.families:
        for field in dataclasses.fields(family):
            value = getattr(family, field.name)
            if field.name.endswith("weight") and value is not None:
                parts.append(np.asarray(value) != 0)
    for w in (problem.levelling_weight, problem.heading_weight, problem.ap_prior_weight):
        if w is not None:
            parts.append(np.asarray(w) != 0)
    return b"|".join(np.ascontiguousarray(x).tobytes() for x in parts)


def _hold_aps(problem, params0, held: np.ndarray, n6: int):
    """``problem`` with the APs ``held`` (a, bool) fixed, ``params0`` with them at zero."""
    fixed = np.asarray(problem.fixed).copy()
    fixed[n6:] |= held
    aps = np.where(held, 0.0, np.asarray(params0.aps))
    return _replace(problem, fixed=_to_device(fixed)), _replace(params0, aps=_to_device(aps))


def _replace(module, **changes):
    """``dataclasses.replace`` for a :class:`tlsjax._pytree.Module` (a dataclass)."""
    return dataclasses.replace(module, **changes)


#: Pseudo-observation sigma [m] that holds a target at an estimate (``control`` of
#: :meth:`Adjustment.problem`) where it has no observations left to determine it (removed as
#: gross errors, or held out of a fold): it carries no information about anything else.
PIN_SIGMA = 1.0


def _device_plan(network: Network, model: CalibrationModel):
    """The index plan with its problem's arrays on the device and its layouts chosen."""
    plan = build_plan(network, model)
    # The layout of each family's sums, chosen once from the static structure (grid or
    # segment sums, :func:`._families.grid_layout`).
    layouts = tuple(grid_layout(f, plan.spec.n_scans) for f in plan.problem.families)
    # The plan is built in numpy; its arrays go to the device in one call.
    problem = jax.device_put(_replace(plan.problem, layouts=layouts))
    return dataclasses.replace(plan, problem=problem)


@functools.cache
def _default_options() -> SolverOptions:
    """One default :class:`SolverOptions` (frozen): its device arrays are made once."""
    return SolverOptions()


class Adjustment:
    """One analysed adjustment: the index plan, the static spec and the approximate values of a
    (network, model) pair, built once on the host (the two phases of jaxls's ``analyze()`` then
    ``solve()``). :meth:`solve` runs the compiled adjustment with the network's weights or with
    others; every call after the first reuses the compiled code.
    """

    def __init__(
        self,
        network: Network,
        model: CalibrationModel | None = None,
        options: SolverOptions | None = None,
    ):
        check_calibration_arguments(network, model, options, "analyze")
        self._setup(network, model, options)

    @classmethod
    def _checked(cls, network, model, options) -> Adjustment:
        """An adjustment of arguments :func:`calibrate` has already checked."""
        self = cls.__new__(cls)
        self._setup(network, model, options)
        return self

    def _setup(self, network, model, options) -> None:
        self.network = network
        self.model = model or CalibrationModel()
        self.options = options or _default_options()
        # Once per network's data and model (:func:`._network.memoised`).
        self.plan = memoised(
            network, ("plan", self.model), lambda: _device_plan(network, self.model)
        )
        self._params0 = None
        self._leaves = None
        self._absent = {}  # support of the data -> (APs found not estimable, their diagnoses)

    @property
    def initial(self) -> Params:
        """Approximate values (computed on first use, :mod:`._approx`)."""
        if self._params0 is None:
            # Kept with the memoised plan (valid while it is: the network's data unchanged), on
            # the device: a calibration of a network met before transfers nothing.
            make = lambda: jax.device_put(initial_params(self.network, self.plan))
            self._params0 = kept(self.plan, "_initial", make)
        return self._params0

    def problem(
        self,
        *,
        weights=None,
        plane_weights=None,
        levelling_weights=None,
        heading_weights=None,
        ap_prior_weights=None,
        fixed_aps=None,
        control=None,
    ):
        """The plan's data with other weights (1/sigma, 0 = removed), in network row order:
        ``weights`` (n, 3) of the target rows, ``plane_weights`` (m, 3) of the plane rows,
        ``levelling_weights`` (s, 2) of the tilt readings, ``heading_weights`` (s,) of the
        observed kappas, ``ap_prior_weights`` (a,) of the AP priors; ``fixed_aps``: AP labels
        held at zero; ``control``: {target index: (xyz, sigma)} pseudo-observations added to (or
        replacing) the control points."""
        plan = self.plan
        fams = list(plan.problem.families)
        for fi, rows in enumerate(plan.family_rows):
            w = plane_weights if fi == plan.plane_family else weights
            if w is not None:
                fams[fi] = _replace(fams[fi], weight=_to_device(np.asarray(w, dtype=float)[rows]))
        if control:
            fams = self._with_control(fams, control)
        changes = {"families": tuple(fams)}
        for key, w in (
            ("levelling_weight", levelling_weights),
            ("heading_weight", heading_weights),
            ("ap_prior_weight", ap_prior_weights),
        ):
            if w is not None:
                changes[key] = _to_device(np.asarray(w, dtype=np.float64))
        if fixed_aps is not None:
            changes["fixed"] = build_plan(
                self.network, self.model, fixed_aps=fixed_aps
            ).problem.fixed
        return _replace(plan.problem, **changes)

    def _with_control(self, fams, control):
        where = {
            int(t): (fi, pi, k)
            for fi, tg in enumerate(self.plan.family_targets)
            for pi, row in enumerate(tg)
            for k, t in enumerate(row)
        }
        for fi in {where[int(t)][0] for t in control}:
            cx, cw = np.asarray(fams[fi].ctrl_xyz).copy(), np.asarray(fams[fi].ctrl_weight).copy()
            for t, (xyz, sigma) in control.items():
                f, pi, k = where[int(t)]
                if f == fi:
                    cx[pi, k], cw[pi, k] = xyz, 1.0 / np.asarray(sigma, dtype=float)
            fams[fi] = _replace(fams[fi], ctrl_xyz=_to_device(cx), ctrl_weight=_to_device(cw))
        return fams

    def with_data(
        self,
        problem=None,
        *,
        observations=None,
        plane_observations=None,
        levelling=None,
        control_xyz=None,
        bar_length=None,
    ):
        """The problem with other observation values, in network order (pure and traceable:
        Monte Carlo calls it inside the compiled batch): ``observations`` (n, 3) of the target
        rows, ``plane_observations`` (m, 3), ``levelling`` (s, 2) readings, ``control_xyz``
        (c, 3) in ``network.control_index`` order, ``bar_length`` (b,) of the scale bars."""
        plan, net = self.plan, self.network
        problem = plan.problem if problem is None else problem
        fams = list(problem.families)
        ctrl = None
        if control_xyz is not None:
            ctrl = jnp.zeros((len(net.targets), 3)).at[net.control_index].set(control_xyz)
        for fi, rows in enumerate(plan.family_rows):
            fam = fams[fi]
            if fi == plan.plane_family:
                if plane_observations is not None:
                    fam = _replace(fam, obs=jnp.asarray(plane_observations)[rows])
            else:
                if observations is not None:
                    fam = _replace(fam, obs=jnp.asarray(observations)[rows])
                tg = plan.family_targets[fi]
                if ctrl is not None and np.asarray(plan.problem.families[fi].ctrl_weight).any():
                    fam = _replace(fam, ctrl_xyz=jnp.where(fam.ctrl_weight > 0, ctrl[tg], 0.0))
                if bar_length is not None and tg.shape[1] == 2:
                    fam = _replace(fam, bar_length=jnp.asarray(bar_length))
            fams[fi] = fam
        changes = {"families": tuple(fams)}
        if levelling is not None:
            changes["levelling"] = jnp.asarray(levelling)
        return _replace(problem, **changes)

    def run(self, problem=None, params0=None, options=None):
        """The compiled call: (solver state, quality) as numpy arrays on the host (fetched in
        one transfer per dtype). ``options``: other numerical settings
        (:meth:`SolverOptions.arrays`, e.g. another ``max_iterations``): the same compiled
        program, they are data."""
        problem = self.plan.problem if problem is None else problem
        params0 = self.initial if params0 is None else params0
        if problem is self.plan.problem and params0 is self._params0 and options is None:
            # The plan's own arguments (solve() again): flattened once, the solver's settings
            # on the device with them (numpy arguments would be transferred on every call).
            if self._leaves is None:
                # Kept with the plan per settings, as its approximate values: a calibration of a
                # network met before flattens nothing, and the compiled call recognises the
                # very arguments of its last call (:class:`tlsjax._jit.StoredProgram`).
                flat = kept(self.plan, "_flat_arguments", dict)
                self._leaves = flat.get(self.options)
                if self._leaves is None:
                    args = (problem, params0, self.options.device_arrays())
                    self._leaves = flat[self.options] = jax.tree.flatten(args)
                    while len(flat) > 8:  # settings tried on one network: the latest few
                        flat.pop(next(iter(flat)))
            leaves, treedef = self._leaves
        else:
            args = (problem, params0, self.options.arrays() if options is None else options)
            leaves, treedef = jax.tree.flatten(args)
        return _flat_run(self.plan.spec, treedef, self.options.full_covariance)(*leaves)

    def run_estimable(self, problem=None, params0=None, options=None):
        """The compiled adjustment with every AP it finds not estimable removed from the
        unknowns (SPEC section 7, "held at zero means absent"): where the final factorisation
        finds an AP dependent, it is diagnosed (what it is confounded with), added to the
        problem's held parameters and the adjustment runs again from ``params0`` with that AP
        at zero. Early iterations may still move such an AP (approximate poses can separate
        it a little) and the other unknowns would carry that value; the re-run is exactly the
        model without it (the held column is the identity in the factorisation), so every
        estimate and output equals that model's to rounding. Costs one more run only when an
        AP is not estimable; same shapes, nothing recompiles. ``options``: other solver
        arrays (:meth:`SolverOptions.arrays`; None: this adjustment's).

        Returns (plan with the problem solved, solver state, quality, absent) on the host,
        ``absent`` the ``(name, confounded_with, reason)`` of the removed APs for
        :func:`._result.assemble`.
        """
        problem = self.plan.problem if problem is None else problem
        params0 = self.initial if params0 is None else params0
        n6 = 6 * self.plan.spec.n_scans
        # The support is read from the device only where it is needed: a run that did not
        # converge with APs held before, or one that found APs not estimable.
        key = functools.partial(_support, problem)
        out = self._estimable_passes(problem, params0, options, (), n6)
        held = self._absent.get(key()) if self._absent and not bool(out[1].converged) else None
        if held is not None:
            # Whether an AP is nearly dependent is judged numerically, so with other weights
            # (VCE's passes) an AP held before may pass the test and then drift along its
            # near-dependence: from the APs held in a converged run on the same observations
            # (estimability depends on which take part, not on their weights) it is the model
            # without them again.
            problem, params0 = _hold_aps(problem, params0, held[0], n6)
            retry = self._estimable_passes(problem, params0, options, held[1], n6)
            out = retry if bool(retry[1].converged) else out
        plan, state, q, absent = out
        if absent and bool(state.converged):
            self._absent[key()] = (np.asarray(plan.problem.fixed)[n6:].copy(), absent)
        return out

    def _estimable_passes(self, problem, params0, options, absent, n6):
        """The passes of :meth:`run_estimable` from ``problem`` (``absent``: the diagnoses of
        the APs it already holds)."""
        previous = None
        # Each pass can only add held columns; an AP found in pass k is held in pass k + 1.
        for _ in range(self.plan.spec.n_aps + 1):
            # On the host already (:meth:`run`: one transfer per dtype); a jax.device_get of
            # the forty numpy outputs would cost 0.15 ms of tree walking per pass.
            state, q = self.run(problem, params0, options)
            if previous is not None and not bool(state.converged):
                # A design that barely determines the other unknowns (more APs than targets)
                # may not converge from the start again; from the last pass's solution with
                # the APs at zero it reaches the same minimum of the model without them.
                state, q = self.run(problem, previous, options)
            plan = (
                self.plan
                if problem is self.plan.problem
                else dataclasses.replace(self.plan, problem=problem)
            )
            dep = np.asarray(q.dependent)[n6:] & ~_on_host(problem)["fixed"][n6:]
            if not dep.any() or not bool(state.finite):
                break
            absent += not_estimable_aps(plan, q, state, np.flatnonzero(dep))
            problem, params0 = _hold_aps(problem, params0, dep, n6)
            previous = _replace(
                state.params, aps=_to_device(np.where(dep, 0.0, np.asarray(state.params.aps)))
            )
        return plan, state, q, absent

    def solve(self, *, initial=None, **weights) -> CalibrationResult:
        """Adjust (with the weights of :meth:`problem`, if given) and return the result.
        ``initial``: (targets (t, 3), eops (s, 6)[, planes (k, 4)]) or a ``Params`` to start
        from. A not-estimable AP is absent from the solution (:meth:`run_estimable`)."""
        problem = self.problem(**weights) if weights else None
        if initial is not None and not isinstance(initial, Params):
            initial = initial_params(self.network, self.plan, *initial)
        plan, state, q, absent = self.run_estimable(problem, initial)
        return assemble(self.network, self.model, plan, state, q, absent)


def analyze(
    network: Network, model: CalibrationModel | None = None, options: SolverOptions | None = None
) -> Adjustment:
    """Analyse a (network, model) pair once: index plan, datum, approximate values. Returns an
    :class:`Adjustment` whose ``solve()`` runs the compiled adjustment, again and again with
    other weights, masks or fixed APs without recompiling."""
    return Adjustment(network, model, options)


def calibrate(
    network: Network,
    model: CalibrationModel | None = None,
    options: SolverOptions | None = None,
    *,
    throw: bool = False,
    initial=None,
) -> CalibrationResult:
    """Self-calibrate a TLS network: one free-network adjustment of targets and/or planes, scan
    poses and APs.

    Targets: Gauss-Markov model of Chow et al. 2013 (eqs. 1-6). Planes: one Gauss-Helmert
    condition per point, ``n . (R^T x(l - Delta) + S) - d = 0`` (eq. 3; SPEC section 4), with
    the unit-normal constraint. Structured Gauss-Newton with LM damping (targets and planes
    eliminated by Schur complement), datum by inner constraints on the object-space primitives
    (or a fixed scan, or control points), quality from the compiled normal matrix. With
    ``throw=True`` a failed result raises ``RuntimeError``. ``initial`` optionally gives
    (targets (t, 3), eops (s, 6)[, planes (k, 4)]) instead of the computed approximate values.
    """
    check_calibration_arguments(network, model, options, "calibrate")
    for note in network_design_warnings(network, model):  # the rules of _model._plausibility
        warnings.warn(note, PlausibilityWarning, stacklevel=2)
    res = Adjustment._checked(network, model, options).solve(initial=initial)
    if throw and not res.ok:
        raise RuntimeError(res.message)
    _, implausible = res.plausibility()  # the rules of _model._plausibility, as the CLI's
    if implausible:
        warnings.warn(implausible, PlausibilityWarning, stacklevel=2)
    return res
