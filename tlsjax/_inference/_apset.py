"""One AP set of one instrument: names, values, full covariance, scanner settings, data noise.

The input of the AP-set compatibility test (SPEC section 9). An AP set is what a calibration
says about an instrument: the values of its additional parameters [SI], their full a posteriori
covariance [SI^2] (never the diagonal alone: the APs of a calibration are correlated, up to
|rho| = 1.000 in a levelled 23-AP set), the scanner settings that fix the basis functions
(architecture, which selects the reduced collimation ``sec(alpha) - 1`` of hybrid scanners or
the full ``sec(alpha)`` of panoramic ones, and the unit lengths of the cyclic terms) and, when
known, the observation noise of the data it came from.

Files: :meth:`APSet.to_json` writes strict JSON (``format: "tlsjax AP set"``);
:meth:`APSet.from_json` reads that or the result JSON of ``tlsjax calibrate --json`` (SPEC
section 11, with its ``ap_covariance``, ``ap_covariance_names`` and ``scanner`` section).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os

import jax.numpy as jnp
import numpy as np

from .._model._aps import get_ap, on_reregistration, resolve_aps
from .._model._scanner import ARCHITECTURES, Scanner
from .._units import display

FORMAT = "tlsjax AP set"
FORMAT_VERSION = 1

#: Observations at which two scanner settings' basis functions are compared (ranges
#: 0.5..60 m, all directions, elevations of both faces away from the zenith).
_PROBE = (
    np.array([0.5, 1.7, 4.0, 9.3, 21.0, 60.0, 2.9, 13.0]),
    np.array([0.0, 0.9, 2.1, 3.3, 4.6, 6.1, 1.4, 2.8]),
    np.array([-1.2, -0.6, -0.1, 0.3, 0.8, 1.3, 2.0, 3.6]),
)

#: Readable forms of the bases that depend on the architecture (SPEC section 3).
_VARIANT_TEXT = {
    ("B6", "hybrid"): "sec(alpha) - 1 (reduced collimation, hybrid)",
    ("B6", "panoramic"): "sec(alpha) (full collimation, panoramic)",
    ("x6", "hybrid"): "2 (sec(alpha) - 1) (reduced, hybrid)",
    ("x6", "panoramic"): "2 sec(alpha) (full, panoramic)",
}


def basis_values(name: str, scanner: Scanner) -> np.ndarray:
    """The basis of AP ``name`` under ``scanner``'s settings at fixed probe observations: two
    settings give one basis exactly when these agree (architecture variants, unit lengths and
    user-registered terms alike)."""
    rho, theta, alpha = (jnp.asarray(a) for a in _PROBE)
    return np.asarray(get_ap(name).basis(rho, theta, alpha, scanner), dtype=np.float64)


@functools.lru_cache(maxsize=1024)
def same_basis(name: str, s1: Scanner, s2: Scanner) -> bool:
    """Whether AP ``name`` has one basis under both settings (the scanners' registration
    tokens are part of the cache key: a replaced term is compared anew)."""
    b1, b2 = basis_values(name, s1), basis_values(name, s2)
    return bool(np.allclose(b1, b2, rtol=1e-12, atol=1e-15))


on_reregistration(same_basis.cache_clear)


def basis_text(name: str, scanner: Scanner) -> str:
    """A readable name of the basis variant of ``name`` under ``scanner``."""
    if (name, scanner.architecture) in _VARIANT_TEXT:
        return _VARIANT_TEXT[(name, scanner.architecture)]
    term = get_ap(name)
    other = "panoramic" if scanner.architecture == "hybrid" else "hybrid"
    alt = dataclasses.replace(scanner, architecture=other)
    if not same_basis(name, scanner, alt):
        return f"{scanner.architecture} form of {name} ({term.description})"
    return term.description or name


def _settings(scanner: Scanner, names: tuple) -> Scanner:
    return Scanner(
        architecture=scanner.architecture,
        aps=names,
        unit_length=scanner.unit_length,
        unit_length_2=scanner.unit_length_2,
    )


@dataclasses.dataclass(frozen=True, eq=False)
class APSet:
    """One AP set: ``names``, ``values`` [SI], full ``covariance`` [SI^2] (a posteriori).

    ``scanner``: the settings that fix the basis functions (architecture, unit lengths; its
    ``aps`` are set to ``names``); default a hybrid scanner with the default unit lengths.
    ``noise``: (sigma_range [m] at normal incidence, sigma_hz [rad], sigma_el [rad]) of the
    data the set came from, or None (the compatibility test then uses its defaults).
    ``notes``: what was assumed when the set was read (e.g. no covariance in a file).
    """

    names: tuple
    values: np.ndarray
    covariance: np.ndarray
    source: str = "<arrays>"
    scanner: Scanner | None = None
    noise: tuple | None = None
    notes: tuple = ()

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
                f"{self.source}: AP values and covariance must be finite "
                "(a non-estimable AP cannot be compared; refit without it)"
            )
        C = 0.5 * (C + C.T)
        if len(names) and np.linalg.eigvalsh(C).min() < -1e-9 * max(np.trace(C), 1e-300):
            raise ValueError(f"{self.source}: AP covariance is not positive semi-definite")
        scanner = self.scanner if self.scanner is not None else Scanner(aps=())
        if not isinstance(scanner, Scanner):
            raise ValueError(f"{self.source}: scanner must be a tlsjax.Scanner")
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "values", v)
        object.__setattr__(self, "covariance", C)
        object.__setattr__(self, "scanner", _settings(scanner, names))
        object.__setattr__(self, "noise", _check_noise(self.noise, self.source))
        object.__setattr__(self, "notes", tuple(self.notes))

    @property
    def sigmas(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))

    @property
    def units(self) -> tuple:
        return tuple(get_ap(n).unit for n in self.names)

    @classmethod
    def from_values(
        cls, names, values, covariance=None, sigmas=None, source="<arrays>", **kw
    ) -> APSet:
        """From values and either a covariance matrix or sigmas (then uncorrelated, which
        a published table forces: it prints no correlations)."""
        if covariance is None:
            if sigmas is None:
                raise ValueError(f"{source}: give the AP covariance or the AP sigmas")
            covariance = np.diag(np.asarray(sigmas, dtype=np.float64) ** 2)
        return cls(tuple(resolve_aps(names)), values, covariance, source, **kw)

    @classmethod
    def from_result(cls, result, scanner: Scanner | None = None, instrument=None) -> APSet:
        """From a converged :class:`tlsjax.CalibrationResult`: its values and its full AP
        covariance ``result.ap_covariance`` (a posteriori), the noise of its data (median a
        priori sigma per observation group times sigma0). ``scanner``: the settings it was
        calibrated with (architecture, unit lengths; default hybrid). ``instrument``: the AP
        block of one instrument of a network with several."""
        if not bool(result.converged) or not result.ok:
            raise ValueError(
                f"the calibration did not succeed (result {int(result.result)}: "
                f"{result.message}); its APs cannot be compared"
            )
        if result.not_estimable:
            names = ", ".join(n for n, *_ in result.not_estimable)
            raise ValueError(f"result has non-estimable APs ({names}); refit without them")
        if result.ap_covariance is None:
            raise ValueError("result has no AP covariance (ap_covariance is None)")
        idx, names = _instrument_block(tuple(result.ap_names), instrument, "<CalibrationResult>")
        C = np.asarray(result.ap_covariance, dtype=np.float64)[np.ix_(idx, idx)]
        return cls(
            names,
            np.asarray(result.ap_values, dtype=np.float64)[idx],
            C,
            "<CalibrationResult>",
            scanner=scanner,
            noise=_result_noise(result),
        )

    @classmethod
    def from_json(cls, path, *, instrument=None, architecture=None) -> APSet:
        """From an AP-set JSON (:meth:`to_json`) or a tlsjax result JSON (``tlsjax calibrate
        --json``: ``aps`` with values in SI, ``ap_covariance`` with ``ap_covariance_names``
        and the ``scanner`` section). A file with sigmas but no covariance gives an
        uncorrelated set, said in ``notes``. ``architecture`` overrides the file's."""
        source = os.fspath(path)
        try:
            with open(source, encoding="utf-8") as fh:
                doc = json.load(fh)
        except FileNotFoundError:
            raise ValueError(f"{source}: no such file") from None
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
            raise ValueError(f"{source}: not a readable JSON file ({err})") from None
        if not isinstance(doc, dict):
            raise ValueError(f"{source}: not an AP set or tlsjax result JSON (not an object)")
        try:
            if doc.get("format") == FORMAT:
                return _from_apset_doc(cls, doc, source, architecture)
            if isinstance(doc.get("aps"), dict):
                return _from_result_doc(cls, doc, source, instrument, architecture)
        except ValueError as err:
            msg = str(err)
            raise ValueError(msg if msg.startswith(source) else f"{source}: {msg}") from None
        raise ValueError(
            f"{source}: not an AP set JSON (format {FORMAT!r}) or a tlsjax result JSON "
            "(no 'aps' object)"
        )

    def to_dict(self) -> dict:
        """The AP-set JSON document (SI units; :func:`tlsjax.write_json` writes it, and
        :meth:`from_json` reads it back)."""
        sc = self.scanner
        noise = None
        if self.noise is not None:
            noise = dict(zip(("sigma_range_m", "sigma_hz_rad", "sigma_el_rad"), self.noise))
        return {
            "format": FORMAT,
            "version": FORMAT_VERSION,
            "units": "SI: metres, radians; dimensionless scale terms as plain numbers",
            "names": list(self.names),
            "ap_units": list(self.units),
            "values": self.values.tolist(),
            "covariance": self.covariance.tolist(),
            "scanner": {
                "architecture": sc.architecture,
                "unit_length": sc.unit_length,
                "unit_length_2": sc.unit_length_2,
                "aps": list(self.names),
                "basis": {n: basis_text(n, sc) for n in self.names},
            },
            "noise": noise,
            "source": self.source,
            "notes": list(self.notes),
        }

    def summary(self) -> str:
        """The set as text: one line per AP with its value and sigma (mm, arc seconds or ppm),
        the scanner and where the set came from."""
        lines = [
            f"AP set of a {self.scanner.architecture} scanner ({len(self.names)} APs)"
            + (f" from {self.source}" if self.source else "")
        ]
        for n, v, s, u in zip(self.names, self.values, self.sigmas, self.units):
            (dv, unit), (ds, _) = display(v, u), display(s, u)
            lines.append(f"  {n:8s} {dv:12.4f} +- {ds:.4f} {unit}")
        return "\n".join(lines + [f"note: {n}" for n in self.notes])

    def on(self, names) -> tuple[np.ndarray, np.ndarray]:
        """Values and covariance on ``names`` (a superset): absent terms are zero, zero variance."""
        idx = np.array([list(names).index(n) for n in self.names], dtype=int)
        v = np.zeros(len(names))
        C = np.zeros((len(names), len(names)))
        v[idx] = self.values
        C[np.ix_(idx, idx)] = self.covariance
        return v, C

    def with_values(self, values) -> APSet:
        """The same set (covariance, scanner, noise) with other values."""
        return dataclasses.replace(self, values=np.asarray(values, dtype=np.float64))


def _check_noise(noise, source):
    if noise is None:
        return None
    n = np.asarray(noise, dtype=np.float64).reshape(-1)
    if n.shape != (3,) or not np.all(np.isfinite(n)) or np.any(n < 0):
        raise ValueError(
            f"{source}: noise must be three non-negative numbers (sigma_range [m], "
            f"sigma_hz [rad], sigma_el [rad]), got {noise!r}"
        )
    return tuple(float(x) for x in n)


def _instrument_block(labels: tuple, instrument, source):
    """Indices and plain names of the AP block of ``instrument`` ("A0[inst]" labels)."""
    blocks = sorted({n.split("[", 1)[1].rstrip("]") for n in labels if "[" in n})
    if blocks and instrument is None:
        raise ValueError(
            f"{source}: the calibration has AP blocks of several instruments "
            f"({', '.join(blocks)}): choose one (instrument=...)"
        )
    if instrument is not None and instrument not in blocks:
        raise ValueError(
            f"{source}: no instrument {instrument!r} (instruments: {blocks or 'none'})"
        )
    idx = [i for i, n in enumerate(labels) if instrument is None or n.endswith(f"[{instrument}]")]
    return idx, tuple(labels[i].split("[", 1)[0] for i in idx)


def _result_noise(result):
    """The data's noise (None if unknown): a priori sigmas times sigma0, the smallest range
    sigma (the range sigma at normal incidence: the network's range sigmas carry the
    incidence, the simulation applies it again) and the median angle sigmas."""
    net = result.network
    if net is None or not np.isfinite(result.sigma0):
        return None
    parts = [np.asarray(net.sigmas), np.asarray(net.plane_sigmas)]
    sig = np.concatenate([p.reshape(-1, 3) for p in parts if p.size])
    if not sig.size:
        return None
    s0 = float(result.sigma0)
    return (
        float(sig[:, 0].min()) * s0,
        float(np.median(sig[:, 1])) * s0,
        float(np.median(sig[:, 2])) * s0,
    )


def _scanner_of(doc, source, names, architecture):
    settings = doc.get("scanner") if isinstance(doc.get("scanner"), dict) else None
    notes = []
    if settings is None:
        settings = {}
        if architecture is None:
            notes.append(f"{source}: no scanner settings stored; taken as a hybrid scanner")
    arch = architecture or settings.get("architecture") or "hybrid"
    if arch not in ARCHITECTURES:
        raise ValueError(f"scanner architecture {arch!r} is not one of {ARCHITECTURES}")
    kw = {}
    for key in ("unit_length", "unit_length_2"):
        if settings.get(key) is not None:
            kw[key] = _number(settings[key], f"scanner.{key}")
    scanner = Scanner(architecture=arch, aps=names, **kw)
    stated = settings.get("basis") if isinstance(settings.get("basis"), dict) else {}
    for name, text in stated.items():
        if name in names and architecture is None and text != basis_text(name, scanner):
            raise ValueError(
                f"scanner.basis.{name} is {text!r}, but this tlsjax evaluates "
                f"{name} as {basis_text(name, scanner)!r} for these settings"
            )
    return scanner, notes


def _number(x, what) -> float:
    if isinstance(x, bool) or not isinstance(x, (int, float)) or not np.isfinite(x):
        raise ValueError(f"{what} must be a finite number, got {x!r}")
    return float(x)


def _names(raw, what):
    if not isinstance(raw, list) or not all(isinstance(n, str) for n in raw):
        raise ValueError(f"'{what}' must be a list of AP names")
    for n in raw:
        get_ap(n)  # unknown names: one line listing the known terms
    return tuple(raw)


def _matrix(rows, n, what):
    try:
        M = np.array(rows, dtype=np.float64)
    except (TypeError, ValueError):
        raise ValueError(
            f"'{what}' must be a list of rows of numbers (null: not estimable)"
        ) from None
    if M.shape != (n, n):
        raise ValueError(f"'{what}' must be {n} x {n}, got shape {M.shape}")
    if not np.all(np.isfinite(M)):
        raise ValueError(f"'{what}' has undefined entries (a non-estimable AP); refit without it")
    return M


def _from_apset_doc(cls, doc, source, architecture):
    names = _names(doc.get("names"), "names")
    vals = doc.get("values")
    if not isinstance(vals, list) or len(vals) != len(names):
        raise ValueError(f"'values' must be a list of {len(names)} numbers")
    values = np.array([_number(v, f"values[{k}]") for k, v in enumerate(vals)])
    C = _matrix(doc.get("covariance"), len(names), "covariance")
    scanner, notes = _scanner_of(doc, source, names, architecture)
    noise = doc.get("noise")
    if isinstance(noise, dict):
        keys = ("sigma_range_m", "sigma_hz_rad", "sigma_el_rad")
        noise = tuple(_number(noise.get(k), f"noise.{k}") for k in keys)
    elif noise is not None:
        raise ValueError("'noise' must be an object or null")
    old = doc.get("notes") if isinstance(doc.get("notes"), list) else []
    return cls(names, values, C, source, scanner, noise, tuple(map(str, old)) + tuple(notes))


def _from_result_doc(cls, doc, source, instrument, architecture):
    estimates = doc.get("estimates", "valid")
    if doc.get("converged") is False or estimates != "valid":
        why = estimates if estimates != "valid" else doc.get("message")  # "withheld: ..." first
        raise ValueError(f"the calibration did not succeed ({why}); its APs cannot be compared")
    aps = doc["aps"]
    idx, names = _instrument_block(tuple(aps), instrument, source)
    keys = [tuple(aps)[i] for i in idx]
    for n in names:
        get_ap(n)
    values, sigmas = [], []
    for k in keys:
        rec = aps[k] if isinstance(aps[k], dict) else {}
        if rec.get("value") is None:
            raise ValueError(
                f"aps.{k} is not estimable in this result (no value); refit without it"
            )
        values.append(_number(rec.get("value"), f"aps.{k}.value"))
        sigmas.append(rec.get("sigma"))
    notes = []
    if doc.get("ap_covariance") is not None:
        cn = doc.get("ap_covariance_names")
        if not isinstance(cn, list) or any(k not in cn for k in keys):
            raise ValueError("'ap_covariance_names' must list every AP of 'aps'")
        M = _matrix(doc["ap_covariance"], len(cn), "ap_covariance")
        j = [cn.index(k) for k in keys]
        C = M[np.ix_(j, j)]
    else:
        s = np.array([_number(x, f"aps.{k}.sigma") for k, x in zip(keys, sigmas)])
        C = np.diag(s**2)
        notes.append(f"{source}: no 'ap_covariance' in the file: the APs are taken as uncorrelated")
    scanner, more = _scanner_of(doc, source, names, architecture)
    return cls(names, np.array(values), C, source, scanner, None, tuple(notes + more))
