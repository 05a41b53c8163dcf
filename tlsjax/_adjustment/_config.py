"""Configuration of a self-calibration: the calibration model and the solver settings."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import jax
import numpy as np

from .._model._scanner import Scanner
from .._pytree import kept
from .._summary import Settings
from ._families import Options

DATUMS = ("auto", "inner", "fixed-scan", "control")


@dataclasses.dataclass(frozen=True)
class CalibrationModel:
    """Configuration of a self-calibration (SPEC sections 3, 6).

    ``scanner``: one :class:`Scanner` for every instrument, or a mapping instrument name ->
    Scanner (each instrument gets its own AP block). ``datum``: "inner" (inner constraints on
    the targets; free network), "fixed-scan" (the pose of ``fixed_scan`` is held; only its
    parameters the datum leaves free: all six, or X, Y, Z, kappa with levelling), "control"
    (control points with their sigmas), or "auto" (control if the network has control points,
    otherwise inner). ``correlation_threshold``: an AP whose largest absolute correlation
    exceeds it is flagged as weakly determined. ``fixed_aps``: AP labels held at zero (they keep
    their place in the parameter vector, so a model that differs only in which APs are fixed
    reuses the compiled adjustment: stepwise selection fits every candidate set this way).
    ``ap_priors``: AP label -> (value, sigma) in SI units (m, rad, or 1 for scale terms), the
    result of a prior calibration, e.g. ``{"B6": (40 * ARCSEC, 5 * ARCSEC)}``: each is a
    weighted constraint ``AP = value +- sigma``, a linear pseudo-observation with its residual,
    redundancy number and variance group (Chow et al. 2013, eq. 7; SPEC section 6). It belongs
    to the model, not the network: it is knowledge about the model's terms (like
    ``fixed_aps``), named by the model's labels, and one network is calibrated with and
    without it by changing the model alone.
    """

    scanner: Scanner | Mapping[str, Scanner] = dataclasses.field(default_factory=Scanner)
    datum: str = "auto"
    fixed_scan: str | None = None
    correlation_threshold: float = 0.99
    fixed_aps: tuple = ()
    ap_priors: Mapping[str, tuple] | tuple = ()

    def __post_init__(self):
        object.__setattr__(
            self,
            "fixed_aps",
            tuple(self.fixed_aps.split() if isinstance(self.fixed_aps, str) else self.fixed_aps),
        )
        object.__setattr__(self, "ap_priors", _ap_priors(self.ap_priors))
        if self.datum not in DATUMS:
            raise ValueError(f"datum {self.datum!r} is not one of {DATUMS}")
        if self.datum == "fixed-scan" and self.fixed_scan is None:
            raise ValueError("datum 'fixed-scan' needs fixed_scan=<scan name>")
        if self.fixed_scan is not None and self.datum != "fixed-scan":
            # Accepted and ignored it would look like a fixed-scan datum and be another one.
            raise ValueError(
                f"fixed_scan={self.fixed_scan!r} takes effect only with datum='fixed-scan' "
                f"(datum is {self.datum!r}); pass datum='fixed-scan' or leave fixed_scan out"
            )
        if not 0 < self.correlation_threshold <= 1:
            raise ValueError(
                f"correlation_threshold must be in (0, 1], got {self.correlation_threshold}"
            )

    def to_dict(self) -> dict:
        """The model as strict JSON (SI units) that :meth:`from_dict` reads back: the scanner
        (architecture, APs, unit lengths; per instrument for several), the datum, the fixed
        APs and the AP priors."""
        return {
            "scanner": scanner_settings(self.scanner),
            "datum": self.datum,
            "fixed_scan": self.fixed_scan,
            "correlation_threshold": self.correlation_threshold,
            "fixed_aps": list(self.fixed_aps),
            "ap_priors": [list(p) for p in self.ap_priors],
        }

    @classmethod
    def from_dict(cls, data: dict) -> CalibrationModel:
        """The model from a dict as :meth:`to_dict` writes it (an unknown field is a one-line
        ValueError naming it)."""
        known = {
            "scanner",
            "datum",
            "fixed_scan",
            "correlation_threshold",
            "fixed_aps",
            "ap_priors",
        }
        if not isinstance(data, Mapping) or set(data) - known:
            extra = sorted(set(data) - known) if isinstance(data, Mapping) else [repr(data)]
            raise ValueError(f"CalibrationModel: unknown field(s) {', '.join(extra)}")
        fields = dict(data)
        if "scanner" in fields:
            fields["scanner"] = _scanner_from_dict(fields["scanner"])
        if "fixed_aps" in fields:
            fields["fixed_aps"] = tuple(fields["fixed_aps"])
        if "ap_priors" in fields:
            fields["ap_priors"] = tuple(tuple(p) for p in fields["ap_priors"])
        return cls(**fields)


#: The fields of a :class:`Scanner` in a model's dict.
_SCANNER_FIELDS = ("architecture", "aps", "unit_length", "unit_length_2")


def scanner_settings(scanner) -> dict:
    """Architecture, unit lengths and AP names of one :class:`~tlsjax.Scanner`, or of each
    instrument (``{"instruments": {name: settings}}``, with the ``architecture`` they share) for
    a mapping: what applying the APs needs (``tlsjax correct``,
    :meth:`tlsjax.Calibration.from_json`) and what :meth:`CalibrationModel.from_dict` reads."""
    if isinstance(scanner, Mapping):
        per = {str(k): scanner_settings(v) for k, v in scanner.items()}
        archs = {d["architecture"] for d in per.values()}
        out = {"instruments": per}
        if len(archs) == 1:
            out["architecture"] = archs.pop()
        return out
    return {
        "architecture": scanner.architecture,
        "unit_length": scanner.unit_length,
        "unit_length_2": scanner.unit_length_2,
        "aps": list(scanner.aps),
    }


def _scanner_from_dict(data):
    if "instruments" in data:
        return {k: _scanner_from_dict(v) for k, v in data["instruments"].items()}
    extra = sorted(set(data) - set(_SCANNER_FIELDS))
    if extra:
        raise ValueError(f"CalibrationModel.scanner: unknown field(s) {', '.join(extra)}")
    return Scanner(**{k: tuple(v) if k == "aps" else v for k, v in data.items()})


def _ap_priors(priors) -> tuple:
    """``((label, value, sigma), ...)`` from a mapping label -> (value, sigma), checked."""
    items = priors.items() if isinstance(priors, Mapping) else priors
    out = []
    for item in items:
        try:
            label, (value, sigma) = item[0], item[1:] if len(item) == 3 else item[1]
            value, sigma = float(value), float(sigma)
        except (TypeError, ValueError):
            raise ValueError(
                f"ap_priors: {item!r} is not AP label -> (value, sigma) in SI units"
            ) from None
        if not (np.isfinite(value) and np.isfinite(sigma) and sigma > 0):
            raise ValueError(
                f"ap_priors: {label} = {value} +- {sigma}: the value must be finite and the sigma "
                "positive and finite (SI units: m, rad, or 1 for scale terms)"
            )
        if any(label == o[0] for o in out):
            raise ValueError(f"ap_priors: {label} is given twice")
        out.append((str(label), value, sigma))
    return tuple(out)


@dataclasses.dataclass(frozen=True)
class SolverOptions(Settings):
    """Numerical settings of the adjustment (every float is a traced array of the compiled
    adjustment: changing it never recompiles).

    ``max_iterations``: most Gauss-Newton / Levenberg-Marquardt steps. ``tolerance``:
    convergence when the largest Gauss-Newton update is below this fraction of the parameter's
    a posteriori standard deviation (invariant to scaling all sigmas). ``rank_tolerance``:
    smallest accepted Cholesky pivot ``1 - R^2`` of a parameter's column regressed on every
    other unknown (below it the parameter is not estimable). The Levenberg-Marquardt schedule:
    a rejected step multiplies the damping by ``damping_increase`` (starting at
    ``damping_initial``), an accepted one by ``damping_decrease``, back to pure Gauss-Newton
    below ``damping_min``; above ``damping_max`` the adjustment gives up. Damping is relative
    to the diagonal of the normal matrix. ``full_covariance``: also form the dense cofactor
    matrix of all unknowns (u^2 memory; the AP correlations with every unknown, the sigmas of
    every target and plane are computed blockwise without it).
    """

    max_iterations: int = 30
    tolerance: float = 1e-6
    rank_tolerance: float = 1e-6
    damping_initial: float = 1e-4
    damping_increase: float = 10.0
    damping_decrease: float = 0.1
    damping_min: float = 1e-7
    damping_max: float = 1e8
    full_covariance: bool = False

    def __post_init__(self):
        if int(self.max_iterations) < 1:
            raise ValueError(
                f"SolverOptions.max_iterations must be >= 1, got {self.max_iterations}"
            )
        for name in (
            "tolerance",
            "rank_tolerance",
            "damping_initial",
            "damping_min",
            "damping_max",
        ):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and v > 0):
                raise ValueError(f"SolverOptions.{name} must be a positive number, got {v!r}")
        if not self.damping_increase > 1:
            raise ValueError(
                f"SolverOptions.damping_increase must be > 1, got {self.damping_increase}"
            )
        if not 0 < self.damping_decrease < 1:
            raise ValueError(
                f"SolverOptions.damping_decrease must be in (0, 1), got {self.damping_decrease}"
            )

    def arrays(self) -> Options:
        """The settings as arrays (host arrays: a compiled call takes them without a device
        transfer per field; cached, the options being frozen)."""
        f = lambda v: np.asarray(v, dtype=np.float64)
        return kept(
            self,
            "_arrays",
            lambda: Options(
                np.asarray(int(self.max_iterations)),
                f(self.tolerance),
                f(self.rank_tolerance),
                f(self.damping_initial),
                f(self.damping_increase),
                f(self.damping_decrease),
                f(self.damping_min),
                f(self.damping_max),
            ),
        )

    def device_arrays(self) -> Options:
        """:meth:`arrays` on the device, made once: a transfer of the eight settings costs about
        0.4 ms, a tenth of a calibration of the Chow room."""
        return kept(self, "_device_arrays", lambda: jax.device_put(self.arrays()))
