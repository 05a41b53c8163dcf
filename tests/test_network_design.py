"""One design description: a NetworkDesign, and the older design types built from it
(``Room.from_design``, ``CloudDesign.from_design``, ``TargetDesign.from_design``,
``PlaneDesign.from_design``) and the entry functions that take it (``simulate``,
``simulate_point_clouds``) reproduce the same geometry, scanner and truth."""

import dataclasses

import numpy as np
import pytest

import tlsjax as tj

DEG = np.pi / 180

#: The scans of the default Room written out (three per station, 60 deg apart in kappa, the
#: second station 20 deg further; tilted: its scans 2 and 3 rolled by -45 and +45 deg).
ROOM_SCANS = (
    (4.5, 4.0, 1.6, 0.0, 0.0, 0.0),
    (4.5, 4.0, 1.6, 0.0, 0.0, 60 * DEG),
    (4.5, 4.0, 1.6, 0.0, 0.0, 120 * DEG),
    (9.5, 7.0, 1.6, 0.0, 0.0, 20 * DEG),
    (9.5, 7.0, 1.6, -45 * DEG, 0.0, 80 * DEG),
    (9.5, 7.0, 1.6, 45 * DEG, 0.0, 140 * DEG),
)


def test_room_from_design_has_the_box_and_the_stations():
    nd = tj.NetworkDesign(room=(10.0, 8.0, 3.5), scans=ROOM_SCANS[:1] + ((6.0, 5.0, 1.2, 0, 0, 1),),
                          n_targets=40, margin=0.4)  # fmt: skip
    room = tj.Room.from_design(nd)
    assert (room.length, room.width, room.height, room.margin) == (10.0, 8.0, 3.5, 0.4)
    assert room.stations == ((4.5, 4.0, 1.6), (6.0, 5.0, 1.2)) and room.n_targets == 40


def test_simulate_of_a_design_is_the_room_simulation_of_its_scans():
    nd = tj.NetworkDesign(scans=ROOM_SCANS, n_targets=120, aps="A0 B6 B7 C0")
    a = tj.simulate(nd, seed=4)
    b = tj.simulate(tj.Room(), tilted=True, aps="A0 B6 B7 C0", seed=4)
    np.testing.assert_allclose(a.true_eops, b.true_eops, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(a.true_targets, b.true_targets)
    np.testing.assert_allclose(a.network.observations, b.network.observations, rtol=0, atol=1e-12)
    assert a.true_aps == b.true_aps and np.array_equal(a.network.levelling, b.network.levelling)
    # The design's scanner, true APs, noise switch and sigmas reach the simulation.
    nd2 = dataclasses.replace(nd, architecture="panoramic", aps=("A0", "C0"),
                              true_aps={"A0": 2e-3}, noise_scale=0.0, sigma_range=1e-3)  # fmt: skip
    c = tj.simulate(nd2, seed=4)
    d = tj.simulate(tj.Room(), architecture="panoramic", aps="A0 C0", true_aps={"A0": 2e-3},
                    noise=False, sigma_range=1e-3, seed=4)  # fmt: skip
    assert c.scanner.architecture == "panoramic" and c.true_aps["A0"] == 2e-3
    np.testing.assert_allclose(c.network.observations, d.network.observations, rtol=0, atol=1e-12)
    np.testing.assert_array_equal(c.network.sigmas, d.network.sigmas)


def test_simulate_refuses_settings_beside_a_design_and_what_it_cannot_reproduce():
    nd = tj.NetworkDesign(scans=ROOM_SCANS, n_targets=60)
    with pytest.raises(ValueError, match="architecture comes from the design"):
        tj.simulate(nd, architecture="panoramic")
    with pytest.raises(ValueError, match="tilted comes from the design"):
        tj.simulate(nd, tilted=False)
    with pytest.raises(ValueError, match="simulate_design"):
        tj.simulate(dataclasses.replace(nd, n_free_targets=3))
    with pytest.raises(ValueError, match="noise_scale 1 or 0"):
        tj.simulate(dataclasses.replace(nd, noise_scale=2.0))


def test_point_clouds_of_a_design_are_those_of_its_cloud_design():
    step = 2.5 * DEG
    ref = tj.CloudDesign(angular_step=step, aps=("A0", "B6"))
    nd = tj.NetworkDesign(scans=ROOM_SCANS, planes=ref.boards, aps=("A0", "B6"),
                          elevation_limits=ref.elevation_limits,
                          max_incidence=ref.max_incidence)  # fmt: skip
    cd = tj.CloudDesign.from_design(nd, angular_step=step)
    assert cd.room.stations == ref.room.stations and cd.boards == ref.boards
    a = tj.simulate_point_clouds(cd, seed=2)
    b = tj.simulate_point_clouds(ref, seed=2)
    np.testing.assert_allclose(a.eops, b.eops, rtol=0, atol=1e-15)
    assert a.plane_names == b.plane_names and a.true_aps == b.true_aps
    for oa, ob in zip(a.observations, b.observations):
        np.testing.assert_allclose(oa, ob, rtol=0, atol=1e-12)
    # Scans of the design's own (two scans, one tilted): only those are rendered.
    nd2 = dataclasses.replace(nd, scans=(ROOM_SCANS[0], ROOM_SCANS[4]))
    c = tj.simulate_point_clouds(tj.CloudDesign.from_design(nd2, angular_step=step), seed=2)
    np.testing.assert_allclose(c.eops, np.array([ROOM_SCANS[0], ROOM_SCANS[4]]), atol=1e-15)
    assert list(c.levelling) == ["S1"]  # the levelled scan only
    with pytest.raises(ValueError, match="only Board planes"):
        tj.CloudDesign.from_design(
            dataclasses.replace(nd, planes=(tj.RoomPlane((0, 0, 1), (1, 1, 1)),))
        )


def test_target_and_plane_designs_of_a_design():
    nd = tj.NetworkDesign(room=(12.0, 9.0, 3.0), scans=ROOM_SCANS[:2] + ROOM_SCANS[4:5],
                          n_targets=24, common_targets=True, faces_as_planes=True,
                          aps=("A0", "B6"), true_aps={"B6": 1e-4}, sigma_scale=2.0)  # fmt: skip
    td = tj.TargetDesign.from_design(nd, seed=1)
    np.testing.assert_allclose(td.eops, np.array(nd.scans), rtol=0, atol=0)
    X, n = np.asarray(td.targets), np.asarray(td.normals)
    assert X.shape == (24, 3)
    # Each target on a face of the box, with the face's inward unit normal.
    size = np.array(nd.room)
    for x, nrm in zip(X, n):
        ax = int(np.flatnonzero(nrm)[0])
        assert x[ax] == (0.0 if nrm[ax] > 0 else size[ax]) and abs(nrm[ax]) == 1.0
    np.testing.assert_allclose(td.aps, [0.010, 1e-4])  # A0 at its default, B6 as given
    assert float(td.sigma_range) == pytest.approx(2 * 0.5e-3)  # a priori: sigma_scale x nominal
    pd = tj.PlaneDesign.from_design(nd, seed=1)
    expected = {(1, 0, 0, 0), (-1, 0, 0, -12), (0, 1, 0, 0), (0, -1, 0, -9), (0, 0, 1, 0),
                (0, 0, -1, -3)}  # fmt: skip
    assert {tuple(float(v) for v in p) for p in np.asarray(pd.planes)} == expected
    np.testing.assert_allclose(pd.eops, td.eops, rtol=0, atol=0)
    # The target design drives DesignProblem: a noise-free network calibrates to its truth.
    scanner = tj.Scanner(architecture="hybrid", aps=("A0", "B6"))
    dn = tj.DesignProblem.targets(td, scanner)
    res = tj.calibrate(dn.network(td), dn.model)  # no seed: no noise
    assert res.ok
    np.testing.assert_allclose(res.ap_values, [0.010, 1e-4], rtol=0, atol=1e-9)


def test_monte_carlo_draws_from_a_design():
    # A0 only and no noise: every plane row's range is the distance from its scan's station to
    # its true point plus A0, which fixes the truth's row order; the points lie on their planes.
    nd = tj.NetworkDesign(n_targets=30, faces_as_planes=True, aps=("A0",), noise_scale=0.0)
    truth = tj.simulate_design(nd, seed=2).truth()
    net = truth.network
    rho = np.linalg.norm(truth.plane_points - truth.eops[net.plane_scan_index, :3], axis=1)
    np.testing.assert_allclose(net.plane_observations[:, 0] - rho, 0.010, rtol=0, atol=1e-12)
    P = truth.planes[net.plane_index]
    np.testing.assert_allclose(np.sum(P[:, :3] * truth.plane_points, 1), P[:, 3], atol=1e-12)
    opts = tj.MonteCarloOptions(runs=40, progress=False)
    mc = tj.monte_carlo(nd, tj.CalibrationModel(tj.Scanner(aps=("A0",))), opts).to_dict()
    assert mc["successful"] == 40
    a0 = mc["aps"]["A0"]
    assert a0["truth_mean"] == 0.010 and abs(a0["bias"]) < 4 * a0["formal_sigma"] / np.sqrt(40)
