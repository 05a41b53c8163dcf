"""Configuration of a self-calibration: the calibration model and the solver settings."""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping

import jax.numpy as jnp

from .._model._scanner import Scanner
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
    """

    scanner: Scanner | Mapping[str, Scanner] = dataclasses.field(default_factory=Scanner)
    datum: str = "auto"
    fixed_scan: str | None = None
    correlation_threshold: float = 0.99
    fixed_aps: tuple = ()

    def __post_init__(self):
        object.__setattr__(
            self,
            "fixed_aps",
            tuple(self.fixed_aps.split() if isinstance(self.fixed_aps, str) else self.fixed_aps),
        )
        if self.datum not in DATUMS:
            raise ValueError(f"datum {self.datum!r} is not one of {DATUMS}")
        if self.datum == "fixed-scan" and self.fixed_scan is None:
            raise ValueError("datum 'fixed-scan' needs fixed_scan=<scan name>")
        if not 0 < self.correlation_threshold <= 1:
            raise ValueError(
                f"correlation_threshold must be in (0, 1], got {self.correlation_threshold}"
            )


@dataclasses.dataclass(frozen=True)
class SolverOptions:
    """Numerical settings. ``tolerance``: convergence when the largest update is below this
    fraction of the parameter's standard deviation (cofactor ``sqrt(Q_ii)``);
    ``rank_tolerance``: smallest accepted Cholesky pivot ``1 - R^2`` of the unit-diagonal
    reduced normal matrix (below it a parameter is not estimable); ``full_covariance``: also form the inner-constraint cofactor matrix of all
    unknowns (needed for correlations with targets)."""

    max_iterations: int = 30
    tolerance: float = 1e-6
    rank_tolerance: float = 1e-6
    full_covariance: bool = True

    def arrays(self) -> Options:
        return Options(
            jnp.asarray(self.max_iterations),
            jnp.asarray(self.tolerance),
            jnp.asarray(self.rank_tolerance),
        )
