"""Networks: observations, their sigmas and the index plan, validated on the host.

A network is data. :func:`make_network` checks it at the boundary (names, finiteness, counts,
connectivity) and builds the index plan once: which observations share a target, which
(target, scan) pairs exist. The compiled adjustment only ever sees fixed-shape arrays.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import threading
import warnings
import weakref
from collections import defaultdict
from collections.abc import Mapping, Sequence

import numpy as np

from .._model._aps import on_reregistration
from .._model._plausibility import PlausibilityWarning, check_ranges, design_warnings
from .._units import ARCSEC

#: Default a priori sigmas (SPEC section 8): 0.5 mm range at normal incidence, 20" for the angles.
DEFAULT_SIGMA_RANGE = 0.5e-3
DEFAULT_SIGMA_ANGLE = 20.0 * ARCSEC
DEFAULT_SIGMA_LEVELLING = 10.0 * ARCSEC


@dataclasses.dataclass(frozen=True, eq=False)
class ObservationTable:
    """The rows of a target or plane observation file, in SI units (m, rad).

    ``sigmas`` is None when the file has no sigma column; a sigma column or cell that is absent
    is NaN (the caller fills the defaults). ``rows`` holds the 1-based line number of each row.
    ``architecture``: the scanner architecture the observations are expressed in (SPEC section
    1), when the file records it (None: not recorded); ``architecture_declared``: it was declared
    when Cartesian target lists (which do not record it) were converted, not measured, so only
    the fit can tell (``tlsjax calibrate`` compares both architectures then); ``notes``: what a
    reader decided (layout, units and the rule that chose them) for the user to check.
    """

    kind: str
    source: str
    scans: tuple[str, ...]
    primitives: tuple[str, ...]
    observations: np.ndarray
    sigmas: np.ndarray | None
    incidence: np.ndarray | None
    instruments: tuple[str, ...] | None
    rows: np.ndarray
    architecture: str | None = None
    notes: tuple = ()
    architecture_declared: bool = False

    def __len__(self) -> int:
        return len(self.scans)


@dataclasses.dataclass(frozen=True, eq=False)
class Network:
    """A point-based TLS network (host-side, numpy). Build it with :func:`make_network`.

    Arrays (n observations of targets, s scans, t targets)::

      observations (n, 3): range [m], horizontal direction [rad], elevation angle [rad]
      sigmas (n, 3): a priori standard deviations [m, rad, rad], incidence already applied
      target_index, scan_index (n,): integer codes into targets / scans
      instrument_of_scan (s,): integer code into instruments
      levelling (s, 2) values [rad] and levelling_sigma (s, 2) [rad]; inf = not levelled:
        the tilt readings (omega_c, phi_c) of a compensator or tilt sensor
      heading (s,) observed kappa [rad] and heading_sigma (s,) [rad] (None or inf: none);
        with the tilt readings the weighted constraints of Chow et al. 2013, eq. (7)
      control_index (c,), control_xyz (c, 3) [m], control_sigma (c, 3) [m]
      scale_bars: tuple of (target_a, target_b) indices with scale_bar_length (b,) and
        scale_bar_sigma (b,) [m]

    Plane observations (m points on k planes, SPEC section 4), empty for a target network::

      planes (k,) names; plane_observations (m, 3), plane_sigmas (m, 3) (incidence applied),
      plane_index, plane_scan_index (m,) integer codes into planes / scans.

    A network may hold targets, planes or both (a combined network).
    """

    scans: tuple[str, ...]
    targets: tuple[str, ...]
    instruments: tuple[str, ...]
    observations: np.ndarray
    sigmas: np.ndarray
    target_index: np.ndarray
    scan_index: np.ndarray
    instrument_of_scan: np.ndarray
    levelling: np.ndarray
    levelling_sigma: np.ndarray
    control_index: np.ndarray
    control_xyz: np.ndarray
    control_sigma: np.ndarray
    scale_bar_targets: np.ndarray
    scale_bar_length: np.ndarray
    scale_bar_sigma: np.ndarray
    source: str = "<arrays>"
    dropped: tuple[str, ...] = ()
    planes: tuple[str, ...] = ()
    plane_observations: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3)))
    plane_sigmas: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros((0, 3)))
    plane_index: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(0, dtype=np.int32))
    plane_scan_index: np.ndarray = dataclasses.field(
        default_factory=lambda: np.zeros(0, dtype=np.int32)
    )
    heading: np.ndarray | None = None
    heading_sigma: np.ndarray | None = None

    @property
    def heading_values(self) -> np.ndarray:
        """Observed kappa per scan [rad] (0 where none)."""
        return np.zeros(len(self.scans)) if self.heading is None else self.heading

    @property
    def heading_sigmas(self) -> np.ndarray:
        """Sigma of the observed kappa per scan [rad] (``inf`` where none)."""
        if self.heading_sigma is None:
            return np.full(len(self.scans), np.inf)
        return self.heading_sigma

    # The input line (1-based, header and comment lines counted) of each target observation and
    # plane point, for the per-observation tables; None where the rows came from arrays.
    lines: np.ndarray | None = None
    plane_lines: np.ndarray | None = None
    plane_source: str = ""
    # The scans CSV of the orientation readings (levelling, tilt, heading) and the line of
    # each scan's row in it (s,), 0 where the scan has none; None where they came from memory.
    scans_source: str = ""
    scan_lines: np.ndarray | None = None

    @property
    def n_observations(self) -> int:
        """Number of scalar observations (three per target observation and per plane point)."""
        return 3 * (self.observations.shape[0] + self.plane_observations.shape[0])

    @property
    def has_planes(self) -> bool:
        return len(self.planes) > 0

    @property
    def has_targets(self) -> bool:
        return len(self.targets) > 0

    @property
    def is_levelled(self) -> np.ndarray:
        return np.isfinite(self.levelling_sigma).all(axis=1)

    def with_observations(
        self, observations: np.ndarray, plane_observations: np.ndarray | None = None
    ) -> Network:
        """The same design with other observation values (Monte Carlo, corrected data)."""
        out = dataclasses.replace(self, observations=np.asarray(observations, dtype=np.float64))
        if plane_observations is not None:
            out = dataclasses.replace(
                out, plane_observations=np.asarray(plane_observations, dtype=np.float64)
            )
        return out


def _check_rows(obs, sigmas, incidence, defaults, where, what, source):
    """Finiteness and positivity of one set of rows; returns the sigmas with defaults and the
    incidence scaling of the range applied (SPEC section 5)."""
    n = obs.shape[0]
    bad = np.argwhere(~np.isfinite(obs))
    if bad.size:
        i, c = bad[0]
        raise ValueError(
            f"{where(i)}: {('range', 'hz', 'el')[c]} of {what(i)} is not finite ({obs[i, c]})"
        )
    bad = np.flatnonzero(obs[:, 0] <= 0)
    if bad.size:
        i = bad[0]
        raise ValueError(f"{where(i)}: range of {what(i)} must be positive, got {obs[i, 0]}")
    for note in check_ranges(obs[:, 0], where, what, source):  # unit mix-ups (_plausibility)
        warnings.warn(note, PlausibilityWarning, stacklevel=4)
    sig = np.empty_like(obs)
    sig[:] = defaults
    if sigmas is not None:
        s_in = np.asarray(sigmas, dtype=np.float64)
        if s_in.shape != obs.shape:
            raise ValueError(f"{source}: sigmas must have shape {obs.shape}, got {s_in.shape}")
        sig = np.where(np.isnan(s_in), sig, s_in)
    bad = np.argwhere(~(np.isfinite(sig) & (sig > 0)))
    if bad.size:
        i, c = bad[0]
        raise ValueError(
            f"{where(i)}: sigma of {('range', 'hz', 'el')[c]} ({what(i)}) must be positive and finite, got {sig[i, c]}"
        )
    if incidence is not None:
        inc = np.asarray(incidence, dtype=np.float64).reshape(-1)
        if inc.shape != (n,):
            raise ValueError(
                f"{source}: incidence must have one angle per row ({n}), got {inc.shape[0]}"
            )
        inc = np.nan_to_num(inc, nan=0.0)
        # The angle between the line of sight and the surface normal: 0 at normal incidence,
        # never negative (a negative value is a sign or convention mistake, not an angle).
        bad = np.flatnonzero(~np.isfinite(inc) | (inc < 0) | (inc >= np.pi / 2))
        if bad.size:
            i = bad[0]
            raise ValueError(
                f"{where(i)}: incidence angle of {what(i)} must be in [0, 90) deg (the angle "
                f"between the line of sight and the surface normal), got {np.degrees(inc[i]):.6g} deg"
            )
        sig[:, 0] = sig[:, 0] / np.cos(inc)
    return sig


def _where(source, rows):
    if source != "<arrays>":
        return lambda i: f"{source}, line {rows[i]}"
    return lambda i: f"{source}, row {rows[i]}"


#: Fewest points on a plane: three determine it, a fourth gives the first redundancy.
MIN_PLANE_POINTS = 4

ARCHITECTURES = ("hybrid", "panoramic")
_HALF_PI, _TWO_PI = 0.5 * np.pi, 2.0 * np.pi
#: Rounding allowance at the limits of the angle ranges [rad].
_ANGLE_SLACK = 1e-9
#: How far a panoramic hz may stray outside [0, 180) deg: the APs and the noise of a direction
#: near a face boundary push it across by arc minutes at most.
PANORAMIC_HZ_SLACK = np.radians(1.0)


def _deg(x) -> str:
    return f"{np.degrees(x):.6g} deg"


def check_angles(obs, architecture, where, what) -> None:
    """Angle ranges of SPEC section 1, row by row; raise a ValueError naming the first bad row.

    Any scanner: ``|hz| < 720 deg`` (a reading one turn off is still a direction; two turns are
    not, e.g. degrees in a ``_rad`` column) and el in [-90, 270) deg. Hybrid: el in [-90, 90] deg.
    Panoramic: hz in [0, 180) deg (wrapped, with :data:`PANORAMIC_HZ_SLACK`); el past 90 deg is
    the second face. ``architecture=None``: elevations past 90 deg occur only on a panoramic
    scanner, so they are refused when some hz is outside the panoramic range.
    """
    hz, el = obs[:, 1], obs[:, 2]
    checks = [
        (np.abs(hz) >= 2 * _TWO_PI, "hz", "is two turns or more (|hz| must be below 720 deg)"),
        (el < -_HALF_PI - _ANGLE_SLACK, "el", "is below -90 deg (the nadir)"),
        (el >= 1.5 * np.pi, "el", "is not below 270 deg"),
    ]
    past_zenith = el > _HALF_PI + _ANGLE_SLACK
    wrapped = np.mod(hz + PANORAMIC_HZ_SLACK, _TWO_PI) - PANORAMIC_HZ_SLACK
    outside_panoramic = wrapped >= np.pi + PANORAMIC_HZ_SLACK
    if architecture is None and past_zenith.any() and outside_panoramic.any():
        # Only a panoramic scanner's second face observes past the zenith, and then every hz
        # is in [0, 180) deg: the elevation is the suspect, and the hz row shows why.
        k = int(np.argmax(outside_panoramic))
        checks.append(
            (
                past_zenith,
                "el",
                f"is beyond 90 deg, which only the second face of a panoramic scanner observes, but "
                f"{where(k)} has hz = {_deg(hz[k])}, outside the panoramic hz range [0, 180) deg",
            )
        )
    if architecture == "hybrid":
        checks.append(
            (
                past_zenith,
                "el",
                "is beyond 90 deg: a hybrid scanner observes el in [-90, 90] deg (only the "
                "second face of a panoramic scanner looks past the zenith: architecture "
                "'panoramic', CLI --architecture panoramic)",
            )
        )
    elif architecture == "panoramic":
        checks.append(
            (outside_panoramic, "hz", "is not in [0, 180) deg, the hz range of a panoramic scanner")
        )
    for bad, name, why in checks:
        rows = np.flatnonzero(bad)
        if rows.size:
            i = rows[0]
            value = hz[i] if name == "hz" else el[i]
            raise ValueError(
                f"{where(i)}: {name} of {what(i)} = {_deg(value)} ({value:.6g} rad) {why}; "
                "check the value and the unit of the column"
            )


def _check_type(value, name: str, kinds, expected: str) -> None:
    if not isinstance(value, kinds):
        raise TypeError(f"{name} must be {expected}, got {type(value).__name__}")


def _names(values, argument: str, what: str, n: int, source: str) -> list[str]:
    """One name per observation row; a single string is refused (it is not one per row)."""
    if isinstance(values, (str, bytes)) or not hasattr(values, "__len__"):
        raise TypeError(
            f"{argument} must be a sequence of {what} names, one per observation row, "
            f"got {type(values).__name__}"
        )
    names = [str(v) for v in values]
    if len(names) != n:
        raise ValueError(
            f"{source}: {n} observations but {len(names)} {what} names in {argument} (one per row)"
        )
    empty = [i for i, v in enumerate(names) if not v.strip()]
    if empty:
        raise ValueError(f"{source}: the {what} name of row {empty[0]} is empty")
    return names


def _inside_transformation() -> bool:
    """True inside ``jax.jit``, ``grad`` or ``vmap`` even where no argument is traced (a network
    closed over): the host-side entries would fail there on their first array conversion. JAX
    has no public question for it; its trace state answers (False where it cannot be asked)."""
    try:
        from jax._src.core import trace_state_clean
    except ImportError:  # pragma: no cover - a JAX without it: the tracer test alone
        return False
    return not trace_state_clean()


def refuse_traced(value, where: str, *, entry: bool = False) -> None:
    """A one-line ValueError when ``value`` holds JAX tracers (or, for an ``entry`` of the
    calibration, when it is called inside a transformation at all, its network closed over):
    the network, its checks and the approximate values are host-side numpy, so they cannot
    run under ``jax.jit``, ``grad`` or ``vmap``; the differentiable, jittable, vmappable
    adjustment is named instead."""
    import jax

    if isinstance(value, Network):
        value = [getattr(value, f.name) for f in dataclasses.fields(value)]
    leaves = jax.tree_util.tree_leaves(value)
    if any(isinstance(x, jax.core.Tracer) for x in leaves) or (entry and _inside_transformation()):
        raise ValueError(
            f"{where} runs on the host and cannot be traced by jax.jit, grad or vmap; build the "
            "network outside the transformation and use f = tlsjax.differentiable_adjustment("
            "tlsjax.analyze(net, model)) with f(tlsjax.network_inputs(adj)) inside it (jitted, "
            "differentiable, vmappable)"
        )


def _as_observations(observations, source: str) -> np.ndarray:
    refuse_traced(observations, "make_network")
    try:
        obs = np.asarray(observations, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise TypeError(
            f"observations must be an (n, 3) array of numbers [range m, hz rad, el rad]: {err}"
        ) from None
    if obs.size == 0:
        obs = obs.reshape(0, 3)
    if obs.ndim != 2 or obs.shape[1] != 3:
        raise ValueError(
            f"{source}: observations must have shape (n, 3) [range, hz, el], got {obs.shape}"
        )
    return obs


def _check_options(architecture, sigma_range, sigma_hz, sigma_el, min_targets_per_scan) -> None:
    if architecture is not None and architecture not in ARCHITECTURES:
        raise ValueError(f"architecture {architecture!r} is not one of {ARCHITECTURES} or None")
    for name, value in (
        ("sigma_range", sigma_range),
        ("sigma_hz", sigma_hz),
        ("sigma_el", sigma_el),
    ):
        if isinstance(value, (bool, str)) or not isinstance(value, (int, float, np.number)):
            raise TypeError(f"{name} must be a number [m or rad], got {type(value).__name__}")
    if isinstance(min_targets_per_scan, bool) or not isinstance(
        min_targets_per_scan, (int, np.integer)
    ):
        raise TypeError(
            f"min_targets_per_scan must be an integer, got {type(min_targets_per_scan).__name__}"
        )
    if min_targets_per_scan < 3:
        raise ValueError(
            f"min_targets_per_scan must be at least 3 (three targets determine a pose), got {min_targets_per_scan}"
        )


def _check_plane_duplicates(p_scans, p_names, p_obs, p_where) -> None:
    """A plane has many points per scan, but the same point twice (one row repeated) would
    count one observation twice: refuse identical (scan, plane, range, hz, el) rows."""
    seen: dict[tuple, int] = {}
    for i, key in enumerate(zip(p_scans, p_names, map(tuple, p_obs.tolist()))):
        if key in seen:
            raise ValueError(
                f"{p_where(i)}: duplicate point of plane {key[1]} in scan {key[0]} "
                f"(the same observation as {p_where(seen[key])})"
            )
        seen[key] = i


@dataclasses.dataclass(frozen=True)
class _Rows:
    """Validated rows of one kind (targets or plane points): the scan, primitive and instrument
    of each row, observations and sigmas (n, 3) in SI units, and ``where(i)``, the file and
    line of row i for messages."""

    kind: str
    scans: list
    names: list
    instruments: list
    obs: np.ndarray
    sig: np.ndarray
    where: object
    source: str
    lines: np.ndarray  # the file line (1-based) of each row, or its index for arrays

    def keep(self, mask) -> _Rows:
        pick = lambda seq: [x for x, k in zip(seq, mask) if k]
        return dataclasses.replace(
            self,
            scans=pick(self.scans),
            names=pick(self.names),
            instruments=pick(self.instruments),
            obs=self.obs[mask],
            sig=self.sig[mask],
            lines=self.lines[mask],
        )


def _checked_rows(table: ObservationTable, defaults, architecture) -> _Rows:
    """The rows of a target or plane table, checked: finite values and sigmas (defaults where
    a sigma is missing, ``sec(incidence)`` on the range), angle ranges, no observation twice
    (:func:`_check_target_duplicates`, :func:`_check_plane_duplicates`)."""
    scans, names, obs, src = (
        list(table.scans),
        list(table.primitives),
        table.observations,
        table.source,
    )
    where = _where(src, np.asarray(table.rows))
    what = lambda i: f"scan {scans[i]}, {table.kind} {names[i]}"
    sig = _check_rows(obs, table.sigmas, table.incidence, defaults, where, what, src)
    check_angles(obs, architecture, where, what)
    if table.kind == "target":
        _check_target_duplicates(scans, names, obs, where)
    else:
        _check_plane_duplicates(scans, names, obs, where)
    inst = ["default"] * len(scans) if table.instruments is None else list(table.instruments)
    lines = np.asarray(table.rows, dtype=np.int64).reshape(-1)
    return _Rows(table.kind, scans, names, inst, obs, sig, where, src, lines)


def _second_face(obs) -> np.ndarray:
    # A panoramic scanner may see a target in both faces of one scan (the two-face design):
    # the face (elevation beyond 90 deg) is part of what makes an observation unique.
    return obs[:, 2] > np.pi / 2


def _check_target_duplicates(scans, targets, obs, where) -> None:
    seen: dict[tuple, int] = {}
    for i, key in enumerate(zip(scans, targets, _second_face(obs).tolist())):
        if key in seen:
            raise ValueError(
                f"{where(i)}: duplicate observation of target {key[1]} in scan {key[0]} (also {where(seen[key])})"
            )
        seen[key] = i


def _plane_rows(planes, defaults, architecture, targets, source) -> _Rows | None:
    """The plane rows of a plane :class:`ObservationTable`, checked like the target rows, plus:
    no name shared with a target, no point twice, enough points per plane."""
    if planes is None:
        return None
    if getattr(planes, "kind", None) != "plane":
        raise ValueError(
            f"{source}: planes must be a plane ObservationTable (read_observations of a file with a "
            f"'plane' column, ExtractedPlanes.to_table() or PointClouds.to_table())"
        )
    p_src = planes.source
    scans = [str(s) for s in planes.scans]
    names = [str(k) for k in planes.primitives]
    obs = np.asarray(planes.observations, dtype=np.float64).reshape(-1, 3)
    if not (len(scans) == len(names) == obs.shape[0]):
        raise ValueError(
            f"{p_src}: {obs.shape[0]} plane observations but {len(scans)} scan names and {len(names)} plane names"
        )
    if obs.shape[0] == 0:
        raise ValueError(f"{p_src}: no plane observations")
    table = dataclasses.replace(
        planes,
        scans=tuple(scans),
        primitives=tuple(names),
        observations=obs,
        instruments=None if planes.instruments is None else tuple(map(str, planes.instruments)),
    )
    rows = _checked_rows(table, defaults, architecture)
    clash = sorted(set(names) & set(targets))
    if clash:
        raise ValueError(
            f"{p_src}: {clash[0]} names both a target and a plane; give planes and targets distinct names"
        )
    return rows


def _assign_instruments(rows: _Rows, scan_instrument: dict) -> dict:
    """``scan_instrument`` (scan -> instrument) completed with ``rows``; one instrument per
    scan."""
    for i, (s, ins) in enumerate(zip(rows.scans, rows.instruments)):
        if scan_instrument.setdefault(s, ins) != ins:
            raise ValueError(
                f"{rows.where(i)}: scan {s} is assigned to instruments {scan_instrument[s]} and {ins}; one scan, one instrument"
            )
    return scan_instrument


def _check_plane_points(planes: _Rows) -> None:
    counts: dict[str, int] = defaultdict(int)
    for k in planes.names:
        counts[k] += 1
    few = [k for k, c in counts.items() if c < MIN_PLANE_POINTS]
    if few:
        raise ValueError(
            f"{planes.source}: plane {few[0]} has {counts[few[0]]} point(s); at least {MIN_PLANE_POINTS} are needed "
            "to determine a plane with redundancy"
        )


def _drop_single_targets(targets: _Rows, p_scans, control, bars, drop: bool, source):
    """Targets seen in one scan only add three unknowns and three observations: no redundancy.
    Refused, or (``drop``) dropped; returns the rows kept and the names dropped."""
    scans_of_target: dict[str, set] = defaultdict(set)
    for s, t, f in zip(targets.scans, targets.names, _second_face(targets.obs).tolist()):
        scans_of_target[t].add((s, f))  # both faces of one scan also give redundancy
    bar_targets = {a for a, _, _, _ in bars} | {b for _, b, _, _ in bars}
    single = sorted(
        t
        for t, ss in scans_of_target.items()
        if len(ss) < 2 and t not in control and t not in bar_targets
    )
    if not single:
        return targets, ()
    if not drop:
        raise ValueError(
            f"{source}: target(s) {', '.join(single[:10])}{' ...' if len(single) > 10 else ''} are seen in one scan only; "
            "they give no redundancy. Pass drop_single_targets=True (CLI: --drop-single-targets) to drop them."
        )
    keep = np.array([t not in set(single) for t in targets.names])
    _check_left_after_dropping(targets.scans, keep, p_scans, tuple(single), source)
    return targets.keep(keep), tuple(single)


def _codes(names) -> dict:
    return {x: i for i, x in enumerate(names)}


@dataclasses.dataclass(frozen=True)
class _IndexPlan:
    """Names in order of first appearance and the integer codes of every row."""

    scans: tuple
    targets: tuple
    planes: tuple
    scan_index: np.ndarray
    target_index: np.ndarray
    plane_scan_index: np.ndarray
    plane_index: np.ndarray

    @classmethod
    def of(cls, tg: _Rows, p_scans, p_names) -> _IndexPlan:
        scans = tuple(dict.fromkeys(tg.scans + p_scans))
        targets, planes = tuple(dict.fromkeys(tg.names)), tuple(dict.fromkeys(p_names))
        s_code, t_code, k_code = _codes(scans), _codes(targets), _codes(planes)
        index = lambda code, seq: np.array([code[x] for x in seq], dtype=np.int32)
        return cls(
            scans,
            targets,
            planes,
            index(s_code, tg.scans),
            index(t_code, tg.names),
            index(s_code, p_scans),
            index(k_code, p_names),
        )


def _check_scan_primitives(
    scan_names, scan_index, plane_scan_index, plane_index, minimum, source, plane_source
) -> None:
    """A scan's pose needs 4 targets (3 determine it), or 3 planes (their normals must also be
    independent, which the approximate values check), or a mix of at least 3."""
    n_t_scan = np.bincount(scan_index, minlength=len(scan_names))
    n_p_scan = np.array(
        [len(set(plane_index[plane_scan_index == j].tolist())) for j in range(len(scan_names))],
        dtype=int,
    )
    for j, s in enumerate(scan_names):
        if n_p_scan[j] == 0 and n_t_scan[j] < minimum:
            raise ValueError(
                f"{source}: scan {s} observes {n_t_scan[j]} target(s); at least {minimum} are needed to determine its pose"
            )
        if n_p_scan[j] and n_t_scan[j] + n_p_scan[j] < 3:
            raise ValueError(
                f"{source if n_t_scan[j] else plane_source}: scan {s} observes {n_t_scan[j]} target(s) and "
                f"{n_p_scan[j]} plane(s); at least 3 primitives are needed to determine its pose"
            )


def _levelling_arrays(lev_entries, s_code, source):
    """Levelling readings and sigmas (s, 2) in scan order; inf sigma: not levelled."""
    lev = np.zeros((len(s_code), 2))
    lev_sigma = np.full((len(s_code), 2), np.inf)
    for s, (values, sg) in lev_entries.items():
        if s not in s_code:
            raise ValueError(f"{source}: levelling given for scan {s}, which has no observations")
        lev[s_code[s]] = values
        lev_sigma[s_code[s]] = sg
    return lev, lev_sigma


def _heading_arrays(heading_entries, s_code, source):
    """Observed kappas and their sigmas (s,) in scan order, or (None, None) when no scan has
    one (the network then carries no heading constraint)."""
    if not heading_entries:
        return None, None
    heading = np.zeros(len(s_code))
    heading_sigma = np.full(len(s_code), np.inf)
    for s, (value, sg) in heading_entries.items():
        if s not in s_code:
            raise ValueError(f"{source}: kappa given for scan {s}, which has no observations")
        heading[s_code[s]], heading_sigma[s_code[s]] = value, sg
    return heading, heading_sigma


def _control_arrays(control, t_code, source):
    c_idx, c_xyz, c_sig = [], [], []
    for t, (xyz, sg) in control.items():
        if t not in t_code:
            raise ValueError(f"{source}: control point {t} is not observed in any scan")
        c_idx.append(t_code[t])
        c_xyz.append(xyz)
        c_sig.append(sg)
    return (
        np.array(c_idx, dtype=np.int32),
        np.array(c_xyz).reshape(-1, 3),
        np.array(c_sig).reshape(-1, 3),
    )


def _scale_bar_arrays(bars, t_code, source):
    b_idx, b_len, b_sig = [], [], []
    for a, b, length, sg in bars:
        for t in (a, b):
            if t not in t_code:
                raise ValueError(f"{source}: scale bar end {t} is not observed in any scan")
        b_idx.append((t_code[a], t_code[b]))
        b_len.append(length)
        b_sig.append(sg)
    return np.array(b_idx, dtype=np.int32).reshape(-1, 2), np.array(b_len), np.array(b_sig)


def make_network(
    scans: Sequence[str],
    targets: Sequence[str],
    observations,
    *,
    sigmas=None,
    sigma_range: float = DEFAULT_SIGMA_RANGE,
    sigma_hz: float = DEFAULT_SIGMA_ANGLE,
    sigma_el: float = DEFAULT_SIGMA_ANGLE,
    incidence=None,
    instruments: Sequence[str] | None = None,
    levelling: Mapping[str, Mapping[str, float]] | None = None,
    orientation: Mapping[str, Mapping[str, float]] | None = None,
    control: Mapping[str, tuple] | None = None,
    scale_bars: Sequence[tuple] = (),
    drop_single_targets: bool = False,
    min_targets_per_scan: int = 4,
    source: str = "<arrays>",
    rows=None,
    planes=None,
    architecture: str | None = None,
) -> Network:
    """Validate observations and build a :class:`Network`.

    ``scans``/``targets`` name the scan and target of each row; ``observations`` is (n, 3) in
    metres and radians. ``sigmas`` (n, 3) overrides the group sigmas per observation (NaN entries
    fall back to them). The range sigma is scaled by ``sec(incidence)`` (SPEC section 5).
    ``levelling`` maps scan -> {"omega", "phi", "sigma_omega", "sigma_phi"} [rad]: a dual-axis
    compensator's readings (within a degree of the vertical).
    ``orientation`` maps scan -> any of {"omega", "phi", "sigma_omega", "sigma_phi"} (a tilt
    sensor's readings, of a tilted scan too: both angles with their sigmas) and {"kappa",
    "sigma_kappa"} (a known heading) [rad]: the weighted constraints with observed values of
    Chow et al. 2013, eq. (7) (SPEC section 6). The tilt readings are the object-space vertical
    seen in the scanner frame (:func:`tlsjax._model._levelling.compensator_reading`, the Cardan
    omega and phi when kappa = 0), kappa the Cardan angle itself. They are observations of a
    scan, so they belong to the network (the scans CSV holds them).
    ``control`` maps target -> (xyz [m], sigma [m] scalar or 3-vector).
    ``scale_bars`` is a list of (target_a, target_b, length [m], sigma [m]).
    ``rows`` (optional) gives the file line of each row for error messages.
    ``architecture`` ("hybrid", "panoramic" or None) selects the angle ranges checked
    (SPEC section 1, :func:`check_angles`); None accepts either, judged from the elevations.

    ``planes``: plane observations (one row per point on a plane in a scan, SPEC sections 4
    and 11) as an :class:`~tlsjax._io.ObservationTable` of kind "plane" (from
    :func:`~tlsjax.read_observations`, :meth:`~tlsjax.ExtractedPlanes.to_table` or
    :meth:`~tlsjax.PointClouds.to_table`); their sigmas default to the same group sigmas. With
    ``planes`` the target rows may be empty (a plane network) or not (a combined network).
    See :func:`make_plane_network`.

    The checks, in order, each a small validator of this module: the options; the target rows
    and the plane rows (names, finite values and sigmas, angle ranges, duplicates); one
    instrument per scan; the levelling, control and scale-bar entries; targets seen in one scan
    only; enough primitives per scan; a connected network. (The signature and this docstring
    are most of this function's length; its body is that sequence.)
    """
    _check_options(architecture, sigma_range, sigma_hz, sigma_el, min_targets_per_scan)
    defaults = (sigma_range, sigma_hz, sigma_el)
    obs = _as_observations(observations, source)
    n = obs.shape[0]
    scans = tuple(_names(scans, "scans", "scan", n, source))
    targets = tuple(_names(targets, "targets", "target", n, source))
    if n == 0 and planes is None:
        raise ValueError(f"{source}: no observations")
    from_file = rows is not None
    rows = np.arange(n) if rows is None else np.asarray(rows)
    table = ObservationTable("target", source, scans, targets, obs, sigmas, incidence, None, rows)
    tg = _checked_rows(table, defaults, architecture)
    if instruments is not None:
        tg = dataclasses.replace(
            tg, instruments=_names(instruments, "instruments", "instrument", n, source)
        )
    scan_instrument = _assign_instruments(tg, {})
    pl = _plane_rows(planes, defaults, architecture, tg.names, source)
    p_scans, p_names, p_source = [], [], source
    if pl is not None:
        _assign_instruments(pl, scan_instrument)
        _check_plane_points(pl)
        p_scans, p_names, p_source = pl.scans, pl.names, pl.source
    lev_entries = _levelling_entries(levelling, source)
    tilt_entries, heading_entries = _orientation_entries(orientation, source)
    for scan in set(lev_entries) & set(tilt_entries):
        raise ValueError(
            f"{source}: scan {scan} has levelling and orientation tilt readings; give one of them"
        )
    lev_entries.update(tilt_entries)
    control = _control_entries(control, source)
    bars = _scale_bar_entries(scale_bars, source)
    tg, dropped = _drop_single_targets(tg, p_scans, control, bars, drop_single_targets, source)

    ip = _IndexPlan.of(tg, p_scans, p_names)
    _check_scan_primitives(
        ip.scans,
        ip.scan_index,
        ip.plane_scan_index,
        ip.plane_index,
        min_targets_per_scan,
        source,
        p_source,
    )
    # Connectivity through shared primitives: targets and planes count alike (codes offset).
    prim_scan = np.concatenate([ip.scan_index, ip.plane_scan_index])
    prim_index = np.concatenate([ip.target_index, ip.plane_index + len(ip.targets)])
    _check_connected(ip.scans, ip.scans, prim_scan, prim_index, source)

    entries = (lev_entries, heading_entries, control, bars)
    net = _network(tg, pl, ip, scan_instrument, entries, dropped, source)
    return dataclasses.replace(
        net,
        lines=tg.lines if from_file else None,
        plane_lines=pl.lines if pl is not None else None,
        plane_source=p_source,
    )


def _network(tg: _Rows, pl, ip: _IndexPlan, scan_instrument, entries, dropped, source) -> Network:
    """The :class:`Network` of validated rows, their index plan and the levelling, heading,
    control and scale-bar entries (each checked against the names observed)."""
    lev_entries, heading_entries, control, bars = entries
    instrument_names = tuple(dict.fromkeys(scan_instrument[s] for s in ip.scans))
    i_code, s_code, t_code = _codes(instrument_names), _codes(ip.scans), _codes(ip.targets)
    lev, lev_sigma = _levelling_arrays(lev_entries, s_code, source)
    heading, heading_sigma = _heading_arrays(heading_entries, s_code, source)
    c_idx, c_xyz, c_sig = _control_arrays(control, t_code, source)
    b_idx, b_len, b_sig = _scale_bar_arrays(bars, t_code, source)
    return Network(
        scans=ip.scans,
        targets=ip.targets,
        instruments=instrument_names,
        observations=tg.obs,
        sigmas=tg.sig,
        target_index=ip.target_index,
        scan_index=ip.scan_index,
        instrument_of_scan=np.array([i_code[scan_instrument[s]] for s in ip.scans], dtype=np.int32),
        levelling=lev,
        levelling_sigma=lev_sigma,
        control_index=c_idx,
        control_xyz=c_xyz,
        control_sigma=c_sig,
        scale_bar_targets=b_idx,
        scale_bar_length=b_len,
        scale_bar_sigma=b_sig,
        source=source,
        dropped=dropped,
        planes=ip.planes,
        plane_observations=pl.obs if pl is not None else np.zeros((0, 3)),
        plane_sigmas=pl.sig if pl is not None else np.zeros((0, 3)),
        plane_index=ip.plane_index,
        plane_scan_index=ip.plane_scan_index,
        heading=heading,
        heading_sigma=heading_sigma,
    )


#: Largest levelling reading accepted [rad]: a dual-axis compensator works within a few arc
#: minutes of the vertical, so a reading of more than a degree is a unit or sign mistake.
MAX_LEVELLING = np.radians(1.0)
_LEVELLING_KEYS = ("omega", "phi", "sigma_omega", "sigma_phi")


def _levelling_entries(levelling, source: str) -> dict:
    """scan -> ((omega, phi), (sigma_omega, sigma_phi)) [rad], checked; omega and phi default
    to 0 (a levelled scan), the sigmas are required (they are the observation's weight)."""
    if levelling is None:
        return {}
    _check_type(
        levelling,
        "levelling",
        Mapping,
        "a mapping scan -> {omega, phi, sigma_omega, sigma_phi} [rad]",
    )
    out = {}
    for scan, d in levelling.items():
        _check_type(
            d,
            f"levelling[{scan!r}]",
            Mapping,
            "a mapping with keys omega, phi, sigma_omega, sigma_phi [rad]",
        )
        unknown = sorted(set(map(str, d)) - set(_LEVELLING_KEYS))
        if unknown:
            raise ValueError(
                f"{source}: levelling of scan {scan}: unknown key(s) {', '.join(unknown)}; "
                f"accepted: {', '.join(_LEVELLING_KEYS)} [rad]"
            )
        missing = [k for k in ("sigma_omega", "sigma_phi") if k not in d]
        if missing:
            raise ValueError(
                f"{source}: levelling of scan {scan} has no {' and no '.join(missing)} [rad]; a levelling "
                "observation needs its sigma (e.g. 10 arc seconds = 4.85e-5 rad for a compensator)"
            )
        try:
            v = np.array(
                [d.get("omega", 0.0), d.get("phi", 0.0), d["sigma_omega"], d["sigma_phi"]],
                dtype=np.float64,
            )
        except (TypeError, ValueError):
            raise TypeError(
                f"levelling of scan {scan}: values must be numbers [rad], got {dict(d)!r}"
            ) from None
        if not np.all(np.isfinite(v)):
            raise ValueError(f"{source}: levelling of scan {scan} is not finite: {dict(d)!r}")
        if not np.all(v[2:] > 0):
            raise ValueError(
                f"{source}: levelling sigmas of scan {scan} must be positive and finite, got {v[2:]}"
            )
        if np.any(np.abs(v[:2]) > MAX_LEVELLING):
            raise ValueError(
                f"{source}: levelling of scan {scan}: omega = {_deg(v[0])}, phi = {_deg(v[1])}; a compensator "
                f"reads within {_deg(MAX_LEVELLING)} of the vertical: check the values and their unit (rad)"
            )
        out[str(scan)] = (v[:2], v[2:])
    return out


_ORIENTATION_KEYS = ("omega", "phi", "kappa", "sigma_omega", "sigma_phi", "sigma_kappa")


def _orientation_entries(orientation, source: str) -> tuple[dict, dict]:
    """(scan -> ((omega, phi), (sigma_omega, sigma_phi)), scan -> (kappa, sigma_kappa)) [rad],
    checked: the tilt readings of a tilted scan lie within 90 deg of the vertical, each
    observed angle has its sigma, omega and phi come together."""
    if orientation is None:
        return {}, {}
    _check_type(orientation, "orientation", Mapping, "a mapping scan -> {omega, phi, kappa, ...}")
    tilt, heading = {}, {}
    for scan, d in orientation.items():
        where = f"{source}: orientation of scan {scan}"
        _check_type(
            d, f"orientation[{scan!r}]", Mapping, f"a mapping with keys {_ORIENTATION_KEYS}"
        )
        unknown = sorted(set(map(str, d)) - set(_ORIENTATION_KEYS))
        if unknown:
            raise ValueError(
                f"{where}: unknown key(s) {', '.join(unknown)}; accepted: {', '.join(_ORIENTATION_KEYS)} [rad]"
            )
        try:
            v = {k: float(d[k]) for k in d}
        except (TypeError, ValueError):
            raise TypeError(f"{where}: values must be numbers [rad], got {dict(d)!r}") from None
        if not all(np.isfinite(x) for x in v.values()):
            raise ValueError(f"{where} is not finite: {dict(d)!r}")
        for angle in ("omega", "phi", "kappa"):
            if angle in v and f"sigma_{angle}" not in v:
                raise ValueError(f"{where}: {angle} has no sigma_{angle} [rad]")
            if f"sigma_{angle}" in v and not v[f"sigma_{angle}"] > 0:
                raise ValueError(
                    f"{where}: sigma_{angle} must be positive, got {v[f'sigma_{angle}']}"
                )
        tilt_keys = [k for k in ("sigma_omega", "sigma_phi") if k in v]
        if len(tilt_keys) == 1:
            raise ValueError(
                f"{where}: a tilt reading needs both omega and phi with their sigmas (one sensor "
                "axis alone would leave the rotation about the other one as a datum defect)"
            )
        if tilt_keys:
            om, ph = v.get("omega", 0.0), v.get("phi", 0.0)
            if max(abs(om), abs(ph)) >= np.pi / 2:
                raise ValueError(
                    f"{where}: omega = {_deg(om)}, phi = {_deg(ph)}; a tilt reading lies within 90 deg "
                    "of the vertical: check the values and their unit (rad)"
                )
            tilt[str(scan)] = (np.array([om, ph]), np.array([v["sigma_omega"], v["sigma_phi"]]))
        if "sigma_kappa" in v:
            if "kappa" not in v:
                raise ValueError(f"{where}: sigma_kappa without kappa [rad]")
            heading[str(scan)] = (v["kappa"], v["sigma_kappa"])
    return tilt, heading


def _control_entries(control, source: str) -> dict:
    """target -> (xyz (3,) [m], sigma (3,) [m]), checked."""
    if control is None:
        return {}
    _check_type(control, "control", Mapping, "a mapping target -> (xyz [m], sigma [m])")
    out = {}
    for t, entry in control.items():
        try:
            xyz, sg = entry
            xyz = np.asarray(xyz, dtype=np.float64).reshape(3)
            sg = np.broadcast_to(np.asarray(sg, dtype=np.float64), (3,)).copy()
        except (TypeError, ValueError):
            raise ValueError(
                f"{source}: control point {t} must be (xyz [m], sigma [m] scalar or 3-vector), got {entry!r}"
            ) from None
        if not (np.all(np.isfinite(xyz)) and np.all(np.isfinite(sg) & (sg > 0))):
            raise ValueError(
                f"{source}: control point {t} needs finite coordinates and positive sigmas"
            )
        out[str(t)] = (xyz, sg)
    return out


def _scale_bar_entries(scale_bars, source: str) -> list:
    """[(target_a, target_b, length [m], sigma [m])], checked: two distinct targets, a positive
    length and sigma, each pair once."""
    if scale_bars is None:
        return []
    if isinstance(scale_bars, (str, bytes, Mapping)) or not hasattr(scale_bars, "__iter__"):
        raise TypeError(
            f"scale_bars must be a sequence of (target_a, target_b, length [m], sigma [m]), got {type(scale_bars).__name__}"
        )
    out, seen = [], {}
    for k, bar in enumerate(scale_bars):
        try:
            a, b, length, sg = bar
            length, sg = float(length), float(sg)
        except (TypeError, ValueError):
            raise ValueError(
                f"{source}: scale bar {k + 1} must be (target_a, target_b, length [m], sigma [m]), got {bar!r}"
            ) from None
        a, b = str(a), str(b)
        if a == b:
            raise ValueError(
                f"{source}: scale bar {k + 1} joins target {a} to itself; a scale bar needs two targets"
            )
        if not (np.isfinite(length) and length > 0 and np.isfinite(sg) and sg > 0):
            raise ValueError(
                f"{source}: scale bar {a}-{b} needs a positive length and sigma, got {length} and {sg}"
            )
        pair = frozenset((a, b))
        if pair in seen:
            raise ValueError(
                f"{source}: scale bar {a}-{b} is given twice (bars {seen[pair]} and {k + 1})"
            )
        seen[pair] = k + 1
        out.append((a, b, length, sg))
    return out


def _check_left_after_dropping(scans, keep, p_scans, dropped, source) -> None:
    """Dropping single targets must leave every scan (and the network) something to adjust."""
    left = {s for s, k in zip(scans, keep) if k} | set(p_scans)
    gone = [s for s in dict.fromkeys(scans) if s not in left]
    names = ", ".join(dropped[:10]) + (" ..." if len(dropped) > 10 else "")
    if not left:
        raise ValueError(
            f"{source}: every target is seen in one scan only ({names}); nothing is left to adjust "
            "after dropping them: a self-calibration needs targets seen from several scans"
        )
    if gone:
        raise ValueError(
            f"{source}: scan(s) {', '.join(gone)} observe only targets seen in no other scan; "
            f"dropping them ({names}) leaves nothing of those scans"
        )


def make_plane_network(planes, **kwargs) -> Network:
    """A plane network (no targets) from a plane ObservationTable; keywords as :func:`make_network`
    (sigmas, levelling, instruments through the table)."""
    if getattr(planes, "kind", None) != "plane":
        raise TypeError(
            f"make_plane_network: planes must be a plane ObservationTable, got "
            f"{type(planes).__name__}; read one with tlsjax.read_planes(path), or take "
            "ExtractedPlanes.to_table() or PointClouds.to_table()"
        )
    kwargs.setdefault("source", planes.source)
    return make_network((), (), np.zeros((0, 3)), planes=planes, **kwargs)


def _check_connected(scan_names, target_names, scan_index, target_index, source):
    """Scans must be linked through chains of >= 3 common primitives, or their relative pose is free."""
    common = defaultdict(set)
    for s, t in zip(scan_index, target_index):
        common[int(s)].add(int(t))
    n_s = len(scan_names)
    linked = {0}
    frontier = [0]
    while frontier:
        a = frontier.pop()
        for b in range(n_s):
            if b not in linked and len(common[a] & common[b]) >= 3:
                linked.add(b)
                frontier.append(b)
    if len(linked) != n_s:
        missing = [scan_names[j] for j in range(n_s) if j not in linked]
        raise ValueError(
            f"{source}: scan(s) {', '.join(missing)} are disconnected from scan {scan_names[0]}: "
            "no chain of scans sharing at least 3 targets or planes links them"
        )


def digest(network: Network) -> bytes:
    """A digest of everything a network holds (its arrays' bytes, shapes and dtypes, and its
    names): equal digests, equal data. Computed on every calibrate, so cheaply: SHA-256 (the
    processor's SHA extensions: twice BLAKE2's rate here) of the arrays' memory without
    copies, dtypes by their codes (``str(dtype)`` costs 2 us each): 53 against 106 us for the
    Chow room (720 observations)."""
    items = [(f.name, getattr(network, f.name)) for f in dataclasses.fields(network)]
    # One header of names, shapes, dtypes and the other fields' values; then the arrays' bytes.
    head = "|".join(
        f"{name}{v.shape}{v.dtype.str}" if isinstance(v, np.ndarray) else f"{name}={v!r}"
        for name, v in items
    )
    h = hashlib.sha256(head.encode())
    for _, v in items:
        if isinstance(v, np.ndarray) and v.size:
            h.update(np.ascontiguousarray(v).reshape(-1).view(np.uint8))
    return h.digest()


#: Host results memoised per network (:func:`memoised`): each network's digest and its values.
_MEMO: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
_MEMO_LOCK = threading.Lock()
#: Values kept per network (models tried on one network, each with its plan; a plan holds a
#: device copy of the observations and weights: 3 MB per (m, 3) float64 array at 130k points).
MEMO_SIZE = 8
# A plan holds the AP terms as registered when it was built: a re-registered term empties it
# (a model made before the replacement then gets the new basis, as the compiled caches do).
on_reregistration(_MEMO.clear)


def memoised(network: Network, key, build):
    """``build()``, computed once per network's data and ``key`` (hashable; an unhashable key is
    not memoised). Approximate values and index plans are pure functions of the network and
    the model, and one network is adjusted many times (models tried, VCE, snooping, selection,
    cross-validation folds, benchmarks): they are the host's share of a calibration.

    Held weakly per network object, and checked against the digest of its arrays on every call
    (:func:`digest`): a network whose arrays were changed in place is computed afresh, never
    answered from its old values. At most :data:`MEMO_SIZE` keys per network (the oldest go)."""
    try:
        hash(key)
    except TypeError:
        return build()
    d = digest(network)
    with _MEMO_LOCK:
        held = _MEMO.get(network)
        if held is None or held[0] != d:
            held = (d, {})
            _MEMO[network] = held
        if key in held[1]:
            return held[1][key]
    value = build()
    with _MEMO_LOCK:
        values = held[1]
        values[key] = value
        while len(values) > MEMO_SIZE:
            values.pop(next(iter(values)))
    return value


def network_design_warnings(network, model) -> list[str]:
    """:func:`tlsjax._model._plausibility.design_warnings` of a network and a model."""
    from ._config import CalibrationModel  # _config is above this module

    scanners = (model or CalibrationModel()).scanner
    scanners = list(scanners.values()) if isinstance(scanners, Mapping) else [scanners]
    return design_warnings(
        n_scans=len(network.scans),
        n_targets=len(network.targets),
        n_planes=len(network.planes),
        n_aps=sum(len(s.aps) for s in scanners),
    )


def check_calibration_arguments(network, model, options, where: str = "calibrate") -> None:
    """Types of the arguments of an entry point, and the network's angles against the
    architecture of each instrument's scanner (SPEC section 1); one-line TypeError/ValueError."""
    from ._config import CalibrationModel, SolverOptions  # _config is above this module

    refuse_traced(network, where, entry=True)
    if not isinstance(network, Network):
        hint = (
            f"read the file with tlsjax.read_network({os.fspath(network)!r})"
            if isinstance(network, (str, os.PathLike))
            else "build one with tlsjax.make_network(...) or tlsjax.read_network(...)"
        )
        raise TypeError(
            f"{where}: network must be a tlsjax Network, got {type(network).__name__}; {hint}"
        )
    if model is not None and not isinstance(model, CalibrationModel):
        hint = "; wrap it: CalibrationModel(scanner)" if type(model).__name__ == "Scanner" else ""
        raise TypeError(
            f"{where}: model must be a tlsjax CalibrationModel or None, got {type(model).__name__}{hint}"
        )
    if options is not None and not isinstance(options, SolverOptions):
        raise TypeError(
            f"{where}: options must be a tlsjax SolverOptions or None, got {type(options).__name__}"
        )
    scanners = (model or CalibrationModel()).scanner
    for code, instrument in enumerate(network.instruments):
        scanner = scanners if not isinstance(scanners, Mapping) else scanners.get(instrument)
        if scanner is not None:  # else the plan names the instrument without a scanner
            _check_instrument_angles(network, code, scanner.architecture)


def _check_instrument_angles(network, code: int, architecture: str) -> None:
    """:func:`check_angles` on the target and plane rows of instrument ``code``."""
    for kind, obs, scan_index, index, names in (
        ("target", network.observations, network.scan_index, network.target_index, network.targets),
        (
            "plane",
            network.plane_observations,
            network.plane_scan_index,
            network.plane_index,
            network.planes,
        ),
    ):
        rows = np.flatnonzero(network.instrument_of_scan[scan_index] == code)

        def what(i, rows=rows, kind=kind, scan_index=scan_index, index=index, names=names):
            j = rows[i]
            return f"scan {network.scans[scan_index[j]]}, {kind} {names[index[j]]} ({architecture} scanner)"

        check_angles(
            obs[rows],
            architecture,
            lambda i, rows=rows, kind=kind: f"{network.source}, {kind} row {rows[i]}",
            what,
        )
