"""AP-set compatibility test by simulation (SPEC section 9; Lichti 2008; Chow et al. 2013, 4.3).

**Why a group test.** Two AP sets of one instrument (two sessions, or point-based vs plane-based
from the same scans) can differ in which terms are significant, and their APs are correlated
with the EOPs and with each other, so comparing APs one by one misleads (Habib & Morgan 2005).
Lichti (2008) compares their joint effect in object space by simulation; Chow et al. (2013) use
"1,000 simulations in a room of the same dimensions and the same observational noise as the real
data", 100 targets at different distances, 10 of them as control.

**What it asks.** Do the two sets correct a point cloud of this scanner differently by more than
the scanner's own noise and the sets' uncertainty explain? With the noise set to zero it becomes
the pure object-space test of the AP difference.

**The statistic** (SPEC section 9):

1. Inputs: AP sets 1 and 2, each with its full AP covariance (``result.ap_covariance``; a term
   absent from a set is zero with zero variance; the sets may use different basis functions,
   e.g. the hybrid reduced collimation sec(alpha) - 1 against the full sec(alpha): each set is
   applied with its own scanner settings to scans of one architecture, and e = (e1, e2) lives on
   the two sets' own terms), a room and scanner design, the observation noise (default: that of
   the data the sets came from), N simulations (default 1,000), alpha (default 5%).
2. Simulation j: draw 100 targets over the room's surfaces at different distances, pick 10 as
   control; simulate two independent noisy scans of them from one station (one per session);
   correct scan 1 with set 1 and scan 2 with set 2; convert both to Cartesian coordinates;
   transform set 2's points onto set 1's by a rigid-body least-squares fit on the control points.
3. Check point i: the difference d_ij, its Jacobians J1_ij, J2_ij with respect to the two AP
   vectors (autodiff through correction, conversion and the fit), the noise part n_ij of d_ij
   (d_ij less its value without noise, the noise-free points to first order in the noise), and
   ``C_ij = J1 C1 J1^T + J2 C2 J2^T + N_ij``, N_ij the two scans' observation covariance
   propagated through the same chain.
4. Statistic: ``T = (1/(N n_c)) sum_ij d_ij^T C_ij^-1 d_ij`` over all simulations and check
   points.
5. Null: to first order d_ij = J1 e1 + J2 e2 + n_ij with e1 ~ N(0, C1), e2 ~ N(0, C2), so over
   the same simulations T is the quadratic form ``e^T G e + 2 e^T b + c`` in e = (e1, e2), with
   ``G = mean_ij [J1 J2]^T C^-1 [J1 J2]``, ``b = mean_ij [J1 J2]^T C^-1 n_ij``,
   ``c = mean_ij n^T C^-1 n``. p = P(T(e) >= T_obs), from at least 1e5 seeded draws of e (or
   Imhof's formula when the noise is zero, where T(e) = sum_m lambda_m chi2_1, lambda_m the
   eigenvalues of ``L^T G L``, L = blockdiag(C1^1/2, C2^1/2)). Compatible when p > alpha.
6. Report: p (no floor beyond 1/(draws + 1)), T, the eigenvalues lambda_m with their AP
   directions (the object-space visibility of each direction; name the least visible), the
   median and quartiles of the share of check points whose d^T C^-1 d exceeds the chi-square(3)
   quantile, the RMS of the differences in mm, and the naive chi-square test of the AP
   differences beside it, labelled as such (and as not meaningful when the two sets' basis
   functions differ).

The null is exact to first order whatever N and the number of check points: T_obs and T(e) are
the same function of e given the simulated noise, which is known. The median share is
descriptive only: thresholding each point and counting wastes each distance's size, its null
has an atom at zero, and a tail quantile estimated from N draws moves with the seed.

**Why the eigenvalues lie in [0, 1] and sum to 3 at zero noise.** Then ``C_ij = W Sigma W^T``
with ``W = [J1 J2]``, ``Sigma = L L^T``, and ``L^T G L = mean_ij Z^T (Z Z^T)^-1 Z`` with
``Z = W L`` (3 x m): each term is the orthogonal projector onto the row space of Z, with
eigenvalues 0 or 1 and trace rank(Z) = 3 where the AP difference moves the check point in
three independent directions. A mean of projectors has its eigenvalues in [0, 1] (``0 <= u^T P
u <= u^T u`` for each) and the mean trace: 3. ``T = sum_m lambda_m chi2_1`` then has mean 3,
as ``d^T C^-1 d ~ chi2(3)`` at each point. lambda_m is the share of a difference along
direction m (in units of its sigma) that object space shows: 1 fully, 0 not at all. With noise
the lambda shrink (N enters C): a difference must then also stand out against the noise.

**Visibility report.** Moves of both sets that change neither correction difference (the
common part when both sets hold a term with one basis) are zeros of ``L^T G L`` that say
nothing; they are found from the pre-fit effect ``Wpre = [-dx1/da1, dx2/da2]`` at zero noise
and left out. Of the remaining directions, one whose pre-fit effect the rigid fit absorbs
(post-fit / pre-fit sum of squares below 1e-6, e.g. a constant horizontal-direction offset,
which is a rotation about the vertical axis) is a difference object space cannot see, and is
reported as such.
"""

from __future__ import annotations

import dataclasses
import math
import time

import jax
import numpy as np

from .._adjustment._network import DEFAULT_SIGMA_ANGLE, DEFAULT_SIGMA_RANGE
from .._model._aps import get_ap
from .._model._scanner import Scanner
from .._simulation._batch import device_key, round_chunk
from .._simulation._room import Room
from .._stats import chi2_quantile, chi2_sf, weighted_chi2_sf
from .._summary import Settings, to_json_value
from .._units import display_unit
from ._apset import APSet, basis_text, same_basis
from ._compatibility_simulation import compiled_chunk, room_vector, run_tests, statistic_function

#: A difference direction whose post-fit effect keeps less than this share of its pre-fit sum of
#: squares is one object space cannot see (the rigid fit absorbs it).
INVISIBLE = 1e-6
#: Directions whose pre-fit effect is below this share of the largest are common moves.
COMMON = 1e-10


@dataclasses.dataclass(frozen=True)
class CompatibilityOptions(Settings):
    """Settings of :func:`compatibility_test` (defaults: Chow et al. 2013, section 4.3).

    ``runs``: simulations; ``level``: the level of the test (the sets are compatible when
    p > level); ``n_targets``, ``n_control``: the simulated room's targets and check points;
    ``null_draws``: draws of e for the p-value (the p-value's Monte Carlo error is at most
    ``sqrt(p (1 - p) / draws)``: 0.0007 at p = 0.05 with the default 1e5). ``null_method``:
    "auto" (Imhof's formula at zero noise, the draws otherwise, as SPEC section 9 says),
    "draws" or "imhof" (Imhof's formula for the noncentral quadratic form: exact at any noise).
    ``chunk_size``: simulations per compiled call.
    """

    runs: int = 1000
    level: float = 0.05
    n_targets: int = 100
    n_control: int = 10
    seed: int = 0
    chunk_size: int = 100
    progress: bool = True
    null_draws: int = 100_000
    null_method: str = "auto"

    def __post_init__(self):
        if int(self.runs) < 1:
            raise ValueError(f"CompatibilityOptions.runs must be >= 1, got {self.runs}")
        if not (0 < self.level < 1):
            raise ValueError(f"CompatibilityOptions.level must be in (0, 1), got {self.level}")
        if not (3 <= int(self.n_control) < int(self.n_targets)):
            raise ValueError(
                "CompatibilityOptions: need 3 <= n_control < n_targets, got "
                f"{self.n_control}, {self.n_targets}"
            )
        if int(self.chunk_size) < 1:
            raise ValueError(f"CompatibilityOptions.chunk_size must be >= 1, got {self.chunk_size}")
        if self.null_method not in ("auto", "draws", "imhof"):
            raise ValueError(
                "CompatibilityOptions.null_method must be 'auto', 'draws' or 'imhof', "
                f"got {self.null_method!r}"
            )
        if int(self.null_draws) < 1000:
            raise ValueError(
                f"CompatibilityOptions.null_draws must be >= 1000, got {self.null_draws}"
            )


@dataclasses.dataclass(frozen=True)
class Design:
    """What a compiled simulation closes over (its cache key): the two sets' scanner settings
    (AP names, architecture, unit lengths, registration tokens), the architecture both scans
    are observed in (panoramic when both sets are, else hybrid: a hybrid set's basis means
    nothing on the back face), the terms of set 2 that get a
    column of their own (``columns2``; the others share set 1's column), the target counts and
    the chi-square(3) quantile of the descriptive share. The room is an argument."""

    scanner1: Scanner
    scanner2: Scanner
    architecture: str
    columns2: tuple
    n_targets: int
    n_control: int
    critical: float


def _columns(set1, set2):
    """Set 2's terms with a column of their own, and P (u x (n1 + n2)) with ``F P e = [J1 J2] e``:
    a term both sets hold with one basis is one column (``e1 - e2``)."""
    n1, n2 = len(set1.names), len(set2.names)
    own, P = [], np.zeros((n1, n1 + n2))
    P[:, :n1] = np.eye(n1)
    rows = []
    for j, name in enumerate(set2.names):
        shared = name in set1.names and same_basis(name, set1.scanner, set2.scanner)
        if shared:
            P[set1.names.index(name), n1 + j] = -1.0
        else:
            own.append(j)
            row = np.zeros(n1 + n2)
            row[n1 + j] = 1.0
            rows.append(row)
    return tuple(own), np.vstack([P] + rows) if rows else P


@dataclasses.dataclass(frozen=True, eq=False)
class CompatibilityResult:
    """Result of :func:`compatibility_test` (fields in the module docstring's terms).

    Decision: ``statistic`` T, ``p_value``, ``p_method`` ("draws" or "imhof"),
    ``critical_value`` (the null's 1 - alpha quantile), ``compatible`` (p > alpha).
    Visibility: ``eigenvalues`` lambda of the difference directions (descending), their
    ``directions`` (columns: set 1's then set 2's APs, SI), ``direction_text`` (each in units of
    the difference sigma), ``seen_share`` (post-fit / pre-fit sum of squares), ``least_visible``
    and ``invisible`` (differences object space cannot see); ``null_eigenvalues``: all of
    ``L^T G L``; ``null_matrix`` ``L^T G L``, ``null_vector`` ``L^T b``, ``null_constant`` c.
    Description: ``shares`` per simulation, ``median_share``, ``share_quartiles``, ``rms_mm``
    (X, Y, Z, 3D). Naive test: ``naive_*`` on the union of names (``naive_meaningful`` False
    when a shared term's basis differs between the sets; ``naive_note`` says why).
    """

    ap_names: tuple
    ap_units: tuple
    difference: np.ndarray
    difference_sigma: np.ndarray
    statistic: float
    p_value: float
    p_method: str
    critical_value: float
    compatible: bool
    eigenvalues: np.ndarray
    directions: np.ndarray
    direction_labels: tuple
    direction_text: tuple
    seen_share: np.ndarray
    least_visible: str
    invisible: tuple
    null_eigenvalues: np.ndarray
    null_matrix: np.ndarray
    null_vector: np.ndarray
    null_constant: float
    shares: np.ndarray
    median_share: float
    share_quartiles: tuple
    rms_mm: np.ndarray
    naive_chi2: float
    naive_dof: int
    naive_p_value: float
    naive_compatible: bool
    naive_meaningful: bool
    naive_note: str
    noise: tuple
    level: float
    runs: int
    null_draws: int
    n_failed: int
    notes: tuple
    compile_s: float
    run_s: float

    def summary(self) -> str:
        """The report as text: AP differences, the decision, visibility, description, naive."""
        head = (
            f"AP-set compatibility test (SPEC section 9; Lichti 2008; Chow et al. 2013, 4.3): "
            f"{self.runs} simulations, alpha {self.level:g}"
        )
        lines = [head, f"{'AP':7s} {'unit':>4s} {'set1 - set2':>12s} {'sigma':>10s}"]
        for k, n in enumerate(self.ap_names):
            f, u = display_unit(self.ap_units[k])
            lines.append(
                f"{n:7s} {u:>4s} {self.difference[k] * f:12.4f} {self.difference_sigma[k] * f:10.4f}"
            )
        (r1, h1, e1), (r2, h2, e2) = self.noise
        lines += [
            f'noise: scan 1 {r1 * 1e3:.3g} mm, {h1 / _ARCSEC:.3g}", {e1 / _ARCSEC:.3g}"; '
            f'scan 2 {r2 * 1e3:.3g} mm, {h2 / _ARCSEC:.3g}", {e2 / _ARCSEC:.3g}"',
            f"T = mean d^T C^-1 d = {self.statistic:.4f}; null: {self.p_method}, "
            f"{100 * (1 - self.level):g} % quantile {self.critical_value:.4f}",
            f"p-value {_fmt_p(self.p_value)}: {'compatible' if self.compatible else 'NOT compatible'}",
            "object-space visibility of the difference directions (1 = fully seen, 0 = not):",
        ]
        for lam, s, text in zip(self.eigenvalues, self.seen_share, self.direction_text):
            lines.append(f"  {lam:8.4f}  (kept after the fit {100 * s:6.2f} %)  {text}")
        lines.append(f"least visible: {self.least_visible}")
        for text in self.invisible:
            lines.append(f"object space cannot see: {text}")
        q1, q3 = self.share_quartiles
        lines += [
            f"share of check points with d^T C^-1 d above chi2(3) (descriptive): median "
            f"{100 * self.median_share:.1f} %, quartiles {100 * q1:.1f} / {100 * q3:.1f} %",
            f"RMS of check-point differences [mm]: X {self.rms_mm[0]:.3f}, "
            f"Y {self.rms_mm[1]:.3f}, Z {self.rms_mm[2]:.3f}, 3D {self.rms_mm[3]:.3f}",
            "naive chi-square test of the AP differences (ignores the correlations with the "
            "EOPs; for comparison only): "
            f"chi2 {self.naive_chi2:.2f}, dof {self.naive_dof}, p {_fmt_p(self.naive_p_value)}: "
            f"{'compatible' if self.naive_compatible else 'NOT compatible'}"
            + ("" if self.naive_meaningful else f" -- NOT MEANINGFUL: {self.naive_note}"),
        ]
        if self.n_failed:
            lines.append(f"{self.n_failed} simulations with non-finite values were excluded")
        lines += list(self.notes)
        return "\n".join(lines)

    def to_dict(self) -> dict:
        """The result as plain JSON values (SI units, mm for the RMS; undefined values None)."""
        return to_json_value(
            {
                "test": "AP-set compatibility (SPEC section 9)",
                "compatible": self.compatible,
                "p_value": self.p_value,
                "p_method": self.p_method,
                "statistic": self.statistic,
                "critical_value": self.critical_value,
                "level": self.level,
                "runs": self.runs,
                "null_draws": self.null_draws if self.p_method == "draws" else None,
                "n_failed": self.n_failed,
                "noise": [
                    dict(zip(("sigma_range_m", "sigma_hz_rad", "sigma_el_rad"), n))
                    for n in self.noise
                ],
                "aps": {
                    n: {"difference": d, "sigma": s, "unit": u}
                    for n, d, s, u in zip(
                        self.ap_names, self.difference, self.difference_sigma, self.ap_units
                    )
                },
                "visibility": [
                    {"eigenvalue": lam, "seen_share": s, "direction": t}
                    for lam, s, t in zip(self.eigenvalues, self.seen_share, self.direction_text)
                ],
                "least_visible": self.least_visible,
                "invisible": list(self.invisible),
                "null_eigenvalues": self.null_eigenvalues,
                "share": {
                    "median": self.median_share,
                    "quartiles": list(self.share_quartiles),
                    "descriptive": True,
                },
                "rms_mm": dict(zip(("X", "Y", "Z", "3D"), self.rms_mm)),
                "naive_chi2_test": {
                    "label": "naive chi-square test of the AP differences (for comparison only)",
                    "chi2": self.naive_chi2,
                    "dof": self.naive_dof,
                    "p_value": self.naive_p_value,
                    "compatible": self.naive_compatible,
                    "meaningful": self.naive_meaningful,
                    "note": self.naive_note or None,
                },
                "notes": list(self.notes),
            }
        )


_ARCSEC = math.pi / 648000.0


def _fmt_p(p: float) -> str:
    return "nan" if not np.isfinite(p) else (f"{p:.4f}" if p >= 1e-4 else f"{p:.2e}")


# ------------------------------------------------------------------------------------------
# Inputs


def _prepare(set1, set2, room, scanner, options, sigma_range, sigma_angle):
    """Validated sets (with the scanner override), design, noise (2, 3) and arrays."""
    for s, k in ((set1, 1), (set2, 2)):
        if not isinstance(s, APSet):
            raise ValueError(
                f"compatibility_test: set{k} must be an APSet "
                "(APSet.from_result / from_json / from_values)"
            )
        if not s.names:
            raise ValueError(f"compatibility_test: set{k} ({s.source}) has no APs")
    if scanner is not None:
        set1, set2 = (_with_scanner(s, scanner) for s in (set1, set2))
    room = room or Room()
    noise = tuple(_noise(s, sigma_range, sigma_angle) for s in (set1, set2))
    own, _ = _columns(set1, set2)
    both = {set1.scanner.architecture, set2.scanner.architecture}
    design = Design(
        set1.scanner.current(),  # the registration tokens now (tlsjax/_model/_aps.py)
        set2.scanner.current(),
        "panoramic" if both == {"panoramic"} else "hybrid",
        own,
        int(options.n_targets),
        int(options.n_control),
        chi2_quantile(1.0 - options.level, 3),
    )
    return set1, set2, design, noise, room_vector(room)


def _setup(set1, set2, room, scanner, options, sigma_range, sigma_angle):
    """:func:`_prepare`, then P onto the union columns and the covariance ``Cu`` of ``P e``."""
    set1, set2, design, noise, room_vec = _prepare(
        set1, set2, room, scanner, options, sigma_range, sigma_angle
    )
    _, P = _columns(set1, set2)
    Cu = P @ _block(set1.covariance, set2.covariance) @ P.T
    return set1, set2, design, noise, room_vec, P, Cu


def _with_scanner(s: APSet, scanner: Scanner) -> APSet:
    if not isinstance(scanner, Scanner):
        raise ValueError("compatibility_test: scanner must be a tlsjax.Scanner")
    return dataclasses.replace(s, scanner=scanner)


def _noise(s: APSet, sigma_range, sigma_angle):
    base = s.noise or (DEFAULT_SIGMA_RANGE, DEFAULT_SIGMA_ANGLE, DEFAULT_SIGMA_ANGLE)
    r = base[0] if sigma_range is None else float(sigma_range)
    h, e = base[1:] if sigma_angle is None else (float(sigma_angle),) * 2
    if not all(np.isfinite(v) and v >= 0 for v in (r, h, e)):
        raise ValueError(
            f"compatibility_test: the noise must be finite and non-negative, got {r}, {h}, {e}"
        )
    return (r, h, e)


def _sqrt_psd(C):
    """Symmetric square root of a PSD matrix; eigenvalues at rounding level are exact zeros."""
    if C.size == 0:
        return C
    w, V = np.linalg.eigh(C)
    w = np.where(w > 1e-14 * max(w.max(), 1e-300), w, 0.0)
    return (V * np.sqrt(w)) @ V.T


def _block(a, b):
    out = np.zeros((a.shape[0] + b.shape[0],) * 2)
    out[: a.shape[0], : a.shape[0]] = a
    out[a.shape[0] :, a.shape[0] :] = b
    return out


# ------------------------------------------------------------------------------------------
# The null: the quadratic form in e, its p-value and its eigenvalues


def null_p_value(T, lam, gamma, c, *, method, draws, rng, alpha=None):
    """p = P(T(e) >= T) for ``T(e) = sum_k lam_k y_k^2 + 2 gamma_k y_k + c`` with y ~ N(0, I)
    (the quadratic form rotated to the eigenvectors of ``L^T G L``). ``method`` "draws":
    ``draws`` seeded draws, p = (1 + #{T(e) >= T}) / (draws + 1); "imhof": Imhof's formula,
    exact (``T(e) = c - sum gamma^2 / lam + sum lam (y + gamma / lam)^2``, a weighted sum of
    noncentral chi-square(1)). With ``alpha``, also the null's 1 - alpha quantile (else NaN).
    Returns (p, quantile)."""
    keep = lam > 1e-12 * max(float(lam.max(initial=0.0)), 1e-300)
    lam, gamma = lam[keep], gamma[keep]
    if not np.isfinite(T):
        return float("nan"), float("nan")
    if method == "imhof":
        shift = c - float(np.sum(gamma**2 / lam))
        nc = (gamma / lam) ** 2
        p = weighted_chi2_sf(T - shift, lam, nc)
        q = float("nan") if alpha is None else shift + _weighted_chi2_quantile(1 - alpha, lam, nc)
        return p, q
    # T(e) - c in single precision: its terms are O(1) at most and the comparison with
    # T - c needs no more digits; it halves the time of the 1e5 draws.
    y = rng.standard_normal((int(draws), lam.size), dtype=np.float32)
    Te = (y * y) @ lam.astype(np.float32) + (y @ (2.0 * gamma).astype(np.float32))
    p = (1.0 + np.count_nonzero(Te >= np.float32(T - c))) / (draws + 1.0)
    q = float("nan") if alpha is None else c + float(np.quantile(Te, 1.0 - alpha))
    return float(p), q


def _weighted_chi2_quantile(q, lam, nc):
    from scipy.optimize import brentq

    if lam.size == 0:
        return 0.0
    mean = float(np.sum(lam * (1.0 + nc)))
    sd = float(np.sqrt(2.0 * np.sum(lam**2 * (1.0 + 2.0 * nc))))
    hi = mean + 40.0 * sd + 1.0
    return float(brentq(lambda x: (1.0 - weighted_chi2_sf(x, lam, nc)) - q, 0.0, hi, xtol=1e-9))


def _method(options, noise):
    """The p-value's method: Imhof's formula at zero noise, seeded draws otherwise, unless
    ``options.null_method`` names one."""
    if options.null_method != "auto":
        return options.null_method
    return "imhof" if not any(any(v > 0 for v in n) for n in noise) else "draws"


def _quadratic_form(sums, n, L, P):
    """Mean T, whitened ``A = L P^T G P L``, ``beta = L P^T b``, c over ``n`` check points (G
    and b on the union columns, P onto them from e = (e1, e2))."""
    T = float(sums["T"]) / n
    A = L @ P.T @ (np.asarray(sums["G"]) / n) @ P @ L
    beta = L @ P.T @ (np.asarray(sums["b"]) / n)
    return T, 0.5 * (A + A.T), beta, float(sums["c"]) / n


# ------------------------------------------------------------------------------------------
# Reporting: the union of names, the naive test, the difference directions


def _union(set1, set2):
    """Labels of the report and how each maps from (set 1's, set 2's) AP vectors: a term of
    both sets with one basis is one label (difference a1 - a2); a term whose basis differs gets
    one label per set ("B6[1]", "B6[2]")."""
    rows = []  # (label, index in set 1 or None, index in set 2 or None, unit)
    for i, n in enumerate(set1.names):
        if n in set2.names:
            j = set2.names.index(n)
            if same_basis(n, set1.scanner, set2.scanner):
                rows.append((n, i, j))
            else:
                rows.append((f"{n}[1]", i, None))
        else:
            rows.append((n, i, None))
    for j, n in enumerate(set2.names):
        if n not in set1.names:
            rows.append((n, None, j))
        elif not same_basis(n, set1.scanner, set2.scanner):
            rows.append((f"{n}[2]", None, j))
    return rows


def _union_vectors(rows, set1, set2, d1, d2):
    """Difference a1 - a2 per label and its sigma (from the two covariances)."""
    diff, sig = np.zeros(len(rows)), np.zeros(len(rows))
    for k, (_, i, j) in enumerate(rows):
        v, var = 0.0, 0.0
        if i is not None:
            v += d1[i]
            var += set1.covariance[i, i]
        if j is not None:
            v -= d2[j]
            var += set2.covariance[j, j]
        diff[k], sig[k] = v, math.sqrt(max(var, 0.0))
    return diff, sig


def _naive(set1, set2, alpha, values1=None, values2=None):
    """The naive chi-square test of the AP differences on the union of names: (chi2, dof, p,
    compatible, meaningful, note); chi2 and p are arrays for stacked ``values1``/``values2``."""
    names = tuple(set1.names) + tuple(n for n in set2.names if n not in set1.names)
    a1, C1 = set1.on(names)
    a2, C2 = set2.on(names)
    if values1 is not None:
        idx1 = [names.index(n) for n in set1.names]
        idx2 = [names.index(n) for n in set2.names]
        a1 = np.zeros((len(values1), len(names)))
        a2 = np.zeros((len(values2), len(names)))
        a1[:, idx1], a2[:, idx2] = values1, values2
    delta, Cd = a1 - a2, C1 + C2
    rank = int(np.linalg.matrix_rank(Cd, hermitian=True)) if Cd.size else 0
    Cp = np.linalg.pinv(Cd, rcond=1e-12, hermitian=True)
    chi2 = np.einsum("...i,ij,...j->...", delta, Cp, delta)
    p = np.vectorize(lambda x: chi2_sf(x, rank) if rank else float("nan"))(chi2)
    if values1 is None:
        chi2, p = float(chi2), float(p)
        return chi2, rank, p, bool(p > alpha), *_naive_note(set1, set2)
    return chi2, rank, p, p > alpha, *_naive_note(set1, set2)


def _naive_note(set1, set2):
    """(meaningful, note): the naive test is not meaningful when a shared term's basis differs."""
    differ = [
        f"{n}: {basis_text(n, set1.scanner)} vs {basis_text(n, set2.scanner)}"
        for n in set1.names
        if n in set2.names and not same_basis(n, set1.scanner, set2.scanner)
    ]
    note = ""
    if differ:
        note = "the sets' basis functions differ (" + "; ".join(differ) + ")"
    return not differ, note


def _describe(vec, labels, top=3):
    order = np.argsort(-np.abs(vec))
    parts = [f"{labels[k]} {vec[k]:+.2f}" for k in order[:top] if abs(vec[k]) >= 0.05]
    return ", ".join(parts) if parts else "(none)"


def _visibility(A, L, P, ref, rows, set1, set2):
    """Eigenvalues of ``L^T G L`` on the difference directions (common moves left out), their
    AP directions, texts and the share of each direction's effect the rigid fit keeps."""
    n1 = len(set1.names)
    Kw = L @ P.T @ np.asarray(ref["Kpre"]) @ P @ L
    Ew = L @ P.T @ np.asarray(ref["Geu"]) @ P @ L
    w, V = np.linalg.eigh(0.5 * (Kw + Kw.T))
    Q = V[:, w > COMMON * max(float(w.max(initial=0.0)), 1e-300)]
    lam, U = np.linalg.eigh(Q.T @ A @ Q)
    order = np.argsort(-lam)
    lam, U = lam[order], Q @ U[:, order]
    directions = L @ U  # (m, r): set 1's APs, then set 2's
    seen = np.einsum("mr,mk,kr->r", U, Ew, U) / np.maximum(
        np.einsum("mr,mk,kr->r", U, Kw, U), 1e-300
    )
    labels = [r[0] for r in rows]
    texts = []
    for k in range(U.shape[1]):
        d, s = _union_vectors(rows, set1, set2, directions[:n1, k], directions[n1:, k])
        z = np.where(s > 0, d / np.where(s > 0, s, 1.0), 0.0)
        z = z / max(np.linalg.norm(z), 1e-300)
        z = z * np.sign(z[np.argmax(np.abs(z))])
        texts.append(_describe(z, labels))
    invisible = tuple(t for t, s in zip(texts, seen) if s < INVISIBLE)
    least = f"lambda {lam[-1]:.4f}: {texts[-1]}" if lam.size else "(no difference directions)"
    return np.clip(lam, 0.0, None), directions, tuple(labels), tuple(texts), seen, least, invisible


# ------------------------------------------------------------------------------------------
# The test


def compatibility_test(
    set1: APSet,
    set2: APSet,
    room: Room | None = None,
    scanner: Scanner | None = None,
    options: CompatibilityOptions | None = None,
    *,
    sigma_range: float | None = None,
    sigma_angle: float | None = None,
) -> CompatibilityResult:
    """Are two AP sets of one instrument compatible? The simulation test of SPEC section 9
    (Lichti 2008; Chow et al. 2013, section 4.3); the statistic, its exact null and the report
    are written out in the module docstring.

    ``room``: the room of the real data (default 14 x 11 x 3 m), the scanner at its first
    station. ``scanner``: when given, overrides both sets' scanner settings (architecture and
    unit lengths); by default each set is applied with its own basis functions to scans
    observed as a panoramic scanner when both sets are panoramic, else as a hybrid one.
    ``sigma_range`` [m] at normal incidence and ``sigma_angle`` [rad] (both angles) of both
    scans; by default each scan has
    the noise of the data its set came from (``APSet.noise``), or 0.5 mm and 20" when unknown;
    0 gives the pure object-space test. All simulations run as one compiled, vmapped
    computation in chunks, sharded over the devices; another test of the same design (AP
    names, scanner settings, room, target counts, alpha) does not recompile.
    """
    options = options or CompatibilityOptions()
    set1, set2, design, noise, room_vec, P, Cu = _setup(
        set1, set2, room, scanner, options, sigma_range, sigma_angle
    )
    N, n_check = int(options.runs), design.n_targets - design.n_control
    t0 = time.perf_counter()
    b = compiled_chunk(design, round_chunk(min(options.chunk_size, N)), device_key())
    compile_s = time.perf_counter() - t0
    key = jax.random.PRNGKey(int(options.seed))
    rest = (Cu, np.asarray(noise[0]), np.asarray(noise[1]), room_vec)
    V1, V2 = set1.values[None], set2.values[None]
    out, run_s = run_tests(b, key, N, V1, V2, rest, reference=True, progress=options.progress)
    ref = {k: v[: min(b.chunk, N)] for k, v in out.items()}
    good = (
        np.all(np.isfinite(out["G"]), axis=(1, 2)) & np.isfinite(out["T"]) & np.isfinite(out["c"])
    )
    sums = {k: v[good].sum(axis=0) for k, v in out.items()}
    ref = {k: v[np.all(np.isfinite(ref["G"]), axis=(1, 2))].sum(axis=0) for k, v in ref.items()}
    n_pts = max(int(good.sum()), 1) * n_check
    res = _analyse(set1, set2, P, options, sums, ref, n_pts, _method(options, noise))
    shares = out["n_sig"] / n_check
    q1, med, q3 = (float(v) for v in np.quantile(shares[good], [0.25, 0.5, 0.75]))
    ms = sums["ss"] / n_pts
    rms = 1e3 * np.sqrt(np.concatenate([ms, [ms.sum()]]))
    notes = tuple(set1.notes) + tuple(set2.notes)
    return CompatibilityResult(
        **res,
        shares=shares,
        median_share=med,
        share_quartiles=(q1, q3),
        rms_mm=rms,
        noise=noise,
        level=float(options.level),
        runs=N,
        null_draws=int(options.null_draws),
        n_failed=int((~good).sum()),
        notes=notes,
        compile_s=compile_s,
        run_s=run_s,
    )


def _analyse(set1, set2, P, options, sums, ref, n_pts, method):
    """Everything of the result that follows from the check-point sums."""
    L = _block(_sqrt_psd(set1.covariance), _sqrt_psd(set2.covariance))
    T, A, beta, c = _quadratic_form(sums, n_pts, L, P)
    lam_all, U = np.linalg.eigh(A)
    rng = np.random.default_rng([int(options.seed), 29])
    p, crit = null_p_value(
        T,
        np.clip(lam_all, 0.0, None),
        U.T @ beta,
        c,
        method=method,
        draws=int(options.null_draws),
        rng=rng,
        alpha=options.level,
    )
    rows = _union(set1, set2)
    diff, sig = _union_vectors(rows, set1, set2, set1.values, set2.values)
    lam, dirs, labels, texts, seen, least, invisible = _visibility(A, L, P, ref, rows, set1, set2)
    chi2, rank, p_naive, naive_ok, meaningful, note = _naive(set1, set2, options.level)
    units = tuple(get_ap(r[0].split("[")[0]).unit for r in rows)
    return {
        "ap_names": labels,
        "ap_units": units,
        "difference": diff,
        "difference_sigma": sig,
        "statistic": T,
        "p_value": p,
        "p_method": method,
        "critical_value": crit,
        "compatible": bool(p > options.level),
        "eigenvalues": lam,
        "directions": dirs,
        "direction_labels": tuple(f"{k}:{n}" for k, s in ((1, set1), (2, set2)) for n in s.names),
        "direction_text": texts,
        "seen_share": seen,
        "least_visible": least,
        "invisible": invisible,
        "null_eigenvalues": np.sort(lam_all)[::-1],
        "null_matrix": A,
        "null_vector": beta,
        "null_constant": c,
        "naive_chi2": chi2,
        "naive_dof": rank,
        "naive_p_value": p_naive,
        "naive_compatible": naive_ok,
        "naive_meaningful": meaningful,
        "naive_note": note,
    }


# ------------------------------------------------------------------------------------------
# Many tests of one design at once (level and power studies), and T as a function


def compatibility_batch(
    set1: APSet,
    set2: APSet,
    values1,
    values2,
    room: Room | None = None,
    scanner: Scanner | None = None,
    options: CompatibilityOptions | None = None,
    *,
    sigma_range: float | None = None,
    sigma_angle: float | None = None,
) -> dict:
    """Many independent compatibility tests of one design in one compiled call: pair k uses
    ``values1[k]`` and ``values2[k]`` with the covariances and settings of ``set1``/``set2`` and
    its own ``options.runs`` simulations (keys ``fold_in(PRNGKey(seed), k)``). For size and power
    studies: the decision of each pair is exactly :func:`compatibility_test`'s (same statistic
    and null), without the visibility report. Returns arrays (P,): ``p_value``, ``statistic``,
    ``compatible``, ``median_share`` (the descriptive share's median over the pair's
    simulations), ``naive_chi2``, ``naive_p_value``."""
    options = options or CompatibilityOptions()
    set1, set2, design, noise, room_vec, P, Cu = _setup(
        set1, set2, room, scanner, options, sigma_range, sigma_angle
    )
    V1 = np.atleast_2d(np.asarray(values1, dtype=np.float64))
    V2 = np.atleast_2d(np.asarray(values2, dtype=np.float64))
    if V1.shape[1:] != (len(set1.names),) or V2.shape != (V1.shape[0], len(set2.names)):
        raise ValueError(
            f"compatibility_batch: values1 must be (P, {len(set1.names)}) and values2 "
            f"(P, {len(set2.names)}), got {V1.shape} and {V2.shape}"
        )
    runs = int(options.runs)
    b = compiled_chunk(design, round_chunk(options.chunk_size), device_key())
    rest = (Cu, np.asarray(noise[0]), np.asarray(noise[1]), room_vec)
    out, _ = run_tests(b, jax.random.PRNGKey(int(options.seed)), runs, V1, V2, rest)
    sums = {k: v.reshape((V1.shape[0], runs) + v.shape[1:]).sum(axis=1) for k, v in out.items()}
    n_sig = out["n_sig"].reshape(V1.shape[0], runs)
    n_check = design.n_targets - design.n_control
    L = _block(_sqrt_psd(set1.covariance), _sqrt_psd(set2.covariance))
    p, T = _batch_p(sums, runs * n_check, L, P, options, _method(options, noise))
    chi2, _, p_naive, *_ = _naive(set1, set2, options.level, V1, V2)
    return {
        "p_value": p,
        "statistic": T,
        "compatible": p > options.level,
        "median_share": np.median(n_sig / n_check, axis=1),
        "naive_chi2": chi2,
        "naive_p_value": p_naive,
    }


def _batch_p(sums, n_pts, L, P, options, method):
    """p-value and T of each test of a batch from its check-point sums (stacked along axis 0)."""
    rng = np.random.default_rng([int(options.seed), 29])
    n = len(sums["T"])
    p, T = np.empty(n), np.empty(n)
    for k in range(n):
        T[k], A, beta, c = _quadratic_form({key: v[k] for key, v in sums.items()}, n_pts, L, P)
        lam, U = np.linalg.eigh(A)
        draws = int(options.null_draws)
        p[k] = null_p_value(
            T[k], np.clip(lam, 0, None), U.T @ beta, c, method=method, draws=draws, rng=rng
        )[0]
    return p, T


def compatibility_statistic(
    set1: APSet,
    set2: APSet,
    room: Room | None = None,
    scanner: Scanner | None = None,
    options: CompatibilityOptions | None = None,
    *,
    sigma_range: float | None = None,
    sigma_angle: float | None = None,
):
    """The statistic T of :func:`compatibility_test` as a pure JAX function ``T(a1, a2)`` of the
    two AP vectors (in the sets' own term orders, SI), with the sets' covariances, the noise and
    ``options.runs`` simulations of seed ``options.seed`` fixed: jit-, vmap- and
    grad-compatible (``jax.grad(T)(a1, a2)`` is dT/da1)."""
    options = options or CompatibilityOptions()
    set1, set2, design, noise, room_vec, P, Cu = _setup(
        set1, set2, room, scanner, options, sigma_range, sigma_angle
    )
    f = statistic_function(design, int(options.runs))
    key = jax.random.PRNGKey(int(options.seed))
    s1, s2 = np.asarray(noise[0]), np.asarray(noise[1])
    return lambda a1, a2: f(a1, a2, Cu, s1, s2, room_vec, key)
