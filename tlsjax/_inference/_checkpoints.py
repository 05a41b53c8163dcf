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
from collections.abc import Mapping

import numpy as np

from .._adjustment._network import Network
from .._adjustment._result import CalibrationResult
from .._model._aps import ap_corrections, resolve_aps
from .._model._geometry import (
    cartesian_from_spherical,
    is_face2,
    rigid_fit,
    spherical_from_cartesian,
)
from .._model._scanner import Scanner
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

    def table(self) -> str:
        head = f"{'':22s}" + "".join(f"{k:>11s}" for k in KEYS)
        lines = [head]
        for name, d in (
            ("without correction", self.without),
            ("with correction", self.with_correction),
        ):
            lines.append(f"{name:22s}" + "".join(f"{d[k]:11.3f}" for k in KEYS))
        return "\n".join(lines)


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


def _differences(l_used, X_chk, scanner):
    x = np.asarray(cartesian_from_spherical(l_used, xp=np))
    R, t = rigid_fit(x, X_chk, xp=np)
    dxyz = x @ R.T + t - X_chk
    x_true = (X_chk - t) @ R  # R^T (X - t) per row
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
) -> CheckpointReport:
    """Check-point accuracy of an AP set on independent scans (Lichti & Licht 2006, sec. 4).

    ``network``: the independent scans (only observations of check points are used);
    ``check_points``: target name -> surveyed (X, Y, Z) [m]; ``aps``: a
    :class:`CalibrationResult` or a mapping AP name -> value [SI]; ``scanner``: architecture and
    unit lengths (default: hybrid with the default unit lengths).
    """
    scanner = scanner or Scanner(aps=())
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
        a = _differences(l[rows], X, sc)
        b = _differences(l_corr[rows], X, sc)
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
