"""The scanner's architecture from the data (issue 41 item 5; SPEC section 1).

Vendor target lists give Cartesian centres in the scanner frame and do not say in which
representation the instrument measured them: one face over the full turn (hybrid: theta in
[0, 2 pi), alpha in [-pi/2, pi/2]) or two faces (panoramic: theta in [0, pi), the back half
observed in the second face as ``(theta' - pi, pi - alpha')``). The conversion between the two
is exact (:func:`tlsjax._model._geometry.scanner_observations`), but the models are not: the
axis errors (collimation, trunnion axis, vertical index) change sign between the faces of a
panoramic scanner and not over the back half of a hybrid one, and the collimation term is
``sec(alpha)`` in the one and ``sec(alpha) - 1`` in the other. Calibrated in the wrong
representation, the same data give wrong APs (issue 41: B6 17" where the truth is 206").

So both are fitted, each by the pipeline of :func:`tlsjax.self_calibrate` with the robust start
and screening (vendor lists hold gross errors), the a priori weights (no VCE, no snooping, no
selection) and the cross-validation step, and compared by what each explains: the a priori
sigma0 (``sqrt(v^T P v / r)`` with the given sigmas, on the observations it keeps) and the
cross-validated misfit of held-out scans (:mod:`._crossval`), the judge where there are folds.
One is *clearly* better when its cross-validated misfit is lower by more than
:attr:`ArchitectureCheckOptions.margin` standard errors of the paired difference over the
folds (without folds: the other's sigma0 more than ``sigma0_ratio`` times its own); where
the architecture the network was read as is clearly worse, the comparison says so in a warning
naming the other. A fit that failed (did not converge, a rank defect) is reported as failed
with its reason, and nothing is concluded from it: no architecture is called better, and a
warning says that the architecture was not checked.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from .._adjustment._config import CalibrationModel
from .._adjustment._network import Network
from .._model._geometry import cartesian_from_spherical, scanner_observations
from .._model._scanner import ARCHITECTURES, Scanner
from .._summary import to_json_value
from ._crossval import CrossValidation, paired_difference
from ._options import ArchitectureCheckOptions, CalibrationOptions
from ._run import run_tests


@dataclasses.dataclass(frozen=True, eq=False)
class ArchitectureFit:
    """One architecture's calibration: ``ok``, ``message``, the a priori ``sigma0`` on the
    screened observations, ``dof``, the observations screening removed (``n_removed``), the
    APs (name -> value, SI; None where not estimable) and the ``cross_validation``."""

    architecture: str
    ok: bool
    message: str
    sigma0: float
    dof: float
    n_removed: int
    aps: dict
    cross_validation: CrossValidation | None

    @property
    def cv_mm(self) -> float:
        cv = self.cross_validation
        return cv.cv_mm if cv is not None and cv.ok else float("nan")

    def summary(self) -> str:
        """One line: the architecture, its sigma0, cross-validated misfit and removals."""
        if not self.ok:
            return f"{self.architecture}: failed: {self.message}"
        cv = f"{self.cv_mm:.3f} mm" if np.isfinite(self.cv_mm) else "not cross-validated"
        return f"{self.architecture}: sigma0 {self.sigma0:.3f}, CV {cv}, {self.n_removed} removed"

    def to_dict(self) -> dict:
        cv = self.cross_validation
        return to_json_value(
            {
                "architecture": self.architecture,
                "ok": self.ok,
                "message": self.message,
                "sigma0": self.sigma0,
                "dof": self.dof,
                "n_removed": self.n_removed,
                "aps": self.aps,
                "cv_mm": self.cv_mm,
                "cross_validation": None if cv is None else cv.to_dict(),
            }
        )


@dataclasses.dataclass(frozen=True, eq=False)
class ArchitectureComparison:
    """Hybrid and panoramic fitted to one network (module docstring): ``fits`` per
    architecture, ``given`` the one the network was read as (None: unknown), ``best`` the one
    that explains the data better, ``clearly`` whether by more than the folds' scatter (or the
    sigma0 ratio), ``reason`` how it was decided and ``warning`` (empty unless ``given`` is
    clearly worse or a fit failed). Where a fit failed, ``best`` is None: no comparison is
    drawn from a failed fit (:meth:`of`)."""

    fits: dict
    given: str | None
    best: str | None
    clearly: bool
    reason: str
    warning: str = ""

    @classmethod
    def of(
        cls, fits: dict, given: str, margins: ArchitectureCheckOptions | None = None
    ) -> ArchitectureComparison:
        """The verdict on ``fits`` (architecture -> :class:`ArchitectureFit`) for data read as
        ``given``. A fit that failed is reported as failed, with its reason, and no
        comparison is drawn from it: ``best`` None, not ``clearly``, and a warning that the
        architecture was not checked (a failed fit is no evidence against its architecture:
        it may fail on the data's gross errors or the solver's settings)."""
        failed = [a for a, f in fits.items() if not f.ok]
        if failed:
            why = "; ".join(f"as {a} the calibration failed: {fits[a].message}" for a in failed)
            reason = f"no comparison drawn ({why})"
            warning = (
                f"architecture check: {reason}; whether the data, read as {given}, are in the "
                "instrument's representation is not checked"
            )
            return cls(fits, given, None, False, reason, warning)
        best, clearly, reason = _decide(fits, margins or ArchitectureCheckOptions())
        warning = ""
        if clearly and best != given:
            f, g = fits[best], fits[given]
            warning = (
                f"the data were read as {given}, but {best} explains them clearly better "
                f"(sigma0 {f.sigma0:.3f} against {g.sigma0:.3f}; held-out misfit "
                f"{_mm(f.cv_mm)} against {_mm(g.cv_mm)}): the instrument probably measures "
                f"{'in two faces' if best == 'panoramic' else 'in one face over the full turn'}; "
                f"read the target lists with architecture '{best}' (--architecture {best}), or "
                "the APs will be wrong"
            )
        return cls(fits, given, best, clearly, reason, warning)

    def summary(self) -> str:
        """Each architecture's sigma0 and cross-validated misfit, the verdict, the warning."""
        lines = ["architecture from the data (a priori sigma0; cross-validated misfit):"]
        for arch, f in self.fits.items():
            mark = " (as read)" if arch == self.given else ""
            lines.append(f"  {f.summary()}{mark}")
        if self.best is None:
            lines.append(f"  {self.reason}")
        else:
            lines.append(f"  explains the data better: {self.best} ({self.reason})")
        if self.warning:
            lines.append(f"warning: {self.warning}")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        """The result JSON's ``architecture_check`` (strict JSON)."""
        return to_json_value(
            {
                "given": self.given,
                "best": self.best,
                "clearly": self.clearly,
                "reason": self.reason,
                "warning": self.warning or None,
                "fits": {a: f.to_dict() for a, f in self.fits.items()},
            }
        )


def read_as(network: Network) -> str | None:
    """The architecture a network's observations are in: panoramic where some elevation is
    beyond 90 deg (the second face), otherwise None (hybrid, or panoramic with every target in
    the front half: the two read alike)."""
    return "panoramic" if (np.asarray(network.observations)[:, 2] > np.pi / 2).any() else None


def as_architecture(network: Network, architecture: str) -> Network:
    """The network's target observations in the representation of ``architecture`` (SPEC
    section 1; exact: the same scanner-frame points)."""
    x = np.asarray(cartesian_from_spherical(np.asarray(network.observations), xp=np))
    return network.with_observations(np.asarray(scanner_observations(x, architecture, xp=np)))


def _fit(network, model, arch, options: CalibrationOptions) -> ArchitectureFit:
    """One architecture's calibration by the pipeline with ``options`` (module docstring)."""
    scanner = dataclasses.replace(model.scanner, architecture=arch)
    m = dataclasses.replace(model, scanner=scanner)
    tested = run_tests(as_architecture(network, arch), m, options)
    res = tested.calibration
    if not res.ok:
        return ArchitectureFit(arch, False, res.message, np.nan, np.nan, 0, {}, None)
    aps = {n: float(v) if np.isfinite(v) else None for n, v in zip(res.ap_names, res.ap_values)}
    return ArchitectureFit(
        arch,
        True,
        res.message,
        float(res.sigma0),
        float(res.dof),
        len(tested.outliers),
        aps,
        tested.cross_validation,
    )


def _fitting_options(options: CalibrationOptions) -> CalibrationOptions:
    """The settings of both fits: the caller's solver, screening and folds, the a priori
    weights (sigma0 is the comparison), no snooping, selection or score tests."""
    return dataclasses.replace(
        options,
        vce=None,
        snooping=None,
        selection=None,
        tests=dataclasses.replace(options.tests, score_tests=False),
        architecture_check=None,
    )


def compare_architectures(
    network: Network,
    model: CalibrationModel | None = None,
    options: CalibrationOptions | None = None,
    *,
    given: str | None = None,
) -> ArchitectureComparison:
    """Fit hybrid and panoramic two-face to ``network`` (module docstring) and say which
    explains the data. ``model``: the calibration model (its scanner's APs and unit lengths,
    one instrument; default physical); ``options``: the solver, screening and cross-validation
    of both fits and the margins (``options.architecture_check``, default
    :class:`tlsjax.ArchitectureCheckOptions`); VCE, snooping and selection are not run (module
    docstring). ``given``: the architecture the data were read as (default: panoramic where an
    elevation is beyond 90 deg, else the model scanner's)."""
    model = model or CalibrationModel()
    options = options or CalibrationOptions()
    if not isinstance(model.scanner, Scanner):
        raise ValueError("compare_architectures: one instrument; pass one Scanner")
    if network.has_planes or not network.has_targets:
        raise ValueError(f"{network.source}: the architecture is judged from target observations")
    if given is not None and given not in ARCHITECTURES:
        raise ValueError(f"given={given!r} is not one of {ARCHITECTURES}")
    given = given or read_as(network) or model.scanner.architecture
    margins = options.architecture_check or ArchitectureCheckOptions()
    fitting = _fitting_options(options)
    fits = {a: _fit(network, model, a, fitting) for a in ARCHITECTURES}
    return ArchitectureComparison.of(fits, given, margins)


def _mm(x: float) -> str:
    return f"{x:.3f} mm" if np.isfinite(x) else "n/a"


def _decide(fits: dict, margins: ArchitectureCheckOptions) -> tuple:
    """(best, clearly, reason) of two successful fits: by the cross-validated misfit where
    both have one, else by the a priori sigma0."""
    ok = fits  # every fit succeeded (ArchitectureComparison.of)
    h, p = (ok[a] for a in ARCHITECTURES)
    if np.isfinite(h.cv_mm) and np.isfinite(p.cv_mm):
        best = min(ok, key=lambda a: ok[a].cv_mm)
        other = next(a for a in ok if a != best)
        d, se = paired_difference(ok[best].cross_validation, ok[other].cross_validation)
        clearly = bool(np.isfinite(d) and np.isfinite(se) and d < -margins.margin * se)
        how = "more than" if clearly else "within"
        return (
            best,
            clearly,
            (
                f"lower cross-validated misfit, by {how} {margins.margin:g} standard errors of "
                "the folds' paired difference"
            ),
        )
    best = min(ok, key=lambda a: ok[a].sigma0)
    other = next(a for a in ok if a != best)
    ratio = ok[other].sigma0 / ok[best].sigma0
    clearly = bool(ratio > margins.sigma0_ratio)
    return best, clearly, f"lower a priori sigma0 (the other's is {ratio:.2f} times it)"
