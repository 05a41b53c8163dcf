"""Applying a calibration to point clouds (SPEC section 11, "Applying a calibration").

Each point's scanner-space observation ``l = (rho, theta, alpha)``, in the scanner's
architecture (a panoramic scanner's second face as ``(theta - pi, pi - alpha)``, SPEC section 1),
is replaced by

    l' = l - Delta(l; AP),

with ``Delta`` evaluated at the observed ``l`` exactly as in the adjustment (SPEC section 2,
Chow et al. 2013 eqs. 4-6), and converted back to Cartesian coordinates in the file's frame
(object-space files, e.g. registered LAS, go through the scan pose: ``x = R (X - S)``, then
``X' = R^T x' + S``). Optionally each point gets the standard deviation of its corrected position
propagated from the AP covariance, ``sigma = sqrt(trace(J C_AP J^T))`` with ``J = dX'/dAP`` by
autodiff: the calibration's share of the point's uncertainty.

Points a reader drops (non-finite, exactly at the origin, flagged invalid) are written back
unchanged, so a corrected file has the input's points, order and attributes. The correction runs
in chunks of one compiled size (:data:`CHUNK`), so memory does not grow with the scan; LAS/LAZ,
PTX and XYZ files are also read and written chunk by chunk (a 50-million-point scan never sits
in memory), PLY files are memory-mapped, and an E57 scan is read whole by pye57 (its writer
takes whole scans; coordinates are written in single precision, about 1e-6 of the range).
"""

from __future__ import annotations

import dataclasses
import functools
import os
import warnings

import jax
import jax.numpy as jnp
import numpy as np

from .._adjustment._network import refuse_traced
from .._jit import jit
from .._model._aps import ap_corrections, get_ap
from .._model._geometry import (
    cartesian_from_spherical,
    rotation_matrix,
    scanner_observations,
)
from .._model._plausibility import PlausibilityWarning, ap_findings
from .._model._scanner import ARCHITECTURES, Scanner
from .._units import display
from ._json import json_kind, read_result_json
from ._point_clouds import MAP_SCALE_RANGE

#: Points per compiled correction step.
CHUNK = 1 << 16


@dataclasses.dataclass(frozen=True)
class Calibration:
    """An AP set to apply: the ``scanner`` (architecture, unit lengths, AP names), the AP
    ``values`` [SI] in the order of ``scanner.aps`` and their ``covariance`` [SI^2] (or None).
    ``notes``: what was assumed when it was read (e.g. a non-estimable AP taken as zero)."""

    scanner: Scanner
    values: np.ndarray
    covariance: np.ndarray | None = None
    source: str = "<arrays>"
    notes: tuple = ()

    def __post_init__(self):
        v = np.asarray(self.values, dtype=np.float64).reshape(-1)
        if v.shape != (len(self.scanner.aps),) or not np.all(np.isfinite(v)):
            raise ValueError(
                f"{self.source}: {len(self.scanner.aps)} APs need as many finite values, got {v}"
            )
        object.__setattr__(self, "values", v)
        self._judge_plausibility()
        if self.covariance is not None:
            C = np.asarray(self.covariance, dtype=np.float64)
            if C.shape != (len(v), len(v)) or not np.all(np.isfinite(C)):
                raise ValueError(
                    f"{self.source}: the AP covariance must be finite {len(v)} x {len(v)}"
                )
            object.__setattr__(self, "covariance", 0.5 * (C + C.T))

    def _judge_plausibility(self) -> None:
        """The rules of :mod:`tlsjax._model._plausibility`, as ``calibrate`` applies them: an
        AP no working instrument has is refused (applying it would corrupt every point), one
        larger than instruments have is a warning (``notes``, :class:`PlausibilityWarning`)."""
        names = self.scanner.aps
        terms = [get_ap(n) for n in names]
        findings = ap_findings(
            names, self.values, [t.unit for t in terms], [t.description for t in terms]
        )
        if any(f.level == "impossible" for f in findings):
            raise ValueError(
                f"{self.source}: refusing to apply it: "
                + "; ".join(f.text for f in findings if f.level == "impossible")
                + " (a calibration whose estimates were implausible or withheld, or values in "
                "the wrong unit: the JSON holds SI units, metres and radians)"
            )
        for f in findings:
            note = f"{self.source}: {f.text}; applied as given"
            warnings.warn(note, PlausibilityWarning, stacklevel=4)
            object.__setattr__(self, "notes", tuple(self.notes) + (note,))

    def describe(self) -> str:
        """What is applied, in words: each AP's value in display units."""
        if not self.scanner.aps:
            return "no APs: the identity correction"
        parts = []
        for name, v in zip(self.scanner.aps, self.values):
            shown, unit = display(v, get_ap(name).unit)
            parts.append(f"{name} = {shown:.4g} {unit}")
        return ", ".join(parts)

    @classmethod
    def from_result(cls, result, scanner: Scanner) -> Calibration:
        """From a :class:`~tlsjax.CalibrationResult` and the scanner it was calibrated with;
        non-estimable APs (no value; the adjustment held them at zero) are applied as zero
        and named in ``notes``. A failed adjustment is refused: it has no estimates."""
        if not result.ok:
            raise ValueError(
                f"the calibration failed (result {result.result}: {result.message}); its numbers "
                "are not estimates and are not applied"
            )
        names = tuple(result.ap_names)
        vals = np.asarray(result.ap_values, dtype=np.float64)
        notes = tuple(
            f"AP {n} is not estimable in this calibration (its adjustment held it at zero): "
            "applied as zero"
            for n, v in zip(names, vals)
            if not np.isfinite(v)
        )
        cov = getattr(result, "ap_covariance", None)
        cov = None if cov is None else np.nan_to_num(np.asarray(cov, dtype=np.float64), nan=0.0)
        return cls(
            dataclasses.replace(scanner, aps=names),
            np.nan_to_num(vals, nan=0.0),
            cov,
            "<CalibrationResult>",
            notes,
        )

    @classmethod
    def from_json(cls, path, *, architecture=None, instrument=None) -> Calibration:
        """From a tlsjax result JSON (SPEC section 11). The architecture and unit lengths come
        from the JSON's ``scanner`` section (written by ``tlsjax calibrate``) unless given."""
        return _calibration_from_json(os.fspath(path), architecture, instrument)


def _scanner_from_doc(doc, source, architecture, names, instrument=None):
    """The Scanner of a result JSON: its ``scanner`` section (per instrument when it has
    ``instruments``), else the top-level ``architecture`` of a simulation's truth JSON."""
    settings = doc.get("scanner") if isinstance(doc.get("scanner"), dict) else {}
    per = settings.get("instruments")
    if instrument is not None and isinstance(per, dict) and isinstance(per.get(instrument), dict):
        settings = per[instrument]
    arch = architecture or settings.get("architecture") or doc.get("architecture")
    notes = []
    if arch is None:
        arch = "hybrid"
        notes.append(
            f"{source}: no scanner architecture stored; applying the APs as a hybrid scanner "
            "(give --architecture)"
        )
    if arch not in ARCHITECTURES:
        raise ValueError(f"{source}: scanner architecture {arch!r} is not one of {ARCHITECTURES}")
    kw = {}
    for k in ("unit_length", "unit_length_2"):
        if k in settings:
            v = settings[k]
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0:
                raise ValueError(f"{source}: scanner.{k} must be a positive number [m], got {v!r}")
            kw[k] = float(v)
    return Scanner(architecture=arch, aps=names, **kw), notes


def _calibration_from_json(source, architecture, instrument) -> Calibration:
    # A simulation's truth and a target check (which records the APs it applied) carry an
    # AP set too; the other kinds of tlsjax JSON are named and refused.
    doc = read_result_json(source, accept=("truth", "target check"))
    estimates = doc.get("estimates", "valid")
    if estimates != "valid":  # withheld (a failed run) or implausible: never applied
        raise ValueError(f"{source}: no calibration to apply: the estimates are {estimates}")
    aps = doc["aps"]
    blocks = sorted({n.split("[", 1)[1].rstrip("]") for n in aps if "[" in n})
    if blocks and instrument is None:
        raise ValueError(
            f"{source}: the calibration has AP blocks of several instruments "
            f"({', '.join(blocks)}): choose one with --instrument"
        )
    if instrument is not None and instrument not in blocks:
        raise ValueError(
            f"{source}: no instrument {instrument!r} (instruments: {blocks or 'none'})"
        )
    keys = [n for n in aps if (instrument is None or n.endswith(f"[{instrument}]"))]
    names = tuple(k.split("[", 1)[0] for k in keys)
    for n in names:
        try:
            get_ap(n)
        except ValueError as err:
            raise ValueError(f"{source}: {err}") from None
    scanner, notes = _scanner_from_doc(doc, source, architecture, names, instrument)
    if json_kind(doc) == "truth":
        notes.append(
            f"{source}: the true APs of a simulation (tlsjax simulate --truth), not a "
            "calibration: applied as they are, without sigmas"
        )
    values = []
    for k in keys:
        # A result JSON has {"value": ..., "sigma": ...} per AP; a simulation's truth JSON the
        # plain true value.
        entry = aps[k] if isinstance(aps[k], dict) else {"value": aps[k]}
        v = entry.get("value")
        if v is None:
            notes.append(
                f"{source}: AP {k} is not estimable in this calibration (no value; its "
                "adjustment held it at zero): applied as zero"
            )
            v = 0.0
        if not isinstance(v, (int, float)) or not np.isfinite(v):
            raise ValueError(f"{source}: AP {k} has no numeric value ({v!r})")
        values.append(float(v))
    if keys and all(isinstance(aps[k], dict) and aps[k].get("value") is None for k in keys):
        raise ValueError(f"{source}: no AP has a value (every estimate is null): nothing to apply")
    return Calibration(
        scanner, np.array(values), _covariance(doc, keys, source), source, tuple(notes)
    )


def _covariance(doc, keys, source):
    names = doc.get("ap_covariance_names")
    rows = doc.get("ap_covariance")
    if not names or rows is None:
        sig = [
            (doc["aps"][k] if isinstance(doc["aps"][k], dict) else {}).get("sigma") for k in keys
        ]
        if any(s is None for s in sig):
            return None
        return np.diag(np.square(np.asarray(sig, dtype=np.float64)))
    try:
        idx = [list(names).index(k) for k in keys]
        C = np.array([[np.nan if v is None else v for v in row] for row in rows], dtype=np.float64)
        C = C[np.ix_(idx, idx)]
    except (ValueError, IndexError, TypeError):
        raise ValueError(f"{source}: ap_covariance does not match ap_covariance_names") from None
    return np.nan_to_num(C, nan=0.0)  # a non-estimable AP: applied as zero, no variance


@functools.partial(jit, static_argnames=("scanner", "with_sigma"))
def _correct_chunk(x, coeffs, cov, scanner: Scanner, with_sigma: bool):
    """Corrected scanner-space points of one chunk and, if asked, their sigma [m]."""

    def corrected(c, xi):
        l = scanner_observations(xi, scanner.architecture)
        return cartesian_from_spherical(l - ap_corrections(c, scanner.aps, l, scanner))

    out = jax.vmap(corrected, in_axes=(None, 0))(coeffs, x)
    if not with_sigma:
        return out, jnp.zeros(x.shape[0])
    J = jax.vmap(jax.jacfwd(corrected), in_axes=(None, 0))(coeffs, x)  # (n, 3, k)
    var = jnp.einsum("nik,kl,nil->n", J, cov, J)
    return out, jnp.sqrt(jnp.maximum(var, 0.0))


def correct_points(
    points, calibration: Calibration, *, pose=None, precision: bool = False, on_chunk=None
):
    """Corrected points (n, 3) [m] in the frame of ``points`` (scanner space, or object space
    when ``pose`` (6,) is given) and, with ``precision``, the sigma (n,) [m] of each corrected
    position from the AP covariance (zeros otherwise). Points at the origin or non-finite are
    returned unchanged with sigma 0. ``on_chunk(n)`` is called after each chunk (progress)."""
    refuse_traced(points, "correct_points")
    if not isinstance(calibration, Calibration):
        raise TypeError(
            f"correct_points: calibration must be a tlsjax Calibration, got "
            f"{type(calibration).__name__}; read one with tlsjax.Calibration.from_json(path)"
        )
    try:
        X = np.asarray(points, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise ValueError(f"correct_points: points must be numbers [m] ({err})") from None
    if X.ndim != 2 or X.shape[1] != 3:
        raise ValueError(
            f"correct_points: points must have shape (n, 3) [x, y, z in m], got {X.shape}"
        )
    if pose is not None:
        pose = np.asarray(pose, dtype=np.float64).reshape(-1)
        if pose.shape != (6,) or not np.all(np.isfinite(pose)):
            raise ValueError(
                "correct_points: pose must be 6 finite numbers (X, Y, Z [m], omega, phi, kappa [rad])"
            )
    if precision and calibration.covariance is None:
        raise ValueError(f"{calibration.source}: no AP covariance or sigmas to propagate")
    valid = np.all(np.isfinite(X), axis=1) & ~np.all(X == 0.0, axis=1)
    x = X[valid]
    if pose is not None:
        R = rotation_matrix(*np.asarray(pose, dtype=np.float64)[3:], xp=np)
        x = (x - pose[:3]) @ R.T
    if len(x) and np.median(np.linalg.norm(x, axis=1)) > MAP_SCALE_RANGE:
        # The APs act on the scanner's own observations; map coordinates would give a
        # plausible-looking but wrong correction.
        raise ValueError(
            f"points have a median range of {np.median(np.linalg.norm(x, axis=1)):.4g} m: map "
            "coordinates, not a scan in its scanner's frame; give the scan's pose (--poses)"
        )
    names = calibration.scanner.aps
    coeffs = jnp.asarray(calibration.values)
    cov = jnp.asarray(
        calibration.covariance
        if calibration.covariance is not None
        else np.zeros((len(names),) * 2)
    )
    out_x = np.empty_like(x)
    sig = np.zeros(len(x))
    # One compiled size for all chunks: CHUNK, or the next power of two for a small cloud.
    size = min(CHUNK, max(256, 1 << int(np.ceil(np.log2(max(len(x), 1))))))
    for i in range(0, len(x), size):
        part = x[i : i + size]
        pad = size - len(part)
        block = np.concatenate([part, np.repeat(part[:1], pad, axis=0)]) if pad else part
        c, s = _correct_chunk(
            jnp.asarray(block), coeffs, cov, calibration.scanner.current(), precision
        )
        out_x[i : i + len(part)] = np.asarray(c)[: len(part)]
        sig[i : i + len(part)] = np.asarray(s)[: len(part)]
        if on_chunk is not None:
            on_chunk(len(part))
    if pose is not None:
        out_x = out_x @ R + pose[:3]
    out = X.copy()
    out[valid] = out_x
    sigma = np.zeros(len(X))
    sigma[valid] = sig
    return out, sigma
