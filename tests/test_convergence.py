"""Convergence, rank decisions and the inner-constraint cofactor on networks the default room
does not cover: sigmas scaled by any factor, noise-free data, one-station designs, failures.

Independent sources: the same observations with ordinary sigmas (scale invariance of every
estimable quantity), the simulated truth, and a dense bordered inverse of the normal matrix
written out by hand (tests/helpers.py)."""

import dataclasses

import jax
import numpy as np
import pytest
from helpers import _constraints, dense_residuals

import tlsjax as tj

APS = ("A0", "B6", "B7", "C0")
DEG = np.pi / 180


@pytest.fixture(scope="module")
def room():
    sim = tj.simulate(seed=0, aps=" ".join(APS), tilted=True)
    model = tj.CalibrationModel(tj.Scanner(aps=APS))
    return sim, model, tj.calibrate(sim.network, model)


def _scaled(net, f):
    return dataclasses.replace(net, sigmas=net.sigmas * f, levelling_sigma=net.levelling_sigma * f)


@pytest.mark.parametrize("factor", [1e-9, 1e-6, 1e6])
def test_scaling_all_sigmas_changes_nothing_estimable(room, factor):
    sim, model, ref = room
    res = tj.calibrate(_scaled(sim.network, factor), model)
    assert res.result == tj.ResultCode.SUCCESS, res.message
    assert res.iterations == ref.iterations
    np.testing.assert_allclose(res.ap_values, ref.ap_values, rtol=1e-9)
    # s0 scales with 1/factor, the a posteriori sigmas do not change.
    assert np.isclose(res.sigma0 * factor, ref.sigma0, rtol=1e-9)
    np.testing.assert_allclose(res.ap_sigmas, ref.ap_sigmas, rtol=1e-9)
    np.testing.assert_allclose(res.redundancy, ref.redundancy, atol=1e-9)


@pytest.mark.parametrize("factor", [1.0, 1e-6, 1e6])
def test_noise_free_data_converge_to_the_truth(factor):
    sim = tj.simulate(seed=1, aps=" ".join(APS), tilted=True, noise=False)
    res = tj.calibrate(_scaled(sim.network, factor), tj.CalibrationModel(tj.Scanner(aps=APS)))
    assert res.result == tj.ResultCode.SUCCESS, res.message
    truth = np.array([sim.true_aps[a] for a in APS])
    np.testing.assert_allclose(res.ap_values, truth, rtol=1e-8, atol=1e-12)
    assert res.sigma0 < 1e-6 / factor  # rounding level, not noise


def test_one_station_names_the_aps_it_cannot_determine(room):
    sim, model, _ = room
    net = sim.network
    keep = np.isin(net.scan_index, [0, 1])  # two scans of the first station, kappa 0 and 60 deg
    two = tj.make_network(
        [net.scans[i] for i in net.scan_index[keep]],
        [net.targets[i] for i in net.target_index[keep]],
        net.observations[keep],
        sigmas=net.sigmas[keep],
    )
    res = tj.calibrate(two, model)
    assert res.result == tj.ResultCode.NOT_ESTIMABLE, res.message
    named = {n: reason for n, _, reason in res.not_estimable}
    # One station: every term that depends on the direction of the line of sight only moves
    # all targets the same way in both scans, and the targets absorb it.
    assert set(named) == set(APS)
    assert all("absorbed by the target" in r for r in named.values())
    assert np.all(np.isnan(res.ap_values)) and np.all(np.isnan(res.ap_sigmas))


def test_failure_comes_with_a_diagnosis(room):
    sim, model, _ = room
    net = sim.network
    obs = net.observations.copy()
    rows = np.flatnonzero(net.scan_index == 4)
    # Scan S5's ranges 0.2 % too long: the approximate values still register it (a few cm of
    # misfit), but no model fits it.
    obs[rows, 0] *= 1.002
    res = tj.calibrate(net.with_observations(obs), model, tj.SolverOptions(max_iterations=2))
    assert res.result == tj.ResultCode.MAX_ITERATIONS
    s0 = res.diagnosis["sigma0_per_scan"]
    assert max(s0, key=s0.get) == "S5"
    assert "scan S5" in res.message
    assert res.diagnosis["largest_misclosures"][0]["scan"] == "S5"


def test_inner_constraint_cofactor_equals_dense_bordered_inverse_on_the_full_room():
    """The full Chow room (120 targets, 6 levelled scans, no levelling observations): the
    cofactor matrix of all unknowns (dense path) and its blocks (default path: target and pose
    sigmas, AP correlations with every unknown) against ``[[N, G], [G^T, 0]]^-1`` with N and G
    at the final estimate, to 1e-8."""
    sim = tj.simulate(seed=0, aps=" ".join(APS), tilted=False, levelling=False)
    net = sim.network
    model = tj.CalibrationModel(tj.Scanner(aps=APS))
    full = tj.calibrate(net, model, tj.SolverOptions(full_covariance=True))
    blocks = tj.calibrate(net, model)
    n_t, n_s = len(net.targets), len(net.scans)
    x = np.concatenate([full.target_xyz.reshape(-1), full.eops.reshape(-1), full.ap_values])
    J = np.asarray(jax.jacfwd(lambda z: dense_residuals(z, net, APS, n_t, n_s))(x))
    u = x.size
    G = _constraints(x, n_t, u, list(range(6)))
    B = np.block([[J.T @ J, G], [G.T, np.zeros((6, 6))]])
    Q = np.linalg.inv(B)[:u, :u] * full.sigma0**2
    scale = np.abs(Q).max()
    np.testing.assert_allclose(full.covariance, Q, rtol=1e-8, atol=1e-8 * scale)
    s = np.sqrt(np.diag(Q))
    np.testing.assert_allclose(blocks.target_sigmas.reshape(-1), s[: 3 * n_t], rtol=1e-8)
    np.testing.assert_allclose(
        blocks.eop_sigmas.reshape(-1), s[3 * n_t : 3 * n_t + 6 * n_s], rtol=1e-8
    )
    R = Q / np.outer(s, s)
    for k in range(len(APS)):
        row = np.abs(R[u - len(APS) + k])
        row[u - len(APS) + k] = 0.0
        assert np.isclose(blocks.ap_max_abs_corr[k], row.max(), atol=1e-8)
        assert blocks.ap_max_corr_with[k] == full.parameter_names[int(row.argmax())]


def test_damped_steps_hold_what_the_targets_absorb():
    """Four scans from one levelled station, noise 3.3 times the sigmas: A0, B7 and C0 are
    absorbed by the targets. A damped step must hold them as the undamped rank test found
    them (with damped target blocks the Schur complement hides the dependency, and the steps
    wandered along it: "did not converge" even after 200 iterations)."""
    st = (11.573, 4.891, 1.205)
    scans = ((*st, 0, 0, 0.0), (*st, 0, 0, 3.584), (*st, 0, 0, 0.0), (*st, 0, 0, 0.0))
    design = tj.NetworkDesign(
        room=(24.44, 11.27, 3.67),
        scans=scans,
        n_targets=24,
        common_targets=True,
        aps=APS,
        levelling=True,
        elevation_limits=(-89 * DEG, 89 * DEG),
        max_incidence=85 * DEG,
        noise_scale=3.336,
    )
    sim = tj.simulate_design(design, seed=0)
    res = tj.calibrate(
        sim.network, tj.CalibrationModel(sim.scanner), tj.SolverOptions(max_iterations=200)
    )
    assert res.result == tj.ResultCode.NOT_ESTIMABLE, res.message
    assert {"A0", "B7", "C0"} <= {n for n, _, _ in res.not_estimable}
