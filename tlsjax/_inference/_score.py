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
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np

from .._adjustment._calibrate import analyze, spec_key
from .._adjustment._config import CalibrationModel, SolverOptions
from .._adjustment._families import Params, on_grid
from .._adjustment._network import Network
from .._adjustment._normal import linearise_rows, linearised_cost, null_space, reduce, reduced_rhs
from .._jit import StoredProgram
from .._model._aps import PRESETS, get_ap, registered_aps
from .._model._scanner import Scanner
from .._stats import chi2_quantile, chi2_sf
from .._units import display

#: Built-in terms that are offered as candidates: Chow et al. 2013 and Lichti & Licht 2006
#: (names A*, B*, C*), or the NIST set for a model in NIST names; users' terms always.
_CHOW = tuple(dict.fromkeys(PRESETS["chow2013"] + PRESETS["lichti2006"]))
_NIST = PRESETS["nist"]


@dataclasses.dataclass(frozen=True)
class ScoreTest:
    """The score test of one candidate term: ``statistic`` T_c (chi^2(1) under H0), ``p_value``,
    ``share`` of ``v^T P v`` it would absorb, the one-step ``estimate`` and its a priori ``sigma``
    (SI, ``unit``; ``display`` in mm, " or ppm), ``significant`` at the family-wise critical
    value; ``testable`` False (with ``note``) where the network cannot tell it from the model."""

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

    def display(self) -> str:
        v, u = display(self.estimate, self.unit)
        s, _ = display(self.sigma, self.unit)
        return f"{v:.4g} +- {s:.2g} {u}"


@dataclasses.dataclass(frozen=True)
class ScoreTests:
    """Score tests of every candidate (:class:`ScoreTest`, largest statistic first), with the
    misfit ``vtpv`` they share, the ``family_level`` of the tests and their ``critical`` value
    (chi^2(1) quantile at ``1 - family_level / k``, k testable candidates)."""

    tests: tuple
    vtpv: float
    family_level: float
    critical: float

    @property
    def significant(self) -> tuple:
        return tuple(t for t in self.tests if t.significant)

    def best(self) -> ScoreTest | None:
        """The testable candidate with the largest statistic (None if there is none)."""
        return next((t for t in self.tests if t.testable), None)

    def summary(self) -> str:
        n = sum(t.testable for t in self.tests)
        head = (
            f"missing terms (score tests of {n} candidate(s), family-wise alpha = {self.family_level:g}, "
            f"chi^2(1) > {self.critical:.2f}):"
        )
        sig = self.significant
        if not sig:
            best = self.best()
            tail = f" largest {best.name}: T = {best.statistic:.1f}" if best else ""
            return f"{head} none significant;{tail}" if tail else f"{head} none significant"
        lines = [head]
        for t in sig:
            lines.append(
                f"  {t.name:5s} ({t.group}) T = {t.statistic:.1f}, would absorb "
                f"{100 * t.share:.1f}% of v^T P v; one-step estimate {t.display()}"
            )
        return "\n".join(lines)

    def to_dict(self) -> dict:
        """The result JSON's ``score_tests`` section (strict JSON: non-finite values are null)."""
        fin = lambda x: float(x) if np.isfinite(x) else None
        return {
            "method": "score (Lagrange-multiplier) test of each candidate term not in the model: "
            "T = (c^T P v)^2 / (c^T P Q_vv P c) ~ chi2(1); share = T / vTPv",
            "family_level": self.family_level,
            "critical_value": fin(self.critical),
            "vtpv": fin(self.vtpv),
            "significant": [t.name for t in self.significant],
            "candidates": [
                {
                    k: (fin(v) if isinstance(v, float) else v)
                    for k, v in dataclasses.asdict(t).items()
                }
                for t in self.tests
            ],
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

    return StoredProgram(system, ("score tests", spec_key(spec), treedef))


def _score_system(spec, problem, params, rank_tolerance):
    """The reduced normal matrix K (poses + APs), the reduced right-hand side ``-J^T e`` and
    ``v^T P v`` at ``params``, and the diagonal of the unreduced matrix (the scale of the
    engine's rank test): the engine's linearisation and Schur elimination."""
    grid = on_grid(problem)
    blocks, rows = linearise_rows(spec, grid, params)
    _, Hz = null_space(spec, grid.families, params)
    red = reduce(spec, grid, blocks, Hz, jnp.asarray(0.0), rank_tolerance)
    cost = linearised_cost(grid, params, rows)
    return red.K, reduced_rhs(blocks.bp, blocks.bz, red), cost, jnp.diagonal(blocks.Nzz)


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


def tests_in(adjustment, problem, params, names, alpha: float) -> ScoreTests:
    """Score tests of the terms ``names`` of an analysed ``adjustment`` whose ``problem`` holds
    them at zero, at its solution ``params`` (a :class:`Params` of that adjustment): what
    stepwise selection asks of its one wide adjustment, and :class:`ScoreTester` of its own."""
    spec, tol = adjustment.plan.spec, float(adjustment.options.rank_tolerance)
    labels = adjustment.plan.ap_labels
    leaves, treedef = jax.tree.flatten((problem, params, np.float64(tol)))
    K, rhs, vtpv, nzz = _score_program(spec, treedef)(*leaves)
    free = ~np.asarray(problem.fixed)
    idx = np.array([labels.index(n) for n in names], dtype=int)
    return _tests(
        np.asarray(K), np.asarray(rhs), float(vtpv), np.asarray(nzz), free, tuple(names), idx,
        6 * spec.n_scans, alpha, tol,
    )  # fmt: skip


def _tests(K, rhs, vtpv, nzz, free, names, cand_index, n_pose, alpha, tol) -> ScoreTests:
    """The statistics of every candidate from the reduced system (module docstring). Not
    testable where ``S_c <= tol N_cc`` (``N_cc`` unreduced): the engine's rank test
    (:func:`tlsjax._adjustment._normal.reduce`) would find the term dependent."""
    F = np.flatnonzero(free & (np.diagonal(K) > 0))
    d = np.sqrt(np.diagonal(K)[F])
    Ks = K[np.ix_(F, F)] / d[:, None] / d[None, :]
    Kinv = np.linalg.pinv(Ks, rcond=1e-10, hermitian=True)
    out = []
    for name, c in zip(names, cand_index):
        j = n_pose + c
        b = K[F, j] / d
        y = Kinv @ b
        kcc = K[j, j]
        S = kcc - b @ y
        g = rhs[j] - y @ (rhs[F] / d)
        term = get_ap(name)
        if not (kcc > 0 and S > tol * nzz[j]):
            note = "no observations of its group" if kcc <= 0 else "confounded with the model"
            out.append(ScoreTest(name, term.group, *(np.nan,) * 5, term.unit, False, False, note))
            continue
        T = g * g / S
        out.append(
            ScoreTest(
                name, term.group, float(T), chi2_sf(float(T), 1.0),
                float(T / vtpv) if vtpv > 0 else np.nan, float(g / S), float(1 / np.sqrt(S)),
                term.unit, False, True,
            )
        )  # fmt: skip
    k = max(sum(t.testable for t in out), 1)
    crit = chi2_quantile(1 - alpha / k, 1.0)
    out = [dataclasses.replace(t, significant=t.testable and t.statistic > crit) for t in out]
    out.sort(key=lambda t: -t.statistic if t.testable else np.inf)
    return ScoreTests(tuple(out), vtpv, alpha, float(crit))
