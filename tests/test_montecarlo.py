"""Batched Monte Carlo and the AP-set compatibility test (SPEC section 9)."""

import json

import numpy as np
import pytest
from scipy import stats

import tlsjax as tj
from tlsjax import (
    APSet,
    CompatibilityOptions,
    MonteCarloOptions,
    compatibility_test,
    monte_carlo,
    monte_carlo_network,
)

ROOM = tj.Room(n_targets=30)
N = 300


@pytest.fixture(scope="module")
def design():
    # The data have no B7; the model estimates it: its t test then shows the test's size.
    return tj.simulate(ROOM, seed=1, aps="A0 B6 C0")


@pytest.fixture(scope="module")
def model():
    return tj.CalibrationModel(tj.Scanner(aps="A0 B6 B7 C0"))


@pytest.fixture(scope="module")
def mc(design, model):
    return monte_carlo(
        design, model, MonteCarloOptions(runs=N, chunk_size=50, seed=3, progress=False)
    )


def test_realisation_equals_calibrate(design, model, mc):
    for k in (0, 17, N - 1):
        net, truth = monte_carlo_network(design, k, seed=3)
        assert truth == pytest.approx(
            {n: design.true_aps[n] for n in design.scanner.aps}, rel=0, abs=0
        )
        ref = tj.calibrate(net, model, tj.SolverOptions(tolerance=1e-10, full_covariance=False))
        assert ref.result == 0 and mc.result[k] == 0
        np.testing.assert_allclose(
            mc.ap_values[k], ref.ap_values, rtol=0, atol=1e-8 * ref.ap_sigmas.min()
        )
        # The design's covariance scaled by the realisation's own s0^2 (the chord method).
        np.testing.assert_allclose(mc.ap_sigmas[k], ref.ap_sigmas, rtol=2e-3)
        assert mc.sigma0_sq[k] == pytest.approx(ref.sigma0**2, rel=1e-8)
        assert mc.dof == ref.dof


def test_empirical_precision_matches_formal(mc):
    sm = mc.summary()
    assert sm["successful"] == N
    # s0^2 ~ chi2(r)/r: the mean of N has sigma sqrt(2 / r / N).
    assert abs(sm["sigma0_sq_mean"] - 1) < 4 * np.sqrt(2 / mc.dof / N)
    assert sm["sigma0_sq_std"] == pytest.approx(np.sqrt(2 / mc.dof), rel=4 / np.sqrt(2 * (N - 1)))
    for name, a in sm["aps"].items():
        # Sample sigma of N normal draws: relative sigma 1/sqrt(2 (N - 1)).
        assert abs(a["ratio"] - 1) < 4 / np.sqrt(2 * (N - 1)), (name, a["ratio"])
        assert abs(a["bias"]) < 4 * a["formal_sigma"] / np.sqrt(N), (name, a["bias"])


def test_power_of_absent_term_is_the_size(mc):
    # B7 is not in the data: |t| > t_crit happens in alpha of the realisations (binomial).
    p = mc.summary()["aps"]["B7"]["power"]
    assert abs(p - 0.05) < 4 * np.sqrt(0.05 * 0.95 / N)
    assert mc.summary()["aps"]["B6"]["power"] == 1.0


def test_table_and_plot(mc, tmp_path):
    text = mc.table()
    assert "mm" in text and '"' in text and "B7" in text
    fig = tj.plot_monte_carlo(mc, tmp_path / "mc.png")
    assert (tmp_path / "mc.png").stat().st_size > 1000
    labels = [ax.get_xlabel() for ax in fig.axes]
    assert any("[mm]" in s for s in labels) and any('["]' in s for s in labels)


def test_failed_realisations_report_codes_and_do_not_stop_the_batch(design, model):
    r = monte_carlo(
        design, model, MonteCarloOptions(runs=7, chunk_size=4, max_iterations=1, progress=False)
    )
    assert r.runs == 7 and np.all(r.result == 1) and np.all(np.isnan(r.ap_values))
    assert r.failures() == {tj.RESULT_MESSAGES[1]: 7}


def test_true_aps_drawn_from_distribution(design, model):
    s = 1e-3
    r = monte_carlo(
        design, model, MonteCarloOptions(runs=60, chunk_size=60, ap_sigma={"A0": s}, progress=False)
    )
    a0 = r.true_aps[:, 0]
    assert np.std(a0, ddof=1) == pytest.approx(s, rel=4 / np.sqrt(2 * 59))
    assert np.all(r.true_aps[:, 1] == design.true_aps["B6"])
    # The estimates follow the drawn truth, not the nominal value.
    assert np.max(np.abs(r.ap_values[:, 0] - a0) / r.ap_sigmas[:, 0]) < 5
    with pytest.raises(ValueError, match="ap_sigma"):
        monte_carlo(design, model, MonteCarloOptions(runs=2, ap_sigma={"B9": 1.0}))


# ------------------------------------------------------------------------------------------
# Compatibility test


@pytest.fixture(scope="module")
def sets(mc):
    n = mc.ap_names
    return APSet(n, mc.ap_values[0], mc.ap_covariance[0]), APSet(
        n, mc.ap_values[1], mc.ap_covariance[1]
    )


def test_null_distribution_has_the_nominal_size(sets):
    # Under the null the propagated T_i ~ chi2(3) exactly (linear in the APs), so every check
    # point is significant with probability alpha: the mean null share is alpha. This checks
    # the autodiff covariance propagation through correction, conversion and the rigid fit.
    s1, s2 = sets
    r = compatibility_test(
        s1, s2, ROOM, options=CompatibilityOptions(runs=400, chunk_size=100, progress=False)
    )
    assert r.n_failed == 0
    # Shares of one simulation are strongly correlated: their sd is at most sqrt(alpha(1-alpha)).
    assert abs(np.mean(r.null_shares) - 0.05) < 4 * np.sqrt(0.05 * 0.95 / 400)
    assert r.compatible and r.median_share <= r.null_quantile
    assert 0 < r.p_value <= 1


def test_identical_and_clearly_different_sets(sets):
    s1, _ = sets
    opts = CompatibilityOptions(runs=100, chunk_size=50, progress=False)
    same = compatibility_test(s1, s1, ROOM, options=opts)
    assert np.all(same.shares == 0) and same.compatible and same.rms_mm[3] < 1e-9
    assert same.naive_chi2 == pytest.approx(0.0, abs=1e-12)
    v = s1.values.copy()
    v[1] += 30 * np.sqrt(s1.covariance[1, 1])  # collimation B6 changed by 30 sigma
    diff = compatibility_test(s1, APSet(s1.names, v, s1.covariance), ROOM, options=opts)
    assert not diff.compatible and diff.p_value < 0.05 and diff.median_share > 0.5
    assert not diff.naive_compatible
    # Naive chi2 by hand: delta^T (C1 + C2)^-1 delta.
    d = s1.values - v
    chi2 = d @ np.linalg.solve(2 * s1.covariance, d)
    assert diff.naive_chi2 == pytest.approx(chi2, rel=1e-9)
    assert diff.naive_p_value == pytest.approx(stats.chi2.sf(chi2, 4), rel=1e-9)


def test_absent_terms_are_zero_with_zero_variance(sets):
    s1, _ = sets
    sub = APSet(("A0", "C0"), s1.values[[0, 3]], s1.covariance[np.ix_([0, 3], [0, 3])])
    v, C = sub.on(("A0", "B6", "B7", "C0"))
    assert v[1] == v[2] == 0 and np.all(C[1:3] == 0) and C[0, 0] == s1.covariance[0, 0]
    r = compatibility_test(
        s1, sub, ROOM, options=CompatibilityOptions(runs=20, chunk_size=20, progress=False)
    )
    assert r.ap_names == ("A0", "B6", "B7", "C0") and r.n_failed == 0


def test_json_input(tmp_path, sets):
    s1, _ = sets
    doc = {
        "sigma0": 1.0,
        "aps": {
            n: {"value": float(v), "sigma": float(np.sqrt(s1.covariance[k, k])), "unit": "m"}
            for k, (n, v) in enumerate(zip(s1.names, s1.values))
        },
    }
    p = tmp_path / "a.json"
    p.write_text(json.dumps(doc))
    a = APSet.from_json(p)
    np.testing.assert_allclose(a.covariance, np.diag(np.diag(s1.covariance)))
    doc["ap_covariance"] = s1.covariance[::-1, ::-1].tolist()
    doc["ap_covariance_names"] = list(s1.names[::-1])
    p.write_text(json.dumps(doc))
    np.testing.assert_allclose(APSet.from_json(p).covariance, s1.covariance)
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"aps": {"A0": {"value": 1.0}}}))
    with pytest.raises(ValueError, match="bad.json"):
        APSet.from_json(bad)
    with pytest.raises(ValueError, match="nothere.json"):
        APSet.from_json(tmp_path / "nothere.json")
