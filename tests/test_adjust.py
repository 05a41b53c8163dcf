"""The structured adjustment against independent references (SPEC section 7)."""

import numpy as np
import pytest
from helpers import dense_oracle, perturbed_start

import tlsjax as tj

APS = ("A0", "B6", "B7", "C0")


@pytest.fixture(scope="module")
def small():
    sim = tj.simulate(tj.Room(n_targets=24), seed=3, aps=" ".join(APS), tilted=True)
    res = tj.calibrate(
        sim.network,
        tj.CalibrationModel(tj.Scanner(aps=APS)),
        tj.SolverOptions(full_covariance=True),
    )
    return sim, res


def test_structured_equals_dense_bordered_solve(small):
    sim, res = small
    net = sim.network
    assert res.result == 0, res.message
    # Start the oracle from the structured solution perturbed: it must come back to it.
    x0 = perturbed_start(res, 1e-3, eop_shift=1e-4, ap_factor=0.5)
    x, Q, r, vtpv, dof = dense_oracle(net, APS, x0)
    n_p = 3 * len(net.targets)
    ns = len(net.scans)
    assert dof == res.dof
    s0sq = vtpv / dof
    assert np.isclose(res.sigma0**2, s0sq, rtol=1e-8)
    np.testing.assert_allclose(res.ap_values, x[n_p + 6 * ns :], rtol=1e-8)
    np.testing.assert_allclose(res.eops.reshape(-1), x[n_p : n_p + 6 * ns], rtol=1e-8, atol=1e-10)
    np.testing.assert_allclose(res.target_xyz.reshape(-1), x[:n_p], rtol=1e-8, atol=1e-10)
    # Covariance (inner constraints on the targets), sigmas and correlations.
    np.testing.assert_allclose(
        res.covariance, Q * s0sq, rtol=1e-7, atol=1e-8 * np.abs(Q * s0sq).max()
    )
    np.testing.assert_allclose(res.ap_sigmas, np.sqrt(np.diag(Q)[n_p + 6 * ns :] * s0sq), rtol=1e-8)
    s = np.sqrt(np.diag(Q))
    C = Q / np.outer(s, s)
    np.testing.assert_allclose(res.correlation(), C, atol=1e-7)
    # Redundancy numbers of the observations, in network row order.
    np.testing.assert_allclose(
        res.redundancy.reshape(-1), r[: res.redundancy.size], rtol=1e-7, atol=1e-9
    )


def test_redundancy_sum_equals_dof(small):
    _, res = small
    total = res.redundancy.sum() + res.redundancy_levelling.sum() + res.redundancy_prior_sum
    assert np.isclose(total, res.dof, rtol=1e-9)
    assert np.isclose(res.to_dict()["redundancy"]["total"]["sum"], res.dof, rtol=1e-9)
    assert np.all(res.redundancy > -1e-9) and np.all(res.redundancy < 1 + 1e-9)


def test_max_correlation_names_the_partner(small):
    _, res = small
    C = res.correlation()
    names = list(res.parameter_names)
    for k, ap in enumerate(res.ap_names):
        row = np.abs(C[names.index(ap)])
        row[names.index(ap)] = 0
        assert np.isclose(res.ap_max_abs_corr[k], row.max(), rtol=1e-10)
        assert res.ap_max_corr_with[k] == names[int(row.argmax())]


@pytest.mark.parametrize("architecture", ["hybrid", "panoramic"])
def test_noiseless_recovers_truth(architecture):
    sim = tj.simulate(
        seed=5, architecture=architecture, tilted=True, noise=False, aps="chow2013-noscale"
    )
    res = tj.calibrate(sim.network, tj.CalibrationModel(sim.scanner))
    assert res.result == 0, res.message
    truth = np.array([sim.true_aps[n] for n in res.ap_names])
    np.testing.assert_allclose(res.ap_values, truth, rtol=1e-8, atol=1e-12)
    assert res.sigma0 < 1e-6


def test_datum_invariance_inner_vs_fixed_scan():
    sim = tj.simulate(tj.Room(n_targets=36), seed=11, aps=" ".join(APS))
    scanner = tj.Scanner(aps=APS)
    a = tj.calibrate(sim.network, tj.CalibrationModel(scanner))
    b = tj.calibrate(sim.network, tj.CalibrationModel(scanner, datum="fixed-scan", fixed_scan="S4"))
    assert a.result == b.result == 0
    np.testing.assert_allclose(a.ap_values, b.ap_values, rtol=1e-9)
    np.testing.assert_allclose(a.ap_sigmas, b.ap_sigmas, rtol=1e-8)
    assert np.isclose(a.sigma0, b.sigma0, rtol=1e-9) and a.dof == b.dof
    np.testing.assert_allclose(a.residuals, b.residuals, atol=1e-12)
    np.testing.assert_allclose(a.redundancy, b.redundancy, atol=1e-9)


def test_sigma0_close_to_one_and_estimates_within_sigma():
    z = []
    s0 = []
    for seed in range(3):
        sim = tj.simulate(seed=100 + seed, aps=" ".join(APS))
        res = tj.calibrate(sim.network, tj.CalibrationModel(tj.Scanner(aps=APS)))
        s0.append(res.sigma0**2)
        z += list((res.ap_values - np.array([sim.true_aps[n] for n in APS])) / res.ap_sigmas)
    # s0^2 ~ chi2(r)/r with r ~ 1770: its sigma is sqrt(2/r) ~ 0.034.
    assert abs(np.mean(s0) - 1) < 0.1
    assert np.max(np.abs(z)) < 4.5


def test_fixed_aps_equal_the_model_without_them():
    """Holding APs at zero (one compiled shape for every subset) gives the adjustment of the
    model without them: the rank-revealing factorisation drops their columns exactly."""
    sim = tj.simulate(tj.Room(n_targets=36), seed=12, aps=" ".join(APS))
    small = tj.calibrate(sim.network, tj.CalibrationModel(tj.Scanner(aps="A0 B7")))
    wide = tj.calibrate(
        sim.network, tj.CalibrationModel(tj.Scanner(aps=APS), fixed_aps=("B6", "C0"))
    )
    assert wide.result == small.result == 0 and wide.ap_fixed == ("B6", "C0")
    assert wide.dof == small.dof and wide.n_unknowns == small.n_unknowns
    assert np.isclose(wide.sigma0, small.sigma0, rtol=1e-10)
    i = [wide.ap_names.index(a) for a in ("A0", "B7")]
    np.testing.assert_allclose(wide.ap_values[i], small.ap_values, rtol=1e-9)
    np.testing.assert_allclose(wide.ap_sigmas[i], small.ap_sigmas, rtol=1e-9)
    np.testing.assert_allclose(wide.redundancy, small.redundancy, atol=1e-10)
    j = [wide.ap_names.index(a) for a in ("B6", "C0")]
    assert np.all(wide.ap_values[j] == 0) and np.all(wide.ap_sigmas[j] == 0)
    assert "held at 0" in wide.summary()
