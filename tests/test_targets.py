"""Target centres from point clouds (issue 33): simulated spheres, checkerboards and circles
extracted, matched and calibrated against the simulation's truth.

Private imports: ``tlsjax._cli.main`` (the console script), the chunked scan reader
``open_scans``, whose chunking is checked, and the batched fit ``_clouds._lsq``, whose device is.
"""

import csv
import dataclasses
import pathlib

import numpy as np
import pytest

import tlsjax as tj
from tlsjax import cartesian_from_spherical, rotation_matrix
from tlsjax._cli import main

DEG = np.pi / 180
DATA = pathlib.Path(__file__).parent / "data"
OPTIONS = tj.TargetExtractionOptions(spheres=(0.0725,), checkerboards=True, circles=True)


def _truth_of(pc, found):
    """Per detection: the nearest true target of its scan (name, error vector [m] in scanner
    space, against the noise-free observation of the centre with the APs applied)."""
    truth = pc.target_observations()
    names, errors = [], []
    for i in range(len(found)):
        scan = found.scans[found.scan_index[i]]
        best = min(
            (np.linalg.norm(cartesian_from_spherical(o, xp=np) - found.centre[i]), n, o)
            for (s, n), o in truth.items()
            if s == scan
        )
        names.append(best[1] if best[0] < 0.03 else "")
        errors.append(cartesian_from_spherical(best[2], xp=np) - found.centre[i])
    return np.array(names, dtype=object), np.array(errors)


@pytest.fixture(scope="module")
def room():
    # The tilted Chow room, APs A0 B6 B7 C0 at SPEC section 8's values, 0.5 mm / 20" noise, a
    # random field of targets scanned on a 0.06 deg grid around each (the room on 3 deg).
    targets = tj.place_targets(spheres=6, checkerboards=6, circles=2, seed=5)
    design = tj.CloudDesign(angular_step=3 * DEG, target_step=0.06 * DEG, **targets)
    return tj.simulate_point_clouds(design, seed=5)


@pytest.fixture(scope="module")
def found(room):
    return tj.extract_targets(room.observations, OPTIONS, intensity=room.intensity)


@pytest.fixture(scope="module")
def matched(found):
    return tj.match_targets(found)


def test_every_visible_target_found_with_small_errors(room, found):
    names, err = _truth_of(room, found)
    acc = found.accepted
    assert set(found.kind[acc]) == {"sphere", "checkerboard", "circle"}
    # Every accepted detection is a true target (no false detections survive the checks).
    assert np.all(names[acc] != "")
    # Every target with enough points at a fair incidence is found in every scan.
    for j, scan in enumerate(room.scans):
        counts = np.bincount(room.target_ids[j][room.target_ids[j] >= 0], minlength=14)
        R = rotation_matrix(*room.eops[j][3:], xp=np)
        for t, name in enumerate(room.target_names):
            if counts[t] < 150:
                continue
            if room.target_kinds[t] != "sphere":
                c = R @ (room.target_centres[t] - room.eops[j][:3])
                n = R @ np.array(room.planes[room.plane_names.index(f"plate{t - 5}")][:3])
                if abs(n @ c) / np.linalg.norm(c) < np.cos(70 * DEG):
                    continue
            hit = acc & (found.scan_index == j) & (names == name)
            assert hit.sum() == 1, (scan, name, counts[t])
    # Centre errors (issue 33: sub-millimetre for spheres at up to 10 m; planar targets on
    # this 0.06 deg grid have 50-600 points, up to 75 deg incidence), and the errors against
    # the propagated covariance (median of chi2(3) is 2.37).
    e = np.linalg.norm(err, axis=1)
    for kind, limit in (("sphere", 0.5e-3), ("checkerboard", 2.0e-3), ("circle", 1.0e-3)):
        assert e[acc & (found.kind == kind)].max() < limit, kind
    chi2 = [err[i] @ np.linalg.solve(found.covariance[i], err[i]) for i in np.flatnonzero(acc)]
    assert np.median(chi2) < 2 * 2.37


def test_observations_and_sigmas_propagate_the_centre(found):
    acc = np.flatnonzero(found.accepted)
    X = found.centre[acc]
    np.testing.assert_allclose(found.observations[acc, 0], np.linalg.norm(X, axis=1), rtol=1e-12)
    # Finite differences of the spherical conversion against the autodiff propagation.
    i = acc[0]
    x = found.centre[i]
    J = np.zeros((3, 3))
    for k in range(3):
        d = np.zeros(3)
        d[k] = 1e-6
        lp = tj.ExtractedTargets.from_centres(("S",), [0, 0], [x + d, x - d]).observations
        J[:, k] = (lp[0] - lp[1]) / 2e-6
    C = J @ found.covariance[i] @ J.T
    np.testing.assert_allclose(found.observation_covariance[i], C, rtol=1e-5, atol=1e-18)
    assert np.all(found.sigmas[acc] > 0)


def test_matching_names_true_targets_one_to_one(room, matched):
    names, _ = _truth_of(room, matched)
    named = matched.names != ""
    assert named.sum() >= 0.9 * matched.accepted.sum()
    for n in set(matched.names[named]):
        assert len(set(names[matched.names == n])) == 1, n  # no false match
    for t in set(names[named]):
        assert len(set(matched.names[named & (names == t)])) == 1, t  # one name per target
    assert all(s in ("reference", "placed") for s in matched.matching.status.values())


def test_calibration_from_extracted_centres_recovers_the_aps(room, matched):
    table = matched.to_table()
    net = tj.make_network(
        table.scans, table.primitives, table.observations, sigmas=table.sigmas,
        levelling=room.levelling,
    )  # fmt: skip
    res = tj.calibrate(net, tj.CalibrationModel(room.scanner))
    assert res.result == 0, res.message
    for name, value in room.true_aps.items():
        ap = res.ap(name)
        assert abs(ap["value"] - value) < 3 * ap["sigma"], (name, ap, value)


def test_partial_and_wrong_radius_spheres_are_rejected():
    # Sphere 1 half hidden behind a board (its edge on the line of sight of S1, the first
    # station (4.5, 4, 1.6)); sphere 2 of radius 0.1 m where 0.0725 m is asked.
    station, sphere = np.array([4.5, 4.0, 1.6]), np.array([7.6, 3.0, 1.5])
    at = station + 0.85 * (sphere - station)
    az = np.arctan2(*(station - at)[1::-1])
    side = np.array([-np.sin(az), np.cos(az), 0.0])
    board = tj.Board.tilted(at + 0.1 * side, 0.2, 0.4, azimuth=az, tilt=0.0)
    design = tj.CloudDesign(
        angular_step=3 * DEG, target_step=0.06 * DEG, tilted=False, boards=(board,),
        spheres=(tj.SphereTarget((7.6, 3.0, 1.5)), tj.SphereTarget((7.0, 6.0, 1.2), 0.1)),
    )  # fmt: skip
    pc = tj.simulate_point_clouds(design, seed=2)
    opts = dataclasses.replace(OPTIONS, checkerboards=False, circles=False)
    found = tj.extract_targets(pc.observations[:1], opts)
    reasons = " | ".join(found.reason)
    assert "coverage" in reasons
    assert "differs from the nominal 72.5 mm" in reasons
    assert not found.accepted.any()
    # Asked for both radii, the big sphere is accepted with the right one.
    both = tj.extract_targets(pc.observations[:1], dataclasses.replace(opts, spheres=(0.0725, 0.1)))
    assert list(both.size[both.accepted]) == [0.1]


def test_contrast_range_bias_is_reported():
    # Dark print 0.5 mm farther than bright (an intensity-dependent range error): the fitted
    # plane sits between the two, the contrast centroid off it as in Lichti & Licht 2006.
    target = tj.PlanarTarget((13.995, 4.0, 1.5), (-1, 0, 0), "circle")
    design = tj.CloudDesign(
        angular_step=3 * DEG, target_step=0.05 * DEG, tilted=False, planar_targets=(target,),
        dark_range_bias=0.5e-3,
    )  # fmt: skip
    pc = tj.simulate_point_clouds(design, seed=1)
    opts = dataclasses.replace(OPTIONS, spheres=(), checkerboards=False)
    found = tj.extract_targets(pc.observations[:1], opts, intensity=pc.intensity[:1])
    (i,) = np.flatnonzero(found.accepted)
    # 0.5 mm of range noise on about 100 dark and 100 bright points: the difference of their
    # means scatters by 0.07 mm.
    assert abs(found.contrast_bias[i] - 0.5e-3) < 0.15e-3
    assert -0.4e-3 < found.plane_offset[i] < -0.1e-3


def test_panoramic_centres_in_two_face_form():
    design = tj.CloudDesign(
        angular_step=3 * DEG, target_step=0.06 * DEG, architecture="panoramic", tilted=False,
        spheres=(tj.SphereTarget((8.0, 3.0, 1.5)), tj.SphereTarget((2.0, 6.0, 1.0))),
    )  # fmt: skip
    pc = tj.simulate_point_clouds(design, seed=3)
    opts = dataclasses.replace(OPTIONS, checkerboards=False, circles=False)
    found = tj.extract_targets(pc.observations[:1], opts, architecture="panoramic")
    truth = pc.target_observations()
    acc = np.flatnonzero(found.accepted)
    assert len(acc) == 2
    for i in acc:
        o = found.observations[i]
        assert 0 <= o[1] < np.pi
        t = min(truth.values(), key=lambda v: np.linalg.norm(v - o))
        assert abs(o[0] - t[0]) < 0.3e-3 and np.all(np.abs(o[1:] - t[1:]) < 2e-4)
    assert (found.observations[acc, 2] > np.pi / 2).any()  # one of them in face 2


def test_streamed_file_equals_in_memory(room, tmp_path):
    x = cartesian_from_spherical(room.observations[0], xp=np)
    path = tmp_path / "S1.ply"
    tj.write_ply(path, x, attributes={"intensity": room.intensity[0]})
    opts = dataclasses.replace(OPTIONS, chunk_points=20_000)
    a = tj.extract_targets_from_files([path], opts)
    b = tj.extract_targets(
        room.observations[:1], OPTIONS, intensity=room.intensity[:1], names=["S1"]
    )
    np.testing.assert_allclose(a.centre, b.centre, atol=1e-9)
    assert list(a.reason) == list(b.reason)


def test_matching_geometry_partial_overlap_false_detections_and_symmetry():
    rng = np.random.default_rng(3)
    T = rng.uniform([0, 0, 0], [14, 11, 3], (30, 3))
    poses = [(range(0, 20), (4, 4, 1.5, 0, 0, 0.3)), (range(8, 28), (9, 7, 1.5, 0.7, 0, 2.0))]
    X, si, truth = [], [], []
    for s, (idx, pose) in enumerate(poses):
        pose = np.array(pose, dtype=float)
        R = rotation_matrix(*pose[3:], xp=np)
        x = (T[list(idx)] - pose[:3]) @ R.T + rng.normal(0, 0.003, (len(idx), 3))
        X += [x, rng.uniform(-5, 5, (3, 3))]  # three false detections per scan
        si += [s] * (len(idx) + 3)
        truth += list(idx) + [-1] * 3
    m = tj.match_targets(tj.ExtractedTargets.from_centres(("A", "B"), si, np.concatenate(X)))
    truth = np.array(truth)
    named = m.names != ""
    assert named.sum() == 2 * 12  # the 12 targets both scans see, nothing else
    for n in set(m.names[named]):
        (t,) = set(truth[m.names == n])
        assert t >= 0
    # A square pyramid turned by 90 deg fits itself four ways: ambiguous, not guessed.
    sq = np.array([[0, 0, 0], [2, 0, 0], [2, 2, 0], [0, 2, 0], [1, 1, 1.6]]) + [3, 0, 0]
    R = rotation_matrix(0, 0, np.pi / 2, xp=np)
    m = tj.match_targets(
        tj.ExtractedTargets.from_centres(("A", "B"), [0] * 5 + [1] * 5, np.vstack([sq, sq @ R.T]))
    )
    assert m.matching.status["B"] == "ambiguous" and not (m.names != "").any()
    assert "ambiguous" in m.matching.messages[0]


def test_target_list_names_targets(tmp_path):
    rng = np.random.default_rng(4)
    T = rng.uniform([0, 0, 0], [14, 11, 3], (12, 3))
    path = tmp_path / "list.csv"
    with open(path, "w") as fh:
        fh.write("name,x,y,z\n")
        for k, t in enumerate(T):
            fh.write(f"P{k},{t[0]:.6f},{t[1]:.6f},{t[2]:.6f}\n")
    listed = tj.read_reference(path)
    pose = np.array([5, 5, 1.5, 0.1, -0.2, 1.0])
    R = rotation_matrix(*pose[3:], xp=np)
    x = (T[2:] - pose[:3]) @ R.T
    m = tj.match_targets(tj.ExtractedTargets.from_centres(("A",), [0] * 10, x), target_list=listed)
    assert list(m.names) == [f"P{k}" for k in range(2, 12)]
    np.testing.assert_allclose(m.matching.pose["A"], pose, atol=1e-5)


def test_cli_extract_targets(room, tmp_path):
    paths = []
    for j in range(2):
        p = tmp_path / f"{room.scans[j]}.ply"
        x = cartesian_from_spherical(room.observations[j], xp=np)
        tj.write_ply(p, x, attributes={"intensity": room.intensity[j].astype(np.float32)})
        paths.append(str(p))
    out = tmp_path / "targets.csv"
    rc = main(
        ["extract-targets", *paths, "--spheres", "0.0725", "--checkerboards",
         "--out", str(out), "--plots", str(tmp_path / "png"), "--no-progress"]
    )  # fmt: skip
    assert rc == 0
    table = tj.read_observations(out)
    assert table.kind == "target" and table.sigmas is not None and len(table) >= 14
    assert set(table.scans) == {"S1", "S2"}
    rows = list(csv.DictReader(open(tmp_path / "targets_table.csv")))
    assert {"n_points", "rms_mm", "incidence_deg", "coverage", "reason"} <= set(rows[0])
    assert sorted(p.name for p in (tmp_path / "png").iterdir()) == ["S1.png", "S2.png"]
    assert main(["extract-targets", paths[0], "--out", str(out)]) == 2  # nothing to look for


def test_real_scan_without_targets_accepts_none(tmp_path):
    # A real scan of an industrial room (pye57's test data, thinned): pipes, tanks and clutter
    # give candidates, and every one is rejected with its reason (pipes by their fit RMS
    # against the scan's own 2-5 mm noise there, or by the shape of their residuals), but for
    # one round object of 42 points that no test can tell from a 100 mm sphere at that noise
    # (fit RMS 1.15 x the points' noise, no trend in its residuals); it finds no partner in
    # another scan, and the CLI says so (exit 1).
    out = tmp_path / "t.csv"
    args = ["extract-targets", str(DATA / "pump_every7th.e57"), "--spheres", "0.0725", "0.1"]
    assert main([*args, "--checkerboards", "--out", str(out), "--no-progress"]) == 1
    rows = list(csv.DictReader(open(tmp_path / "t_table.csv")))
    rejected = [r for r in rows if r["accepted"] == "False"]
    assert len(rejected) >= len(rows) - 1 and all(r["reason"] for r in rejected)
    assert {r["kind"] for r in rows if r["accepted"] == "True"} <= {"sphere"}
    assert not out.exists()


@pytest.mark.internal
def test_streamed_readers_carry_intensity():
    from tlsjax._io._scan_chunks import open_scans

    (scan,) = open_scans(DATA / "pump_every7th.e57")
    parts = list(scan.chunks(5000))
    pts = np.concatenate([p for p, _, _ in parts])
    inten = np.concatenate([i for _, i, _ in parts])
    ref = tj.read_point_clouds(DATA / "pump_every7th.e57")[0]
    np.testing.assert_allclose(pts, ref.points)
    assert scan.has_intensity and len(inten) == len(pts) and np.ptp(inten) > 0


@pytest.mark.parametrize(
    "kw, match",
    [
        (dict(spheres=(-0.1,)), "sphere radius"),
        (dict(sphere_model="exact"), "sphere_model"),
        (dict(min_coverage=2.0), "min_coverage"),
        (dict(pattern_size=0.0), "pattern_size"),
    ],
)
def test_options_are_checked(kw, match):
    with pytest.raises(ValueError, match=match):
        tj.TargetExtractionOptions(**kw)
    with pytest.raises(ValueError, match="nothing to look for"):
        tj.extract_targets([np.ones((10, 3))], tj.TargetExtractionOptions())


@pytest.fixture(scope="module")
def noisy_plate():
    # One checkerboard 9.5 m from S1 on the far wall, seen square on, with the range noise of
    # a phase scanner on black paper (5 x the white's 1.5 mm) and 3 % stray points 5-60 mm
    # behind it along their rays (mixed pixels at the plate's edge, a wall behind).
    target = tj.PlanarTarget((13.995, 4.5, 1.5), (-1, 0, 0), "checkerboard")
    design = tj.CloudDesign(
        angular_step=3 * DEG, target_step=0.04 * DEG, tilted=False, planar_targets=(target,),
        sigma_range=1.5e-3, dark_noise_factor=5.0,
    )  # fmt: skip
    pc = tj.simulate_point_clouds(design, seed=4)
    obs, inten = pc.observations[0].copy(), pc.intensity[0]
    on = np.flatnonzero(pc.target_ids[0] >= 0)
    stray = np.random.default_rng(0).choice(on, len(on) * 3 // 100, replace=False)
    obs[stray, 0] += np.random.default_rng(1).uniform(0.005, 0.06, len(stray))
    truth = cartesian_from_spherical(pc.target_observations()[("S1", pc.target_names[0])], xp=np)
    return obs, inten, truth


@pytest.mark.parametrize("size", [0.13, 0.15, 0.17])
def test_noisy_dark_squares_found_whatever_the_size_within_its_tolerance(noisy_plate, size):
    # Fixed limits (voxel flatness 0.1, plane RMS 3 mm) lost such targets; the tests now
    # compare with the points' own noise, and the size given is a prior +-30 %.
    obs, inten, truth = noisy_plate
    opts = tj.TargetExtractionOptions(checkerboards=True, pattern_size=size)
    found = tj.extract_targets([obs], opts, intensity=[inten])
    (i,) = np.flatnonzero(found.accepted)
    assert np.linalg.norm(found.centre[i] - truth) < 1e-3
    # Every rejected candidate says which test it failed, with its figure.
    for why in found.reason[~found.accepted]:
        assert any(ch.isdigit() for ch in why), why


def test_a_fit_that_wandered_off_says_so():
    from tlsjax._clouds._contrast import _judge

    rec = dict(kind="checkerboard", shift=0.72, n_points=0, converged=False, covariance=np.eye(3))
    why = _judge(rec, OPTIONS)
    assert why.startswith("the fit wandered 720 mm from the candidate, out of its 75 mm window")


def test_sphere_rms_limit_from_the_scans_noise():
    # A sphere scanned with 4 mm of range noise: a fixed 3 mm RMS limit refused it; the limit
    # is 3 x the noise the voxels measure there. A radius 9 mm off the nominal passes unless
    # the user gives a radius misfit limit.
    design = tj.CloudDesign(
        angular_step=3 * DEG, target_step=0.06 * DEG, tilted=False, sigma_range=4e-3,
        spheres=(tj.SphereTarget((8.0, 3.0, 1.5), 0.0815),),
    )  # fmt: skip
    pc = tj.simulate_point_clouds(design, seed=3)
    opts = dataclasses.replace(OPTIONS, checkerboards=False, circles=False)
    found = tj.extract_targets(pc.observations[:1], opts)
    (i,) = np.flatnonzero(found.accepted)
    assert found.rms[i] > 3e-3
    strict = tj.extract_targets(
        pc.observations[:1], dataclasses.replace(opts, max_radius_misfit=3e-3)
    )
    assert not strict.accepted.any() and "differs from the nominal" in " ".join(strict.reason)


def _one_target_scans(target, station, seeds, **design):
    """Scanner-space centre errors [m] (seeds, 3) of one target seen from one levelled station
    of a 40 x 40 x 4 m hall on a 0.03 deg grid, one simulation per seed (NaN: not accepted)."""
    errors = []
    for seed in range(seeds):
        d = tj.CloudDesign(
            room=tj.Room(length=40.0, width=40.0, height=4.0, stations=(station,)),
            scans=((*station, 0.0, 0.0, 0.2),), boards=(), angular_step=3 * DEG,
            target_step=0.03 * DEG, **design,
        )  # fmt: skip
        pc = tj.simulate_point_clouds(d, seed=seed)
        kinds = dict(spheres=(0.0725,)) if design.get("spheres") else dict(checkerboards=True)
        found = tj.extract_targets(
            pc.observations, tj.TargetExtractionOptions(**kinds), intensity=pc.intensity
        )
        X = cartesian_from_spherical(next(iter(pc.target_observations().values())), xp=np)
        acc = np.flatnonzero(found.accepted)
        errors.append(found.centre[acc[0]] - X if len(acc) == 1 else np.full(3, np.nan))
    return np.array(errors)


def test_far_sphere_judged_by_its_angular_noise_too():
    # At 28 m, 20" moves the limb's points along the sphere's normal by up to 2.7 mm, which
    # the voxels (one or two points each there) do not measure: with 0.5 mm of range noise the
    # fit RMS (about 2 mm) was judged against twice the voxels' 0.5 mm and the sphere refused
    # (benchmarks/bench_target_rooms.py lost such spheres at 1 mm of range noise too).
    err = _one_target_scans(
        None, (8.0, 20.0, 1.5), 2, sigma_range=0.5e-3,
        spheres=(tj.SphereTarget((36.0, 21.0, 1.6), 0.0725),),
    )  # fmt: skip
    assert np.all(np.isfinite(err)) and np.max(np.linalg.norm(err, axis=1)) < 2.5e-3


def test_checkerboard_points_go_onto_the_plate_along_their_noise():
    # 6.3 m at 57 deg, 4 mm of range noise on the black squares: projected along the plate's
    # normal, each point kept dr sin(57 deg) = 3.4 mm of it in the plane and the centres
    # scattered by 0.54 mm along the incidence (8 seeds); moved as a condition adjustment of
    # the point moves it (nearly along its ray), by 0.19 mm.
    beta = 57 * DEG
    c = np.array([39.998, 20.0, 1.5])
    station = (40.0 - 6.3 * np.cos(beta), 20.0 - 6.3 * np.sin(beta), 1.5)
    target = tj.PlanarTarget(tuple(c), (-1, 0, 0), "checkerboard", rotation=0.3)
    err = _one_target_scans(
        target, station, 6, sigma_range=1e-3, dark_noise_factor=4.0, planar_targets=(target,)
    )
    assert np.all(np.isfinite(err))
    assert np.sqrt(np.mean(np.sum(err**2, axis=1))) < 0.35e-3


@pytest.mark.internal
def test_target_fits_run_on_the_host_cpu_whatever_the_default_device(monkeypatch):
    """The small batched fits ask for the CPU device (an accelerator's default device is not
    used for them), and run on the default device where JAX has no CPU backend."""
    import jax

    from tlsjax._clouds import _lsq

    asked = []
    real = jax.default_device

    def recording(device):
        asked.append(device)
        return real(device)

    monkeypatch.setattr(jax, "default_device", recording)
    x = np.tile(np.linspace(0.0, 1.0, 8), (3, 1))
    line = lambda y, a: y[0] + y[1] * a[0] - a[1]  # noqa: E731
    y, *_ = _lsq.fit_batch(line, np.zeros((3, 2)), (x, 2.0 + 3.0 * x))
    np.testing.assert_allclose(y, [[2.0, 3.0]] * 3, atol=1e-9)
    assert [d.platform for d in asked] == ["cpu"]

    def no_cpu(*backend):
        raise RuntimeError("Unknown backend cpu")

    monkeypatch.setattr(jax, "devices", no_cpu)
    y, *_ = _lsq.fit_batch(line, np.zeros((3, 2)), (x, 1.0 - x))
    np.testing.assert_allclose(y, [[1.0, -1.0]] * 3, atol=1e-9)
    assert asked[-1] is None
