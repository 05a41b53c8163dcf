"""Data snooping, internal and external reliability of plane points (SPEC sections 4 and 7):
one Gauss-Helmert condition per point, screened and snooped by :func:`tlsjax.self_calibrate`
with the same critical values and removal rules as target observations; checked against gross
errors planted at random points, against the identity ``w_i^2 = v^T P v - (v^T P v without
point i)`` (the w-test is the score test of one more parameter, SPEC section 7), and in the
residual plot.

Private imports: ``tlsjax._report._plots._rows`` (the rows the residual plot draws).
"""

import dataclasses

import numpy as np
import pytest

import tlsjax as tj

SIGMA_FACTOR = 20.0  # size of the planted gross errors, in sigmas of the range


@pytest.fixture(scope="module")
def planted():
    """A 6-scan plane room, 1 % of its points with a 20-sigma range error at random rows."""
    pc = tj.simulate_point_clouds(tj.CloudDesign(angular_step=np.radians(1.0)), seed=1)
    net = pc.to_network(max_points=16, seed=0)
    rng = np.random.default_rng(2)
    m = net.plane_observations.shape[0]
    bad = np.sort(rng.choice(m, round(0.01 * m), replace=False))
    obs = net.plane_observations.copy()
    error = rng.choice([-1.0, 1.0], len(bad)) * SIGMA_FACTOR * net.plane_sigmas[bad, 0]
    obs[bad, 0] += error
    bnet = dataclasses.replace(net, plane_observations=obs)
    model = tj.CalibrationModel(pc.scanner)
    snooping = tj.CalibrationOptions(snooping=tj.SnoopingOptions())
    return pc, net, bnet, bad, model, tj.self_calibrate(bnet, model, snooping)


def test_planted_gross_errors_are_all_found_with_few_false_removals(planted):
    pc, net, _, bad, _, tested = planted
    res = tested.calibration
    assert tested.ok and res.ok, tested.message
    points = [o for o in tested.outliers if o.group == "plane"]
    found = {o.row for o in points}
    assert set(bad.tolist()) <= found  # none of the planted ones left in
    # Screening (family-wise level 0.1 %) takes every planted one and no clean point; the
    # snooping after it (3.29 per test) may take clean points at its level: alpha per point.
    screened = {o.row for o in points if o.reason.startswith("screening")}
    assert screened == set(bad.tolist())
    n_clean = net.plane_observations.shape[0] - len(bad)
    expected = tested.options.w_test_level * n_clean
    assert len(found - set(bad.tolist())) <= expected + 3 * np.sqrt(expected) + 1
    # The removed points have weight 0 and no test; the others a finite w below the critical
    # value, an MDB and an external reliability.
    mask = tested.plane_mask
    assert not mask[sorted(found)].any() and mask.sum() == len(mask) - len(found)
    assert not res.plane_used[~mask].any() and res.plane_used[mask].all()
    assert np.all(np.isnan(tested.plane_w[~mask]))
    assert np.nanmax(np.abs(tested.plane_w)) <= tested.critical_value
    # The range MDB is finite; an angle the condition does not depend on (hz on a horizontal
    # plane) has none: no error of it is detected.
    mdb = tested.plane_mdb[mask]
    assert np.all(np.isfinite(mdb[:, 0])) and np.all(mdb > 0)
    assert np.all(np.isfinite(tested.plane_external[mask]))
    assert set(tested.plane_external_ap[mask]) <= set(res.ap_names)
    # The a priori test after screening accepts the sigmas; the APs hold their truth.
    assert tested.a_priori_tests[-1]["global"]["accepted"]
    truth = np.array([pc.true_aps[a] for a in res.ap_names])
    assert np.all(np.abs(res.ap_values - truth) < 4 * res.ap_sigmas)


@pytest.mark.internal
def test_removed_points_keep_their_misfit_in_the_residuals_and_the_plot(planted, tmp_path):
    from tlsjax._report._plots import _rows

    _, _, _, bad, _, tested = planted
    res = tested.calibration
    v = res.plane_residuals[bad]
    # Not the 0 of a zero weight: each point's residuals at the final unknowns, whose
    # whitened condition is near the 20 sigmas planted (the angles absorb a share of it).
    e = np.sqrt(np.sum((v / res.network.plane_sigmas[bad]) ** 2, axis=1))
    assert np.all(e > 0.5 * SIGMA_FACTOR) and np.all(e < 1.5 * SIGMA_FACTOR)
    l, vp, used = _rows(res)
    assert not used[bad].any() and np.array_equal(vp[bad], v)
    path = tj.plot_residuals(res, tmp_path / "planes.png", mask=tested.mask)
    assert path.exists() and path.stat().st_size > 0


def test_plane_w_squared_is_the_drop_of_vtpv_without_the_point(planted):
    """Baarda's w-test of a condition is the score test of one more parameter on it:
    ``w_i^2`` equals the reduction of ``v^T P v`` when point i is left out (exact in the
    linear model; to 1e-3 here, the Gauss-Helmert conditions are slightly nonlinear)."""
    _, net, _, _, model, _ = planted
    options = tj.CalibrationOptions(screening=None, plane_screening=None)
    tested = tj.self_calibrate(net, model, options)
    res = tested.calibration
    omega = res.sigma0**2 * res.dof
    adj = tj.analyze(net, model)
    for k in np.argsort(-np.abs(np.nan_to_num(tested.plane_w)))[:3]:
        weight = 1.0 / net.plane_sigmas
        weight[k] = 0.0
        without = adj.solve(plane_weights=weight)
        assert without.dof == res.dof - 1
        drop = omega - without.sigma0**2 * without.dof
        np.testing.assert_allclose(drop, tested.plane_w[k] ** 2, rtol=1e-3)
