"""The plane adjustment is the rigorous Gauss-Helmert solution (SPEC section 4; issue 30).

Small plane networks with oblique planes are drawn at random (tests/networks.py drawers,
derandomised) and adjusted by ``tj.calibrate`` and by the dense textbook Gauss-Helmert
adjustment of ``helpers.dense_gauss_helmert`` (full A and B, linearised at ``l + v``, hard
unit-normal constraints and inner constraints in a bordered system), started from the truth.
APs agree to 1e-6 of their sigma, their sigmas and sigma0 to 1e-6 relatively, the residuals and
redundancy numbers of every observation to 1e-6 of a sigma, and the degrees of freedom exactly.
"""

import numpy as np
from helpers import dense_gauss_helmert
from hypothesis import given, settings
from hypothesis import strategies as st
from networks import HypothesisDrawer, examples, oblique_case

import tlsjax as tj

APS = ("A0", "B6", "B7", "C0")  # the APs of networks.oblique_case


def _oracle_start(sim):
    return np.concatenate(
        [sim.true_planes.reshape(-1), sim.true_eops.reshape(-1), np.zeros(len(APS))]
    )


@settings(max_examples=examples(3))
@given(st.composite(lambda draw: oblique_case(HypothesisDrawer(draw)))())
def test_plane_calibration_is_the_rigorous_gauss_helmert_solution(case):
    design, seed = case
    sim = tj.simulate_design(design, seed=seed)
    res = tj.calibrate(
        sim.network, tj.CalibrationModel(sim.scanner), tj.SolverOptions(tolerance=1e-10)
    )
    assert res.result == 0, res.message
    ref = dense_gauss_helmert(sim.network, APS, _oracle_start(sim))
    assert ref["iterations"] < 40
    assert res.dof == ref["dof"]
    assert res.n_constraints == len(sim.network.planes)
    assert res.n_observations == 3 * ref["n_points"] + int(
        np.isfinite(sim.network.levelling_sigma).sum()
    )
    s0 = np.sqrt(ref["vtpv"] / ref["dof"])
    np.testing.assert_allclose(res.sigma0, s0, rtol=1e-6)
    a = slice(-len(APS), None)
    sig = s0 * np.sqrt(np.diag(ref["Q"])[a])
    np.testing.assert_allclose((res.ap_values - ref["x"][a]) / sig, 0.0, atol=1e-6)
    np.testing.assert_allclose(res.ap_sigmas, sig, rtol=1e-6)
    m = ref["n_points"]
    sigmas = np.asarray(sim.network.plane_sigmas)
    np.testing.assert_allclose(
        res.plane_residuals / sigmas, ref["v"][: 3 * m].reshape(m, 3) / sigmas, atol=1e-6
    )
    np.testing.assert_allclose(res.plane_redundancy, ref["r"][: 3 * m].reshape(m, 3), atol=1e-6)
    # Redundancy numbers sum to the degrees of freedom (points and levelling).
    np.testing.assert_allclose(ref["r"].sum(), ref["dof"], rtol=1e-9)
    np.testing.assert_allclose(res.to_dict()["redundancy"]["total"]["sum"], res.dof, rtol=1e-9)
