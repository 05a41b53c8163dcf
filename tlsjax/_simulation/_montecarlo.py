"""Batched Monte Carlo self-calibration of one network design (SPEC section 9).

N realisations of a simulated design (noise on every observation and on the levelling, and
optionally true APs drawn around their values) are simulated and fully self-calibrated as one
compiled computation: ``vmap`` over realisations, processed in chunks of a fixed size (one
compile per design, never one per chunk), sharded over every JAX device along the batch axis
with :class:`jax.sharding.NamedSharding` (a no-op on one CPU device).

Seeds: realisation k draws its noise from ``fold_in(PRNGKey(seed), k)``, so its result does not
depend on the chunk size or on the number of devices.

The adjustment of one realisation is the Gauss-Markov model of Chow et al. (2013, eqs. 1-6),
solved by Gauss-Newton on the block normal equations with the targets eliminated by Schur
complement (as :mod:`._solver`), but lean, for the Monte Carlo case:

* it starts from the simulated truth (the standard Monte Carlo choice: the estimator's
  sampling distribution does not depend on the start, and 2-3 iterations suffice);
* every target is observed in every scan (the design of :func:`tlsjax.simulate`), so the
  normal blocks are reshapes and sums, not segment sums or scatters;
* the datum is a minimal one (X, Y, Z and kappa of the first levelled scan held, or the six
  parameters of the first scan without levelling). APs, their cofactor block and ``v^T P v``
  are estimable quantities and do not depend on the datum, so they equal the inner-constraint
  results of :func:`tlsjax.calibrate`;
* quality is only what Monte Carlo needs: ``s0^2 = v^T P v / r`` with ``r = n - u + d`` and the
  AP block of the cofactor matrix, ``Q_aa = (K^-1)_aa`` of the reduced normal matrix ``K``.

Empirical precision (Lichti 2008): from the N estimates, the scatter of each AP, its bias
against the truth, the ratio of empirical to formal sigma, and the power (share of
realisations with ``|t| > t_crit``).
"""

from __future__ import annotations

import dataclasses
import weakref
from collections.abc import Mapping

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .._adjustment._config import CalibrationModel
from .._adjustment._linalg import forward_substitution, spd_inverse
from .._adjustment._normal import matvec_t, outer
from .._adjustment._result import MAX_ITERATIONS, NONFINITE, RESULT_MESSAGES, SUCCESS
from .._model._aps import ap_corrections, get_ap, on_reregistration
from .._model._geometry import is_face2, spherical_from_cartesian, wrap_angle
from .._model._levelling import compensator_reading
from .._model._points import distorted_observations, point_geometry, predict_point
from .._model._scanner import Scanner
from .._units import display_unit
from ._batch import compile_batched, device_key, round_chunk, run_batched


@dataclasses.dataclass(frozen=True)
class MonteCarloOptions:
    """Settings of :func:`monte_carlo`.

    ``runs``: number of realisations N. ``chunk_size``: realisations per compiled call (a
    measured choice: intermediates of a chunk should stay in cache; rounded up to a multiple of
    the device count). ``seed``: realisation k uses ``fold_in(PRNGKey(seed), k)``.
    ``ap_sigma``: optional {AP name: sigma [SI]}; each realisation's true AP is then drawn
    ``N(true, sigma^2)``. ``max_iterations``, ``tolerance``: Gauss-Newton stops when the largest
    update in units of the parameter's stand-alone sigma ``1/sqrt(N_ii)`` is below tolerance.
    ``alpha``: two-sided significance level of the AP t test (power). ``progress``: tqdm bar.
    """

    runs: int = 1000
    chunk_size: int = 10
    seed: int = 0
    ap_sigma: Mapping[str, float] | None = None
    max_iterations: int = 10
    tolerance: float = 1e-5
    alpha: float = 0.05
    progress: bool = True

    def __post_init__(self):
        if int(self.runs) < 1:
            raise ValueError(f"MonteCarloOptions.runs must be >= 1, got {self.runs}")
        if int(self.chunk_size) < 1:
            raise ValueError(f"MonteCarloOptions.chunk_size must be >= 1, got {self.chunk_size}")
        if int(self.max_iterations) < 1:
            raise ValueError(
                f"MonteCarloOptions.max_iterations must be >= 1, got {self.max_iterations}"
            )
        if not (self.tolerance > 0):
            raise ValueError(f"MonteCarloOptions.tolerance must be positive, got {self.tolerance}")
        if not (0 < self.alpha < 1):
            raise ValueError(f"MonteCarloOptions.alpha must be in (0, 1), got {self.alpha}")


# ----------------------------------------------------------------------------------------
# The design: host-side plan of one simulated network


@dataclasses.dataclass(frozen=True, eq=False)
class _Design:
    scanner: Scanner  # estimated model
    true_scanner: Scanner  # model that generates the data
    true_aps: np.ndarray  # (a_true,)
    ap_draw_sigma: np.ndarray  # (a_true,)
    truth_in_model: np.ndarray  # (a,) true value of each estimated AP (0 when absent)
    truth_map: np.ndarray  # (a,) index into the true APs, -1 when absent
    targets: np.ndarray  # (t, 3)
    eops: np.ndarray  # (s, 6)
    sigmas: np.ndarray  # (s, t, 3)
    face2: np.ndarray  # (s, t)
    geometry: np.ndarray  # (s, t, 3) error-free F(X, EOP) of the true design
    lev_sigma: np.ndarray  # (s, 2), inf = not levelled
    fixed: np.ndarray  # (r,) minimal datum
    n_obs: int
    n_unknowns: int
    datum_defect: int

    @property
    def dof(self) -> int:
        return self.n_obs - self.n_unknowns + self.datum_defect


def _design(simulation, model: CalibrationModel | None, ap_sigma) -> _Design:
    net = simulation.network
    model = model or CalibrationModel(simulation.scanner)
    if not isinstance(model.scanner, Scanner):
        raise ValueError(
            "monte_carlo: one instrument only; give CalibrationModel(scanner=Scanner(...))"
        )
    scanner = model.scanner
    if len(net.instruments) != 1:
        raise ValueError("monte_carlo: the simulated network must have one instrument")
    if len(net.scale_bar_targets) or len(net.control_index):
        raise ValueError(
            "monte_carlo: networks with scale bars or control points are not supported yet"
        )
    if scanner.architecture != simulation.scanner.architecture:
        raise ValueError(
            f"monte_carlo: model scanner is {scanner.architecture!r} but the data are {simulation.scanner.architecture!r}"
        )
    n_t, n_s = len(net.targets), len(net.scans)
    if net.observations.shape[0] != n_t * n_s:
        raise ValueError(
            "monte_carlo: every target must be observed in every scan (the design of tlsjax.simulate)"
        )
    # Rows in scan-major order: row = s * n_t + t.
    order = np.lexsort((net.target_index, net.scan_index))
    if not (
        np.array_equal(net.scan_index[order], np.repeat(np.arange(n_s), n_t))
        and np.array_equal(net.target_index[order], np.tile(np.arange(n_t), n_s))
    ):
        raise ValueError(
            "monte_carlo: every target must be observed in every scan (the design of tlsjax.simulate)"
        )
    true_names = simulation.scanner.aps
    true_vals = np.array([simulation.true_aps[n] for n in true_names], dtype=np.float64)
    draw = np.zeros(len(true_names))
    for name, s in dict(ap_sigma or {}).items():
        if name not in true_names:
            raise ValueError(
                f"MonteCarloOptions.ap_sigma: AP {name!r} is not in the simulated data ({' '.join(true_names)})"
            )
        if not (np.isfinite(s) and s >= 0):
            raise ValueError(
                f"MonteCarloOptions.ap_sigma[{name!r}] must be a non-negative number, got {s}"
            )
        draw[true_names.index(name)] = s
    tmap = np.array(
        [true_names.index(n) if n in true_names else -1 for n in scanner.aps], dtype=np.int64
    )
    truth = np.where(tmap >= 0, true_vals[np.maximum(tmap, 0)], 0.0)

    obs = net.observations[order]
    face2 = (
        np.asarray(is_face2(obs[:, 2], xp=np))
        if scanner.architecture == "panoramic"
        else np.zeros(len(obs), bool)
    )
    X = np.asarray(simulation.true_targets, dtype=np.float64)
    E = np.asarray(simulation.true_eops, dtype=np.float64)
    x = jax.vmap(jax.vmap(point_geometry, in_axes=(0, None)), in_axes=(None, 0))(
        jnp.asarray(X), jnp.asarray(E)
    )
    geo = np.asarray(
        spherical_from_cartesian(
            x, jnp.asarray(face2.reshape(n_s, n_t)) if scanner.architecture == "panoramic" else None
        )
    )
    lev_sigma = np.asarray(net.levelling_sigma, dtype=np.float64)
    levelled = np.isfinite(lev_sigma).all(axis=1)
    n_a = len(scanner.aps)
    fixed = np.zeros(6 * n_s + n_a, dtype=bool)
    if levelled.any():
        j = int(np.flatnonzero(levelled)[0])
        fixed[[6 * j + c for c in (0, 1, 2, 5)]] = True
    else:
        fixed[:6] = True
    d = int(fixed.sum())
    n_obs = 3 * len(obs) + int(np.isfinite(lev_sigma).sum())
    n_unknowns = 3 * n_t + 6 * n_s + n_a
    return _Design(
        scanner,
        simulation.scanner,
        true_vals,
        draw,
        truth,
        tmap,
        np.asarray(simulation.true_targets, dtype=np.float64),
        np.asarray(simulation.true_eops, dtype=np.float64),
        net.sigmas[order].reshape(n_s, n_t, 3),
        face2.reshape(n_s, n_t),
        geo,
        lev_sigma,
        fixed,
        n_obs,
        n_unknowns,
        d,
    )


# ----------------------------------------------------------------------------------------
# One realisation: simulation and lean Gauss-Newton (pure; vmapped over realisations)


def _simulate_one(design: _Design, key):
    """Observations (s, t, 3), levelling readings (s, 2) and true APs of one realisation.

    ``l = F(X, EOP) + Delta(l; AP) + e`` with Delta evaluated at the observations (SPEC
    section 2). The design's true geometry ``F`` is the same in every realisation, so it is
    computed once on the host; only the fixed point in the AP corrections is iterated (the
    corrections are small, each iteration gains about three digits).
    """
    n_s, n_t = design.sigmas.shape[:2]
    k_obs, k_lev, k_ap = jax.random.split(key, 3)
    noise = jax.random.normal(k_obs, (n_s, n_t, 3)) * design.sigmas
    lev_w = np.isfinite(design.lev_sigma)
    lev = jnp.where(
        lev_w, jax.random.normal(k_lev, (n_s, 2)) * np.where(lev_w, design.lev_sigma, 0.0), 0.0
    )
    true_aps = (
        design.true_aps + jax.random.normal(k_ap, design.true_aps.shape) * design.ap_draw_sigma
    )
    sc = design.true_scanner
    base = design.geometry + noise

    obs = distorted_observations(base, lambda l: ap_corrections(true_aps, sc.aps, l, sc))
    return obs, lev, true_aps


def _gauss_newton(design: _Design, obs, lev, targets0, eops0, aps0, tolerance, max_iterations):
    """Lean Gauss-Newton of one realisation (see the module docstring); returns a dict."""
    sc = design.scanner
    n_s, n_t = obs.shape[:2]
    n_a = len(sc.aps)
    r = 6 * n_s + n_a
    weight = 1.0 / design.sigmas
    lev_w = np.where(np.isfinite(design.lev_sigma), 1.0 / design.lev_sigma, 0.0)
    fixed = jnp.asarray(design.fixed)
    ap_rows = np.arange(6 * n_s, r)

    # Misclosure = F(X, EOP) + Delta(l; AP) - l. Delta is linear in the APs with bases at the
    # observations, so its Jacobian block is the same in every iteration: taken once, and the
    # geometry is differentiated with 9 tangents instead of 9 + n_a.
    def geometry(X, eop, l, w):
        F = predict_point(X, eop, l, sc.architecture)
        return F * w, F * w

    def correction(aps, l, w):
        return ap_corrections(aps, sc.aps, l, sc) * w

    jac_geo = jax.vmap(
        jax.vmap(jax.jacfwd(geometry, argnums=(0, 1), has_aux=True), in_axes=(0, None, 0, 0)),
        in_axes=(None, 0, 0, 0),
    )
    Ja = jax.vmap(jax.vmap(jax.jacfwd(correction), in_axes=(None, 0, 0)), in_axes=(None, 0, 0))(
        jnp.zeros(n_a), obs, weight
    )  # (s, t, 3, a)
    Naa = jnp.sum(outer(Ja, Ja), axis=(0, 1))
    lw = obs * weight

    def linearise(T, E, A):
        (Jp, Js), Fw = jac_geo(T, E, obs, weight)  # (s, t, 3, k)
        e = Fw + jnp.sum(Ja * A, axis=-1) - lw
        # Angles wrapped to (-pi, pi] (in whitened units: wrap before whitening).
        ang = e[..., 1:] / weight[..., 1:]
        e = e.at[..., 1:].set(wrap_angle(ang) * weight[..., 1:])
        Npp = jnp.sum(outer(Jp, Jp), axis=0)  # (t, 3, 3)
        bp = -jnp.sum(matvec_t(Jp, e), axis=0)  # (t, 3)
        Nps = jnp.transpose(outer(Jp, Js), (1, 2, 0, 3)).reshape(n_t, 3, 6 * n_s)
        Npa = jnp.sum(outer(Jp, Ja), axis=0)  # (t, 3, a)
        Nss = jnp.sum(outer(Js, Js), axis=1)  # (s, 6, 6)
        Nsa = jnp.sum(outer(Js, Ja), axis=1)  # (s, 6, a)
        bs = -jnp.sum(matvec_t(Js, e), axis=1)
        ba = -jnp.sum(matvec_t(Ja, e), axis=(0, 1))
        # Levelling (compensator) pseudo-observations act on the scan rotations.
        lr = (jax.vmap(compensator_reading)(E) - lev) * lev_w
        Jl = jax.vmap(jax.jacfwd(compensator_reading))(E) * lev_w[:, :, None]
        Nss = Nss + outer(Jl, Jl)
        bs = bs - matvec_t(Jl, lr)
        eye = jnp.eye(n_s)
        Nss_full = (
            (Nss[:, None] * eye[:, :, None, None]).transpose(0, 2, 1, 3).reshape(6 * n_s, 6 * n_s)
        )
        Nsa_full = Nsa.reshape(6 * n_s, n_a)
        Nzz = jnp.block([[Nss_full, Nsa_full], [Nsa_full.T, Naa]])
        bz = jnp.concatenate([bs.reshape(-1), ba])
        vtpv = jnp.sum(e * e) + jnp.sum(lr * lr)
        return Npp, bp, jnp.concatenate([Nps, Npa], axis=-1), Nzz, bz, vtpv

    def body(st):
        T, E, A = st["T"], st["E"], st["A"]
        Npp, bp, Npz, Nzz, bz, vtpv = linearise(T, E, A)
        Ninv = spd_inverse(Npp)
        Y = jnp.sum(Ninv[..., :, :, None] * Npz[..., None, :, :], axis=-2)  # (t, 3, r)
        K = Nzz - jnp.einsum("npr,npq->rq", Npz, Y)
        c = bz - jnp.einsum("npr,np->r", Y, bp)
        # Minimal datum: the held parameters get unit rows and a zero right-hand side.
        K = jnp.where(fixed[:, None] | fixed[None, :], jnp.eye(r), K)
        c = jnp.where(fixed, 0.0, c)
        s = 1.0 / jnp.sqrt(jnp.diagonal(K))
        L = jnp.linalg.cholesky(K * s[:, None] * s[None, :])
        y = jax.scipy.linalg.solve_triangular(L, c * s, lower=True)
        dz = jax.scipy.linalg.solve_triangular(L.T, y, lower=False) * s
        dp = jnp.einsum("npq,nq->np", Ninv, bp) - jnp.einsum("npr,r->np", Y, dz)
        # AP block of K^-1 from one triangular solve with the AP unit columns: W = L^-1 E_a.
        W = forward_substitution(L, jnp.eye(r)[:, ap_rows])
        Qaa = (W.T @ W) * s[ap_rows, None] * s[None, ap_rows]
        size = jnp.maximum(
            jnp.max(jnp.abs(dz) * jnp.sqrt(jnp.abs(jnp.diagonal(Nzz))), initial=0.0),
            jnp.max(
                jnp.abs(dp) * jnp.sqrt(jnp.abs(jnp.diagonal(Npp, axis1=-2, axis2=-1))), initial=0.0
            ),
        )
        finite = jnp.isfinite(size) & jnp.isfinite(vtpv) & jnp.all(jnp.isfinite(Qaa))
        return dict(
            T=T + dp,
            E=E + dz[: 6 * n_s].reshape(n_s, 6),
            A=A + dz[6 * n_s :],
            vtpv=vtpv,
            Qaa=Qaa,
            it=st["it"] + 1,
            converged=finite & (size < tolerance),
            finite=finite,
            size=size,
        )

    def cond(st):
        return (~st["converged"]) & st["finite"] & (st["it"] < max_iterations)

    init = dict(
        T=jnp.asarray(targets0),
        E=jnp.asarray(eops0),
        A=aps0,
        vtpv=jnp.asarray(0.0),
        Qaa=jnp.zeros((n_a, n_a)),
        it=jnp.asarray(0),
        converged=jnp.asarray(False),
        finite=jnp.asarray(True),
        size=jnp.asarray(jnp.inf),
    )
    return lax.while_loop(cond, body, init)


def _realisation(design: _Design, seed_key, tolerance, max_iterations, index):
    key = jax.random.fold_in(seed_key, index)
    obs, lev, true_aps = _simulate_one(design, key)
    tmap = design.truth_map
    truth = jnp.where(tmap >= 0, true_aps[np.maximum(tmap, 0)], 0.0)
    st = _gauss_newton(
        design, obs, lev, design.targets, design.eops, truth, tolerance, max_iterations
    )
    dof = float(design.dof)
    s0sq = st["vtpv"] / dof
    code = jnp.where(~st["finite"], NONFINITE, jnp.where(st["converged"], SUCCESS, MAX_ITERATIONS))
    ok = code == SUCCESS
    cov = st["Qaa"] * s0sq
    return {
        "true_aps": truth,
        "ap_values": jnp.where(ok, st["A"], jnp.nan),
        "ap_covariance": jnp.where(ok, cov, jnp.nan),
        "sigma0_sq": jnp.where(ok, s0sq, jnp.nan),
        "iterations": st["it"],
        "result": code.astype(jnp.int32),
    }


# Compiled chunk functions per (simulation, model, AP draw sigmas, chunk, devices): the seed,
# tolerance and iteration limit are traced arguments, so changing them never recompiles.
_COMPILED: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
# A simulation's own scanner may predate a re-registered AP: empty the cache then.
on_reregistration(_COMPILED.clear)


def _compiled_chunk(simulation, model, ap_sigma, chunk: int):
    if model is not None and not isinstance(model.scanner, Scanner):
        raise ValueError(
            "monte_carlo: one instrument only; give CalibrationModel(scanner=Scanner(...))"
        )
    key = (model, tuple(sorted(dict(ap_sigma or {}).items())), chunk, device_key())
    cache = _COMPILED.setdefault(simulation, {})
    if key in cache:
        design, b = cache[key]
        return design, dataclasses.replace(b, compile_s=0.0)
    design = _design(simulation, model, ap_sigma)
    constants = (jax.random.PRNGKey(0), jnp.asarray(0.0), jnp.asarray(0, dtype=jnp.int64))
    b = compile_batched(
        lambda i, seed_key, tol, mit: _realisation(design, seed_key, tol, mit, i), constants, chunk
    )
    cache[key] = (design, b)
    return design, b


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
    alpha: float
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

    def summary(self) -> dict:
        """Empirical precision per AP (Lichti 2008): mean, bias, empirical and mean formal sigma,
        their ratio, and power = share of realisations with ``|t| > t_crit`` at ``alpha``.
        Values in SI units. The ratio's own sampling sigma is about ``1/sqrt(2 (N - 1))``."""
        from scipy import stats

        ok = self.ok
        n = int(ok.sum())
        v = self.ap_values[ok]
        s = self.ap_sigmas[ok]
        t_crit = float(stats.t.ppf(1.0 - self.alpha / 2.0, self.dof))
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

    def table(self) -> str:
        """Text table of :meth:`summary` in mm, arc seconds and ppm."""
        sm = self.summary()
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

    ``simulation`` is a :class:`tlsjax.Simulation` (the design: targets, scan poses, sigmas,
    levelling, the true APs and the scanner that generates the data); ``model`` the calibration
    model whose APs are estimated (default: the simulation's scanner). Realisation k:
    ``l = F(X, EOP) + Delta(l; AP_true) + e``, ``e ~ N(0, Sigma_l)`` drawn from
    ``fold_in(PRNGKey(seed), k)``, then the Gauss-Markov self-calibration of Chow et al. (2013,
    eqs. 1-6) started from the truth. A failed realisation returns its result code and NaN
    estimates; it never stops the batch. Lichti (2008) for the empirical-precision analysis.
    """
    options = options or MonteCarloOptions()
    chunk = round_chunk(options.chunk_size)
    design, b = _compiled_chunk(simulation, model, options.ap_sigma, chunk)
    constants = (
        jax.random.PRNGKey(int(options.seed)),
        jnp.asarray(float(options.tolerance)),
        jnp.asarray(int(options.max_iterations), dtype=jnp.int64),
    )
    res, run_s = run_batched(
        b, int(options.runs), constants, desc="Monte Carlo chunks", progress=options.progress
    )
    cov = res["ap_covariance"]
    sig = np.sqrt(np.clip(np.diagonal(cov, axis1=1, axis2=2), 0, None))
    return MonteCarloResult(
        ap_names=design.scanner.aps,
        ap_units=tuple(get_ap(n).unit for n in design.scanner.aps),
        true_aps=res["true_aps"],
        ap_values=res["ap_values"],
        ap_sigmas=sig,
        ap_covariance=cov,
        sigma0_sq=res["sigma0_sq"],
        iterations=res["iterations"],
        result=res["result"],
        dof=design.dof,
        alpha=float(options.alpha),
        seed=int(options.seed),
        chunk_size=chunk,
        n_devices=len(jax.devices()),
        compile_s=b.compile_s,
        run_s=run_s,
    )


def monte_carlo_network(
    simulation, index, *, seed: int = 0, ap_sigma: Mapping[str, float] | None = None
):
    """The :class:`tlsjax.Network` of realisation ``index`` of :func:`monte_carlo` (same seed):
    the observations and levelling readings it adjusts, for checks with :func:`tlsjax.calibrate`.
    Returns (network, true APs {name: value}); for a sequence of indices, a list of them."""
    design = _design(simulation, None, ap_sigma)
    many = not np.isscalar(index)
    idx = np.atleast_1d(np.asarray(index, dtype=np.int64))
    seed_key = jax.random.PRNGKey(int(seed))
    obs, lev, true_aps = jax.jit(
        jax.vmap(lambda i: _simulate_one(design, jax.random.fold_in(seed_key, i)))
    )(jnp.asarray(idx))
    net = simulation.network
    order = np.lexsort((net.target_index, net.scan_index))
    out = []
    for k in range(len(idx)):
        new_obs = np.empty_like(net.observations)
        new_obs[order] = np.asarray(obs[k]).reshape(-1, 3)
        levelling = np.where(np.isfinite(net.levelling_sigma), np.asarray(lev[k]), net.levelling)
        out.append(
            (
                dataclasses.replace(net, observations=new_obs, levelling=levelling),
                dict(zip(design.true_scanner.aps, np.asarray(true_aps[k]).tolist())),
            )
        )
    return out if many else out[0]
