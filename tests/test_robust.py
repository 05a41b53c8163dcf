"""Outlier screening of plane networks (IGG-III on the Gauss-Helmert conditions), checked
against the blunders put into simulated data and the simulated truth.

Private imports: ``tlsjax._cli.main`` is the ``tlsjax`` console script's entry point
(pyproject), called in process; the IGG-III weight function; ``ObservationTable`` to build a
plane table.
"""

import dataclasses

import numpy as np
import pytest
from helpers import printed_is_summary, same_run

import tlsjax as tj


@pytest.fixture(scope="module")
def clouds():
    pc = tj.simulate_point_clouds(tj.CloudDesign(angular_step=np.radians(1.0)), seed=1)
    net = pc.to_network(max_points=60, seed=0)
    rng = np.random.default_rng(0)
    bad = rng.choice(net.plane_observations.shape[0], 30, replace=False)
    obs = net.plane_observations.copy()
    obs[bad, 0] += rng.choice([-1, 1], 30) * rng.uniform(0.02, 0.2, 30)  # 2-20 cm off the surface
    return pc, net, dataclasses.replace(net, plane_observations=obs), bad


@pytest.mark.internal
def test_igg3_weights():
    from tlsjax._inference._robust import igg3

    w = np.array([0.0, 1.0, 3.29, 3.8, 4.32, 9.0])
    f = igg3(w, 3.29, 4.32)
    assert np.all(f[:3] == 1.0) and f[4] == 0.0 and f[5] == 0.0
    assert np.isclose(f[3], 3.29 / 3.8 * ((4.32 - 3.8) / (4.32 - 3.29)) ** 2)


@pytest.mark.parametrize("sigma_factor", [1.0, 1 / 40, 40.0])
def test_blunders_on_planes_are_found_whatever_the_sigmas(clouds, sigma_factor):
    pc, _, net, bad = clouds
    net = dataclasses.replace(net, plane_sigmas=net.plane_sigmas * sigma_factor)
    result = tj.self_calibrate(net, tj.CalibrationModel(pc.scanner))
    s = result.plane_screening
    found = set(s.removed.tolist())
    assert set(bad.tolist()) <= found
    assert len(found - set(bad.tolist())) <= 3  # clean points near the family-wise limit
    res = result.calibration
    assert res.ok, res.message
    assert not res.plane_used[s.removed].any()
    truth = np.array([pc.true_aps[a] for a in res.ap_names])
    assert np.all(np.abs(res.ap_values - truth) < 4.5 * res.ap_sigmas)
    # The report counts per scan and plane add up to the removals.
    assert sum(c["removed"] for c in s.per_pair.values()) == len(found)


def test_clean_planes_lose_almost_nothing(clouds):
    pc, net, _, _ = clouds
    result = tj.self_calibrate(net, tj.CalibrationModel(pc.scanner))
    s = result.plane_screening
    plain = tj.calibrate(net, tj.CalibrationModel(pc.scanner))
    assert len(s.removed) <= 2
    assert np.isclose(s.scale, 1.0, atol=0.1)
    # Without removals the final adjustment is the plain one.
    if len(s.removed) == 0:
        np.testing.assert_allclose(result.calibration.ap_values, plain.ap_values, rtol=1e-9)


def test_cli_screens_plane_points_by_default(clouds, tmp_path, capsys):
    import json

    from tlsjax import ObservationTable, write_observations
    from tlsjax._cli import main

    pc, _, net, bad = clouds
    table = ObservationTable(
        kind="plane",
        source="<test>",
        scans=tuple(net.scans[j] for j in net.plane_scan_index),
        primitives=tuple(net.planes[k] for k in net.plane_index),
        observations=net.plane_observations,
        sigmas=net.plane_sigmas,
        incidence=None,
        instruments=None,
        rows=np.arange(len(net.plane_index)),
    )
    path, out = tmp_path / "planes.csv", tmp_path / "r.json"
    write_observations(path, table)
    assert (
        main(["calibrate", "--planes", str(path), "--plane-spacing", "0", "--json", str(out)]) == 0
    )
    printed = capsys.readouterr().out
    assert "plane outlier screening" in printed
    js = json.loads(out.read_text())
    assert js["plane_screening"]["n_removed"] >= len(bad)
    assert js["n_plane_points"] == len(net.plane_index) - js["plane_screening"]["n_removed"]
    # What the command printed and wrote is the entry's result (plane networks: no VCE).
    result = tj.self_calibrate(
        tj.read_network(planes=str(path)), tj.CalibrationModel(), tj.CalibrationOptions(vce=None)
    )
    same_run(js, result.to_dict())
    printed_is_summary(printed, result.summary())
