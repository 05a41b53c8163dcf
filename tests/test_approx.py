"""Approximate values of any plausible network (issue 12, item 1).

Independent source: the simulation's truth. The approximate values live in a frame of their
own (the free network's datum), so they are compared through what a rigid motion of that frame
leaves unchanged: the relative rotations ``R_i R_j^T`` of the scans, each scan's view of the
other stations ``R_i (S_j - S_i)``, the angles between plane normals and the scans' distances
from the planes. The APs (10 mm, 180") are not in the approximate values, so they are good to
about a centimetre and a fifth of a degree, not better.

Private imports: the approximate values are a private algorithm (``_adjustment._approx``); its
parts are tested directly, with ``rotation_matrix`` to build the poses.
"""

import dataclasses

import numpy as np
import pytest
from networks import SIX_SCANS, ST1, ST2

import tlsjax as tj
from tlsjax import ObservationTable, rotation_matrix
from tlsjax._adjustment._approx import ApproxConfig, approximate, approximate_network
from tlsjax._adjustment._approx._local import Prims
from tlsjax._adjustment._approx._register import register

pytestmark = pytest.mark.internal

DEG = np.pi / 180
ROOM = (14.0, 11.0, 3.0)

#: The issue's oblique planes: normals (1,1,1), (-1,2,3), (2,-1,1.5), 0.35 to 2 m from the stations.
OBLIQUE = (
    tj.RoomPlane((1, 1, 1), (5.0, 4.5, 2.1)),
    tj.RoomPlane((-1, 2, 3), (9.5, 7.0, 2.6)),
    tj.RoomPlane((2, -1, 1.5), (7.0, 5.5, 1.5)),
)


def _relative(eops):
    R = np.stack([rotation_matrix(*e[3:], xp=np) for e in eops])
    rel_rot = np.einsum("iab,jcb->ijac", R, R)
    rel_pos = np.einsum("iab,ijb->ija", R, eops[None, :, :3] - eops[:, None, :3])
    return rel_rot, rel_pos


def pose_errors(est, true):
    """Largest error of the relative poses: position [m] and rotation [rad]."""
    (ra, pa), (rb, pb) = _relative(est), _relative(true)
    cos = (np.einsum("ijab,ijab->ij", ra, rb) - 1) / 2
    return np.abs(pa - pb).max(), np.arccos(np.clip(cos, -1, 1)).max()


def plane_errors(est_eops, est_planes, true_eops, true_planes):
    """Largest error of the angles between normals [rad] and of the scans' signed distances
    from the planes [m]; each estimated normal's sign is matched to the truth's through the
    side of the plane the scan farthest from it is on."""
    de = est_planes[:, 3][None, :] - est_eops[:, :3] @ est_planes[:, :3].T
    dt = true_planes[:, 3][None, :] - true_eops[:, :3] @ true_planes[:, :3].T
    k = np.arange(len(true_planes))
    far = np.argmax(np.abs(dt), axis=0)
    sign = np.sign(de[far, k]) * np.sign(dt[far, k])
    n = est_planes[:, :3] * sign[:, None]
    dn = np.abs(n @ n.T - true_planes[:, :3] @ true_planes[:, :3].T).max()
    return dn, np.abs(de * sign - dt).max()


def _approx_ok(sim, length=0.03, angle=0.3 * DEG):
    a = approximate(sim.network)
    assert np.isfinite(a.eops).all() and np.isfinite(a.targets).all()
    dp, da = pose_errors(a.eops, sim.true_eops)
    assert dp < length and da < angle, (dp, da / DEG)
    if sim.network.has_planes:
        dn, dd = plane_errors(a.eops, a.planes, sim.true_eops, sim.true_planes)
        assert dn < np.sin(angle) and dd < length, (dn, dd)
        np.testing.assert_allclose(np.linalg.norm(a.planes[:, :3], axis=1), 1.0, atol=1e-12)
    if sim.network.has_targets:
        # Targets: distances from the scans, a rigid-motion invariant.
        R = np.stack([rotation_matrix(*e[3:], xp=np) for e in a.eops])
        Rt = np.stack([rotation_matrix(*e[3:], xp=np) for e in sim.true_eops])
        xa = np.einsum("sab,tsb->tsa", R, a.targets[:, None] - a.eops[None, :, :3])
        xt = np.einsum("sab,tsb->tsa", Rt, sim.true_targets[:, None] - sim.true_eops[None, :, :3])
        assert np.abs(xa - xt).max() < 3 * length
    return a


def test_oblique_planes_crossing_the_room():
    """The issue's room: six faces and three oblique planes 0.35-2 m from the stations, so
    that the two stations see them from opposite sides; two scans rolled by -45 and +45 deg."""
    design = tj.NetworkDesign(
        room=ROOM, scans=SIX_SCANS, faces_as_planes=True, planes=OBLIQUE, points_per_plane=30
    )
    sim = tj.simulate_design(design, seed=0)
    n, d = sim.true_planes[:, :3], sim.true_planes[:, 3]
    side = np.sign(sim.true_eops[:, :3] @ n.T - d)
    assert (side.min(axis=0) < 0).sum() >= 2  # some planes are seen from both sides
    a = _approx_ok(sim)
    assert a.inconsistent == ()
    # Each plane gets one orientation: towards the side most of its points were seen from;
    # the room's faces therefore point into the room, as the truth's do.
    faces = [sim.network.planes.index(f) for f in ("floor", "ceiling", "wall_x0")]
    _, _, planes = approximate_network(sim.network)
    assert np.all(planes[faces, 3] - np.einsum("ki,i->k", planes[faces, :3], a.eops[0, :3]) < 0)


def test_old_start_of_the_issue_is_fixed_on_the_point_cloud_room():
    """The point-cloud simulation of the issue's reproduction: 30 points per plane and scan
    from an angular grid, three 30 m boards through the room."""

    def big_board(n, point, size=30.0):
        n = np.asarray(n, float) / np.linalg.norm(n)
        u = np.cross(n, [0, 0, 1.0])
        u /= np.linalg.norm(u)
        v = np.cross(n, u)
        c = np.asarray(point, float)
        return tj.Board(tuple(c - 0.5 * size * (u + v)), tuple(size * u), tuple(size * v))

    boards = tuple(big_board(p.normal, p.point) for p in OBLIQUE)
    cd = tj.CloudDesign(room=tj.Room(14, 11, 3), boards=boards, angular_step=2.0 * DEG)
    pc = tj.simulate_point_clouds(cd, seed=0)
    net = pc.to_network(max_points=30, seed=0)
    _, eops, planes = approximate_network(net)
    dp, da = pose_errors(eops, pc.eops)
    assert dp < 0.03 and da < 0.3 * DEG, (dp, da / DEG)
    true_planes = pc.planes[[pc.plane_names.index(k) for k in net.planes]]
    dn, dd = plane_errors(eops, planes, pc.eops, true_planes)
    assert dn < 0.005 and dd < 0.03


@pytest.mark.parametrize("architecture", ["hybrid", "panoramic"])
def test_stations_close_to_planes_and_tilts_up_to_90_degrees(architecture):
    """Boards 0.3 m from the stations; scans tilted by 90 deg about x (omega) and about y
    (phi, the Cardan gimbal lock of the truth's frame), no levelling."""
    boards = (
        tj.Board.tilted((4.8, 4.0, 1.6), 2.0, 2.0, azimuth=180 * DEG, tilt=10 * DEG),
        tj.Board.tilted((9.5, 7.0, 1.9), 2.0, 2.0, azimuth=40 * DEG, tilt=-80 * DEG),
    )
    scans = (
        (*ST1, 0.0, 0.0, 0.0),
        (*ST1, 90 * DEG, 0.0, 30 * DEG),
        (*ST2, 0.0, 90 * DEG, 0.0),
        (*ST2, -60 * DEG, 30 * DEG, 200 * DEG),
    )
    design = tj.NetworkDesign(
        room=ROOM,
        scans=scans,
        faces_as_planes=True,
        planes=boards,
        points_per_plane=15,
        architecture=architecture,
        levelling=False,
        elevation_limits=(-89 * DEG, 89 * DEG),
    )
    sim = tj.simulate_design(design, seed=1)
    a = _approx_ok(sim)
    # The frame keeps every scan away from phi = +-90 deg, where omega and kappa coincide.
    assert np.abs(a.eops[:, 4]).max() < 60 * DEG


def test_partial_visibility_and_a_narrow_field_of_view():
    """Each scan sees a different subset of the planes: a plane crossing the room hides one
    side of it, the field of view ends at -20 and +45 deg and the range at 9 m."""
    design = tj.NetworkDesign(
        room=ROOM,
        scans=SIX_SCANS,
        faces_as_planes=True,
        planes=(tj.RoomPlane((1, 0.3, 0.2), (7.0, 5.5, 1.5)), OBLIQUE[1]),
        points_per_plane=12,
        elevation_limits=(-20 * DEG, 45 * DEG),
        max_range=9.0,
    )
    sim = tj.simulate_design(design, seed=2)
    net = sim.network
    seen = [set(net.plane_index[net.plane_scan_index == j]) for j in range(len(net.scans))]
    assert len({frozenset(s) for s in seen}) > 1 and min(map(len, seen)) < len(net.planes)
    _approx_ok(sim)


@pytest.mark.parametrize("levelling", [True, False])
def test_targets_only(levelling):
    design = tj.NetworkDesign(
        room=(20.0, 8.0, 4.0),
        scans=SIX_SCANS,
        n_targets=40,
        levelling=levelling,
        elevation_limits=(-50 * DEG, 70 * DEG),
    )
    sim = tj.simulate_design(design, seed=3)
    a = _approx_ok(sim)
    if levelling:
        # The levelled scans' vertical axes point up: their omega and phi start near zero.
        lev = sim.network.is_levelled
        assert np.abs(a.eops[lev, 3:5]).max() < 0.2 * DEG


def test_combined_targets_and_planes_panoramic():
    design = tj.NetworkDesign(
        room=ROOM,
        scans=SIX_SCANS,
        n_targets=30,
        faces_as_planes=True,
        planes=OBLIQUE[:1],
        points_per_plane=10,
        architecture="panoramic",
    )
    sim = tj.simulate_design(design, seed=4)
    assert sim.network.has_targets and sim.network.has_planes
    _approx_ok(sim)


def _swap_plane(table, scan, a, b):
    """The table with the points of plane a in one scan labelled b (a wrong match)."""
    prims = np.array(table.primitives, dtype=object)
    m = (np.array(table.scans) == scan) & (prims == a)
    prims[m] = b
    return dataclasses.replace(table, primitives=tuple(prims))


def test_a_wrong_match_is_reported_and_spoils_nothing_else():
    design = tj.NetworkDesign(
        room=ROOM, scans=SIX_SCANS, faces_as_planes=True, planes=OBLIQUE, points_per_plane=20
    )
    sim = tj.simulate_design(design, seed=5)
    net = sim.network
    # S5's wall_y0 points are labelled plane2 (a wrong match, as extraction may produce): its
    # plane2 pair now holds the points of two planes, and its wall_y0 pair is gone.
    rows = np.flatnonzero(net.plane_scan_index == 4)
    prims = np.array(net.planes)[net.plane_index]
    t = ObservationTable(
        kind="plane",
        source="<wrong match>",
        scans=tuple(np.array(net.scans)[net.plane_scan_index]),
        primitives=tuple(prims),
        observations=net.plane_observations,
        sigmas=None,
        incidence=None,
        instruments=None,
        rows=np.arange(len(prims)) + 2,
    )
    t = _swap_plane(t, "S5", "wall_y0", "plane2")
    bad = tj.make_plane_network(t)
    assert len(rows)
    a = approximate(bad)
    flagged = {(i.scan, i.name) for i in a.inconsistent}
    assert ("S5", "plane2") in flagged and len(flagged) <= 2, a.inconsistent
    item = next(i for i in a.inconsistent if i.name == "plane2")
    assert item.distance > 0.1 and "S5" in str(item) and "mm" in str(item)
    # The other scans and planes come out as well as without the wrong match.
    dp, da = pose_errors(a.eops, sim.true_eops)
    assert dp < 0.03 and da < 0.3 * DEG


def test_normals_of_either_sign_give_one_registration():
    """Pairwise registration from plane normals whose signs are drawn at random in both frames
    (as extracted planes come): the rotation and position are those of the truth."""
    rng = np.random.default_rng(7)
    n = rng.normal(size=(7, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    c = rng.uniform(-4, 4, size=(7, 3))
    R = rotation_matrix(0.3, -1.1, 2.0, xp=np)
    t = np.array([1.0, -2.0, 0.5])
    cb = (c - t) @ R  # x_b = R^T (x_a - t)
    nb = n @ R

    def prims(normals, centres, signs):
        k = len(normals)
        return Prims(
            np.arange(k),
            normals * signs[:, None],
            np.ones(k, dtype=bool),
            np.full(k, 1e-3),
            centres,
            np.full(k, 1e-3),
            np.zeros(0, dtype=int),
            np.zeros((0, 3)),
            np.zeros(0),
        )

    for _ in range(5):
        sa, sb = rng.choice([-1.0, 1.0], size=(2, 7))
        fit = register(prims(n, c, sa), prims(nb, cb, sb), ApproxConfig(), rng)
        assert fit.determined and fit.n_inliers == 7
        np.testing.assert_allclose(fit.R, R, atol=1e-9)
        np.testing.assert_allclose(fit.t, t, atol=1e-9)
        np.testing.assert_array_equal(fit.sign, sa * sb)


def test_parallel_planes_do_not_fix_a_rotation():
    """S3 keeps only the floor, the ceiling and a horizontal board: three primitives (enough
    for make_network) whose normals are parallel, so its rotation about the vertical is free."""
    board = tj.Board.tilted((7.0, 5.5, 1.0), 3.0, 3.0, azimuth=0.0, tilt=90 * DEG)
    design = tj.NetworkDesign(
        room=ROOM,
        scans=SIX_SCANS[:4],
        faces_as_planes=True,
        planes=(board,),
        points_per_plane=10,
    )
    sim = tj.simulate_design(design, seed=6)
    net = sim.network
    prims = np.array(net.planes)[net.plane_index]
    scans = np.array(net.scans)[net.plane_scan_index]
    keep = (scans != "S3") | np.isin(prims, ["floor", "ceiling", "board1"])
    t = ObservationTable(
        "plane",
        "<parallel>",
        tuple(scans[keep]),
        tuple(prims[keep]),
        net.plane_observations[keep],
        None,
        None,
        None,
        np.flatnonzero(keep) + 2,
    )
    with pytest.raises(ValueError, match="scan S3: its rotation is not determined"):
        approximate(tj.make_plane_network(t))


def test_a_mislabelled_target_is_reported():
    """Two targets' labels swapped in one scan (a wrong identification): both are reported
    for that scan, at their true separation, and the poses stay as good as without it."""
    design = tj.NetworkDesign(room=ROOM, scans=SIX_SCANS, n_targets=30, common_targets=True)
    sim = tj.simulate_design(design, seed=8)
    net = sim.network
    names = np.array(net.targets)[net.target_index]
    in_s2 = np.array(net.scans)[net.scan_index] == "S2"
    a_row = np.flatnonzero(in_s2 & (names == "T001"))[0]
    b_row = np.flatnonzero(in_s2 & (names == "T030"))[0]
    names[[a_row, b_row]] = names[[b_row, a_row]]
    bad = tj.make_network(list(np.array(net.scans)[net.scan_index]), list(names), net.observations)
    a = approximate(bad)
    assert {(i.scan, i.name) for i in a.inconsistent} == {("S2", "T001"), ("S2", "T030")}
    i1, i30 = net.targets.index("T001"), net.targets.index("T030")
    gap = np.linalg.norm(sim.true_targets[i1] - sim.true_targets[i30])
    assert all(abs(i.distance - gap) < 0.05 and i.kind == "target" for i in a.inconsistent)
    dp, da = pose_errors(a.eops, sim.true_eops)
    assert dp < 0.03 and da < 0.3 * DEG


def test_blunders_among_common_targets_are_flagged_per_observation():
    """A target 3 m off in one scan and a target observation filed under the wrong scan: the
    registration flags exactly those two rows (``target_inlier``, network row order), names
    them, and the poses stay as good as without them."""
    design = tj.NetworkDesign(room=ROOM, scans=SIX_SCANS, n_targets=30, common_targets=True)
    sim = tj.simulate_design(design, seed=9)
    net = sim.network
    scans = np.array(net.scans)[net.scan_index]
    names = np.array(net.targets)[net.target_index]
    obs = net.observations.copy()
    row = lambda s, t: int(np.flatnonzero((scans == s) & (names == t))[0])
    obs[row("S1", "T003"), 0] += 3.0
    moved, dropped = row("S4", "T010"), row("S6", "T010")
    scans[moved] = "S6"
    keep = np.arange(len(obs)) != dropped
    bad = tj.make_network(list(scans[keep]), list(names[keep]), obs[keep])
    a = approximate(bad)
    bad_scans = np.array(bad.scans)[bad.scan_index]
    bad_names = np.array(bad.targets)[bad.target_index]
    flagged = set(zip(bad_scans[~a.target_inlier], bad_names[~a.target_inlier]))
    assert flagged == {("S1", "T003"), ("S6", "T010")}
    assert {(i.scan, i.name) for i in a.inconsistent} == flagged
    assert a.target_inlier.shape == (len(bad.observations),)
    assert len(a.registrations) == len(bad.scans) - 1
    dp, da = pose_errors(a.eops[[bad.scans.index(s) for s in net.scans]], sim.true_eops)
    assert dp < 0.03 and da < 0.3 * DEG


def test_robust_fit_recovers_the_motion_with_a_third_of_the_points_wrong():
    from tlsjax._adjustment._approx._rigid import robust_fit

    rng = np.random.default_rng(3)
    xb = rng.uniform(-8, 8, size=(24, 3))
    R = rotation_matrix(0.4, -0.2, 2.5, xp=np)
    t = np.array([3.0, -1.0, 0.4])
    xa = xb @ R.T + t
    wrong = rng.choice(24, 8, replace=False)
    xa[wrong] += rng.normal(scale=2.0, size=(8, 3))
    tol = np.full(24, 0.05)
    R_est, t_est, inlier, _ = robust_fit(xb, xa, tol, np.ones(24), np.random.default_rng(0), 12)
    np.testing.assert_array_equal(np.flatnonzero(~inlier), np.sort(wrong))
    np.testing.assert_allclose(R_est, R, atol=1e-12)
    np.testing.assert_allclose(t_est, t, atol=1e-11)


def test_memoised_per_network_data_never_stale():
    """A network is adjusted many times; its approximate values and plan are computed once per
    data. The source: the uncached computation (``_approximate``) on the same arrays, before
    and after an in-place edit of the network."""
    import gc

    from tlsjax._adjustment import _network
    from tlsjax._adjustment._approx._approximate import _approximate

    net = tj.simulate(seed=3).network
    first = approximate(net)
    first.targets[:] = 0.0  # the caller's copy: the memo is untouched
    again = approximate(net)
    fresh = _approximate(net, ApproxConfig())
    np.testing.assert_array_equal(again.targets, fresh.targets)
    np.testing.assert_array_equal(again.eops, fresh.eops)
    model = tj.CalibrationModel()
    assert tj.analyze(net, model).plan is tj.analyze(net, model).plan
    other = tj.CalibrationModel(tj.Scanner(aps=("A0", "B6")))
    assert tj.analyze(net, other).plan is not tj.analyze(net, model).plan
    # An in-place edit (a target moved by 0.3 m in one scan) is new data: computed afresh.
    rows = np.flatnonzero(net.target_index == net.target_index[0])
    net.observations[rows[0], 0] += 0.3
    edited = approximate(net)
    np.testing.assert_array_equal(edited.targets, _approximate(net, ApproxConfig()).targets)
    assert not edited.target_inlier[rows[0]] and fresh.target_inlier[rows[0]]
    # Held weakly: a network no longer referenced takes its values with it.
    n_before = len(_network._MEMO)
    del net, first, again, edited
    gc.collect()
    assert len(_network._MEMO) == n_before - 1
