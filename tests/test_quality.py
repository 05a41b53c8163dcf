"""Masked observations, w-tests and external reliability in the compiled quality (SPEC
section 7), against the dense oracle of tests/helpers.py.

Private imports: the compiled quality (MDB, w-tests, the re-weighted adjustment) is compared
with the dense oracle element by element.
"""

import dataclasses

import jax
import numpy as np
import pytest
from helpers import DELTA0, dense_oracle, dense_residuals, perturbed_start

import tlsjax as tj
from tlsjax._adjustment._quality import minimal_detectable_bias, w_tests
from tlsjax._inference._pipeline import Reweighter

pytestmark = pytest.mark.internal

APS = ("A0", "B6", "B7", "C0")
ROW, COL = 11, 1  # the masked observation


def _oracle_start(res):
    return perturbed_start(res, 1e-4, ap_factor=0.9)


@pytest.fixture(scope="module")
def small():
    sim = tj.simulate(tj.Room(n_targets=12), seed=7, aps=" ".join(APS), tilted=True)
    model = tj.CalibrationModel(tj.Scanner(aps=APS))
    net = sim.network
    rw = Reweighter(net, model, tj.SolverOptions())
    w = 1.0 / net.sigmas
    lw = np.where(np.isfinite(net.levelling_sigma), 1.0 / net.levelling_sigma, 0.0)
    full = rw.run(w, lw, {}).result
    w[ROW, COL] = 0.0
    adjusted = rw.run(w, lw, {})
    res, infl = adjusted.result, adjusted.influence
    # Oracle: an infinite sigma removes the row from the normal equations.
    sig = net.sigmas.copy()
    sig[ROW, COL] = np.inf
    onet = dataclasses.replace(net, sigmas=sig)
    oracle = dense_oracle(onet, APS, _oracle_start(res))
    n_t, ns = len(net.targets), len(net.scans)
    x = oracle[0]
    # Eager (no jit): compiling these unrolled loops costs more than running them once.
    e = np.asarray(dense_residuals(x, net, APS, n_t, ns))
    J = np.asarray(jax.jacfwd(lambda z: dense_residuals(z, onet, APS, n_t, ns))(x))
    return net, full, res, infl, oracle, e, J


def test_masked_observation_matches_dense_oracle_without_it(small):
    net, full, res, _, (x, Q, r, vtpv, dof), e, _ = small
    assert res.ok and full.ok, res.message
    # One observation fewer: dof and the observation count drop by exactly one.
    assert res.dof == full.dof - 1
    assert res.n_observations == full.n_observations - 1
    assert res.redundancy[ROW, COL] == 0.0
    total = res.redundancy.sum() + res.redundancy_levelling.sum() + res.redundancy_prior_sum
    assert np.isclose(total, res.dof, rtol=1e-9)
    # The oracle counts the infinite-sigma row; the structured adjustment does not.
    assert dof - 1 == res.dof
    assert np.isclose(res.sigma0**2, vtpv / (dof - 1), rtol=1e-8)
    n_p, ns = 3 * len(net.targets), len(net.scans)
    np.testing.assert_allclose(res.ap_values, x[n_p + 6 * ns :], rtol=1e-7)
    n = res.redundancy.size
    keep = np.ones(n, dtype=bool)
    keep[3 * ROW + COL] = False
    np.testing.assert_allclose(res.redundancy.reshape(-1)[keep], r[:n][keep], atol=1e-8)
    # The removed observation's residual is still reported: the misclosure at the solution.
    assert np.isclose(
        res.residuals[ROW, COL], e[3 * ROW + COL] * net.sigmas[ROW, COL], rtol=1e-6, atol=1e-10
    )
    assert abs(res.residuals[ROW, COL]) > 0


def test_w_tests_and_mdb_match_dense_oracle(small):
    net, _, res, _, (x, Q, r, vtpv, dof), e, _ = small
    n = res.redundancy.size
    r_ref = r[:n].reshape(-1, 3)
    keep = np.ones_like(r_ref, dtype=bool)
    keep[ROW, COL] = False
    w_ref = e[:n].reshape(-1, 3) / np.sqrt(r_ref)
    w = w_tests(res.residuals, net.sigmas, res.redundancy)
    np.testing.assert_allclose(w[keep], w_ref[keep], rtol=1e-5, atol=1e-6)
    assert np.isnan(w[ROW, COL])  # removed: redundancy 0, not tested
    mdb = minimal_detectable_bias(net.sigmas, res.redundancy)
    np.testing.assert_allclose(mdb[keep], (DELTA0 * net.sigmas / np.sqrt(r_ref))[keep], rtol=1e-6)
    assert np.isinf(mdb[ROW, COL])  # no error of any size is detected


def test_ap_influence_matches_dense_q_jt(small):
    net, _, res, infl, (x, Q, r, vtpv, dof), _, J = small
    n_t, ns = len(net.targets), len(net.scans)
    J = J[: 3 * len(net.observations)]
    a = slice(3 * n_t + 6 * ns, None)
    # AP change for a one-sigma error in observation i: Q_(a, .) J_i^T, in a priori AP sigmas.
    ref = (Q[a] @ J.T / np.sqrt(np.diag(Q)[a])[:, None]).T.reshape(-1, 3, len(APS))
    np.testing.assert_allclose(np.abs(infl), np.abs(ref), rtol=1e-6, atol=1e-9)
    assert np.all(infl[ROW, COL] == 0.0)
    assert np.abs(infl).max() > 0.01
