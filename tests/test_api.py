"""The public API as a user holds it: settings objects are called ``Options``, and the names of
earlier releases still resolve, with a DeprecationWarning naming their replacement."""

import dataclasses
import inspect
import json
import types
import warnings

import numpy as np
import pytest

import tlsjax as tj


@pytest.mark.parametrize(
    "old, new", [("ExtractionConfig", "ExtractionOptions"), ("MatchingConfig", "MatchingOptions")]
)
def test_old_names_warn_and_resolve_to_the_new_ones(old, new):
    with pytest.warns(DeprecationWarning, match=f"tlsjax.{new}"):
        obj = getattr(tj, old)
    assert obj is getattr(tj, new)


def test_unknown_names_still_raise_attribute_error():
    with pytest.raises(AttributeError, match="NoSuchThing"):
        _ = tj.NoSuchThing


def test_settings_objects_share_one_word():
    settings = [n for n in dir(tj) if n.endswith(("Config", "Settings", "Params"))]
    assert settings == [], settings


# --- summary() is text, to_dict() strict JSON, on every public result type -------------------


def _result_types_with(method):
    return [
        getattr(tj, n)
        for n in sorted(dir(tj))
        if not n.startswith("_")
        and n not in ("ExtractionConfig", "MatchingConfig")  # deprecated aliases (they warn)
        and inspect.isclass(getattr(tj, n))
        and callable(getattr(getattr(tj, n), method, None))
    ]


def test_every_public_summary_is_annotated_as_text():
    types = _result_types_with("summary")
    assert {"MonteCarloResult", "DesignOptimisation", "ExtractedPlanes"} <= {
        t.__name__ for t in types
    }
    for t in types:
        ann = inspect.signature(t.summary).return_annotation
        assert ann in ("str", str), (t.__name__, ann)


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
        alpha=0.05,
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


def test_old_summary_access_warns_and_returns_the_old_value():
    mc = _monte_carlo()
    text = mc.summary()
    with pytest.warns(DeprecationWarning, match=r"summary\(\) returns text now; use to_dict\(\)"):
        assert text["aps"]["A0"]["mean"] == pytest.approx(1.0e-3)
    with pytest.warns(DeprecationWarning, match="use to_dict"):
        assert set(text.keys()) == set(mc.to_dict())
    with pytest.warns(DeprecationWarning, match="use to_dict"):
        assert dict(text.items())["runs"] == 4
    with pytest.warns(DeprecationWarning, match="use to_dict"):
        assert text.get("dof") == 20 and text.get("nothing", 3) == 3
    # NaN in the old dict (failed realisations) where to_dict() has None.
    with pytest.warns(DeprecationWarning):
        assert np.isnan(_monte_carlo(ok=False).summary()["sigma0_sq_mean"])
    with pytest.warns(DeprecationWarning, match="use to_dict"):
        assert _design_optimisation().summary()["value"] == 0.5
    with pytest.warns(DeprecationWarning, match="use to_dict"):
        assert _extracted_planes().summary()[0]["n_points"] == 400
    # Plain text use does not warn.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert text[:11] == "Monte Carlo" and text.splitlines()[0].startswith("Monte")
        assert _extracted_planes().summary()[0:2] == "1 "


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
