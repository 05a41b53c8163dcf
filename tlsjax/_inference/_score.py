"""The missing term named: score (Lagrange-multiplier) tests of the registered terms that are
not in the model (SPEC section 7, "one test for blunders and for missing terms").

For a term with column ``c`` (its basis function at every observation of its group), the
reduction of ``v^T P v`` that adding it would bring is, to first order (Baarda's alternative
hypothesis; Rao's score test),

    T_c = g_c^2 / S_c,    g_c = c^T P v - N_cx N_xx^- (A^T P v),
                          S_c = c^T P c - N_cx N_xx^- N_xc   (= c^T P Q_vv P c),

with ``x`` the unknowns of the model (targets or planes, scan poses, its APs). Nothing is refitted:
the model is analysed once more with the candidates as APs held at zero, linearised at the
solution (the engine's one linearisation, :func:`tlsjax._adjustment._normal.linearise_rows`),
the primitives eliminated by the same Schur complement (:func:`._normal.reduce`), and every
candidate's ``g_c`` and ``S_c`` read off the reduced gradient and matrix: one Schur complement
of the small (poses + APs) system per candidate, against a generalised inverse of the model's
block (the datum defect does not matter: ``N_xc`` is orthogonal to the rigid-motion null space).
``g_x`` is 0 at convergence; it is kept so that ``T_c`` is the one-step reduction of the
augmented model exactly.

With the weights in use, ``T_c ~ chi^2(1)`` under H0 (a priori sigma0 = 1); the candidates are
tested at the family-wise level ``alpha`` (Bonferroni over the testable candidates), and
``T_c / v^T P v`` is the share of the misfit the term would absorb. A candidate whose ``S_c`` is
(close to) 0 is confounded with the model (A1 without a scale, a term whose basis the model
already has) and is reported as not testable. The one-step estimate ``x_c = g_c / S_c`` and its
a priori sigma ``1 / sqrt(S_c)`` say how large the term would be.

**Only terms the design can estimate** (SPEC section 7, "candidates the design can estimate"):
a candidate is testable only where the model with it would pass the engine's own rank test
(:func:`tlsjax._adjustment._normal.reduce`: ``1 - R^2`` of its column regressed on every other
unknown above ``rank_tolerance``), with its column evaluated at the *adjusted* observations
``l + v``. Estimability is a property of the design, not of the noise: at the observations a
range scale A1 (basis rho) differs from the network's scale (the computed ranges) by the
residuals, which a large systematic misfit makes large enough to pass the test, so a free
network would be told to add a term it cannot determine; at ``l + v`` its column is exactly a
change of scale, the design's real defect. Likewise the scans of one station (positions within
:data:`tlsjax._adjustment._diagnose.STATION_TOLERANCE`) are placed at their station's mean
position for this test: the few tenths of a millimetre between their estimated positions would
let a short-period range term (A3, A4) pass the rank test from one station, where every range
term is a change of the targets' distances. The reason is named: no scale information (scale
bars, control), absorbed by the targets (one station), or confounded with the model.

**Alternatives.** Two candidates whose whitened columns after the model, ``Q_vv^(1/2) P c``,
correlate with ``|rho| > ALTERNATIVE_CORRELATION`` (``rho_ij = S_ij / sqrt(S_ii S_jj)``, ``S``
the Schur complement of the candidates' block given the model) predict nearly the same
residuals: their statistics are nearly equal for any misfit, and the larger one is no evidence
that it is the right term. They are reported as one group of alternatives with each one's
``T_c``; only prediction on held-out scans decides between them (:mod:`._crossval`).

**Plausibility.** A one-step estimate beyond the bounds of
:mod:`tlsjax._model._plausibility` is flagged beside its test (a term that would take a value
no instrument has is a sign of a misfit the term does not describe).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from .._adjustment._calibrate import analyze, spec_key
from .._adjustment._config import CalibrationModel, SolverOptions
from .._adjustment._diagnose import ABSORBED, is_scale, station_positions
from .._adjustment._families import Params, PointFamily, on_grid
from .._adjustment._network import Network
from .._adjustment._normal import linearise_rows, linearised_cost, reduced_rhs, schur
from .._jit import StoredProgram
from .._model._aps import PRESETS, get_ap, registered_aps
from .._model._plausibility import ap_findings
from .._model._scanner import Scanner
from .._stats import chi2_quantile, chi2_sf
from .._units import display

#: Built-in terms that are offered as candidates: Chow et al. 2013 and Lichti & Licht 2006
#: (names A*, B*, C*), or the NIST set for a model in NIST names; users' terms always.
_CHOW = tuple(dict.fromkeys(PRESETS["chow2013"] + PRESETS["lichti2006"]))
_NIST = PRESETS["nist"]
#: Candidates whose whitened columns after the model correlate beyond this are alternatives.
ALTERNATIVE_CORRELATION = 0.9


@dataclasses.dataclass(frozen=True)
class ScoreTest:
    """The score test of one candidate term: ``statistic`` T_c (chi^2(1) under H0), ``p_value``,
    ``share`` of ``v^T P v`` it would absorb, the one-step ``estimate`` and its a priori ``sigma``
    (SI, ``unit``; ``display`` in mm, " or ppm), ``significant`` at the family-wise critical
    value; ``testable`` False (with ``note``) where the design cannot estimate it in this datum
    or the network has no observations of its group. ``alternatives``: the other candidates
    whose effect after the model is nearly the same (module docstring), with
    ``alternative_correlation`` the largest |correlation| with one of them; ``plausibility``:
    "" or the level ("warning", "impossible") of a one-step estimate beyond the plausibility
    bounds, with ``plausibility_note``."""

    name: str
    group: str
    statistic: float
    p_value: float
    share: float
    estimate: float
    sigma: float
    unit: str
    significant: bool
    testable: bool
    note: str = ""
    alternatives: tuple = ()
    alternative_correlation: float = float("nan")
    plausibility: str = ""
    plausibility_note: str = ""

    def display(self) -> str:
        v, u = display(self.estimate, self.unit)
        s, _ = display(self.sigma, self.unit)
        return f"{v:.4g} +- {s:.2g} {u}"

    def summary(self) -> str:
        """One line: the term, its statistic, share and one-step estimate, its flags."""
        if not self.testable:
            return f"{self.name} ({self.group}): not tested: {self.note}"
        text = (
            f"{self.name} ({self.group}) T = {self.statistic:.1f}, would absorb "
            f"{100 * self.share:.1f}% of v^T P v; one-step estimate {self.display()}"
        )
        if self.plausibility:
            text += f" [{self.plausibility}: {self.plausibility_note}]"
        return text

    def to_dict(self) -> dict:
        """Strict JSON (non-finite numbers are null; SI units)."""
        out = {}
        for k, v in dataclasses.asdict(self).items():
            if isinstance(v, float):
                v = float(v) if np.isfinite(v) else None
            elif isinstance(v, tuple):
                v = list(v)
            out[k] = v
        return out


@dataclasses.dataclass(frozen=True)
class ScoreTests:
    """Score tests of every candidate (:class:`ScoreTest`, largest statistic first), with the
    misfit ``vtpv`` they share, the ``family_level`` of the tests and their ``critical`` value
    (chi^2(1) quantile at ``1 - family_level / k``, k testable candidates) and ``groups``: the groups of
    alternatives (names, largest statistic first; module docstring), groups of one left out.
    ``variance_factor``: the s0^2 that significance is judged in (``T / s0^2 > critical``; 1:
    the a priori sigma0, the weights in use; stepwise selection judges in its fit's s0^2)."""

    tests: tuple
    vtpv: float
    family_level: float
    critical: float
    groups: tuple = ()
    variance_factor: float = 1.0

    @property
    def significant(self) -> tuple:
        return tuple(t for t in self.tests if t.significant)

    @property
    def not_estimable(self) -> tuple:
        """The candidates this design cannot estimate (never proposed), with the reason."""
        return tuple(t for t in self.tests if not t.testable)

    def best(self) -> ScoreTest | None:
        """The testable candidate with the largest statistic (None if there is none)."""
        return next((t for t in self.tests if t.testable), None)

    def test(self, name: str) -> ScoreTest:
        return next(t for t in self.tests if t.name == name)

    def group_of(self, name: str) -> tuple:
        """The group of alternatives ``name`` belongs to (itself alone if none)."""
        return next((g for g in self.groups if name in g), (name,))

    def summary(self) -> str:
        """The significant candidates (each group of alternatives together), else the largest
        statistic, and the candidates the design cannot estimate. A header only with a
        candidate under it: without a testable one, one line says so."""
        n = sum(t.testable for t in self.tests)
        gone = self.not_estimable
        if not n:
            why = "; ".join(f"{t.name}: {t.note}" for t in gone) or "no candidate terms"
            return f"missing terms: no candidate could be tested ({why})"
        stat = (
            "chi^2(1)"
            if self.variance_factor == 1.0
            else f"T / s0^2 (s0^2 = {self.variance_factor:.4g})"
        )
        head = (
            f"missing terms (score tests of {n} candidate(s), family-wise alpha = {self.family_level:g}, "
            f"{stat} > {self.critical:.2f}):"
        )
        sig = self.significant
        lines = [head]
        if not sig:
            best = self.best()
            tail = f" largest {best.name}: T = {best.statistic:.1f}" if best else ""
            lines = [f"{head} none significant;{tail}" if tail else f"{head} none significant"]
        shown = set()
        for t in sig:
            if t.name in shown:
                continue
            group = self.group_of(t.name)
            if len(group) > 1:
                shown.update(group)
                alts = ", ".join(
                    f"{self.test(a).name} T = {self.test(a).statistic:.1f}" for a in group
                )
                lines.append(
                    f"  alternatives (|corr| > {ALTERNATIVE_CORRELATION:g} after the model; they "
                    f"predict nearly the same residuals, only cross-validation tells them apart): "
                    f"{alts}"
                )
                lines += [f"    {self.test(a).summary()}" for a in group]
            else:
                lines.append(f"  {t.summary()}")
        if gone:
            lines.append(
                "  not estimable in this design (never proposed): "
                + "; ".join(f"{t.name}: {t.note}" for t in gone)
            )
        return "\n".join(lines)

    def to_dict(self) -> dict:
        """The result JSON's ``score_tests`` section (strict JSON: non-finite values are null)."""
        fin = lambda x: float(x) if np.isfinite(x) else None
        return {
            "method": "score (Lagrange-multiplier) test of each candidate term not in the model: "
            "T = (c^T P v)^2 / (c^T P Q_vv P c) ~ chi2(1); share = T / vTPv; candidates only "
            "where the design can estimate them; alternatives: |corr| > "
            f"{ALTERNATIVE_CORRELATION:g} between their whitened columns after the model",
            "family_level": self.family_level,
            "critical_value": fin(self.critical),
            "variance_factor": fin(self.variance_factor),
            "vtpv": fin(self.vtpv),
            "significant": [t.name for t in self.significant],
            "alternatives": [list(g) for g in self.groups],
            "not_estimable": [{"name": t.name, "reason": t.note} for t in self.not_estimable],
            "candidates": [t.to_dict() for t in self.tests],
        }


def default_candidates(scanner: Scanner) -> tuple:
    """Every registered term a model in these names could add: the built-in set of its naming
    (Chow/Lichti, or NIST for a model in NIST names) and every user-registered term."""
    builtin = set(_CHOW) | set(PRESETS["nist"]) | {"x7", "x9n"}
    nist = any(a in _NIST or a in ("x7", "x9n") for a in scanner.aps)
    own = tuple(a for a in registered_aps() if a not in builtin)
    return tuple(a for a in (_NIST if nist else _CHOW) + own if a not in scanner.aps)


@functools.cache
def _score_program(spec, treedef):
    """:func:`_score_system` compiled for one spec and argument structure, stored traced."""

    def system(*leaves):
        return _score_system(spec, *jax.tree.unflatten(treedef, leaves))

    return StoredProgram(system, ("score tests", spec_key(spec), treedef), quick=True)


def _score_system(spec, problem, params, positions):
    """The reduced normal matrix K (poses + APs), the reduced right-hand side ``-J^T e`` and
    ``v^T P v`` at ``params``, the diagonal of the unreduced matrix (the scale of the engine's
    rank test): the engine's linearisation and Schur elimination (:func:`._normal.schur`; the
    rank test itself runs on the host, :class:`_System`). Then the same reduced matrix and
    diagonal of the design (module docstring): the scans at their stations' ``positions``
    (s, 3) and the AP columns evaluated at the observations computed there, ``l + v``.

    The two are one batch of two (``vmap``): one trace of the linearisation, and a third less
    compile than two copies (1.31 to 0.93 s for the demo room's 23 APs and 8 candidates)."""
    grid = on_grid(problem)
    at = Params(params.prims, params.eops.at[:, :3].set(positions), params.aps)
    # The observations computed at ``at`` (the unweighted misclosure added to l): no Jacobian.
    obs = tuple(
        jnp.stack([f.obs, f.obs + f.residuals(spec, grid, at, fi, unit_weight=True)])
        if isinstance(f, PointFamily)
        else None
        for fi, f in enumerate(grid.families)
    )

    def one(obs, p):
        fams = tuple(
            f if o is None else dataclasses.replace(f, obs=o) for f, o in zip(grid.families, obs)
        )
        g = dataclasses.replace(grid, families=fams)
        blocks, rows = linearise_rows(spec, g, p)
        _, Y, K = schur(blocks)
        rhs = reduced_rhs(blocks.bp, blocks.bz, Y)
        return K, rhs, linearised_cost(g, p, rows), jnp.diagonal(blocks.Nzz)

    both = jax.tree.map(lambda a, b: jnp.stack([a, b]), params, at)
    K, rhs, cost, nzz = jax.vmap(one)(obs, both)
    return K[0], rhs[0], cost[0], nzz[0], K[1], nzz[1]


class ScoreTester:
    """The model analysed once with the candidates as APs held at zero; :meth:`__call__` tests
    them at a solution of the model (any weights, pinned targets), recompiling nothing."""

    def __init__(self, network: Network, model: CalibrationModel, candidates=None, solver=None):
        scanner = model.scanner
        if not isinstance(scanner, Scanner):
            raise ValueError("score tests work on one instrument; pass one Scanner")
        cands = default_candidates(scanner) if candidates is None else tuple(candidates)
        self.candidates = tuple(c for c in cands if c not in scanner.aps)
        wide = dataclasses.replace(
            model,
            scanner=dataclasses.replace(scanner, aps=scanner.aps + self.candidates),
            fixed_aps=tuple(model.fixed_aps) + self.candidates,
        )
        self.model = model
        self.adjustment = analyze(network, wide, solver or SolverOptions(full_covariance=False))
        labels = self.adjustment.plan.ap_labels
        self.model_index = np.array([labels.index(a) for a in scanner.aps], dtype=int)

    def __call__(
        self,
        params,
        *,
        weights=None,
        levelling_weights=None,
        plane_weights=None,
        control=None,
        alpha: float = 0.05,
    ) -> ScoreTests:
        """``params``: the model's estimates (its :class:`Params`, APs in the model's order);
        the weights as :meth:`tlsjax.Adjustment.problem` takes them (None: the network's)."""
        adj = self.adjustment
        aps = np.zeros(adj.plan.spec.n_aps)
        aps[self.model_index] = np.asarray(params.aps)
        wide = Params(params.prims, params.eops, jax.device_put(aps))
        problem = adj.problem(
            weights=weights,
            levelling_weights=levelling_weights,
            plane_weights=plane_weights,
            control=control,
            fixed_aps=adj.model.fixed_aps,
        )
        return tests_in(adj, problem, wide, self.candidates, alpha)

    def prepare(self) -> None:
        """Compile the tests in the background (:func:`prepare_tests`), at the start values
        and the network's weights (the shapes of every later call)."""
        adj = self.adjustment
        prepare_tests(adj, adj.problem(fixed_aps=adj.model.fixed_aps), adj.initial)


def _program_and_arguments(adjustment, problem, params):
    """The score tests' compiled program for ``adjustment`` and its flat arguments."""
    positions = station_positions(np.asarray(params.eops))
    leaves, treedef = jax.tree.flatten((problem, params, positions))
    return _score_program(adjustment.plan.spec, treedef), leaves


def prepare_tests(adjustment, problem, params) -> None:
    """Compile the program of :func:`tests_in` for arguments shaped as these in the
    background (:meth:`tlsjax._jit.StoredProgram.prepare`), e.g. while the first adjustment
    of a pipeline compiles."""
    program, leaves = _program_and_arguments(adjustment, problem, params)
    program.prepare(*leaves)


def tests_in(adjustment, problem, params, names, alpha: float) -> ScoreTests:
    """Score tests of the terms ``names`` of an analysed ``adjustment`` whose ``problem`` holds
    them at zero, at its solution ``params`` (a :class:`Params` of that adjustment): what
    stepwise selection asks of its one wide adjustment, and :class:`ScoreTester` of its own."""
    spec, tol = adjustment.plan.spec, float(adjustment.options.rank_tolerance)
    labels = adjustment.plan.ap_labels
    program, leaves = _program_and_arguments(adjustment, problem, params)
    out = jax.device_get(program(*leaves))
    K, rhs, vtpv, nzz, K_d, nzz_d = (np.asarray(a) for a in out)
    free = ~np.asarray(problem.fixed)
    idx = np.array([labels.index(n) for n in names], dtype=int)
    system = _System(K, rhs, float(vtpv), nzz, K_d, nzz_d, free, 6 * spec.n_scans, tol)
    return _tests(system, tuple(names), idx, alpha, np.asarray(params.eops))


@dataclasses.dataclass(frozen=True)
class _System:
    """The reduced system of the model with the candidates held (:func:`_score_system`): ``K``,
    ``rhs``, ``vtpv`` and ``nzz`` at the observations, ``K_d`` and ``nzz_d`` with the AP
    columns at the adjusted observations; ``free`` the model's unknowns among the reduced
    ones, ``n_pose`` = 6 scans, ``tol`` the engine's rank tolerance."""

    K: np.ndarray
    rhs: np.ndarray
    vtpv: float
    nzz: np.ndarray
    K_d: np.ndarray
    nzz_d: np.ndarray
    free: np.ndarray
    n_pose: int
    tol: float


def _schur(K, free, cols):
    """The model's unknowns F (free, with a diagonal), their scale d, and for the columns
    ``cols`` the Schur complement ``S = K_cc - K_cF K_FF^- K_Fc`` and the regression ``Y =
    K_FF^- K_Fc`` (scaled coordinates)."""
    F = np.flatnonzero(free & (np.diagonal(K) > 0))
    d = np.sqrt(np.diagonal(K)[F])
    Ks = K[np.ix_(F, F)] / d[:, None] / d[None, :]
    Kinv = np.linalg.pinv(Ks, rcond=1e-10, hermitian=True)
    B = K[np.ix_(F, cols)] / d[:, None]
    Y = Kinv @ B
    return F, d, K[np.ix_(cols, cols)] - B.T @ Y, Y


def _not_estimable_reason(system: _System, j: int, F, d, y, eops) -> str:
    """Why candidate column ``j`` is not estimable in this design, in the words of the engine's
    diagnosis (:mod:`tlsjax._adjustment._diagnose`): absorbed by the primitives (``K_jj /
    N_jj``), a change of scale (its dependency moves the scan positions radially), or the
    model's other unknowns."""
    if system.nzz_d[j] > 0 and system.K_d[j, j] / system.nzz_d[j] < ABSORBED:
        return (
            "absorbed by the target coordinates: this design cannot separate them (e.g. every "
            "scan from one station); add stations or tilts"
        )
    v = np.zeros(system.K.shape[0])
    v[F] = y / d
    if is_scale(v, Params((), eops, None), len(eops)):
        return "a change of the network's scale: needs scale bars or control points"
    return "confounded with the model's unknowns in this design"


def _tests(system: _System, names, cand_index, alpha, eops) -> ScoreTests:
    """The statistics of every candidate from the reduced system (module docstring). Not
    testable where the engine's rank test at the adjusted observations would find the term
    dependent (``S_c <= tol N_cc``, ``N_cc`` unreduced) or where it has no observations."""
    K, rhs, tol = system.K, system.rhs, system.tol
    cols = system.n_pose + np.asarray(cand_index, dtype=int)
    F, d, S, Y = _schur(K, system.free, cols)
    Fd, dd, S_d, Y_d = _schur(system.K_d, system.free, cols)
    g = rhs[cols] - Y.T @ (rhs[F] / d)
    out = []
    for k, (name, j) in enumerate(zip(names, cols)):
        term = get_ap(name)
        kcc = K[j, j]
        note = ""
        if not kcc > 0:
            note = "no observations of its group"
        elif not S_d[k, k] > tol * system.nzz_d[j] or not S[k, k] > tol * system.nzz[j]:
            note = _not_estimable_reason(system, j, Fd, dd, Y_d[:, k], eops)
        if note:
            out.append(ScoreTest(name, term.group, *(np.nan,) * 5, term.unit, False, False, note))
            continue
        T = g[k] ** 2 / S[k, k]
        est = float(g[k] / S[k, k])
        found = ap_findings([name], [est], [term.unit], [term.description])
        out.append(
            ScoreTest(
                name, term.group, float(T), chi2_sf(float(T), 1.0),
                float(T / system.vtpv) if system.vtpv > 0 else np.nan, est,
                float(1 / np.sqrt(S[k, k])), term.unit, False, True,
                plausibility=found[0].level if found else "",
                plausibility_note=found[0].text if found else "",
            )
        )  # fmt: skip
    out = _with_alternatives(out, S)
    k = max(sum(t.testable for t in out), 1)
    crit = chi2_quantile(1 - alpha / k, 1.0)
    out = [dataclasses.replace(t, significant=t.testable and t.statistic > crit) for t in out]
    order = np.argsort([-t.statistic if t.testable else np.inf for t in out], kind="stable")
    out = [out[i] for i in order]
    groups = _groups(out)
    return ScoreTests(tuple(out), system.vtpv, alpha, float(crit), groups)


def _with_alternatives(tests: list, S) -> list:
    """Each testable candidate with the others whose whitened columns after the model
    correlate with it beyond :data:`ALTERNATIVE_CORRELATION` (``S_ij / sqrt(S_ii S_jj)``),
    joined transitively into groups (single linkage)."""
    ok = np.array([t.testable for t in tests])
    s = np.sqrt(np.where(ok, np.abs(np.diagonal(S)), 1.0))
    with np.errstate(invalid="ignore", divide="ignore"):
        C = np.abs(S) / np.outer(s, s)
    C = np.where(np.outer(ok, ok), C, 0.0)
    np.fill_diagonal(C, 0.0)
    n = len(tests)
    label = np.arange(n)
    linked = C > ALTERNATIVE_CORRELATION
    changed = True
    while changed:  # connected components of the linked pairs
        changed = False
        for i, j in zip(*np.nonzero(linked)):
            m = min(label[i], label[j])
            if label[i] != m or label[j] != m:
                label[label == label[i]] = m
                label[label == label[j]] = m
                changed = True
    out = []
    for i, t in enumerate(tests):
        members = [k for k in range(n) if label[k] == label[i] and k != i]
        if not members:
            out.append(t)
            continue
        out.append(
            dataclasses.replace(
                t,
                alternatives=tuple(tests[k].name for k in members),
                alternative_correlation=float(C[i, members].max()),
            )
        )
    return out


def _groups(tests: list) -> tuple:
    """The groups of alternatives (names in the order of ``tests``, largest statistic first)."""
    seen, groups = set(), []
    for t in tests:
        if t.alternatives and t.name not in seen:
            group = tuple(u.name for u in tests if u.name == t.name or u.name in t.alternatives)
            seen.update(group)
            groups.append(group)
    return tuple(groups)
