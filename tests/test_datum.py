"""Datums other than inner constraints, and several instruments in one adjustment (SPEC 2, 6)."""

import numpy as np

import tlsjax as tj


def _rows(net):
    return [net.scans[j] for j in net.scan_index], [net.targets[t] for t in net.target_index]


def _levelling(net):
    return {
        s: {
            "omega": net.levelling[j, 0],
            "phi": net.levelling[j, 1],
            "sigma_omega": net.levelling_sigma[j, 0],
            "sigma_phi": net.levelling_sigma[j, 1],
        }
        for j, s in enumerate(net.scans)
        if net.is_levelled[j]
    }


def test_control_points_fix_position_orientation_and_scale():
    """Noiseless data with control at the true coordinates: the control datum puts the targets
    at the truth (no datum shift to remove) and makes the range scale A1 estimable."""
    aps = "A0 A1 B6 B7 C0"
    sim = tj.simulate(tj.Room(n_targets=36), seed=7, aps=aps, noise=False)
    net = sim.network
    scans, targets = _rows(net)
    control = {net.targets[i]: (sim.true_targets[i], 1e-3) for i in range(0, 36, 6)}
    cnet = tj.make_network(
        scans,
        targets,
        net.observations,
        sigmas=net.sigmas,
        levelling=_levelling(net),
        control=control,
    )
    res = tj.calibrate(cnet, tj.CalibrationModel(tj.Scanner(aps=aps)))
    assert res.result == 0 and res.datum == "control", res.message
    np.testing.assert_allclose(
        res.ap_values, [sim.true_aps[n] for n in res.ap_names], rtol=1e-7, atol=1e-12
    )
    np.testing.assert_allclose(res.target_xyz, sim.true_targets, atol=1e-8)
    np.testing.assert_allclose(res.eops, sim.true_eops, atol=1e-8)
    # 6 control points x 3 coordinates are observations; no datum defect remains.
    assert res.n_observations == 3 * len(net.scan_index) + 18 + int(net.is_levelled.sum()) * 2
    assert res.dof == res.n_observations - res.n_unknowns
    assert np.isclose(res.to_dict()["redundancy"]["total"]["sum"], res.dof, rtol=1e-9)


def test_two_instruments_get_their_own_ap_blocks():
    """Two scanners observe the same targets from the same stations; noiseless data made with
    different true APs. Each block recovers its own truth."""
    a = tj.simulate(tj.Room(n_targets=36), seed=8, aps="A0 B7 C0", noise=False)
    b = tj.simulate(
        tj.Room(n_targets=36),
        seed=8,
        aps="A0 B7 C0",
        noise=False,
        true_aps={"A0": -0.004, "B7": 0.0002, "C0": -0.0005},
    )
    np.testing.assert_array_equal(a.true_targets, b.true_targets)
    sa, ta = _rows(a.network)
    sb, tb = _rows(b.network)
    sb = [s + "b" for s in sb]
    lev = {**_levelling(a.network), **{s + "b": v for s, v in _levelling(b.network).items()}}
    net = tj.make_network(
        sa + sb,
        ta + tb,
        np.concatenate([a.network.observations, b.network.observations]),
        sigmas=np.concatenate([a.network.sigmas, b.network.sigmas]),
        instruments=["A"] * len(sa) + ["B"] * len(sb),
        levelling=lev,
    )
    scanner = tj.Scanner(aps="A0 B7 C0")
    res = tj.calibrate(net, tj.CalibrationModel({"A": scanner, "B": scanner}))
    assert res.result == 0, res.message
    assert res.ap_names == ("A0[A]", "B7[A]", "C0[A]", "A0[B]", "B7[B]", "C0[B]")
    truth = [a.true_aps[n] for n in ("A0", "B7", "C0")] + [
        b.true_aps[n] for n in ("A0", "B7", "C0")
    ]
    np.testing.assert_allclose(res.ap_values, truth, rtol=1e-7, atol=1e-12)
