"""Issue 13: the default statistics cannot hide a blunder, and VCE converges or stops with a
result code and its reason (scaled sigmas, noise-free data), never a NaN.

Private imports: the VCE step's safeguards are exercised through its module (a fake variance
estimate, a lower factor limit); the statistics' pure functions and the strict JSON writer
directly.
"""

import dataclasses
import json

import numpy as np
import pytest
import scipy.stats

import tlsjax as tj
from tlsjax import VCEResult

APS = "A0 B6 B7 C0"
MODEL = tj.CalibrationModel(tj.Scanner(aps=APS))
NO_SNOOP = tj.CalibrationOptions()


@pytest.fixture(scope="module")
def sim():
    return tj.simulate(tj.Room(n_targets=36), seed=11, aps=APS)


def _strict(tested):
    """The testing fields as strict JSON (raises on NaN/inf) and the critical values finite."""
    text = json.dumps(tested.testing_fields(), allow_nan=False)
    assert np.isfinite(tested.critical_value)
    return json.loads(text)


def _scaled(net, factor):
    return dataclasses.replace(
        net, sigmas=net.sigmas * factor, levelling_sigma=net.levelling_sigma * factor
    )


def test_blunders_are_screened_out_before_vce(sim):
    net = sim.network
    obs = net.observations.copy()
    bad = {(10, 0): 1.0, (50, 1): np.radians(10.0), (90, 2): np.radians(10.0)}
    for (i, g), e in bad.items():
        obs[i, g] += e
    # Screening itself, without the robust start before it (tests/test_robust_start.py).
    no_robust_start = tj.CalibrationOptions(screening=tj.ScreeningOptions(robust_start=False))
    r = tj.self_calibrate(net.with_observations(obs), MODEL, no_robust_start)
    assert {(o.row, ("range", "hz", "el").index(o.group)) for o in r.outliers} == set(bad)
    assert all(o.reason.startswith("screening before VCE") for o in r.outliers)
    first, after = r.a_priori_tests
    assert first["global"]["accepted"] is False and first["groups"]["range"]["factor"] > 100
    assert after["stage"] == "after screening" and after["global"]["statistic"] is not None
    assert r.vce_result == VCEResult.CONVERGED and r.ok
    f = {vc.group: vc.factor for vc in r.variance_components}
    assert all(0.5 < f[g] < 2.0 for g in ("range", "hz", "el")), f  # the data's own noise
    c = r.calibration
    for k, name in enumerate(c.ap_names):
        assert abs(c.ap_values[k] - sim.true_aps[name]) < 4.5 * c.ap_sigmas[k], name
    d = _strict(r)
    assert d["global_test"] == {**after["global"], "stage": "a priori"}
    assert "not a test" in d["global_test_after_vce"]["note"]
    text = r.summary()
    assert "REJECTED" in text and "not a test" in text and "T011" not in text.split("step")[0]


def test_without_screening_the_inflated_factors_are_named(sim):
    net = sim.network
    obs = net.observations.copy()
    obs[10, 0] += 1.0
    r = tj.self_calibrate(net.with_observations(obs), MODEL, tj.CalibrationOptions(screening=None))
    assert r.outliers == () and r.a_priori_tests[0]["groups"]["range"]["accepted"] is False
    f = {vc.group: vc.factor for vc in r.variance_components}
    assert f["range"] > 25  # VCE absorbed the blunder ...
    # ... and the warning names the observation that holds the misfit, not the sigmas or units
    target = net.targets[net.target_index[10]]
    assert any(w.startswith("one observation holds") and target in w for w in r.warnings)
    assert not any(w.startswith("range: variance factor") for w in r.warnings)
    assert "global_test" in r.testing_fields() and not r.testing_fields()["global_test"]["accepted"]


def test_vce_is_scale_equivariant_and_names_the_scale(sim):
    net = sim.network
    base = tj.self_calibrate(net, MODEL, NO_SNOOP)
    f0 = np.array([vc.factor for vc in base.variance_components])
    for scale in (1 / 40, 40.0):
        r = tj.self_calibrate(_scaled(net, scale), MODEL, NO_SNOOP)
        _strict(r)
        if r.vce_result == VCEResult.CONVERGED:
            f = np.array([vc.factor for vc in r.variance_components])
            np.testing.assert_allclose(f * scale**2, f0, rtol=2e-2)
        else:  # the engine may fail at the new weights: then VCE says so and keeps what worked
            assert r.vce_result == VCEResult.ADJUSTMENT_FAILED and r.calibration.ok
        word = "times too large" if scale > 1 else "times too small"
        for g in ("range", "hz", "el"):
            assert any(w.startswith(g + ":") and word in w for w in r.warnings), r.warnings


def test_unit_mixups_are_named(sim):
    net = sim.network
    deg = tj.self_calibrate(_scaled(net, np.degrees(1.0)), MODEL, NO_SNOOP)
    hz = next(w for w in deg.warnings if w.startswith("hz:"))
    assert "degrees vs radians" in hz and "times too large" in hz
    mm = dataclasses.replace(net, sigmas=net.sigmas * np.array([1e-3, 1.0, 1.0]))
    r = tj.self_calibrate(mm, MODEL, NO_SNOOP)
    (rng,) = [w for w in r.warnings if w.startswith("range:")]
    assert "millimetres vs metres" in rng and "degrees" not in rng
    assert not any(w.startswith(("hz:", "el:")) for w in r.warnings)


def test_noise_free_data_stop_vce_with_a_reason():
    s = tj.simulate(tj.Room(n_targets=36), seed=11, aps=APS, noise=False)
    r = tj.self_calibrate(s.network, MODEL, tj.CalibrationOptions(snooping=tj.SnoopingOptions()))
    assert r.vce_result == VCEResult.NOISE_FREE and r.ok
    assert all(vc.factor == 1.0 and not vc.estimated for vc in r.variance_components)
    assert r.outliers == ()
    np.testing.assert_allclose(
        r.calibration.ap_values, [s.true_aps[n] for n in r.calibration.ap_names], rtol=1e-7
    )
    d = _strict(r)
    assert d["vce"]["status"] == "noise_free" and "rounding" in d["vce"]["message"]


def test_sigmas_far_too_small_are_named_not_nan(sim):
    r = tj.self_calibrate(
        _scaled(sim.network, 1e-6), MODEL, tj.CalibrationOptions(snooping=tj.SnoopingOptions())
    )
    d = _strict(r)
    assert any("1e+06 times too small" in w or "1.0" in w and "too small" in w for w in r.warnings)
    if not r.calibration.ok:  # the adjustment with the a priori sigmas failed: a code, a reason
        assert r.vce_result == VCEResult.ADJUSTMENT_FAILED and not r.ok
        assert d["vce"]["result"] == int(VCEResult.ADJUSTMENT_FAILED)


@pytest.mark.internal
def test_safeguards_stop_with_their_codes(sim, monkeypatch):
    from tlsjax._inference import _steps

    net = sim.network
    r = tj.self_calibrate(net, MODEL, tj.CalibrationOptions(vce=tj.VCEOptions(min_redundancy=1e6)))
    assert r.vce_result == VCEResult.NO_REDUNDANCY and r.ok
    assert all("redundancy" in vc.note for vc in r.variance_components)
    r = tj.self_calibrate(
        _scaled(net, 2.0), MODEL, tj.CalibrationOptions(vce=tj.VCEOptions(max_iterations=1))
    )
    assert r.vce_result == VCEResult.MAX_ITERATIONS and not r.ok and r.calibration.ok
    monkeypatch.setattr(_steps, "VCE_FACTOR_LIMIT", 100.0)
    r = tj.self_calibrate(_scaled(net, 1 / 40), MODEL, tj.CalibrationOptions(screening=None))
    assert r.vce_result == VCEResult.FACTOR_LIMIT and "beyond" in " ".join(r.warnings)
    assert all(vc.factor == 1.0 for vc in r.variance_components)
    _strict(r)


@pytest.mark.internal
def test_oscillating_factors_are_damped_and_reported(sim, monkeypatch):
    """A fake VCE step that alternates between s^2 = 4 and 1/4: the damping halves every
    change of direction, so the factors stay between 1/4 and 4 and the stop says why."""
    from tlsjax._inference import _steps

    calls = {"n": 0}
    real = _steps.group_statistics

    def alternating(ctx, state):
        s2, r_g, n_g = real(ctx, state)
        calls["n"] += 1
        return np.where(np.arange(len(s2)) < 3, 4.0 if calls["n"] % 2 else 0.25, s2), r_g, n_g

    monkeypatch.setattr(_steps, "group_statistics", alternating)
    r = tj.self_calibrate(
        sim.network,
        MODEL,
        tj.CalibrationOptions(screening=None, vce=tj.VCEOptions(max_iterations=8)),
    )
    assert r.vce_result == VCEResult.OSCILLATING
    f = np.array([h["factors"][:3] for h in r.history if "vce_iteration" in h])
    assert np.all((f >= 0.25) & (f <= 4.0))
    steps = np.abs(np.diff(np.log(f[:, 0])))
    assert steps[-1] < steps[0] / 16  # each change of direction halves the step


@pytest.mark.internal
def test_group_variance_test_against_scipy():
    from tlsjax._io._json import dumps_strict
    from tlsjax._stats import group_variance_test

    t = group_variance_test(omega=350.0, redundancy=300.0, level=0.05)
    assert np.isclose(t["factor"], 350 / 300)
    assert np.isclose(t["upper"], scipy.stats.chi2.ppf(0.975, 300))
    assert np.isclose(t["p_value"], 2 * scipy.stats.chi2.sf(350.0, 300), rtol=1e-8)
    assert t["accepted"] is False
    assert group_variance_test(290.0, 300.0)["accepted"] is True
    empty = group_variance_test(0.0, 0.0)
    assert empty["accepted"] is None and empty["factor"] is None
    dumps_strict(empty)


@pytest.mark.internal
def test_unit_suspicion_table():
    from tlsjax._inference._variance_factors import implausible_factor, suspected_units

    assert suspected_units(57.3) == ("degrees vs radians", "gon vs radians")
    assert suspected_units(1 / 1000.0, "length") == ("millimetres vs metres",)
    assert suspected_units(1000.0, "angle") == ()
    assert suspected_units(40.0) == ()
    assert implausible_factor("hz", 3.0) is None
    assert "about 40 times too large" in implausible_factor("range", 1 / 1600)
    assert "not a variance" in implausible_factor("el", float("nan"))
