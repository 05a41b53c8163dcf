"""Batched Monte Carlo (SPEC section 9); the AP-set compatibility test is in test_compat.py."""

import numpy as np
import pytest

import tlsjax as tj
from tlsjax import MonteCarloOptions, monte_carlo, monte_carlo_network

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
    sm = mc.to_dict()
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
    aps = mc.to_dict()["aps"]
    assert abs(aps["B7"]["power"] - 0.05) < 4 * np.sqrt(0.05 * 0.95 / N)
    assert aps["B6"]["power"] == 1.0


def test_table_and_plot(mc, tmp_path):
    text = mc.table()
    assert "mm" in text and '"' in text and "B7" in text
    assert mc.summary().endswith(text) and f"{N} realisations" in mc.summary()
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
