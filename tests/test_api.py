"""The public API as a user holds it (issue 39): every result has ``summary()`` (text) and
``to_dict()`` (strict JSON), written by :func:`tlsjax.write_json`; every settings object is
called ``...Options``, round-trips through ``to_dict()``/``from_dict()``, and is passed as
``options=``; levels are named for the test they are the level of."""

import dataclasses
import inspect
import json
import types

import numpy as np
import pytest

import tlsjax as tj


def test_unknown_names_raise_attribute_error():
    with pytest.raises(AttributeError, match="NoSuchThing"):
        _ = tj.NoSuchThing


def test_settings_objects_share_one_word():
    settings = [n for n in dir(tj) if n.endswith(("Config", "Settings", "Params"))]
    assert settings == [], settings


# --- One convention (issue 39 item 2) --------------------------------------------------------

#: Public classes a public function returns that are inputs or data for further work, not
#: results to read: networks and tables, the analysed adjustment, differentiable inputs and
#: estimates, simulations (their truth is an input of the tests), a registered AP term, one
#: scan's points.
NOT_RESULTS = {
    "Network",
    "ObservationTable",
    "Adjustment",
    "NetworkInputs",
    "Estimates",
    "Simulation",
    "DesignSimulation",
    "PointClouds",
    "APTerm",
    "CorrectedScan",
    "PointCloudScan",
    "DesignCriterion",
}
#: Results that are parts of other results (``SelfCalibration.selection`` ...) or made by a
#: constructor (``APSet.from_result``), beside those a public function returns.
PARTS = {
    "ScoreTests",
    "SelectionResult",
    "PlaneScreening",
    "CheckpointReport",
    "TargetMatching",
    "APSet",
}
#: Names of the variants the convention replaced.
OLD_VARIANTS = (
    "json_fields",
    "outliers_json",
    "as_dict",
    "as_json",
    "report",
    "redundancy_summary",
    "to_json",
)


def _returned_classes():
    """Names of the public classes that public functions are annotated to return."""
    public = {n for n in dir(tj) if not n.startswith("_") and inspect.isclass(getattr(tj, n))}
    out = set()
    for n in dir(tj):
        f = getattr(tj, n)
        if n.startswith("_") or inspect.isclass(f) or not callable(f):
            continue
        ann = inspect.signature(f).return_annotation
        text = ann if isinstance(ann, str) else getattr(ann, "__name__", str(ann))
        out |= {c for c in public if c in text.replace("|", " ").replace(",", " ").split()}
    return out


def test_every_public_result_type_has_summary_and_to_dict():
    """The public result types: every class a public function returns, and the results that
    are parts of others. Each answers ``summary() -> str`` and ``to_dict() -> dict`` and
    keeps none of the variants the convention replaced."""
    results = (_returned_classes() - NOT_RESULTS) | PARTS
    assert {
        "SelfCalibration",
        "CalibrationResult",
        "MonteCarloResult",
        "CompatibilityResult",
    } <= results
    for name in sorted(results):
        cls = getattr(tj, name)
        for method, kind in (("summary", str), ("to_dict", dict)):
            assert callable(getattr(cls, method, None)), f"{name}.{method}"
            ann = inspect.signature(getattr(cls, method)).return_annotation
            assert ann in (kind.__name__, kind), (name, method, ann)
        assert not [m for m in OLD_VARIANTS if hasattr(cls, m)], name


def test_every_settings_object_round_trips_and_is_passed_as_options():
    """Every public ``...Options`` reads its ``to_dict()`` back (strict JSON); every public
    function takes its settings as ``options=`` (no ``config=``, ``solver=``, ``testing=``) and
    names no parameter ``alpha``."""
    options = [n for n in dir(tj) if n.endswith("Options")]
    assert len(options) >= 12, options
    for name in options:
        cls = getattr(tj, name)
        default = cls()
        doc = json.loads(json.dumps(default.to_dict(), allow_nan=False))
        assert cls.from_dict(doc) == default, name
        assert not [f.name for f in dataclasses.fields(cls) if "alpha" in f.name], name
    for n in dir(tj):
        f = getattr(tj, n)
        if n.startswith("_") or inspect.isclass(f) or not callable(f):
            continue
        params = inspect.signature(f).parameters
        assert not {"config", "solver", "testing"} & set(params), n
        assert not [p for p in params if "alpha" in p], n


def _monte_carlo(ok=True):
    """A MonteCarloResult of 4 realisations of one AP (A0, m) with known statistics."""
    values = np.array([[1.0e-3], [1.2e-3], [0.8e-3], [1.0e-3]])
    sigmas = np.full((4, 1), 0.1e-3)
    return tj.MonteCarloResult(
        ap_names=("A0",),
        ap_units=("m",),
        true_aps=np.full((4, 1), 0.9e-3),
        ap_values=values if ok else np.full((4, 1), np.nan),
        ap_sigmas=sigmas if ok else np.full((4, 1), np.nan),
        ap_covariance=sigmas[:, :, None] ** 2,
        sigma0_sq=np.array([1.0, 1.2, 0.8, 1.0]),
        iterations=np.full(4, 3),
        result=np.zeros(4, dtype=int) if ok else np.full(4, 1),
        dof=20,
        t_test_level=0.05,
        seed=7,
        chunk_size=4,
        n_devices=1,
        compile_s=0.5,
        run_s=0.25,
    )


def _design_optimisation():
    eops = np.array([[1.0, 2.0, 1.5, 0.0, 0.0, np.radians(30.0)], [4.0, 2.0, 1.5, 0, 0, 0]])
    return tj.DesignOptimisation(
        design=types.SimpleNamespace(eops=eops),
        value=0.5,
        start_value=2.0,
        values=np.array([0.5, np.nan]),
        designs=(),
        history=np.zeros((3, 2)),
        criterion="max sigma/tolerance of B6",
        compile_s=1.0,
        run_s=2.0,
    )


def _extracted_planes():
    """One scan at the origin, one floor patch at z = -1.5 m, its points +-2 mm off the plane:
    RMS 2 mm, 400 points, patch parallel to the plane."""
    g = np.linspace(-1.0, 1.0, 20)
    x, y = (a.ravel() + 2.0 for a in np.meshgrid(g, g))
    z = -1.5 + 0.002 * np.where(np.arange(x.size) % 2, 1.0, -1.0)
    rho = np.sqrt(x**2 + y**2 + z**2)
    obs = np.stack([rho, np.mod(np.arctan2(y, x), 2 * np.pi), np.arcsin(z / rho)], axis=1)
    n = x.size
    return tj.ExtractedPlanes(
        scans=("S1",),
        patch_scan=np.zeros(1, dtype=int),
        patch_normal=np.array([[0.0, 0.0, 1.0]]),
        patch_distance=np.array([-1.5]),
        patch_rms=np.array([0.002]),
        patch_inliers=np.array([n]),
        patch_plane=np.zeros(1, dtype=int),
        point_patch=np.zeros(n, dtype=int),
        point_index=np.arange(n),
        observations=obs,
        incidence=np.zeros(n),
        poses=np.zeros((1, 6)),
        planes=np.array([[0.0, 0.0, 1.0, -1.5]]),
    )


def test_summaries_are_text_with_units():
    mc = _monte_carlo().summary()
    assert isinstance(mc, str) and "4 realisations" in mc and "A0" in mc and " mm" in mc
    # Bias 1.0e-3 - 0.9e-3 = 0.1 mm, shown in mm.
    assert "0.1000" in mc.splitlines()[-1]
    do = _design_optimisation().summary()
    assert (
        "2 at the start -> 0.5 at the best" in do
        and "kappa [deg]" in do
        and "30.00" in do
        and "X [m]" in do
    )
    ex = _extracted_planes().summary()
    line = ex.splitlines()[-1].split()
    assert line[:4] == ["P1", "1", "1", "400"] and float(line[4]) == pytest.approx(2.0)
    assert float(line[5]) == pytest.approx(0.0) and "RMS [mm]" in ex


def test_to_dict_is_strict_json_with_the_data():
    mc = _monte_carlo().to_dict()
    a = mc["aps"]["A0"]
    assert a["mean"] == pytest.approx(1.0e-3) and a["bias"] == pytest.approx(0.1e-3)
    assert a["empirical_sigma"] == pytest.approx(np.std([1.0, 1.2, 0.8, 1.0], ddof=1) * 1e-3)
    assert a["power"] == 1.0 and mc["successful"] == 4
    failed = _monte_carlo(ok=False).to_dict()
    assert failed["aps"]["A0"]["mean"] is None and failed["sigma0_sq_mean"] is None
    assert failed["failures"] == {tj.RESULT_MESSAGES[1]: 4}
    do = _design_optimisation().to_dict()
    assert do["values_per_start"] == [0.5, None] and do["kappa_deg"][0] == pytest.approx(30.0)
    ex = _extracted_planes().to_dict()
    assert ex["planes"][0]["rms"] == pytest.approx(0.002) and ex["planes"][0]["n_points"] == 400
    unmatched = dataclasses.replace(_extracted_planes(), poses=None, planes=None)
    assert unmatched.to_dict()["planes"] is None and "not matched" in unmatched.summary()
    for d in (mc, failed, do, ex, unmatched.to_dict()):
        json.dumps(d, allow_nan=False)


def test_settings_and_models_round_trip_through_strict_json():
    """What a result records of the settings that made it reads back as the same objects
    (issue 40 item 5: a result can be re-run from its own file)."""
    options = tj.CalibrationOptions(
        solver=tj.SolverOptions(max_iterations=7),
        vce=None,
        snooping=tj.SnoopingOptions(w_test_level=0.01, removal="target", critical_value=3.0),
        tests=tj.TestOptions(candidates="A3 C2", score_test_level=0.01),
        selection=tj.SelectionOptions(candidates="A3 C2", test_level=0.02),
    )
    text = json.dumps(options.to_dict(), allow_nan=False)
    assert tj.CalibrationOptions.from_dict(json.loads(text)) == options
    model = tj.CalibrationModel(
        {"a": tj.Scanner(aps="A0 B6"), "b": tj.Scanner(architecture="panoramic", aps="A0 C0")},
        datum="inner",
        correlation_threshold=0.95,
        fixed_aps=("C0[b]",),
        ap_priors={"B6[a]": (1e-4, 1e-5)},
    )
    text = json.dumps(model.to_dict(), allow_nan=False)
    assert tj.CalibrationModel.from_dict(json.loads(text)) == model
    with pytest.raises(ValueError, match="VCEOptions: unknown setting.*tol"):
        tj.VCEOptions.from_dict({"tol": 1e-3})
    with pytest.raises(
        TypeError, match="CalibrationOptions.snooping must be a tlsjax SnoopingOptions"
    ):
        tj.CalibrationOptions(snooping=True)
