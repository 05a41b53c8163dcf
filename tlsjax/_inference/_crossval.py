"""Cross-validation by scan groups: a model judged by how well it predicts scans it was not
fitted to (SPEC section 7, "Prediction"; issue 41 item 1).

For a partition of the scans into folds F_k, each complement still determining the model's APs:

1. adjust the complement: the one compiled adjustment of the whole network with the held-out
   scans' observations, tilt readings and headings at weight 0 and their poses held (same
   shapes, nothing recompiles; :meth:`tlsjax.Adjustment.run_estimable`). A target that the
   complement sees from fewer than two scans carries no information about anything else (its
   three coordinates absorb its observations): its rows get weight 0 too, and it is pinned
   (:data:`tlsjax._adjustment._calibrate.PIN_SIGMA`) so that its block stays regular. Keep the complement's targets
   X_k and APs a_k;
2. correct each held-out scan's observations with a_k, ``l_c = l - Delta(l; a_k)`` (SPEC section
   11, as ``tlsjax correct`` applies a calibration; one compiled program of the whole network's
   observations, the same for every fold), convert them to scanner-space coordinates;
3. place the scan on X_k by its own pose, fitted to the targets it shares with the complement:
   rigid (6 parameters, Horn 1987), or for a scan with tilt readings levelled (its vertical from
   the readings, the heading and position fitted: 4 parameters, as the scanner is used);
4. the misfits ``e = X_placed - X_k``; ``CV = sqrt(mean |e|^2)`` over every placed target of every
   fold, per axis too, in mm; beside it the same with ``a_k = 0``: the complement adjusted with
   every AP held at zero (the same compiled adjustment) and the held-out scan uncorrected,
   placed on those targets. (Placing the uncorrected scan on the X_k adjusted *with* the APs
   would favour any AP set: targets adjusted with spurious APs carry their distortion, which a
   scan corrected with the same APs shares.) Observations that screening or snooping removed
   (gross errors) are left out of the placement.

A model, an added term or a selection's end point is better only if it lowers CV; a
calibration whose CV is not below that of no calibration does not improve prediction, and
says so (:attr:`CrossValidationCode.NOT_IMPROVED`). The folds' scatter gives
the standard error of CV (per-fold mean squared misfits), and two models are compared fold by
fold (:func:`paired_difference`).

Folds by default: every scan alone, where the rest still holds scans from two stations (one
station does not separate A0 from the targets' distances: leaving out one of two stations can
never be a fold); a fold whose complement the engine finds unable to determine an AP is
skipped with that reason. ``CrossValidationOptions.folds`` overrides the choice.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from .._adjustment._calibrate import PIN_SIGMA, Adjustment, analyze, spec_key
from .._adjustment._config import CalibrationModel, SolverOptions
from .._adjustment._diagnose import station_of_scans
from .._adjustment._network import Network
from .._adjustment._plan import initial_params
from .._adjustment._result import CalibrationResult, assemble
from .._jit import StoredProgram
from .._model._aps import ap_corrections
from .._model._geometry import cartesian_from_spherical, helmert_fit
from .._summary import Settings, to_json_value

AXES = ("xyz", "x", "y", "z")
PLACEMENTS = ("auto", "rigid", "levelled")


class CrossValidationCode(enum.IntEnum):
    """Result codes of a cross-validation; ``.message`` says what each means."""

    IMPROVED = 0
    NOT_SIGNIFICANT = 1
    NOT_IMPROVED = 2
    NO_APS = 3
    NO_FOLDS = 4

    @property
    def message(self) -> str:
        return _MESSAGES[self]


_MESSAGES = {
    CrossValidationCode.IMPROVED: "the calibration improves the prediction of held-out scans",
    CrossValidationCode.NOT_SIGNIFICANT: (
        "the calibration improves the prediction of held-out scans by less than twice the "
        "standard error between folds: not demonstrably better than no calibration"
    ),
    CrossValidationCode.NOT_IMPROVED: (
        "the calibration does not improve the prediction of held-out scans: corrected with it "
        "they fit the rest's targets no better than uncorrected scans fit the targets adjusted "
        "without APs; do not apply it (try fewer terms, another architecture, or a better "
        "network design)"
    ),
    CrossValidationCode.NO_APS: "the model has no APs: its prediction is that of no calibration",
    CrossValidationCode.NO_FOLDS: (
        "no fold could be held out: the rest of every candidate fold does not determine the "
        "model (scans from two stations at least must remain; targets, not planes)"
    ),
}


@dataclasses.dataclass(frozen=True)
class CrossValidationOptions(Settings):
    """Cross-validation by scan groups (module docstring). ``folds``: groups of scan names held out together (None: each scan alone where the rest
    keeps two stations, module docstring); ``placement``: "auto" (levelled for scans with tilt
    readings, rigid otherwise), "rigid" or "levelled"; ``min_targets``: fewest targets a
    held-out scan must share with the complement to be placed (a rigid fit needs 3; more
    makes the misfit a test of the calibration rather than of the fit)."""

    folds: tuple | None = None
    placement: str = "auto"
    min_targets: int = 4

    def __post_init__(self):
        if self.placement not in PLACEMENTS:
            raise ValueError(f"placement {self.placement!r} is not one of {PLACEMENTS}")
        if int(self.min_targets) < 3:
            raise ValueError(f"min_targets must be >= 3 (a rigid fit), got {self.min_targets}")
        if self.folds is not None:
            folds = tuple((f,) if isinstance(f, str) else tuple(f) for f in self.folds)
            if not folds or any(not f for f in folds):
                raise ValueError("folds must be non-empty groups of scan names")
            object.__setattr__(self, "folds", folds)


@dataclasses.dataclass(frozen=True)
class Fold:
    """One fold: the ``held_out`` scans, whether it was evaluated (``ok``; otherwise ``note``
    says why not), the complement's APs (``aps``, SI), and of the placed targets: their
    number ``n``, the misfit RMS with the APs (``rms_mm``) and with none (``rms_none_mm``) in 3D
    and per axis ("xyz", "x", "y", "z"), the sums of squared 3D misfits ``sse``/``sse_none``
    [m^2], and the ``placement`` of each held-out scan."""

    held_out: tuple
    ok: bool
    note: str = ""
    aps: dict = dataclasses.field(default_factory=dict)
    n: int = 0
    rms_mm: dict = dataclasses.field(default_factory=dict)
    rms_none_mm: dict = dataclasses.field(default_factory=dict)
    sse: float = float("nan")
    sse_none: float = float("nan")
    placement: tuple = ()

    @property
    def name(self) -> str:
        return "+".join(self.held_out)

    def to_dict(self) -> dict:
        return to_json_value(
            {
                "held_out": list(self.held_out),
                "ok": self.ok,
                "note": self.note,
                "n_targets": self.n,
                "rms_mm": self.rms_mm,
                "rms_none_mm": self.rms_none_mm,
                "aps": self.aps,
                "placement": list(self.placement),
            }
        )


@dataclasses.dataclass(frozen=True, eq=False)
class CrossValidation:
    """Cross-validation of a model by scan groups (module docstring): ``code``
    (:class:`CrossValidationCode`) with ``message``; ``folds`` (:class:`Fold`); the pooled
    misfit RMS over every placed target with the APs (``rms_mm``) and with none
    (``rms_none_mm``), 3D and per axis in mm; ``se_mm``: the standard error of the 3D RMS from
    the folds' scatter; ``aps``: the model's AP names."""

    code: CrossValidationCode
    folds: tuple
    rms_mm: dict
    rms_none_mm: dict
    se_mm: float
    aps: tuple

    @property
    def message(self) -> str:
        return self.code.message

    @property
    def ok(self) -> bool:
        """Some fold was evaluated."""
        return self.code != CrossValidationCode.NO_FOLDS

    @property
    def cv_mm(self) -> float:
        """The cross-validated 3D misfit RMS with the APs [mm] (NaN without folds)."""
        return self.rms_mm.get("xyz", float("nan"))

    @property
    def mse(self) -> np.ndarray:
        """Mean squared 3D misfit per fold [m^2] (NaN for a fold not evaluated)."""
        return np.array([f.sse / f.n if f.ok and f.n else np.nan for f in self.folds])

    def summary(self) -> str:
        """The pooled misfit RMS with and without the APs, each fold's, and the verdict."""
        if not self.ok:
            skipped = "; ".join(f"{f.name}: {f.note}" for f in self.folds)
            return f"cross-validation: {self.message}" + (f" ({skipped})" if skipped else "")
        fmt = lambda d: ", ".join(f"{k} {d[k]:.3f}" for k in AXES)
        lines = [
            f"cross-validation by scan groups ({sum(f.ok for f in self.folds)} of "
            f"{len(self.folds)} folds; held-out scans placed on the targets adjusted from the "
            "rest): misfit RMS [mm]",
            f"  with the APs:  {fmt(self.rms_mm)}"
            + (f" (+- {self.se_mm:.3f} between folds)" if np.isfinite(self.se_mm) else ""),
            f"  without APs:   {fmt(self.rms_none_mm)}",
        ]
        for f in self.folds:
            if f.ok:
                lines.append(
                    f"  fold {f.name:10s} {f.n:4d} targets  {f.rms_mm['xyz']:8.3f} mm with, "
                    f"{f.rms_none_mm['xyz']:8.3f} mm without ({', '.join(sorted(set(f.placement)))})"
                )
            else:
                lines.append(f"  fold {f.name:10s} not evaluated: {f.note}")
        if self.code != CrossValidationCode.IMPROVED:
            warn = self.code == CrossValidationCode.NOT_IMPROVED
            lines.append(f"  {'warning: ' if warn else ''}{self.message}")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        """Strict JSON: the code and message, the pooled RMS with and without the APs (mm),
        the standard error between folds and every fold."""
        return to_json_value(
            {
                "method": "folds of held-out scans: the rest adjusted, the held-out scans "
                "corrected with its APs and placed by their own pose on its targets; misfit "
                "e = X_placed - X_rest, RMS over all folds",
                "code": int(self.code),
                "message": self.message,
                "improves": self.code == CrossValidationCode.IMPROVED,
                "aps": list(self.aps),
                "rms_mm": self.rms_mm,
                "rms_none_mm": self.rms_none_mm,
                "se_mm": self.se_mm,
                "folds": [f.to_dict() for f in self.folds],
            }
        )


def paired_difference(a: CrossValidation, b: CrossValidation) -> tuple[float, float]:
    """Mean over the folds both evaluated of (MSE of ``a`` - MSE of ``b``) [mm^2], and its
    standard error from the folds' scatter (paired: the folds are the same scans). Negative:
    ``a`` predicts better. NaN where fewer than two folds are common or the folds differ."""
    if [f.held_out for f in a.folds] != [f.held_out for f in b.folds]:
        return float("nan"), float("nan")
    d = (a.mse - b.mse) * 1e6
    d = d[np.isfinite(d)]
    if d.size < 2:
        return float("nan"), float("nan")
    return float(d.mean()), float(d.std(ddof=1) / np.sqrt(d.size))


# --- Folds -----------------------------------------------------------------------------------


def default_folds(net: Network, eops: np.ndarray) -> tuple[tuple, tuple]:
    """(folds, refused): each scan alone where the rest keeps scans from two stations (or
    from as many as the network has, if it has one), and the scans refused with the reason."""
    st = station_of_scans(eops)
    n_st = len(set(st.tolist()))
    folds, refused = [], []
    for j, scan in enumerate(net.scans):
        rest = np.delete(st, j)
        if len(rest) < 2 or len(set(rest.tolist())) < min(2, n_st) or n_st < 2:
            why = (
                "the rest would hold scans from one station only, which does not separate the "
                "APs from the targets (A0 from their distances)"
            )
            refused.append(((scan,), why))
            continue
        folds.append((scan,))
    return tuple(folds), tuple(refused)


# --- One fold --------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class FoldData:
    """The weights in use (1/sigma, 0 = removed) and the warm start of one cross-validation
    (the pipeline's cross-validation step and stepwise selection build it from their state)."""

    weights: np.ndarray  # (n, 3)
    levelling: np.ndarray  # (s, 2)
    extra: dict  # heading_weights, ap_prior_weights as Adjustment.problem takes them
    pinned: dict  # target index -> xyz held by a pin already
    params: object  # warm start (Params) or None
    targets: np.ndarray  # (t, 3) estimates of the whole network (pins of undetermined targets)
    used_rows: np.ndarray  # (n,) observations whose three components are in use (placement)
    fixed_aps: tuple | None = None  # AP labels held at zero (None: the model's)
    # fold -> the fit without APs (the same for every AP set of one adjustment and weights:
    # stepwise selection cross-validates many sets with one such cache)
    none_cache: dict | None = None


def _fold(adj: Adjustment, data: FoldData, held: Sequence[str], opts: CrossValidationOptions):
    net, plan = adj.network, adj.plan
    out_scans = np.array([net.scans.index(s) for s in held])
    if plan.fixed_scan_index is not None and plan.fixed_scan_index in out_scans:
        return Fold(tuple(held), False, "holds the scan that defines the datum (fixed-scan)")
    rows_out = np.isin(net.scan_index, out_scans)
    w = np.where(rows_out[:, None], 0.0, data.weights)
    # Targets the complement sees from fewer than two scans: no information, weight 0, pinned.
    active = (w > 0).any(axis=1)
    pairs = np.unique(np.stack([net.target_index[active], net.scan_index[active]]), axis=1)
    seen = np.bincount(pairs[0], minlength=len(net.targets))
    lonely = seen < 2
    w = np.where(lonely[net.target_index][:, None], 0.0, w)
    pins = dict(data.pinned)
    for t in np.flatnonzero(lonely):
        pins.setdefault(int(t), data.targets[t])
    lw = data.levelling.copy()
    lw[out_scans] = 0.0
    extra = dict(data.extra)
    if "heading_weights" in extra:
        extra["heading_weights"] = np.where(
            np.isin(np.arange(len(net.scans)), out_scans), 0.0, extra["heading_weights"]
        )
    problem = adj.problem(
        weights=w,
        levelling_weights=lw,
        control={t: (xyz, PIN_SIGMA) for t, xyz in pins.items()},
        fixed_aps=data.fixed_aps,
        **extra,
    )
    fixed = np.asarray(problem.fixed).copy()
    for j in out_scans:
        fixed[6 * j : 6 * j + 6] = True  # no observations: held where the start has them
    fits = []
    # The model, then no calibration: the same adjustment with every AP held at zero.
    n_ap = adj.plan.spec.n_aps
    cache = {} if data.none_cache is None else data.none_cache
    start = adj.initial if data.params is None else data.params
    start_aps = np.asarray(start.aps)
    for held_aps in (False, True) if n_ap else (False,):
        if held_aps and tuple(held) in cache:
            fits.append(cache[tuple(held)])
            continue
        f = fixed.copy()
        if held_aps:
            f[len(f) - n_ap :] = True
        # A held AP stays at its start value: zero (held at zero means absent). Host arrays
        # moved by a transfer: nothing is dispatched eagerly.
        aps0 = np.where(f[len(f) - n_ap :], 0.0, start_aps)
        params0 = dataclasses.replace(start, aps=jax.device_put(aps0))
        fit = _fit(adj, dataclasses.replace(problem, fixed=jax.device_put(f)), params0)
        if isinstance(fit, str):
            return Fold(tuple(held), False, fit)
        if held_aps:
            cache[tuple(held)] = fit
        fits.append(fit)
    determined = ~lonely & ~np.isin(np.arange(len(net.targets)), list(data.pinned))
    return _place_fold(adj, fits[0], fits[-1], held, out_scans, determined, data, opts)


def _fit(adj: Adjustment, problem, params0):
    """(targets (t, 3), APs (a,)) of the complement, or the reason it failed."""
    fitted_plan, state, q, absent = adj.run_estimable(problem, params0)
    if absent:
        return f"the rest does not determine {', '.join(n for n, *_ in absent)}"
    res = assemble(adj.network, adj.model, fitted_plan, state, q)
    if not res.ok:
        return f"the adjustment of the rest failed: {res.message}"
    return res.target_xyz, np.asarray(state.params.aps)


@functools.cache
def _corrections_program(spec):
    """``Delta(l; a)`` (n, 3) of every observation of the network with the AP vector ``a`` of
    the model (each row with its instrument's terms): one compiled program for every fold
    (the same shapes), stored traced like the adjustment."""

    def corrections(l, instrument, aps):
        out = jnp.zeros_like(l)
        for i, (scanner, names) in enumerate(zip(spec.scanners, spec.ap_names)):
            if names:
                a, b = spec.ap_slices[i]
                d = ap_corrections(aps[a:b], names, l, scanner)
                out = jnp.where((instrument == i)[:, None], d, out)
        return out

    return StoredProgram(corrections, ("cross-validation corrections", spec_key(spec)))


def _corrected(adj: Adjustment, aps: np.ndarray) -> np.ndarray:
    """Every observation of the network corrected with the APs ``aps``, ``l - Delta(l; a)``."""
    net = adj.network
    l = np.asarray(net.observations, dtype=np.float64)
    instrument = np.asarray(net.instrument_of_scan, dtype=np.int32)[net.scan_index]
    delta = _corrections_program(adj.plan.spec)(l, instrument, np.asarray(aps, dtype=np.float64))
    return l - np.asarray(jax.device_get(delta))


def _place_fold(adj, fit, fit_none, held, out_scans, determined, data, opts):
    """Place every held-out scan on the complement's targets: corrected with its APs on the
    targets adjusted with them, uncorrected on the targets adjusted without APs."""
    net = adj.network
    (X_all, aps), (X0_all, _) = fit, fit_none
    corrected_all = _corrected(adj, aps) if adj.plan.spec.n_aps else net.observations
    errs, errs_none, kinds, notes = [], [], [], []
    for j in out_scans:
        rows = np.flatnonzero((net.scan_index == j) & data.used_rows & determined[net.target_index])
        if len(rows) < opts.min_targets:
            notes.append(f"scan {net.scans[j]} shares {len(rows)} targets with the rest")
            continue
        l, corrected = net.observations[rows], corrected_all[rows]
        t = net.target_index[rows]
        kind = _placement(net, j, opts.placement)
        errs.append(_misfit(corrected, X_all[t], kind, net.levelling[j]))
        errs_none.append(_misfit(l, X0_all[t], kind, net.levelling[j]))
        kinds.append(kind)
    if not errs:
        return Fold(tuple(held), False, "; ".join(notes) or "no target to place")
    e, e0 = np.concatenate(errs), np.concatenate(errs_none)
    return Fold(
        tuple(held),
        True,
        "; ".join(notes),
        {n: float(v) for n, v in zip(adj.plan.ap_labels, aps)},
        len(e),
        _rms(e),
        _rms(e0),
        float(np.sum(e**2)),
        float(np.sum(e0**2)),
        tuple(kinds),
    )


def _placement(net: Network, j: int, placement: str) -> str:
    has_readings = bool(np.isfinite(net.levelling_sigma[j]).all())
    if placement == "levelled" and not has_readings:
        raise ValueError(
            f"{net.source}: placement 'levelled' needs tilt readings; scan {net.scans[j]} has none"
        )
    if placement == "auto":
        return "levelled" if has_readings else "rigid"
    return placement


def _misfit(l, X, kind: str, reading) -> np.ndarray:
    """``X_placed - X`` (n, 3) of observations ``l`` placed on the targets ``X``."""
    x = np.asarray(cartesian_from_spherical(l, xp=np))
    if kind == "rigid":
        _, R, t = helmert_fit(x, X, xp=np)
        return x @ R.T + t - X
    # Levelled: the scanner's vertical from its tilt readings (SPEC section 6: the compensator
    # senses g = R e3, omega_c = asin(g_y), phi_c = asin(-g_x / cos omega_c)), so B with
    # B g = e3 levels the scan; then a rotation about Z and a translation (4 parameters).
    om, ph = float(reading[0]), float(reading[1])
    g = np.array([-np.sin(ph) * np.cos(om), np.sin(om), np.cos(ph) * np.cos(om)])
    xl = x @ _levelling_rotation(g).T
    cs, cd = xl.mean(axis=0), X.mean(axis=0)
    u, v = (xl - cs)[:, :2], (X - cd)[:, :2]
    # The rotation about Z minimising sum |R u - v|^2 (the planar Procrustes angle).
    k = np.arctan2(np.sum(u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0]), np.sum(u * v))
    R = np.array([[np.cos(k), -np.sin(k), 0.0], [np.sin(k), np.cos(k), 0.0], [0.0, 0.0, 1.0]])
    return (xl - cs) @ R.T + cd - X


def _levelling_rotation(g) -> np.ndarray:
    """The smallest rotation taking the unit vector ``g`` onto e3 (Rodrigues)."""
    g = g / np.linalg.norm(g)
    v = np.cross(g, [0.0, 0.0, 1.0])
    s, c = np.linalg.norm(v), g[2]
    if s < 1e-15:
        return np.eye(3)
    K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]]) / s
    return np.eye(3) + s * K + (1 - c) * K @ K


def _rms(e) -> dict:
    return {
        "xyz": float(np.sqrt(np.mean(np.sum(e**2, axis=1))) * 1e3),
        "x": float(np.sqrt(np.mean(e[:, 0] ** 2)) * 1e3),
        "y": float(np.sqrt(np.mean(e[:, 1] ** 2)) * 1e3),
        "z": float(np.sqrt(np.mean(e[:, 2] ** 2)) * 1e3),
    }


# --- The whole cross-validation --------------------------------------------------------------


def run_folds(
    adj: Adjustment, data: FoldData, opts: CrossValidationOptions, planned=None
) -> CrossValidation:
    """Every fold of ``opts`` on the analysed adjustment ``adj`` with the weights ``data``;
    ``planned``: the (folds, refused) of :func:`plan_folds`, if already chosen."""
    net = adj.network
    labels = tuple(adj.plan.ap_labels)
    if planned is None:
        planned = plan_folds(adj, _eops(adj, data), opts)
    folds, refused = planned
    out = [_fold(adj, data, held, opts) for held in folds]
    out += [Fold(held, False, why) for held, why in refused]
    return _finish(tuple(out), labels, net)


def plan_folds(adj: Adjustment, eops, opts: CrossValidationOptions) -> tuple:
    """(folds, refused): the folds of ``opts`` (checked), or the default ones from the scan
    positions ``eops`` (:func:`default_folds`); none for a network with planes."""
    net = adj.network
    if net.has_planes or not net.has_targets:
        why = "cross-validation places held-out scans by their targets (not planes, yet)"
        return (), (((), why),)
    if opts.folds is not None:
        return _checked_folds(net, opts.folds), ()
    return default_folds(net, eops)


def _eops(adj: Adjustment, data: FoldData) -> np.ndarray:
    params = adj.initial if data.params is None else data.params
    return np.asarray(params.eops)


def _checked_folds(net: Network, folds) -> tuple:
    for f in folds:
        for s in f:
            if s not in net.scans:
                raise ValueError(
                    f"cross-validation fold {'+'.join(f)}: scan {s!r} is not a scan of "
                    f"{net.source}; scans: {', '.join(net.scans)}"
                )
        if len(set(f)) >= len(net.scans):
            raise ValueError(f"cross-validation fold {'+'.join(f)} leaves no scan to adjust")
    return tuple(tuple(f) for f in folds)


def _finish(folds: tuple, labels: tuple, net: Network) -> CrossValidation:
    done = [f for f in folds if f.ok]
    nan = {k: float("nan") for k in AXES}
    if not done:
        return CrossValidation(CrossValidationCode.NO_FOLDS, folds, nan, nan, float("nan"), labels)
    n = sum(f.n for f in done)
    pooled = lambda key: {
        k: float(np.sqrt(sum(f.n * getattr(f, key)[k] ** 2 for f in done) / n)) for k in AXES
    }
    rms, rms0 = pooled("rms_mm"), pooled("rms_none_mm")
    mse = np.array([f.sse / f.n for f in done]) * 1e6  # mm^2
    se = float("nan")
    if len(done) > 1 and rms["xyz"] > 0:
        se = float(mse.std(ddof=1) / np.sqrt(len(done)) / (2 * rms["xyz"]))
    # Paired over the folds (the same held-out scans): mean and standard error of the
    # difference of the mean squared misfits with and without the calibration.
    d = mse - np.array([f.sse_none / f.n for f in done]) * 1e6
    d_se = d.std(ddof=1) / np.sqrt(len(d)) if len(d) > 1 else np.inf
    if not labels:
        code = CrossValidationCode.NO_APS
    elif rms["xyz"] >= rms0["xyz"]:
        code = CrossValidationCode.NOT_IMPROVED
    elif d.mean() + 2 * d_se > 0:
        code = CrossValidationCode.NOT_SIGNIFICANT
    else:
        code = CrossValidationCode.IMPROVED
    return CrossValidation(code, folds, rms, rms0, se, labels)


def validate(
    network: Network,
    model: CalibrationModel | None,
    options: CrossValidationOptions,
    solver: SolverOptions,
    result: CalibrationResult | None = None,
) -> CrossValidation:
    """Cross-validation of ``model`` on ``network`` by scan groups with the network's weights
    (:func:`tlsjax.cross_validate`, module docstring); ``result``: a calibration whose removed
    observations stay out and whose estimates warm-start the folds (None: calibrated here)."""
    adj = analyze(network, model, solver)
    eops = np.asarray(adj.initial.eops if result is None else result.eops)
    planned = plan_folds(adj, eops, options)
    if not planned[0]:  # nothing to hold out: no adjustment needed to say so
        return _finish(
            tuple(Fold(h, False, why) for h, why in planned[1]), adj.plan.ap_labels, network
        )
    if result is None:
        result = adj.solve()
    used = np.ones((network.observations.shape[0], 3), dtype=bool)
    if result.used is not None:
        used = np.asarray(result.used, dtype=bool)
    params = None
    if result.ok:
        params = initial_params(network, adj.plan, result.target_xyz, result.eops)
        params = dataclasses.replace(params, aps=jax.device_put(np.nan_to_num(result.ap_values)))
    data = FoldData(
        np.where(used, 1.0 / network.sigmas, 0.0),
        np.where(np.isfinite(network.levelling_sigma), 1.0 / network.levelling_sigma, 0.0),
        {},
        {},
        params,
        result.target_xyz,
        used.all(axis=1),
    )
    return run_folds(adj, data, options, planned)
