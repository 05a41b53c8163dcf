"""Accuracy assessment with independent check points (Lichti & Licht 2006, section 4; SPEC
section 10).

For every scan of an independent network: correct the observations with the estimated APs,
``l_c = l - Delta(l; AP)`` (the model is ``l + v = F + Delta(l)``), convert them to scanner-space
coordinates, fit the scan onto the surveyed check points by a rigid-body least-squares
transformation (Horn 1987; equal weights, which is the inner-constraint solution on the check
points), and compare: XYZ differences in object space, and (rho, theta, alpha) differences
between the corrected observations and the check points expressed in the fitted scanner
frame. The same is done without correction. RMS values are reported in mm and arc seconds
(the 2006 paper's tables 3 and 4).
"""

from __future__ import annotations

import dataclasses
import os
import types
from collections.abc import Mapping

import numpy as np

from .._adjustment._network import Network
from .._adjustment._result import CalibrationResult
from .._model._aps import ap_corrections, resolve_aps
from .._model._geometry import (
    cartesian_from_spherical,
    helmert_fit,
    is_face2,
    spherical_from_cartesian,
)
from .._model._scanner import Scanner
from .._summary import to_json_value
from .._units import ARCSEC

KEYS = ("range_mm", "hz_arcsec", "el_arcsec", "x_mm", "y_mm", "z_mm", "xyz_mm")


@dataclasses.dataclass(frozen=True, eq=False)
class CheckpointReport:
    """RMS differences at the check points without and with AP correction (mm, arc seconds).

    ``xyz_mm`` is the RMS of the 3D distance. ``per_scan`` maps scan -> {"without", "with",
    "n"}; ``differences_with``/``differences_without`` are (n, 6) arrays of (d rho [m],
    d theta [rad], d alpha [rad], dX, dY, dZ [m]) in network row order of the used rows
    ``rows``. Scans with fewer than ``min_points`` check points are skipped and listed.
    """

    without: dict
    with_correction: dict
    per_scan: dict
    n_points: int
    rows: np.ndarray
    differences_without: np.ndarray
    differences_with: np.ndarray
    skipped_scans: tuple

    def summary(self) -> str:
        """RMS differences without and with the correction, one line each."""
        head = f"{'':22s}" + "".join(f"{k:>11s}" for k in KEYS)
        lines = [head]
        for name, d in (
            ("without correction", self.without),
            ("with correction", self.with_correction),
        ):
            lines.append(f"{name:22s}" + "".join(f"{d[k]:11.3f}" for k in KEYS))
        return "\n".join(lines)

    def to_dict(self) -> dict:
        """Strict JSON: the RMS differences without and with the correction (mm, arc seconds),
        per scan, the number of check points and the scans skipped."""
        return to_json_value(
            {
                "without": self.without,
                "with": self.with_correction,
                "scans": self.per_scan,
                "n_points": self.n_points,
                "skipped_scans": list(self.skipped_scans),
            }
        )


#: ``transform`` names -> with scale (7-parameter Helmert) or not (rigid body).
TRANSFORMS = {"rigid": False, "similarity": True, "7-parameter": True, "helmert": True}


def _transform_scale(transform: str) -> bool:
    if transform not in TRANSFORMS:
        raise ValueError(f"transform {transform!r} is not one of {', '.join(TRANSFORMS)}")
    return TRANSFORMS[transform]


def _ap_setup(aps, scanner: Scanner | None):
    if isinstance(aps, CalibrationResult):
        if len(aps.network.instruments) != 1:
            raise ValueError(
                "aps: a calibration of one instrument is needed; pass a mapping name -> value instead"
            )
        values = {n: float(v) for n, v in zip(aps.ap_names, aps.ap_values) if np.isfinite(v)}
    elif isinstance(aps, Mapping):
        values = {str(k): float(v) for k, v in aps.items()}
    else:
        raise ValueError("aps must be a CalibrationResult or a mapping AP name -> value [SI units]")
    names = resolve_aps(tuple(values))
    return names, np.array([values[n] for n in names])


def _differences(l_used, X_chk, scanner, scale=False):
    x = np.asarray(cartesian_from_spherical(l_used, xp=np))
    s, R, t = helmert_fit(x, X_chk, scale=scale, xp=np)
    dxyz = s * (x @ R.T) + t - X_chk
    x_true = (X_chk - t) @ R / s  # R^T (X - t) / s per row
    face2 = is_face2(l_used[:, 2], xp=np) if scanner.architecture == "panoramic" else None
    l_true = np.asarray(spherical_from_cartesian(x_true, face2, xp=np))
    dl = l_used - l_true
    dl[:, 1:] = np.arctan2(np.sin(dl[:, 1:]), np.cos(dl[:, 1:]))
    return np.concatenate([dl, dxyz], axis=1)


def _rms(d):
    with np.errstate(invalid="ignore"):
        return {
            "range_mm": float(np.sqrt(np.mean(d[:, 0] ** 2)) * 1e3),
            "hz_arcsec": float(np.sqrt(np.mean(d[:, 1] ** 2)) / ARCSEC),
            "el_arcsec": float(np.sqrt(np.mean(d[:, 2] ** 2)) / ARCSEC),
            "x_mm": float(np.sqrt(np.mean(d[:, 3] ** 2)) * 1e3),
            "y_mm": float(np.sqrt(np.mean(d[:, 4] ** 2)) * 1e3),
            "z_mm": float(np.sqrt(np.mean(d[:, 5] ** 2)) * 1e3),
            "xyz_mm": float(np.sqrt(np.mean(np.sum(d[:, 3:] ** 2, axis=1))) * 1e3),
        }


def assess_checkpoints(
    network: Network,
    check_points: Mapping[str, object],
    aps,
    *,
    scanner: Scanner | None = None,
    min_points: int = 4,
    transform: str = "rigid",
) -> CheckpointReport:
    """Check-point accuracy of an AP set on independent scans (Lichti & Licht 2006, sec. 4).

    ``network``: the independent scans (only observations of check points are used);
    ``check_points``: target name -> surveyed (X, Y, Z) [m]; ``aps``: a
    :class:`CalibrationResult` or a mapping AP name -> value [SI]; ``scanner``: architecture and
    unit lengths (default: hybrid with the default unit lengths); ``transform``: "rigid" (6
    parameters) or "similarity" (7-parameter Helmert; its scale absorbs a range scale error).
    """
    scanner = scanner or Scanner(aps=())
    scale = _transform_scale(transform)
    if min_points < 3:
        raise ValueError(
            f"min_points must be >= 3 (a rigid-body fit needs 3 points), got {min_points}"
        )
    names, coeffs = _ap_setup(aps, scanner)
    sc = dataclasses.replace(scanner, aps=names)
    known = {t: i for i, t in enumerate(network.targets)}
    chk = {}
    for t, xyz in check_points.items():
        xyz = np.asarray(xyz, dtype=np.float64).reshape(-1)
        if xyz.shape != (3,) or not np.all(np.isfinite(xyz)):
            raise ValueError(f"check_points: {t} needs three finite coordinates [m], got {xyz}")
        if t in known:
            chk[known[t]] = xyz
    if not chk:
        raise ValueError("check_points: none of the given points is observed in the network")
    l = np.asarray(network.observations, dtype=np.float64)
    delta = np.asarray(ap_corrections(coeffs, names, l, sc)) if len(names) else np.zeros_like(l)
    l_corr = l - delta
    rows_all, d_without, d_with, per_scan, skipped = [], [], [], {}, []
    for j, s in enumerate(network.scans):
        rows = np.flatnonzero((network.scan_index == j) & np.isin(network.target_index, list(chk)))
        if len(rows) < min_points:
            skipped.append(s)
            continue
        X = np.stack([chk[int(t)] for t in network.target_index[rows]])
        a = _differences(l[rows], X, sc, scale)
        b = _differences(l_corr[rows], X, sc, scale)
        per_scan[s] = {"without": _rms(a), "with": _rms(b), "n": int(len(rows))}
        rows_all.append(rows)
        d_without.append(a)
        d_with.append(b)
    if not rows_all:
        raise ValueError(f"check_points: no scan observes at least {min_points} check points")
    A, B = np.concatenate(d_without), np.concatenate(d_with)
    return CheckpointReport(
        _rms(A), _rms(B), per_scan, int(A.shape[0]), np.concatenate(rows_all), A, B, tuple(skipped)
    )


# --- Before and after against a reference survey (issue 27 item 5) --------------------------

NETWORK_KEYS = ("x_mm", "y_mm", "z_mm", "xyz_mm")


@dataclasses.dataclass(frozen=True, eq=False)
class TargetCheck:
    """Targets placed from scans without and with the calibration, compared with a reference.

    ``network``: the targets of all scans adjusted together (APs held at zero on the raw, then
    on the corrected observations), fitted onto the reference on the common names by
    ``transform`` (least squares, equal weights: inner constraints on the check points); per
    case (``"without"``, ``"with"``) the RMS of the X, Y, Z and 3D differences [mm], the fitted
    scale [ppm] (similarity only), the adjustment's message and the differences per target
    [m]. ``per_scan``: each scan fitted on its own (the 2006 paper's tables 3 and 4, with
    range, horizontal direction and elevation angle), or None. ``notes``: what was left out
    and why. A case whose adjustment failed has ``rms`` None and its message.
    """

    transform: str
    names: tuple
    excluded: tuple
    network: dict
    per_scan: CheckpointReport | None
    notes: tuple = ()

    def improvement(self) -> dict:
        """Per RMS key: 100 (without - with) / without [%] (network placement)."""
        a, b = self.network["without"]["rms"], self.network["with"]["rms"]
        if a is None or b is None:
            return {}
        return {k: 100.0 * (a[k] - b[k]) / a[k] if a[k] > 0 else None for k in NETWORK_KEYS}

    def summary(self) -> str:
        """The RMS differences from the reference without and with the calibration, the
        improvement, per scan where computed, and the notes."""
        lines = [
            f"reference fit: {self.transform}, {len(self.names)} common targets"
            + (f" ({len(self.excluded)} excluded)" if self.excluded else "")
        ]
        head = f"{'':30s}" + "".join(f"{k:>10s}" for k in NETWORK_KEYS)
        lines += ["targets placed by all scans together, RMS of differences [mm]:", head]
        for case, label in (("without", "without calibration"), ("with", "with calibration")):
            d = self.network[case]
            if d["rms"] is None:
                lines.append(f"{label:30s}not computed: {d['message']}")
                continue
            row = f"{label:30s}" + "".join(f"{d['rms'][k]:10.3f}" for k in NETWORK_KEYS)
            if d.get("scale_ppm") is not None:
                row += f"   scale {d['scale_ppm']:+.1f} ppm"
            lines.append(row)
        imp = self.improvement()
        if imp:
            lines.append(
                f"{'improvement [%]':30s}"
                + "".join("         -" if v is None else f"{v:10.1f}" for v in imp.values())
            )
        if self.per_scan is not None:
            lines += ["", "each scan fitted on its own (Lichti & Licht 2006, table 4):"]
            lines.append(self.per_scan.summary())
        lines += [f"note: {n}" for n in self.notes]
        return "\n".join(lines)

    def worst(self, k: int = 5, case: str = "with") -> list:
        """The ``k`` targets with the largest 3D difference [m] in ``case``."""
        diffs = self.network[case].get("differences") or {}
        norm = {n: float(np.linalg.norm(v)) for n, v in diffs.items()}
        return sorted(norm.items(), key=lambda kv: -kv[1])[:k]

    def to_dict(self) -> dict:
        """JSON fields (SI inside the per-target differences, mm and arc seconds in RMS keys)."""
        out = {
            "transform": self.transform,
            "n_common": len(self.names),
            "common": list(self.names),
            "excluded": list(self.excluded),
            "network": self.network,
            "improvement_percent": self.improvement(),
            "notes": list(self.notes),
        }
        if self.per_scan is not None:
            out["per_scan"] = self.per_scan.to_dict()
        return to_json_value(out)


def _index_view(obs):
    """The arrays :func:`assess_checkpoints` reads, from a Network or an ObservationTable."""
    if hasattr(obs, "scan_index"):
        return obs
    scans = tuple(dict.fromkeys(obs.scans))
    targets = tuple(dict.fromkeys(obs.primitives))
    s_code = {s: i for i, s in enumerate(scans)}
    t_code = {t: i for i, t in enumerate(targets)}
    return types.SimpleNamespace(
        scans=scans,
        targets=targets,
        scan_index=np.array([s_code[s] for s in obs.scans]),
        target_index=np.array([t_code[t] for t in obs.primitives]),
        observations=np.asarray(obs.observations, dtype=np.float64),
    )


def _network_of(obs, architecture, levelling, notes):
    """A validated Network for placing the targets (targets seen in one scan dropped)."""
    from .._adjustment._network import Network, make_network

    if isinstance(obs, Network):
        return obs
    if obs.kind != "target":
        raise ValueError(f"{obs.source}: target observations are needed, not {obs.kind}s")
    try:
        net = make_network(
            obs.scans,
            obs.primitives,
            obs.observations,
            sigmas=obs.sigmas,
            incidence=None if obs.incidence is None else np.nan_to_num(obs.incidence, nan=0.0),
            instruments=obs.instruments,
            # The scans CSV (read_scans): tilt readings and headings, eq. (7).
            orientation=levelling,
            drop_single_targets=True,
            source=obs.source,
            rows=obs.rows,
            architecture=architecture,
        )
    except ValueError as err:
        notes.append(f"no network placement: {err}")
        return None
    if net.dropped:
        notes.append(
            f"{len(net.dropped)} target(s) seen in one scan only left out of the placement"
        )
    return net


def _place(net, calibration, solver):
    """Target coordinates of ``net`` adjusted with the APs held at zero, on the raw and on the
    corrected observations ``l - Delta(l)``: {"without": result, "with": result}."""
    from .._adjustment._calibrate import calibrate
    from .._adjustment._config import CalibrationModel

    names = tuple(calibration.scanner.aps) or ("A0",)
    values = (
        np.asarray(calibration.values, dtype=np.float64) if calibration.scanner.aps else np.zeros(1)
    )
    scanner = dataclasses.replace(calibration.scanner, aps=names)
    if len(net.instruments) > 1:
        raise ValueError(
            f"{net.source}: {len(net.instruments)} instruments; check one instrument's scans"
        )
    # Zero APs directly: the same compiled adjustment for both cases, no "no APs" model needed.
    model = CalibrationModel(scanner, fixed_aps=names)
    l = np.asarray(net.observations, dtype=np.float64)
    delta = np.asarray(ap_corrections(values, names, l, scanner))
    return {
        case: calibrate(net.with_observations(obs), model, solver)
        for case, obs in (("without", l), ("with", l - delta))
    }


def _fit_onto_reference(xyz, ref, scale):
    s, R, t = helmert_fit(xyz, ref, scale=scale, xp=np)
    d = s * (xyz @ R.T) + t - ref
    rms = {
        "x_mm": float(np.sqrt(np.mean(d[:, 0] ** 2)) * 1e3),
        "y_mm": float(np.sqrt(np.mean(d[:, 1] ** 2)) * 1e3),
        "z_mm": float(np.sqrt(np.mean(d[:, 2] ** 2)) * 1e3),
        "xyz_mm": float(np.sqrt(np.mean(np.sum(d**2, axis=1))) * 1e3),
    }
    return d, rms, (float((s - 1.0) * 1e6) if scale else None)


def _check_scale(placed, ref, source):
    """A reference in other units than the scans (millimetres read as metres) is named."""
    spread = lambda X: float(np.sqrt(np.mean(np.sum((X - X.mean(axis=0)) ** 2, axis=1))))
    a, b = spread(placed), spread(ref)
    if a > 0 and b > 0 and not 0.05 < b / a < 20:
        raise ValueError(
            f"{source}: the reference points spread {b / a:.4g} times as far as the targets "
            "placed from the scans: a unit mix-up (e.g. millimetres read as metres)? give the "
            "reference's --length-unit or put the unit in its header"
        )


def check_targets(
    observations,
    calibration,
    reference,
    *,
    transform: str = "rigid",
    exclude=(),
    levelling=None,
    min_points: int = 4,
    options=None,
) -> TargetCheck:
    """The accuracy assessment of SPEC section 10 and Lichti & Licht (2006, tables 3 and 4)
    without and with a calibration, on targets observed by scans and surveyed independently.

    ``observations``: the target observations (a :class:`~tlsjax.Network` or a table from
    :func:`~tlsjax.read_observations` / :func:`~tlsjax.read_target_list`), from the calibration
    scans or, better, independent ones; ``calibration``: a :class:`~tlsjax.Calibration` (AP
    values, architecture, unit lengths); ``reference``: target name -> (X, Y, Z) [m] in any
    frame, e.g. a total-station survey read by :func:`~tlsjax.read_reference` (a point list, or
    a result JSON with targets: another calibration's, for the cross-validation of held-out
    scans). ``transform``: "rigid" or "similarity" (= "7-parameter"). ``exclude``:
    target names left out of the fit. ``levelling``: scan -> levelling observations (as
    :func:`~tlsjax.make_network` takes them) for a table; a Network carries its own.

    Two comparisons: (1) the targets placed by adjusting all scans together with the APs held
    at zero, once on the raw and once on the corrected observations ``l - Delta(l)`` (SPEC
    section 11), each fitted onto the reference (RMS of X, Y, Z, 3D); (2) each scan fitted on
    its own (:func:`assess_checkpoints`, with range, direction and elevation differences).
    """
    scale = _transform_scale(transform)
    notes: list[str] = []
    if isinstance(reference, (str, os.PathLike)):
        raise TypeError(
            "reference: a mapping name -> (X, Y, Z) [m]; read a file with tj.read_reference"
        )
    ref = {str(k): np.asarray(v, dtype=np.float64).reshape(3) for k, v in dict(reference).items()}
    exclude = tuple(exclude)
    unknown = [n for n in exclude if n not in ref]
    if unknown:
        raise ValueError(f"exclude: {', '.join(unknown)} not in the reference")
    for n in exclude:
        ref.pop(n)
    net = _network_of(observations, calibration.scanner.architecture, levelling, notes)
    network = {c: {"rms": None, "message": "", "differences": {}} for c in ("without", "with")}
    names = ()
    if net is not None:
        common = [t for t in net.targets if t in ref]
        if len(common) < 3:
            raise ValueError(
                f"{net.source}: {len(common)} target(s) in common with the reference; a "
                "transformation needs at least 3 (4 for redundancy)"
            )
        names = tuple(common)
        idx = np.array([net.targets.index(t) for t in common])
        X_ref = np.stack([ref[t] for t in common])
        for case, res in _place(net, calibration, options).items():
            entry = network[case]
            entry["message"] = res.message
            if not res.ok:
                continue
            xyz = res.target_xyz[idx]
            _check_scale(xyz, X_ref, "reference")
            d, rms, ppm = _fit_onto_reference(xyz, X_ref, scale)
            entry.update(rms=rms, scale_ppm=ppm, sigma0=float(res.sigma0))
            entry["differences"] = {t: d[k].tolist() for k, t in enumerate(common)}
    view = _index_view(observations)
    try:
        per_scan = assess_checkpoints(
            view,
            ref,
            dict(zip(calibration.scanner.aps, np.asarray(calibration.values).tolist())),
            scanner=calibration.scanner,
            min_points=min_points,
            transform=transform,
        )
        if per_scan.skipped_scans:
            notes.append(
                f"scans with fewer than {min_points} reference targets left out of the per-scan "
                f"fit: {', '.join(per_scan.skipped_scans)}"
            )
    except ValueError as err:
        per_scan = None
        notes.append(f"no per-scan fit: {err}")
    if not names and per_scan is not None:
        names = tuple(sorted({view.targets[t] for t in view.target_index[per_scan.rows]}))
    return TargetCheck(transform, names, exclude, network, per_scan, tuple(notes))
