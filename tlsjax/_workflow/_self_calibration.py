"""The one tested entry of a self-calibration, :func:`self_calibrate`, and its result,
:class:`SelfCalibration`: what ``tlsjax calibrate`` runs, prints and writes.

The steps are those of the one pipeline (:data:`tlsjax._inference._steps.PIPELINE`: plane
screening, robust start, a priori tests, screening, selection, variance components, data
snooping, score tests of the missing terms, cross-validation), each switched on or off by its
concern in :class:`tlsjax.CalibrationOptions`. The result's ``summary()`` is the text the
command prints, its ``to_dict()`` the JSON it writes (SPEC section 11), so a notebook gets what
the command line gets from one call.

This layer sits above the report (:mod:`tlsjax._report`), whose text and JSON of an adjustment
it composes with what the pipeline found.
"""

from __future__ import annotations

import dataclasses

from .._adjustment._config import CalibrationModel, scanner_settings
from .._adjustment._json import withhold_estimates
from .._adjustment._network import Network, check_calibration_arguments, network_design_warnings
from .._adjustment._text import ap_table, summary
from .._inference._options import CalibrationOptions
from .._inference._outcome import TestedCalibration
from .._inference._run import run_tests
from .._model._scanner import Scanner
from .._report._html import provenance, reliability_summary
from .._report._tables import table_json, with_lines
from .._summary import to_json_value
from .._version import __version__


@dataclasses.dataclass(frozen=True, eq=False)
class SelfCalibration(TestedCalibration):
    """The result of :func:`self_calibrate`: the final adjustment (``calibration``, a
    :class:`tlsjax.CalibrationResult`), its model and what every step found (the fields of
    the pipeline's outcome: removals, variance components, w-tests, MDB, external reliability,
    a priori tests, AP t-tests, selection, plane screening, score tests; see
    :class:`tlsjax._inference._outcome.TestedCalibration`), and what made it:

    ``settings``: the model given (before any selection) and the options, as the dicts that
    :meth:`tlsjax.CalibrationModel.from_dict` and :meth:`tlsjax.CalibrationOptions.from_dict`
    read back; ``provenance``: tlsjax version, time, Python, platform and the network's input
    files with their SHA-256; ``inputs``: how the network was read (files, reading settings,
    the command line), recorded by whoever read it (:meth:`with_inputs`; ``tlsjax calibrate``
    does); ``design_warnings``: what the design (scans, primitives, APs) cannot determine well.

    ``summary()`` is the text ``tlsjax calibrate`` prints, ``to_dict()`` the JSON it writes.
    """

    settings: dict = dataclasses.field(default_factory=dict)
    provenance: dict = dataclasses.field(default_factory=dict)
    inputs: dict = dataclasses.field(default_factory=dict)
    design_warnings: tuple = ()

    @property
    def ok(self) -> bool:
        """The run is a calibration: the adjustment succeeded, VCE ended usable and no AP has
        a magnitude no working instrument has (``tlsjax calibrate`` exits 0 exactly then)."""
        return self.calibration.ok and self.vce_result.ok and not self.implausible

    @property
    def implausible(self) -> bool:
        """An estimated AP has a magnitude no working instrument has (:meth:`tlsjax.
        CalibrationResult.plausibility`): the run is then no calibration."""
        return any(f.level == "impossible" for f in self.calibration.plausibility()[0])

    @property
    def withheld(self) -> str | None:
        """Why the estimates of a converged adjustment are no calibration (variance components
        that failed: the weights are not estimated), or None."""
        if not (self.calibration.ok and not self.vce_result.ok):
            return None
        return (
            f"the variance components failed ({self.vce_result.message}); the adjustment with "
            "the last weights that worked converged, but those weights are not estimated, so its "
            "estimates and sigmas are not a calibration"
        )

    def with_inputs(self, **inputs) -> SelfCalibration:
        """The result with ``inputs`` recorded (how the network was read: the files, the
        reading settings, the command line), so that its JSON can re-run it."""
        return dataclasses.replace(self, inputs={**self.inputs, **inputs})

    def summary(self) -> str:
        """The text ``tlsjax calibrate`` prints: what the steps found, the adjustment's summary
        (sigma0 and its test, redundancy, flags) and the AP table (no numbers where the run is
        no calibration)."""
        res, withheld = self.calibration, self.withheld
        lines = [self.testing_summary(), summary(res, after_vce=self.weights_fitted)]
        if withheld:
            lines.append(f"error: {withheld}")
        lines += ["", ap_table(res, withheld=withheld)]
        return "\n".join(lines)

    def to_dict(self) -> dict:
        """The result JSON of ``tlsjax calibrate --json`` (SPEC section 11; SI units, strict
        JSON): the adjustment, what the steps found, the per-observation and per-group tables
        (none for a run that is no calibration), reliability, the scanner settings that
        applying the APs needs, and the settings, inputs and provenance that re-run it."""
        res = self.calibration
        doc = res.to_dict()
        doc.update(self.testing_fields())
        doc["scanner"] = scanner_settings(self.model.scanner)
        doc["provenance"] = {**self.provenance, "command": self.inputs.get("command")}
        if res.network.has_targets:
            doc["reliability"] = reliability_summary(res, mdb=self.mdb, mask=self.mask)
        if self.ok:
            doc.update(table_json(res, self))
        if self.outliers:
            doc["outliers"] = with_lines(doc["outliers"], res)
        if self.design_warnings:
            doc["design_warnings"] = list(self.design_warnings)
        doc["settings"] = {**self.settings, "inputs": dict(self.inputs)}
        if self.withheld:
            withhold_estimates(doc, self.withheld)
        return to_json_value(doc)


def self_calibrate(
    network: Network,
    model: CalibrationModel | None = None,
    options: CalibrationOptions | None = None,
) -> SelfCalibration:
    """Self-calibration as ``tlsjax calibrate`` runs it (SPEC sections 5 and 7): the steps of
    the one pipeline, each with its concern of ``options`` (None: off; the defaults are the
    command's):

    plane screening (IGG-III, plane points without snooping); the robust start (IGG-III
    reweighting from the misclosures at the approximate values: gross errors out before the
    first least-squares adjustment); the a priori tests (global and group tests with the a
    priori sigmas); screening (robust group scales, family-wise level; a removal is weighed
    against the score tests of the missing terms); stepwise AP selection from the model's APs
    (``options.selection``) on the screened observations; variance component estimation
    (``s_g^2 = v_g^T P_g v_g / r_g``, Förstner 1979); Baarda's data snooping
    (``w_i = v_i / (sigma_i sqrt(r_i))``, Baarda 1968); the score tests of the terms missing
    from the final model; then reliability (MDB, external reliability) and the AP t-tests.

    Every re-adjustment is the one compiled adjustment of the model with other weights (only a
    model that selection chose is analysed once more). Returns a :class:`SelfCalibration`:
    ``summary()`` is what the command prints, ``to_dict()`` the JSON it writes, ``ok`` whether
    the run is a calibration.
    """
    check_calibration_arguments(network, model, None, "self_calibrate")
    if options is not None and not isinstance(options, CalibrationOptions):
        raise TypeError(
            "self_calibrate: options must be a tlsjax CalibrationOptions or None, got "
            f"{type(options).__name__}"
        )
    model = model or CalibrationModel()
    options = options or CalibrationOptions()
    if options.selection is not None and not isinstance(model.scanner, Scanner):
        raise ValueError(
            "self_calibrate: stepwise selection works on one instrument; give the model one Scanner"
        )
    tested = run_tests(network, model, options)
    fields = {f.name: getattr(tested, f.name) for f in dataclasses.fields(TestedCalibration)}
    return SelfCalibration(
        **fields,
        settings={
            "tlsjax_version": __version__,
            "model": model.to_dict(),
            "options": options.to_dict(),
        },
        provenance=provenance((network.source, network.plane_source, network.scans_source)),
        design_warnings=tuple(network_design_warnings(network, model)),
    )
