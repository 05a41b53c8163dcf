"""AP-set compatibility test by simulation (SPEC section 9; Lichti 2008; Chow et al. 2013, 4.3).

Two AP sets of one instrument (two sessions, or point-based vs plane-based calibration of the
same scans) can differ in which terms are significant, and their APs are correlated with the
EOPs and with each other, so comparing APs one by one misleads (Habib & Morgan 2005). The test
compares their joint effect in object space.

**The statistic** (SPEC section 9):

1. Inputs: AP sets 1 and 2 with their covariance matrices (on the union of their terms; a term
   absent from a set is zero with zero variance), a room and scanner design, the noise, N
   (default 1,000) and alpha (default 5%).
2. For each simulation: draw 100 targets over the room's surfaces (uniform by area, so at
   different distances from the scanner), pick 10 as control; simulate the observations once
   from one levelled scan at the room's first station; correct them with set 1 and with set 2
   (``l - Delta(l; AP)``); convert both to Cartesian coordinates; transform set 2 onto set 1 by
   a rigid-body least-squares fit on the 10 control points (closed form, Kabsch/Horn by SVD).
3. At the 90 check points, the coordinate differences ``d_i`` and their covariance
   ``C_i = J1_i C_1 J1_i^T + J2_i C_2 J2_i^T`` (independent sessions: they add), propagated from
   the two AP covariances through correction, conversion and the control-point fit by autodiff
   (``jax.jacfwd``); per point ``T_i = d_i^T C_i^-1 d_i``, significant when above the
   chi-square(3) quantile at alpha. The simulation's statistic is the share of significant
   check points.
4. The null distribution of the share comes from the same simulations with both AP sets
   replaced by draws around their common weighted mean ``a = a_1 + C_1 (C_1 + C_2)^+ (a_2 -
   a_1)`` with their own covariances. The sets are compatible when the observed median share
   does not exceed the null distribution's (1 - alpha) quantile; the p-value is
   ``(1 + #{null share >= observed median}) / (N + 1)``. Reported with the shares and the RMS of
   the differences in mm.
5. Beside it, labelled as such, the naive chi-square test of the AP differences:
   ``(a_1 - a_2)^T (C_1 + C_2)^+ (a_1 - a_2) ~ chi-square(rank)``.

``C_i`` gets a relative ridge of 1e-12 of its trace so that a point whose difference is
determined by fewer than three independent AP combinations still gives a finite ``T_i``.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np

from .._adjustment._linalg import spd_inverse
from .._adjustment._network import DEFAULT_SIGMA_ANGLE, DEFAULT_SIGMA_RANGE
from .._model._aps import ap_corrections, get_ap, on_reregistration, resolve_aps
from .._model._geometry import cartesian_from_spherical, rigid_fit, spherical_from_cartesian
from .._model._points import distorted_observations
from .._model._scanner import Scanner
from .._simulation._batch import compile_batched, device_key, round_chunk, run_batched
from .._simulation._room import Room
from .._stats import chi2_quantile, chi2_sf
from .._units import display_unit


@dataclasses.dataclass(frozen=True, eq=False)
class APSet:
    """One AP set: names, values [SI] and their covariance [SI^2] (a posteriori)."""

    names: tuple
    values: np.ndarray
    covariance: np.ndarray
    source: str = "<arrays>"

    def __post_init__(self):
        names = resolve_aps(self.names)
        v = np.asarray(self.values, dtype=np.float64).reshape(-1)
        C = np.asarray(self.covariance, dtype=np.float64)
        if v.shape != (len(names),):
            raise ValueError(f"{self.source}: {len(names)} AP names but {v.size} values")
        if C.shape != (len(names), len(names)):
            raise ValueError(
                f"{self.source}: AP covariance must be {len(names)} x {len(names)}, got {C.shape}"
            )
        if not (np.all(np.isfinite(v)) and np.all(np.isfinite(C))):
            raise ValueError(
                f"{self.source}: AP values and covariance must be finite (a non-estimable AP cannot be compared)"
            )
        if np.linalg.eigvalsh(0.5 * (C + C.T)).min() < -1e-9 * max(np.trace(C), 1e-300):
            raise ValueError(f"{self.source}: AP covariance is not positive semi-definite")
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "values", v)
        object.__setattr__(self, "covariance", 0.5 * (C + C.T))

    @classmethod
    def from_values(cls, names, values, covariance=None, sigmas=None, source="<arrays>") -> APSet:
        """From values and either a covariance matrix or sigmas (then uncorrelated)."""
        if covariance is None:
            if sigmas is None:
                raise ValueError(f"{source}: give the AP covariance or the AP sigmas")
            covariance = np.diag(np.asarray(sigmas, dtype=np.float64) ** 2)
        return cls(tuple(resolve_aps(names)), values, covariance, source)

    @classmethod
    def from_result(cls, result) -> APSet:
        """From a :class:`tlsjax.CalibrationResult` (full AP covariance when it was formed)."""
        names = tuple(result.ap_names)
        if result.not_estimable:
            raise ValueError(
                f"result has non-estimable APs ({', '.join(n for n, *_ in result.not_estimable)}); refit without them"
            )
        if result.covariance is not None:
            idx = [list(result.parameter_names).index(n) for n in names]
            C = np.asarray(result.covariance)[np.ix_(idx, idx)]
        else:
            C = np.diag(np.asarray(result.ap_sigmas) ** 2)
        return cls(names, np.asarray(result.ap_values), C, "<CalibrationResult>")

    @classmethod
    def from_json(cls, path) -> APSet:
        """From a tlsjax result JSON (SPEC section 11): ``aps`` {name: {value, sigma}} in SI
        units; optional ``ap_covariance`` (list of rows, SI) with ``ap_covariance_names`` (its
        row order). Without the covariance the APs are taken as uncorrelated."""
        path = pathlib.Path(path)
        try:
            doc = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise ValueError(f"{path}: cannot read a tlsjax result JSON ({exc})") from None
        aps = doc.get("aps") if isinstance(doc, dict) else None
        if not isinstance(aps, dict) or not aps:
            raise ValueError(f"{path}: no 'aps' object with per-AP 'value' and 'sigma'")
        names, vals, sig = [], [], []
        for name, rec in aps.items():
            if isinstance(rec, dict) and rec.get("value", 0) is None:
                # tlsjax writes non-estimable APs as null, never as numbers.
                raise ValueError(
                    f"{path}: aps.{name} is not estimable in this result; refit without it"
                )
            try:
                v, s = float(rec["value"]), float(rec["sigma"])
            except (KeyError, TypeError, ValueError):
                raise ValueError(f"{path}: aps.{name} needs numeric 'value' and 'sigma'") from None
            if not (np.isfinite(v) and np.isfinite(s)):
                raise ValueError(
                    f"{path}: aps.{name} is not estimable (value {v}, sigma {s}); refit without it"
                )
            names.append(name)
            vals.append(v)
            sig.append(s)
        C = np.diag(np.square(sig))
        if doc.get("ap_covariance") is not None:
            cn = doc.get("ap_covariance_names")
            M = np.asarray(doc["ap_covariance"], dtype=np.float64)
            if not isinstance(cn, list) or M.shape != (len(cn), len(cn)):
                raise ValueError(
                    f"{path}: 'ap_covariance' must be a square list of rows with matching 'ap_covariance_names'"
                )
            missing = [n for n in names if n not in cn]
            if missing:
                raise ValueError(f"{path}: 'ap_covariance_names' lacks {', '.join(missing)}")
            idx = [cn.index(n) for n in names]
            C = M[np.ix_(idx, idx)]
        try:
            return cls(tuple(names), np.array(vals), C, str(path))
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from None

    def on(self, names) -> tuple[np.ndarray, np.ndarray]:
        """Values and covariance on ``names`` (a superset): absent terms are zero, zero variance."""
        idx = np.array([names.index(n) for n in self.names], dtype=int)
        v = np.zeros(len(names))
        C = np.zeros((len(names), len(names)))
        v[idx] = self.values
        C[np.ix_(idx, idx)] = self.covariance
        return v, C


@dataclasses.dataclass(frozen=True)
class CompatibilityOptions:
    """Settings of :func:`compatibility_test` (defaults: Chow et al. 2013, section 4.3)."""

    runs: int = 1000
    alpha: float = 0.05
    n_targets: int = 100
    n_control: int = 10
    seed: int = 0
    chunk_size: int = 100
    progress: bool = True

    def __post_init__(self):
        if int(self.runs) < 2:
            raise ValueError(f"CompatibilityOptions.runs must be >= 2, got {self.runs}")
        if not (0 < self.alpha < 1):
            raise ValueError(f"CompatibilityOptions.alpha must be in (0, 1), got {self.alpha}")
        if not (3 <= int(self.n_control) < int(self.n_targets)):
            raise ValueError(
                f"CompatibilityOptions: need 3 <= n_control < n_targets, got {self.n_control}, {self.n_targets}"
            )
        if int(self.chunk_size) < 1:
            raise ValueError(f"CompatibilityOptions.chunk_size must be >= 1, got {self.chunk_size}")


@dataclasses.dataclass(frozen=True, eq=False)
class CompatibilityResult:
    """Result of :func:`compatibility_test`.

    ``shares`` (N,): share of significant check points per simulation with the two given sets;
    ``null_shares`` (N,): the same with both sets drawn around their weighted mean;
    ``median_share``, ``null_quantile`` (its 1 - alpha quantile), ``p_value``, ``compatible``.
    ``rms_mm`` (X, Y, Z, 3D) RMS of the check-point differences over all simulations [mm].
    The naive test of the AP differences: ``naive_chi2``, ``naive_dof``, ``naive_p_value``,
    ``naive_compatible``. ``n_failed``: simulations with non-finite statistics (excluded).
    """

    ap_names: tuple
    ap_units: tuple
    difference: np.ndarray  # a1 - a2 on the union [SI]
    difference_sigma: np.ndarray
    shares: np.ndarray
    null_shares: np.ndarray
    median_share: float
    null_quantile: float
    p_value: float
    compatible: bool
    rms_mm: np.ndarray
    naive_chi2: float
    naive_dof: int
    naive_p_value: float
    naive_compatible: bool
    alpha: float
    runs: int
    n_failed: int
    compile_s: float
    run_s: float

    def table(self) -> str:
        lines = [
            f"AP-set compatibility test (Lichti 2008; Chow et al. 2013, 4.3), {self.runs} simulations, alpha {self.alpha:g}",
            f"{'AP':5s} {'unit':>4s} {'set1 - set2':>12s} {'sigma':>10s}",
        ]
        for k, n in enumerate(self.ap_names):
            f, u = display_unit(self.ap_units[k])
            lines.append(
                f"{n:5s} {u:>4s} {self.difference[k] * f:12.4f} {self.difference_sigma[k] * f:10.4f}"
            )
        lines += [
            f"median share of significant check points: {100 * self.median_share:.1f} %",
            f"null distribution: mean {100 * np.nanmean(self.null_shares):.1f} %, {100 * (1 - self.alpha):g} % quantile {100 * self.null_quantile:.1f} %",
            f"p-value {self.p_value:.4f}: {'compatible' if self.compatible else 'NOT compatible'}",
            f"RMS of check-point differences [mm]: X {self.rms_mm[0]:.3f}, Y {self.rms_mm[1]:.3f}, Z {self.rms_mm[2]:.3f}, 3D {self.rms_mm[3]:.3f}",
            f"naive chi-square test of the AP differences (ignores correlations with EOPs; for comparison only): "
            f"chi2 {self.naive_chi2:.2f}, dof {self.naive_dof}, p {self.naive_p_value:.4f}: "
            f"{'compatible' if self.naive_compatible else 'NOT compatible'}",
        ]
        if self.n_failed:
            lines.append(f"{self.n_failed} simulations with non-finite statistics were excluded")
        return "\n".join(lines)


def _weighted_mean(a1, C1, a2, C2):
    """Common weighted mean on the union; works with zero-variance (absent) terms."""
    S = np.linalg.pinv(C1 + C2, rcond=1e-12, hermitian=True)
    return a1 + C1 @ S @ (a2 - a1)


def _sqrt_psd(C):
    w, V = np.linalg.eigh(C)
    return V * np.sqrt(np.clip(w, 0.0, None))


def _room_points(room: Room, key, n):
    """``n`` points uniform by area over the six faces (margin from the edges)."""
    L, W, H, m = room.length, room.width, room.height, room.margin
    area = np.array([W * H, W * H, L * H, L * H, L * W, L * W])
    axis = np.array([0, 0, 1, 1, 2, 2])
    value = np.array([0.0, L, 0.0, W, 0.0, H])
    normal = np.array(
        [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.float64
    )
    kf, ku = jax.random.split(key)
    face = jax.random.categorical(kf, jnp.log(area / area.sum()), shape=(n,))
    size = np.array([L, W, H])
    u = m + jax.random.uniform(ku, (n, 3)) * (size - 2 * m)
    ax = jnp.asarray(axis)[face]
    X = jnp.where(jnp.arange(3)[None, :] == ax[:, None], jnp.asarray(value)[face][:, None], u)
    return X, jnp.asarray(normal)[face]


def _make_simulation(
    names, scanner, room, station, sigma_range, sigma_angle, n_targets, n_control, alpha
):
    crit = chi2_quantile(1.0 - alpha, 3)
    S = jnp.asarray(station)

    def observations(key, a_true):
        kX, kn = jax.random.split(key)
        X, nrm = _room_points(room, kX, n_targets)
        los = X - S
        cosb = jnp.abs(jnp.sum(los * nrm, axis=1)) / jnp.linalg.norm(los, axis=1)
        sig = jnp.stack(
            [
                sigma_range / jnp.maximum(cosb, 0.05),
                jnp.full(n_targets, sigma_angle),
                jnp.full(n_targets, sigma_angle),
            ],
            axis=1,
        )
        base = spherical_from_cartesian(los) + jax.random.normal(kn, (n_targets, 3)) * sig
        return distorted_observations(base, lambda l: ap_corrections(a_true, names, l, scanner))

    def differences(a1, a2, l):
        x1 = cartesian_from_spherical(l - ap_corrections(a1, names, l, scanner))
        x2 = cartesian_from_spherical(l - ap_corrections(a2, names, l, scanner))
        R, t = rigid_fit(x2[:n_control], x1[:n_control])
        return (x2[n_control:] @ R.T + t) - x1[n_control:]

    jac = jax.jacfwd(differences, argnums=(0, 1))

    def share(a1, a2, C1, C2, l):
        d = differences(a1, a2, l)  # (c, 3)
        J1, J2 = jac(a1, a2, l)  # (c, 3, a)
        C = jnp.einsum("cia,ab,cjb->cij", J1, C1, J1) + jnp.einsum("cia,ab,cjb->cij", J2, C2, J2)
        tr = jnp.trace(C, axis1=1, axis2=2)
        C = C + (1e-12 * tr)[:, None, None] * jnp.eye(3)
        T = jnp.einsum("ci,cij,cj->c", d, spd_inverse(C), d)
        return jnp.mean(T > crit), jnp.sum(d * d, axis=0)

    return observations, share


@functools.lru_cache(maxsize=8)
def _compiled(
    names, scanner, room, sigma_range, sigma_angle, n_targets, n_control, alpha, chunk, devices
):
    """One compiled chunk function per design (and devices); the AP sets and the seed are
    arguments, so repeated tests of one design (e.g. a level study) do not recompile."""
    observations, share = _make_simulation(
        names,
        scanner,
        room,
        room.stations[0],
        sigma_range,
        sigma_angle,
        n_targets,
        n_control,
        alpha,
    )
    na = len(names)

    def one(index, seed_key, a1, a2, C1, C2, a_bar, L1, L2):
        key = jax.random.fold_in(seed_key, index)
        k_obs, k1, k2 = jax.random.split(key, 3)
        l = observations(k_obs, a_bar)
        s_obs, ss = share(a1, a2, C1, C2, l)
        b1 = a_bar + L1 @ jax.random.normal(k1, (na,))
        b2 = a_bar + L2 @ jax.random.normal(k2, (na,))
        s_null, _ = share(b1, b2, C1, C2, l)
        return s_obs, s_null, ss

    v, m = jnp.zeros(na), jnp.zeros((na, na))
    return compile_batched(one, (jax.random.PRNGKey(0), v, v, m, m, v, m, m), chunk)


# Keyed on AP names, not on their bases: emptied when a term is re-registered.
on_reregistration(_compiled.cache_clear)


def compatibility_test(
    set1: APSet,
    set2: APSet,
    room: Room | None = None,
    scanner: Scanner | None = None,
    options: CompatibilityOptions | None = None,
    *,
    sigma_range: float = DEFAULT_SIGMA_RANGE,
    sigma_angle: float = DEFAULT_SIGMA_ANGLE,
) -> CompatibilityResult:
    """Are two AP sets of one instrument compatible? The simulation test of SPEC section 9
    (Lichti 2008; Chow et al. 2013, section 4.3; see the module docstring for the statistic).

    ``room``: the room of the real data (default 14 x 11 x 3 m), the scanner at its first
    station. ``scanner``: architecture and unit lengths (its ``aps`` are ignored; the union of
    the two sets is used). ``sigma_range`` [m] at normal incidence, ``sigma_angle`` [rad].
    All simulations run as one compiled, vmapped computation in chunks, sharded over devices.
    """
    options = options or CompatibilityOptions()
    room = room or Room()
    if not isinstance(set1, APSet) or not isinstance(set2, APSet):
        raise ValueError(
            "compatibility_test: set1 and set2 must be APSet (APSet.from_json / from_result / from_values)"
        )
    if not (sigma_range > 0 and sigma_angle > 0):
        raise ValueError(
            f"compatibility_test: sigma_range and sigma_angle must be positive, got {sigma_range}, {sigma_angle}"
        )
    names = tuple(set1.names) + tuple(n for n in set2.names if n not in set1.names)
    base = scanner or Scanner()
    sc = Scanner(
        architecture=base.architecture,
        aps=names,
        unit_length=base.unit_length,
        unit_length_2=base.unit_length_2,
    )
    a1, C1 = set1.on(names)
    a2, C2 = set2.on(names)
    a_bar = _weighted_mean(a1, C1, a2, C2)
    L1, L2 = _sqrt_psd(C1), _sqrt_psd(C2)
    N = int(options.runs)

    chunk = round_chunk(options.chunk_size)
    t0 = time.perf_counter()
    b = _compiled(
        names,
        sc.current(),
        room,
        float(sigma_range),
        float(sigma_angle),
        int(options.n_targets),
        int(options.n_control),
        float(options.alpha),
        chunk,
        device_key(),
    )
    compile_s = time.perf_counter() - t0
    consts = (jax.random.PRNGKey(int(options.seed)), a1, a2, C1, C2, a_bar, L1, L2)
    (shares, null, ss), run_s = run_batched(
        b, N, consts, desc="compatibility chunks", progress=options.progress
    )
    good = np.isfinite(shares) & np.isfinite(null) & np.all(np.isfinite(ss), axis=1)
    n_chk = int(options.n_targets) - int(options.n_control)
    med = float(np.median(shares[good]))
    q = float(np.quantile(null[good], 1.0 - options.alpha))
    p = float((1 + np.sum(null[good] >= med)) / (good.sum() + 1))
    ms = ss[good].sum(axis=0) / (good.sum() * n_chk)
    rms = 1e3 * np.sqrt(np.concatenate([ms, [ms.sum()]]))

    dlt = a1 - a2
    Cd = C1 + C2
    rank = int(np.linalg.matrix_rank(Cd, hermitian=True))
    chi2 = float(dlt @ np.linalg.pinv(Cd, rcond=1e-12, hermitian=True) @ dlt)
    p_naive = chi2_sf(chi2, rank) if rank else float("nan")
    return CompatibilityResult(
        ap_names=names,
        ap_units=tuple(get_ap(n).unit for n in names),
        difference=dlt,
        difference_sigma=np.sqrt(np.clip(np.diag(Cd), 0, None)),
        shares=shares,
        null_shares=null,
        median_share=med,
        null_quantile=q,
        p_value=p,
        compatible=bool(med <= q),
        rms_mm=rms,
        naive_chi2=chi2,
        naive_dof=rank,
        naive_p_value=p_naive,
        naive_compatible=bool(p_naive > options.alpha),
        alpha=float(options.alpha),
        runs=N,
        n_failed=int((~good).sum()),
        compile_s=compile_s,
        run_s=run_s,
    )
