"""Field checks of a scanner from target centres: the DVW guideline and an ISO 17123-9-style
distance comparison.

**DVW-Merkblatt 7-2014** ("Verfahren zur standardisierten Überprüfung von terrestrischen
Laserscannern", DVW AK 3, Neitzel, Gordon and Wujanz 2014, sections 2.3-2.8): four targets,
T1 and T2 on the line through the stations S1 and S2, T3 at the far corner of a horizontal
right triangle, T4 high above T2; each scanned at least three times from each station. From
the mean centre of each target per station (after a check for outliers among the repeats) the
distances T1T2, T1T4 and T3T4 are formed from S1 and from S2 (eq. 1) and differenced,
``Delta_ij = TiTj(S1) - TiTj(S2)`` (eq. 2). With ``u_T`` the uncertainty of one target centre
(eq. 3: type A from the repeats, ``sqrt(u_A^2 + u_B^2)`` with a type B figure such as the
maker's), a distance has ``u_S = sqrt(2) u_T`` (eq. 4), a difference ``u_Delta = 2 u_T``
(eq. 5), and the limit is the expanded uncertainty ``U_Delta = k u_Delta = 4 u_T`` for k = 2
(eq. 7). ``|Delta_12| > U_Delta`` reveals a systematic error of the distance meter (twice a
constant offset, eq. 8-9), and then the angle checks are not judged (section 2.6: the offset
would overlay them); else ``|Delta_14| > U_Delta`` or ``|Delta_34| > U_Delta`` reveals a
systematic error of the horizontal direction or the vertical angle (eq. 11-13).

**ISO 17123-9-style comparison.** ISO 17123-9:2018 (field procedures for terrestrial laser
scanners) judges distances between targets scanned from two stations, or against reference
distances, and the repeatability of the centres; its text is not public, and what is done
here is stated in full rather than quoted from it: (a) every distance between two targets
seen from both stations, differenced between them, against the same ``U_Delta = 2 k u_T``;
(b) with reference distances (a survey of higher order), each station's distance minus the
reference, against ``k sqrt(2) u_T`` (the reference taken as exact); (c) with a stated
``u_T`` (type B), the repeatability test of the ISO 17123 parts: the experimental standard
deviation ``s`` of a centre coordinate from the repeats (``nu`` degrees of freedom) passes
when ``s <= u_T sqrt(chi2_0.95(nu) / nu)``.
"""

from __future__ import annotations

import dataclasses
import itertools

import numpy as np

from .._stats import chi2_quantile
from .._summary import Settings, to_json_value

#: The guideline's target names, in its order (section 2.3).
DVW_TARGETS = ("T1", "T2", "T3", "T4")
#: The guideline's distances: T1T2 (distance meter), T1T4 and T3T4 (directions, angles).
DVW_PAIRS = (("T1", "T2"), ("T1", "T4"), ("T3", "T4"))


@dataclasses.dataclass(frozen=True)
class FieldCheckOptions(Settings):
    """Settings of :func:`field_check` (lengths in metres).

    ``u_t``: type B uncertainty of a target centre (e.g. the maker's figure for its targets);
    None: type A only, from the repeats. ``k``: coverage factor of the expanded uncertainty
    (DVW: 2). ``dvw_targets``: the names of the guideline's T1..T4 among the targets (None:
    "T1".."T4" where present). ``reference``: optional mapping (name_a, name_b) -> reference
    distance [m] for the ISO-style comparison (b). ``stations``: the two station names, S1 then
    S2 (None: the first two in the data, sorted)."""

    u_t: float | None = None
    k: float = 2.0
    dvw_targets: tuple | None = None
    reference: dict | None = None
    stations: tuple | None = None

    def __post_init__(self):
        if self.u_t is not None and not (np.isfinite(self.u_t) and self.u_t > 0):
            raise ValueError(f"FieldCheckOptions.u_t must be positive, got {self.u_t}")
        if not (np.isfinite(self.k) and self.k > 0):
            raise ValueError(f"FieldCheckOptions.k must be positive, got {self.k}")
        if self.dvw_targets is not None and len(self.dvw_targets) != 4:
            raise ValueError("FieldCheckOptions.dvw_targets must name T1, T2, T3 and T4")
        if self.stations is not None and len(self.stations) != 2:
            raise ValueError("FieldCheckOptions.stations must name two stations (S1, S2)")

    def to_dict(self) -> dict:
        # JSON has no tuple keys: the reference distances as [name_a, name_b, distance_m] rows.
        out = super().to_dict()
        if self.reference is not None:
            out["reference"] = [[a, b, float(d)] for (a, b), d in self.reference.items()]
        return out

    @classmethod
    def _field_from_dict(cls, name: str, value):
        if name == "reference" and value is not None:
            return {(a, b): float(d) for a, b, d in value}
        return super()._field_from_dict(name, value)


@dataclasses.dataclass(frozen=True)
class FieldCheck:
    """The result of :func:`field_check`: ``stations`` (S1, S2); ``centres`` station -> target
    -> mean centre (3,) [m]; ``repeats`` station -> target -> number of centres; ``u_a``,
    ``u_b``, ``u_t`` [m] (type A from the repeats, type B given, combined; NaN where not
    available); ``rows``: one dict per quantity (``check``: "DVW", "ISO distance", "ISO
    reference" or "ISO repeatability"; ``quantity``, ``value_m``, ``limit_m``, ``passed``
    (None when not judged) and ``note``); ``passed``: every judged quantity passed;
    ``messages``: what could not be formed and why."""

    stations: tuple
    centres: dict
    repeats: dict
    u_a: float
    u_b: float
    u_t: float
    rows: tuple
    passed: bool
    messages: tuple

    def summary(self) -> str:
        s1, s2 = self.stations
        lines = [
            f"field check of stations {s1} and {s2}: u_T = {self.u_t * 1e3:.2f} mm "
            f"(type A {self.u_a * 1e3:.2f} mm from the repeats, type B "
            f"{'-' if not np.isfinite(self.u_b) else f'{self.u_b * 1e3:.2f} mm'})",
            f"{'check':18s} {'quantity':24s} {'value [mm]':>11s} {'limit [mm]':>11s}  result",
        ]
        for r in self.rows:
            verdict = {True: "pass", False: "FAIL", None: "not judged"}[r["passed"]]
            lines.append(
                f"{r['check']:18s} {r['quantity']:24s} {r['value_m'] * 1e3:11.2f} "
                f"{r['limit_m'] * 1e3:11.2f}  {verdict}{'  ' + r['note'] if r['note'] else ''}"
            )
        lines.append(f"overall: {'PASS' if self.passed else 'FAIL'}")
        return "\n".join(lines + list(self.messages))

    def to_dict(self) -> dict:
        return {
            "stations": list(self.stations),
            "centres_m": {
                s: {t: [float(v) for v in c] for t, c in d.items()} for s, d in self.centres.items()
            },
            "repeats": {s: dict(d) for s, d in self.repeats.items()},
            "u_a_m": to_json_value(self.u_a),
            "u_b_m": to_json_value(self.u_b),
            "u_t_m": to_json_value(self.u_t),
            "rows": [
                {k: (to_json_value(v) if isinstance(v, float) else v) for k, v in r.items()}
                for r in self.rows
            ],
            "passed": bool(self.passed),
            "messages": list(self.messages),
        }


def _type_a(repeats):
    """Pooled experimental standard deviation of one centre coordinate and its degrees of
    freedom: ``s^2 = sum (x - mean)^2 / sum (r - 1)`` over targets, stations and the three
    coordinates."""
    ss, dof = 0.0, 0
    for per_target in repeats.values():
        for X in per_target.values():
            if len(X) > 1:
                ss += float(np.sum((X - X.mean(axis=0)) ** 2))
                dof += 3 * (len(X) - 1)
    return (np.sqrt(ss / dof) if dof else np.nan), dof


def _row(check, quantity, value, limit, note=""):
    passed = None if not (np.isfinite(value) and np.isfinite(limit)) else bool(abs(value) <= limit)
    return {
        "check": check,
        "quantity": quantity,
        "value_m": float(value),
        "limit_m": float(limit),
        "passed": passed,
        "note": note,
    }


def field_check(centres, options: FieldCheckOptions | None = None) -> FieldCheck:
    """The DVW guideline's check and the ISO 17123-9-style comparison (module docstring) of
    target centres from two stations. ``centres``: mapping station -> target name -> (r, 3)
    scanner-space centres [m] of its r repeated scans (e.g. from
    :func:`~tlsjax.field_check_centres`)."""
    options = options or FieldCheckOptions()
    data = {
        str(s): {str(t): np.asarray(X, dtype=np.float64).reshape(-1, 3) for t, X in d.items()}
        for s, d in centres.items()
    }
    stations = tuple(options.stations or sorted(data)[:2])
    if len(stations) != 2 or any(s not in data for s in stations):
        raise ValueError(f"a field check needs two stations, got {sorted(data)}")
    s1, s2 = stations
    data = {s: data[s] for s in stations}
    mean = {s: {t: X.mean(axis=0) for t, X in d.items() if len(X)} for s, d in data.items()}
    u_a, dof = _type_a(data)
    u_b = np.nan if options.u_t is None else float(options.u_t)
    parts = [u for u in (u_a, u_b) if np.isfinite(u)]
    if not parts:
        raise ValueError(
            "no uncertainty of the target centres: scan each target at least twice from a "
            "station, or give u_t (e.g. the maker's figure; CLI --u-t-mm)"
        )
    u_t = float(np.sqrt(np.sum(np.square(parts))))
    U = options.k * 2.0 * u_t  # DVW eq. 5-7
    rows, messages = [], []
    dist = {s: lambda a, b, s=s: float(np.linalg.norm(mean[s][a] - mean[s][b])) for s in stations}
    both = sorted(set(mean[s1]) & set(mean[s2]))
    names = dict(zip(DVW_TARGETS, options.dvw_targets or DVW_TARGETS))
    dvw_fail_distance = False
    for a, b in DVW_PAIRS:
        ta, tb = names[a], names[b]
        q = f"Delta {a[1:]},{b[1:]} = {ta}{tb}(S1)-(S2)"
        if ta not in both or tb not in both:
            messages.append(
                f"DVW: {ta}{tb} is not seen from both stations, so Delta {a[1:]},{b[1:]} "
                "cannot be formed"
            )
            continue
        delta = dist[s1](ta, tb) - dist[s2](ta, tb)
        row = _row("DVW", q, delta, U, "distance meter" if (a, b) == DVW_PAIRS[0] else "angles")
        if (a, b) == DVW_PAIRS[0]:
            dvw_fail_distance = row["passed"] is False
        elif dvw_fail_distance:
            row["passed"] = None
            row["note"] = "not judged: Delta 1,2 failed (DVW section 2.6)"
        rows.append(row)
    for a, b in itertools.combinations(both, 2):
        delta = dist[s1](a, b) - dist[s2](a, b)
        rows.append(_row("ISO distance", f"{a}{b}(S1)-(S2)", delta, U))
    for (a, b), ref in (options.reference or {}).items():
        for s in stations:
            if a in mean[s] and b in mean[s]:
                d = dist[s](a, b) - float(ref)
                lim = options.k * np.sqrt(2.0) * u_t
                rows.append(_row("ISO reference", f"{a}{b}({s})-ref", d, lim))
    if np.isfinite(u_b) and dof:
        lim = u_b * np.sqrt(chi2_quantile(0.95, dof) / dof)
        rows.append(_row("ISO repeatability", f"s of a coordinate (nu={dof})", u_a, lim))
    judged = [r["passed"] for r in rows if r["passed"] is not None]
    return FieldCheck(
        stations=stations,
        centres=mean,
        repeats={s: {t: len(X) for t, X in d.items()} for s, d in data.items()},
        u_a=float(u_a),
        u_b=float(u_b),
        u_t=u_t,
        rows=tuple(rows),
        passed=bool(judged) and all(judged),
        messages=tuple(messages),
    )


def field_check_centres(targets, station_of) -> dict:
    """Mapping station -> target name -> (r, 3) centres of the accepted, named detections of
    :class:`~tlsjax.ExtractedTargets` (after :func:`~tlsjax.match_targets`, or named by the
    caller); ``station_of``: scan name -> station name (a dict, or a function)."""
    get = station_of if callable(station_of) else station_of.__getitem__
    out = {}
    for i in np.flatnonzero(targets.accepted & (targets.names != "")):
        s = str(get(targets.scans[targets.scan_index[i]]))
        out.setdefault(s, {}).setdefault(str(targets.names[i]), []).append(targets.centre[i])
    return {s: {t: np.array(v) for t, v in d.items()} for s, d in out.items()}
