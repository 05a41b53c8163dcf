"""Bad input gives a clear ValueError that names the scan, target or parameter at fault."""

import dataclasses
import re

import jax.numpy as jnp
import numpy as np
import pytest

import tlsjax as tj


@pytest.fixture(scope="module")
def rows():
    """(scans, targets, observations) of a noiseless 6-scan, 24-target room, row by row."""
    net = tj.simulate(tj.Room(n_targets=24), aps="none", noise=False).network
    scans = np.array([net.scans[j] for j in net.scan_index])
    targets = np.array([net.targets[t] for t in net.target_index])
    return scans, targets, net.observations.copy()


def _make(scans, targets, obs, **kw):
    return tj.make_network(list(scans), list(targets), obs, **kw)


def test_valid_rows_build_a_network(rows):
    scans, targets, obs = rows
    net = _make(scans, targets, obs)
    assert net.scans == ("S1", "S2", "S3", "S4", "S5", "S6")
    assert len(net.targets) == 24 and net.observations.shape == (144, 3)
    assert net.dropped == ()


def test_nan_observation_names_scan_and_target(rows):
    scans, targets, obs = rows
    obs = obs.copy()
    i = 37
    obs[i, 1] = np.nan
    with pytest.raises(ValueError, match=rf"hz of scan {scans[i]}, target {targets[i]}") as e:
        _make(scans, targets, obs)
    assert "finite" in str(e.value)
    obs = rows[2].copy()
    obs[5, 0] = np.inf
    with pytest.raises(ValueError, match=rf"range of scan {scans[5]}, target {targets[5]}"):
        _make(scans, targets, obs)


@pytest.mark.parametrize("value", [0.0, -1.5])
def test_non_positive_range(rows, value):
    scans, targets, obs = rows
    obs = obs.copy()
    i = 60
    obs[i, 0] = value
    with pytest.raises(
        ValueError, match=rf"range of scan {scans[i]}, target {targets[i]} must be positive"
    ):
        _make(scans, targets, obs)


def test_duplicate_rows(rows):
    scans, targets, obs = rows
    s = np.append(scans, scans[10])
    t = np.append(targets, targets[10])
    o = np.vstack([obs, obs[10]])
    with pytest.raises(
        ValueError, match=rf"duplicate observation of target {targets[10]} in scan {scans[10]}"
    ):
        _make(s, t, o)


def test_scan_with_too_few_targets(rows):
    scans, targets, obs = rows
    # S4 keeps only three targets; every target is still seen by S1..S3.
    keep = (scans != "S4") | np.isin(targets, ["T001", "T002", "T003"])
    with pytest.raises(ValueError, match=r"scan S4 observes 3 target\(s\)"):
        _make(scans[keep], targets[keep], obs[keep])
    # With four it is accepted (the SPEC minimum for a pose).
    keep = (scans != "S4") | np.isin(targets, ["T001", "T002", "T003", "T004"])
    net = _make(scans[keep], targets[keep], obs[keep])
    assert np.sum(net.scan_index == net.scans.index("S4")) == 4


def test_target_in_one_scan_only(rows):
    scans, targets, obs = rows
    keep = (targets != "T005") | (scans == "S2")
    s, t, o = scans[keep], targets[keep], obs[keep]
    with pytest.raises(ValueError, match="T005") as e:
        _make(s, t, o)
    assert "drop_single_targets" in str(e.value)
    net = _make(s, t, o, drop_single_targets=True)
    assert net.dropped == ("T005",)
    assert "T005" not in net.targets and len(net.targets) == 23
    assert net.observations.shape == (144 - 6, 3)  # five rows removed above, the last one dropped
    # The remaining rows are unchanged and in order.
    np.testing.assert_array_equal(net.observations, o[t != "T005"])


def test_disconnected_scans(rows):
    scans, targets, obs = rows
    tnum = np.array([int(x[1:]) for x in targets])
    group_a = np.isin(scans, ["S1", "S2", "S3"]) & (tnum <= 12)
    group_b = np.isin(scans, ["S4", "S5", "S6"]) & (tnum > 12)
    keep = group_a | group_b
    with pytest.raises(ValueError, match="disconnected") as e:
        _make(scans[keep], targets[keep], obs[keep])
    msg = str(e.value)
    assert all(s in msg for s in ("S4", "S5", "S6")) and "S2" not in msg.split("disconnected")[0]
    # Two shared targets are still not enough to link the groups (a pose needs three).
    shared = np.isin(scans, ["S4"]) & np.isin(targets, ["T001", "T002"])
    with pytest.raises(ValueError, match="disconnected"):
        _make(scans[keep | shared], targets[keep | shared], obs[keep | shared])
    shared = np.isin(scans, ["S4"]) & np.isin(targets, ["T001", "T002", "T003"])
    net = _make(scans[keep | shared], targets[keep | shared], obs[keep | shared])
    assert len(net.scans) == 6


def test_bad_sigmas(rows):
    scans, targets, obs = rows
    with pytest.raises(ValueError, match="sigma of range"):
        _make(scans, targets, obs, sigma_range=-0.5e-3)
    with pytest.raises(ValueError, match="sigma of hz"):
        _make(scans, targets, obs, sigma_hz=0.0)
    sig = np.full(obs.shape, np.nan)
    i = 77
    sig[i, 2] = -1e-4
    with pytest.raises(ValueError, match=rf"sigma of el \(scan {scans[i]}, target {targets[i]}\)"):
        _make(scans, targets, obs, sigmas=sig)
    with pytest.raises(ValueError, match="sigmas must have shape"):
        _make(scans, targets, obs, sigmas=np.ones((3, 3)))


def test_wrong_observation_shape(rows):
    scans, targets, obs = rows
    with pytest.raises(ValueError, match=re.escape("shape (n, 3)")):
        _make(scans, targets, obs[:, :2])
    with pytest.raises(ValueError, match=re.escape("shape (n, 3)")):
        _make(scans, targets, obs.reshape(-1))
    with pytest.raises(ValueError, match="scan names"):
        _make(scans[:-1], targets, obs)


def test_scanner_errors():
    with pytest.raises(ValueError, match="'x'"):
        tj.Scanner(architecture="x")
    with pytest.raises(ValueError, match="Q9"):
        tj.Scanner(aps="A0 Q9")
    with pytest.raises(ValueError, match="unit_length"):
        tj.Scanner(unit_length=-1.0)


def test_calibration_model_errors(rows):
    with pytest.raises(ValueError, match="bogus"):
        tj.CalibrationModel(datum="bogus")
    with pytest.raises(ValueError, match="fixed_scan"):
        tj.CalibrationModel(datum="fixed-scan")
    scans, targets, obs = rows
    net = _make(scans, targets, obs)
    model = tj.CalibrationModel(datum="fixed-scan", fixed_scan="S99")
    # Validation happens on the host before anything is compiled.
    with pytest.raises(ValueError, match="S99"):
        tj.calibrate(net, model)
    with pytest.raises(ValueError, match="control"):
        tj.calibrate(net, tj.CalibrationModel(datum="control"))


def test_register_ap_errors():
    basis = lambda r, t, a, s: jnp.ones_like(r)  # noqa: E731
    with pytest.raises(ValueError, match="Zbadgroup.*'angle'"):
        tj.register_ap("Zbadgroup", "angle", basis, "rad")
    with pytest.raises(ValueError, match="Zbadunit.*'mm'"):
        tj.register_ap("Zbadunit", "range", basis, "mm")
    with pytest.raises(ValueError, match="A0.*already registered"):
        tj.register_ap("A0", "range", basis, "m")
    with pytest.raises(ValueError, match="spaces"):
        tj.register_ap("Z bad", "range", basis, "m")
    # Failed registrations leave no trace.
    assert not {"Zbadgroup", "Zbadunit", "Z bad"} & set(tj.registered_aps())


def test_room_parse():
    with pytest.raises(ValueError, match="14by11"):
        tj.Room.parse("14by11")
    with pytest.raises(ValueError, match="14x11"):
        tj.Room.parse("14x11")
    r = tj.Room.parse("20x10x4")
    assert (r.length, r.width, r.height) == (20.0, 10.0, 4.0)


@pytest.fixture(scope="module")
def plane_table():
    """Plane rows of a noiseless 3 deg scan of the room, at most 30 points per plane and scan."""
    pc = tj.simulate_point_clouds(tj.CloudDesign(angular_step=3 * np.pi / 180, noise=False), seed=0)
    return pc.to_table(30)


def _subset(table, keep, **changes):
    keep = np.asarray(keep)
    return dataclasses.replace(
        table,
        scans=tuple(np.array(table.scans)[keep]),
        primitives=tuple(np.array(table.primitives)[keep]),
        observations=table.observations[keep],
        sigmas=table.sigmas[keep],
        incidence=table.incidence[keep],
        rows=table.rows[keep],
        **changes,
    )


def test_plane_rows_are_validated(plane_table):
    t = plane_table
    assert tj.make_plane_network(t).planes
    obs = t.observations.copy()
    obs[7, 2] = np.nan
    with pytest.raises(
        ValueError,
        match=rf"line {t.rows[7]}: el of scan {t.scans[7]}, plane {t.primitives[7]} is not finite",
    ):
        tj.make_plane_network(dataclasses.replace(t, observations=obs))


def test_plane_with_too_few_points(plane_table):
    t = plane_table
    board = np.flatnonzero(np.array(t.primitives) == "board2")
    keep = np.ones(len(t.scans), bool)
    keep[board[3:]] = False
    with pytest.raises(ValueError, match="plane board2 has 3 point\\(s\\); at least 4"):
        tj.make_plane_network(_subset(t, keep))


def test_scan_with_two_planes_only(plane_table):
    t = plane_table
    keep = np.array([s != "S3" or p in ("floor", "wall_x0") for s, p in zip(t.scans, t.primitives)])
    with pytest.raises(
        ValueError,
        match="scan S3 observes 0 target\\(s\\) and 2 plane\\(s\\); at least 3 primitives",
    ):
        tj.make_plane_network(_subset(t, keep))


def test_plane_and_target_names_must_differ(rows, plane_table):
    scans, targets, obs = rows
    t = plane_table
    clash = dataclasses.replace(
        t, primitives=tuple("T001" if p == "floor" else p for p in t.primitives)
    )
    with pytest.raises(ValueError, match="T001 names both a target and a plane"):
        _make(scans, targets, obs, planes=clash)


def test_planes_must_be_a_plane_table(rows, plane_table):
    scans, targets, obs = rows
    wrong = dataclasses.replace(plane_table, kind="target")
    with pytest.raises(ValueError, match="planes must be a plane ObservationTable"):
        _make(scans, targets, obs, planes=wrong)


# --------------------------------------------------------------------------------------------
# Issue 13: inputs checked at the boundary


@pytest.mark.parametrize(
    "column, degrees, architecture, message",
    [
        (2, 95.0, "hybrid", "el of scan .* = 95 deg .*beyond 90 deg: a hybrid scanner"),
        (2, 95.0, None, "el of .* = 95 deg .*only the second face of a panoramic scanner.*hz = "),
        (2, -120.0, None, "el of .* = -120 deg .*below -90 deg"),
        (2, -120.0, "panoramic", "below -90 deg"),
        (2, 270.0, "panoramic", "not below 270 deg"),
        (1, 720.0, None, "hz of scan .* = 720 deg .*two turns"),
        (1, -800.0, "hybrid", "two turns"),
    ],
)
def test_angles_outside_the_architecture_are_refused(rows, column, degrees, architecture, message):
    scans, targets, obs = rows
    obs = obs.copy()
    i = 40
    obs[i, column] = np.radians(degrees)
    with pytest.raises(ValueError, match=rf"row {i}: .*" + message):
        _make(scans, targets, obs, architecture=architecture)


def test_angles_checked_against_the_model_at_calibration(rows):
    scans, targets, obs = rows
    net = _make(scans, targets, obs)
    # A panoramic model needs every hz in [0, 180) deg: this hybrid network has them all round.
    with pytest.raises(ValueError, match=r"hz of scan .*panoramic scanner\).*not in \[0, 180\)"):
        tj.calibrate(net, tj.CalibrationModel(tj.Scanner(architecture="panoramic", aps="A0")))
    pan = tj.simulate(tj.Room(n_targets=24), aps="none", architecture="panoramic", noise=False)
    assert np.degrees(pan.network.observations[:, 2].max()) > 90  # second-face rows exist
    with pytest.raises(ValueError, match="beyond 90 deg: a hybrid scanner"):
        tj.self_calibrate(pan.network, tj.CalibrationModel(tj.Scanner(aps="A0")))
    # Angles one turn off (a reading of 370 deg, or -10 deg) are directions, not errors.
    o = obs.copy()
    o[3, 1] += 2 * np.pi
    o[4, 1] -= 2 * np.pi
    _make(scans, targets, o, architecture="hybrid")


def test_levelling_needs_known_keys_and_sigmas(rows):
    scans, targets, obs = rows
    with pytest.raises(
        ValueError, match="levelling of scan S1 has no sigma_omega and no sigma_phi"
    ):
        _make(scans, targets, obs, levelling={"S1": {"omega": 0}})
    with pytest.raises(ValueError, match="S2 has no sigma_phi"):
        _make(scans, targets, obs, levelling={"S2": {"sigma_omega": 1e-5}})
    good = {"omega": 0.0, "phi": 1e-5, "sigma_omega": 5e-5, "sigma_phi": 5e-5}
    with pytest.raises(ValueError, match="unknown key.*kappa"):
        _make(scans, targets, obs, levelling={"S1": {**good, "kappa": 0.0}})
    with pytest.raises(ValueError, match="omega = 5.7.*deg.*check the values and their unit"):
        _make(scans, targets, obs, levelling={"S1": {**good, "omega": 0.1}})
    with pytest.raises(ValueError, match="S3 must be positive"):
        _make(scans, targets, obs, levelling={"S3": {**good, "sigma_phi": 0.0}})
    with pytest.raises(TypeError, match="levelling\\['S1'\\] must be a mapping"):
        _make(scans, targets, obs, levelling={"S1": (0.0, 0.0, 1e-5, 1e-5)})
    with pytest.raises(TypeError, match="values must be numbers"):
        _make(scans, targets, obs, levelling={"S1": {**good, "phi": "flat"}})
    net = _make(scans, targets, obs, levelling={"S1": good})
    assert net.is_levelled.tolist() == [True] + [False] * 5
    np.testing.assert_array_equal(net.levelling_sigma[0], [5e-5, 5e-5])


def test_degenerate_and_repeated_scale_bars(rows):
    scans, targets, obs = rows
    with pytest.raises(ValueError, match="scale bar 1 joins target T001 to itself"):
        _make(scans, targets, obs, scale_bars=[("T001", "T001", 1.0, 1e-4)])
    bars = [("T001", "T002", 1.0, 1e-4), ("T002", "T001", 1.0, 1e-4)]
    with pytest.raises(ValueError, match="T002-T001 is given twice"):
        _make(scans, targets, obs, scale_bars=bars)
    with pytest.raises(ValueError, match="scale bar 1 must be"):
        _make(scans, targets, obs, scale_bars=[("T001", "T002", 1.0)])
    with pytest.raises(ValueError, match="positive length"):
        _make(scans, targets, obs, scale_bars=[("T001", "T002", 0.0, 1e-4)])
    net = _make(scans, targets, obs, scale_bars=[("T001", "T002", 1.0, 1e-4)])
    assert net.scale_bar_targets.tolist() == [[0, 1]]


def test_wrong_argument_types_name_the_argument(rows):
    scans, targets, obs = rows
    with pytest.raises(TypeError, match="scans must be a sequence of scan names"):
        tj.make_network("S1", list(targets), obs)
    with pytest.raises(TypeError, match="observations must be an \\(n, 3\\) array of numbers"):
        tj.make_network(list(scans), list(targets), [["a", "b", "c"]] * len(scans))
    with pytest.raises(TypeError, match="sigma_range must be a number"):
        _make(scans, targets, obs, sigma_range="0.5 mm")
    with pytest.raises(ValueError, match="architecture 'hybird'"):
        _make(scans, targets, obs, architecture="hybird")
    with pytest.raises(ValueError, match="3 instrument names"):
        _make(scans, targets, obs, instruments=["a", "b", "c"])
    net = _make(scans, targets, obs)
    with pytest.raises(TypeError, match="network must be a tlsjax Network, got str.*read_network"):
        tj.calibrate("obs.csv", tj.CalibrationModel())
    with pytest.raises(
        TypeError, match="model must be a tlsjax CalibrationModel.*Scanner.*wrap it"
    ):
        tj.calibrate(net, tj.Scanner())
    with pytest.raises(TypeError, match="options must be a tlsjax SolverOptions"):
        tj.calibrate(net, None, {"max_iterations": 3})
    with pytest.raises(TypeError, match="options must be a tlsjax CalibrationOptions"):
        tj.self_calibrate(net, None, {"vce": False})
    with pytest.raises(
        TypeError, match="CalibrationOptions.vce must be a tlsjax VCEOptions or None"
    ):
        tj.CalibrationOptions(vce=False)
    with pytest.raises(TypeError, match="observations_path must be a file path"):
        tj.read_network(net)


def test_dropping_single_targets_may_not_empty_a_scan(rows):
    scans, targets, obs = rows
    # S6 sees only targets that no other scan sees: dropping them leaves nothing of S6.
    own = [f"X{i}" for i in range(6)]
    s = np.append(scans, ["S6"] * 6)
    t = np.append(targets, own)
    o = np.vstack([obs, obs[scans == "S6"][:6]])
    keep = s != "S6"
    keep[-6:] = True
    with pytest.raises(ValueError, match="scan\\(s\\) S6 observe only targets seen in no other"):
        _make(s[keep], t[keep], o[keep], drop_single_targets=True)
    with pytest.raises(ValueError, match="every target is seen in one scan only"):
        _make(["S1"] * 6, own, obs[:6], drop_single_targets=True)


def test_repeated_plane_points_are_refused(rows, plane_table):
    t = plane_table
    idx = np.r_[np.arange(len(t.scans)), 5]
    twice = _subset(t, idx)
    with pytest.raises(
        ValueError, match=rf"line {t.rows[5]}: duplicate point of plane {t.primitives[5]}"
    ):
        tj.make_plane_network(twice)
