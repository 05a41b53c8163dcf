"""Plane extraction and matching against the simulation's ground-truth plane labels.

Private imports: ``tlsjax._cli.main`` is the ``tlsjax`` console script's entry point
(pyproject), called in process and its parser; the poses file reader and the PTX/XYZ writers
make the fixtures; geometry helpers build the reference points.
"""

import argparse
import dataclasses
import json
import pathlib

import numpy as np
import open3d  # noqa: F401  (CI fails, not skips, without it)
import pytest

import tlsjax as tj
from tlsjax import (
    CloudDesign,
    ExtractionOptions,
    MatchingOptions,
    extract_planes,
    match_planes,
    read_extracted_planes,
    read_observations,
    simulate_point_clouds,
    write_extracted_planes,
    write_observations,
)
from tlsjax._cli import main

DEG = np.pi / 180
DATA = pathlib.Path(__file__).parent / "data"
MIN_FOUND = 0.95  # fraction of a plane's points in a scan that extraction must find


@pytest.fixture(scope="module")
def room():
    # 1 deg grid: boards get 50-200 points per scan, walls thousands. APs and noise as SPEC 8.
    return simulate_point_clouds(CloudDesign(angular_step=1.0 * DEG), seed=11)


@pytest.fixture(scope="module")
def matched(room):
    ex = extract_planes(room.observations, ExtractionOptions(), seed=0)
    return match_planes(ex, room.eops)


@pytest.fixture(scope="module")
def small(room):
    # Two scans (of one station), at most 100 points per patch.
    return extract_planes(room.observations[:2], ExtractionOptions(budget=100), seed=4)


def _true_labels(pc, planes):
    return np.concatenate(
        [pc.plane_ids[j][planes.point_index[planes.point_scan == j]] for j in range(len(pc.scans))]
    )


def test_every_plane_found_in_every_scan(room, matched):
    cfg = ExtractionOptions()
    n_checked = 0
    for j, ids in enumerate(room.plane_ids):
        found = np.zeros(len(ids), dtype=bool)
        found[matched.point_index[matched.point_scan == j]] = True
        for k in range(len(room.planes)):
            n_k = int((ids == k).sum())
            if n_k < 2 * cfg.min_points:
                continue  # too few points in this scan to be a patch at all
            n_checked += 1
            assert found[ids == k].mean() >= MIN_FOUND, (
                room.scans[j],
                room.plane_names[k],
                found[ids == k].mean(),
            )
    assert n_checked >= 45  # 6 scans x 9 planes, less the boards seen by fewer than 60 points


def test_matching_gives_one_global_plane_per_true_plane(room, matched):
    true = _true_labels(room, matched)
    K, G = len(room.planes), len(matched.planes)
    assert G == K  # no false planes, no split planes
    confusion = np.zeros((G, K), dtype=int)
    np.add.at(confusion, (matched.point_plane, true), 1)
    purity = confusion.max(axis=1) / confusion.sum(axis=1)
    assert purity.min() > 0.995
    # A bijection: each true plane is the majority of exactly one global plane.
    assert sorted(confusion.argmax(axis=1)) == list(range(K))
    # Fitted object-space planes agree with the truth to within the uncalibrated APs' effect.
    for g, k in enumerate(confusion.argmax(axis=1)):
        n, d = matched.planes[g, :3], matched.planes[g, 3]
        assert np.degrees(np.arccos(min(1.0, n @ room.planes[k, :3]))) < 0.2
        assert abs(d - room.planes[k, 3]) < 0.03


def test_incidence_and_refinement(room, matched):
    true = _true_labels(room, matched)
    inc_true = np.concatenate(
        [room.incidence[j][matched.point_index[matched.point_scan == j]] for j in range(6)]
    )
    confusion = np.zeros((len(matched.planes), len(room.planes)), dtype=int)
    np.add.at(confusion, (matched.point_plane, true), 1)
    # Points on the right plane (the few edge points of a neighbour plane have its incidence).
    ok = confusion.argmax(axis=1)[matched.point_plane] == true
    assert ok.mean() > 0.995
    assert np.degrees(np.abs(matched.incidence[ok] - inc_true[ok])).max() < 1.0
    # Patch RMS a few mm: noise 0.5 mm sec(beta) + 20" plus the APs' bending of the planes.
    assert matched.patch_rms.max() < 0.006
    assert len(true) == len(matched.observations)


def test_deterministic_and_budget(room, small):
    obs = room.observations[:2]
    a = small
    b = extract_planes(obs, ExtractionOptions(budget=100), seed=4)
    for name in ("patch_scan", "patch_normal", "point_index", "observations"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    counts = np.bincount(a.point_patch)
    assert counts.max() <= 100
    np.testing.assert_array_equal(counts, np.minimum(a.patch_inliers, 100))
    # The kept observations are rows of the input.
    for j in range(2):
        sel = a.point_scan == j
        np.testing.assert_array_equal(a.observations[sel], obs[j][a.point_index[sel]])


def _plane_points(rng, centre, u, v, half, n):
    s = rng.uniform(-half, half, size=(n, 2))
    return centre + s[:, :1] * u + s[:, 1:] * v


def test_disjoint_coplanar_patches_and_overlap():
    # Two 1 m squares of the plane z = -1.5 in scanner space, 3 m apart, and one wall x = 4:
    # DBSCAN splits the floor into two patches; matching joins them only without the overlap test.
    rng = np.random.default_rng(0)
    ex_, ey, ez = np.eye(3)
    floor1 = _plane_points(rng, np.array([1.0, -1.5, -1.5]), ex_, ey, 0.5, 2000)
    floor2 = _plane_points(rng, np.array([1.0, 1.5, -1.5]), ex_, ey, 0.5, 2000)
    wall = _plane_points(rng, np.array([4.0, 0.0, 0.0]), ey, ez, 1.0, 2000)
    x = np.concatenate([floor1, floor2, wall])
    rho = np.linalg.norm(x, axis=1)
    obs = np.stack(
        [rho, np.mod(np.arctan2(x[:, 1], x[:, 0]), 2 * np.pi), np.arcsin(x[:, 2] / rho)], axis=1
    )
    ex = extract_planes([obs], ExtractionOptions(min_points=50), seed=0)
    assert len(ex.patch_scan) == 3
    normals = np.round(np.abs(ex.patch_normal), 6)
    assert sorted(map(tuple, normals)) == [(0, 0, 1), (0, 0, 1), (1, 0, 0)]
    # Normals face the scanner at the origin: n . 0 - d > 0.
    assert np.all(ex.patch_distance < 0)
    label = np.repeat([0, 1, 2], 2000)
    for p in range(3):
        assert len(np.unique(label[ex.point_index[ex.point_patch == p]])) == 1
    np.testing.assert_allclose(np.sort(-ex.patch_distance), [1.5, 1.5, 4.0], atol=1e-9)
    # Coplanar patches of one scan are one plane (an occluded floor), with or without overlap.
    merged = match_planes(ex, np.zeros((1, 6)), MatchingOptions(overlap_distance=0.5))
    joined = match_planes(ex, np.zeros((1, 6)), MatchingOptions(overlap_distance=None))
    apart = match_planes(
        ex, np.zeros((1, 6)), MatchingOptions(overlap_distance=0.5, merge_coplanar_in_scan=False)
    )
    assert len(merged.planes) == 2 and len(joined.planes) == 2 and len(apart.planes) == 3
    floor = [p for p in merged.to_dict()["planes"] if abs(p["normal"][2]) > 0.9]
    assert len(floor) == 1 and floor[0]["n_patches"] == 2 and floor[0]["n_points"] == 4000


def _patches(specs, rng, n=400):
    """ExtractedPlanes of one scan from (centre, normal) squares of 1 m, points exact."""

    obs, normals, dists, patch = [], [], [], []
    for p, (c, nrm) in enumerate(specs):
        nrm = np.asarray(nrm, float) / np.linalg.norm(nrm)
        u = np.cross(nrm, [0.0, 1.0, 0.0] if abs(nrm[1]) < 0.9 else [1.0, 0.0, 0.0])
        u /= np.linalg.norm(u)
        v = np.cross(nrm, u)
        x = _plane_points(rng, np.asarray(c, float), u, v, 0.5, n)
        rho = np.linalg.norm(x, axis=1)
        obs.append(np.stack([rho, np.mod(np.arctan2(x[:, 1], x[:, 0]), 2 * np.pi),
                             np.arcsin(x[:, 2] / rho)], axis=1))  # fmt: skip
        d = float(nrm @ np.asarray(c, float))
        normals.append(nrm if d < 0 else -nrm)
        dists.append(-abs(d))
        patch.append(np.full(n, p))
    P = len(specs)
    return tj.ExtractedPlanes(
        scans=("S1",),
        patch_scan=np.zeros(P, dtype=np.int64),
        patch_normal=np.array(normals),
        patch_distance=np.array(dists),
        patch_rms=np.zeros(P),
        patch_inliers=np.full(P, n),
        patch_plane=np.full(P, -1),
        point_patch=np.concatenate(patch),
        point_index=np.arange(P * n),
        observations=np.concatenate(obs),
        incidence=np.zeros(P * n),
    )


def test_no_chaining_past_the_angle_limit():
    # Floor patches side by side, each tilted 2.4 deg more than its neighbour about the y axis
    # through its own centre: neighbours are within the 3 deg limit, the ends 4.8 deg apart. A
    # chain of matches joined all three; every patch of a plane must be within the limits of
    # every other and of the plane's fit.
    rng = np.random.default_rng(1)
    t = np.radians(2.4)
    specs = [((1.0 + 1.05 * k, 0.0, -1.5), (np.sin(k * t), 0.0, np.cos(k * t))) for k in range(3)]
    planes = match_planes(_patches(specs, rng), np.zeros((1, 6)))
    assert len(planes.planes) == 2
    for p in planes.to_dict()["planes"]:
        assert np.degrees(p["max_patch_angle"]) <= 3.0
    groups = [set(np.flatnonzero(planes.patch_plane == g)) for g in range(2)]
    assert {0, 2} not in [g & {0, 2} for g in groups]  # the ends are never one plane
    # Within the limit (1.1 deg, 2 mm apart): one floor, not two planes.
    t = np.radians(1.1)
    specs = [((1.0, 0.0, -1.5), (0, 0, 1)), ((3.0, 0.0, -1.502), (np.sin(t), 0, np.cos(t)))]
    one = match_planes(_patches(specs, rng), np.zeros((1, 6)))
    assert len(one.planes) == 1 and one.to_dict()["planes"][0]["n_patches"] == 2


def test_table_and_npz_round_trip(tmp_path, room, small):
    matched = match_planes(small, room.eops[:2])
    table = matched.to_table()
    assert table.kind == "plane" and len(table) == len(matched.observations)
    write_observations(tmp_path / "planes.csv", table, angle_unit="rad")
    back = read_observations(tmp_path / "planes.csv")
    assert back.primitives == table.primitives and back.scans == table.scans
    np.testing.assert_allclose(back.observations, table.observations, rtol=0, atol=1e-12)
    write_extracted_planes(tmp_path / "planes.npz", matched)
    again = read_extracted_planes(tmp_path / "planes.npz")
    assert again.scans == matched.scans
    for name in ("patch_plane", "point_index", "observations", "incidence", "planes", "poses"):
        np.testing.assert_array_equal(getattr(again, name), getattr(matched, name))
    with pytest.raises(ValueError, match="match_planes"):
        extract_planes([matched.observations[:10]], ExtractionOptions(min_points=3)).to_table()
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(ValueError, match="bad.npz"):
        read_extracted_planes(tmp_path / "bad.npz")


@pytest.mark.internal
def test_read_poses(tmp_path):
    from tlsjax._io._plane_files import read_poses

    p = tmp_path / "poses.csv"
    p.write_text("scan,x_m,y_m,z_mm,omega_deg,phi_deg,kappa_gon\nA,1,2,3000,90,0,100\n")
    poses = read_poses(p)
    np.testing.assert_allclose(poses["A"], [1, 2, 3, np.pi / 2, 0, np.pi / 2])
    p.write_text("scan,x_m,y_m,z_deg,omega_deg,phi_deg,kappa_deg\nA,1,2,3,0,0,0\n")
    with pytest.raises(ValueError, match=r"poses.csv, line 1, column z_deg"):
        read_poses(p)
    p.write_text("scan,x_m,y_m,z_m,omega_deg,phi_deg,kappa_deg\nA,1,2,oops,0,0,0\n")
    with pytest.raises(ValueError, match=r"line 2, column z_m"):
        read_poses(p)


@pytest.mark.internal
def test_cli_extract_planes(tmp_path, room):
    # Two scans of different stations as one PTX file with their poses; CSV and npz out.
    from tlsjax import cartesian_from_spherical
    from tlsjax._cli._extract import add_extract_parser
    from tlsjax._io._point_clouds import write_ptx

    scans = [(cartesian_from_spherical(room.observations[j], xp=np), room.eops[j]) for j in (0, 3)]
    write_ptx(tmp_path / "room.ptx", scans)
    parser = argparse.ArgumentParser()
    add_extract_parser(parser.add_subparsers())
    args = parser.parse_args(
        [
            "extract-planes",
            str(tmp_path / "room.ptx"),
            "--out",
            str(tmp_path / "p.npz"),
            "--csv",
            str(tmp_path / "p.csv"),
            "--budget",
            "200",
        ]
    )
    assert args.func(args) == 0
    planes = read_extracted_planes(tmp_path / "p.npz")
    assert planes.scans == ("room_1", "room_2")
    assert len(planes.planes) == 9
    table = read_observations(tmp_path / "p.csv")
    assert len(set(table.primitives)) == 9 and len(table) <= 200 * len(planes.patch_scan)
    # The matched planes go straight into a calibration (the poses in the file are not needed:
    # tlsjax registers the scans plane to plane for its approximate values).
    out = tmp_path / "r.json"
    args = ["--planes", str(tmp_path / "p.npz"), "--json", str(out), "--plane-spacing", "0"]
    assert main(["calibrate", *args]) == 0  # all points (no thinning), as extracted
    js = json.loads(out.read_text())
    assert js["n_plane_points"] == len(planes.observations) and len(js["planes"]) == 9
    assert js["converged"] and set(js["aps"]) == {"A0", "B6", "B7", "C0"}


@pytest.mark.internal
def test_cli_with_poses_file(tmp_path, room, capsys):
    from tlsjax import cartesian_from_spherical
    from tlsjax._cli._extract import add_extract_parser
    from tlsjax._io._point_clouds import write_xyz

    rows = ["scan,x_m,y_m,z_m,omega_rad,phi_rad,kappa_rad"]
    files = []
    for j in (1, 4):
        write_xyz(
            tmp_path / f"{room.scans[j]}.xyz", cartesian_from_spherical(room.observations[j], xp=np)
        )
        files.append(str(tmp_path / f"{room.scans[j]}.xyz"))
        rows.append(",".join([room.scans[j]] + [f"{v:.17g}" for v in room.eops[j]]))
    (tmp_path / "poses.csv").write_text("\n".join(rows) + "\n")
    parser = argparse.ArgumentParser()
    add_extract_parser(parser.add_subparsers())
    args = parser.parse_args(
        [
            "extract-planes",
            *files,
            "--out",
            str(tmp_path / "p.npz"),
            "--poses",
            str(tmp_path / "poses.csv"),
            "--budget",
            "50",
        ]
    )
    assert args.func(args) == 0
    printed = capsys.readouterr()
    assert "9 planes" in printed.out
    # Progress on stderr (no terminal here: one line per phase and per scan, with times).
    for line in ("extracting planes", f"scan {room.scans[4]}: ", "matched 9 planes"):
        assert line in printed.err, printed.err
    planes = read_extracted_planes(tmp_path / "p.npz")
    np.testing.assert_allclose(planes.poses, room.eops[[1, 4]], rtol=0, atol=1e-15)
    # Without poses two scans cannot be matched; asking for the CSV then is an error.
    args = parser.parse_args(
        [
            "extract-planes",
            *files,
            "--out",
            str(tmp_path / "q.npz"),
            "--csv",
            str(tmp_path / "q.csv"),
        ]
    )
    with pytest.raises(ValueError, match="--poses"):
        args.func(args)


def _at_most(table, n, seed):
    """At most ``n`` random rows of each (scan, plane) of a plane table."""
    rng = np.random.default_rng(seed)
    key = np.unique(np.stack([table.scans, table.primitives], 1), axis=0, return_inverse=True)[
        1
    ].reshape(-1)
    keep = np.sort(
        np.concatenate(
            [rng.permutation(np.flatnonzero(key == k))[:n] for k in range(key.max() + 1)]
        )
    )
    return dataclasses.replace(
        table,
        scans=tuple(np.array(table.scans)[keep]),
        primitives=tuple(np.array(table.primitives)[keep]),
        observations=table.observations[keep],
        incidence=table.incidence[keep],
        rows=table.rows[keep],
        sigmas=None if table.sigmas is None else table.sigmas[keep],
    )


def test_calibration_from_extracted_planes_agrees_with_known_planes(room, matched):
    # The same scans, adjusted once with the simulation's plane labels and once with the planes
    # that extraction and matching found (their own names, incidence estimated from the fitted
    # normals). Both draw 300 points per plane and scan; the APs must agree within their sigmas.
    model = tj.CalibrationModel(room.scanner)
    known = tj.calibrate(room.to_network(300, seed=0), model)
    found = tj.calibrate(
        tj.make_plane_network(_at_most(matched.to_table(), 300, seed=1), levelling=room.levelling),
        model,
    )
    for r in (known, found):
        assert r.ok and r.converged, r.message
        assert abs(r.sigma0 - 1) < 0.1  # extraction kept no outliers that would inflate sigma0
    assert len(found.planes) == len(known.planes)
    z = (found.ap_values - known.ap_values) / np.hypot(found.ap_sigmas, known.ap_sigmas)
    assert np.abs(z).max() < 3, dict(zip(known.ap_names, z))
    truth = np.array([room.true_aps[n] for n in found.ap_names])
    assert (np.abs(found.ap_values - truth) / found.ap_sigmas).max() < 4


def test_clutter_gives_no_false_planes(room):
    # Random points in a shell 2-10 m around the scanner: no plane, so no patch. The same number
    # of random points inside the room added to a real scan: the same planes, nearly pure.
    rng = np.random.default_rng(1)
    u = rng.standard_normal((20000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)

    def observe(x):
        rho = np.linalg.norm(x, axis=1)
        return np.stack(
            [rho, np.mod(np.arctan2(x[:, 1], x[:, 0]), 2 * np.pi), np.arcsin(x[:, 2] / rho)], axis=1
        )

    assert (
        len(extract_planes([observe(u * rng.uniform(2, 10, 20000)[:, None])], seed=0).patch_scan)
        == 0
    )
    from tlsjax import rotation_matrix

    j = 3
    X = rng.uniform([0.5, 0.5, 0.2], [13.5, 10.5, 2.8], size=(20000, 3))
    clutter = (X - room.eops[j, :3]) @ rotation_matrix(*room.eops[j, 3:], xp=np).T
    obs = np.concatenate([room.observations[j], observe(clutter)])
    label = np.concatenate([room.plane_ids[j], np.full(20000, -1)])
    ex = match_planes(extract_planes([obs], seed=0), room.eops[j : j + 1])
    counts = np.bincount(room.plane_ids[j], minlength=len(room.planes))
    visible = np.flatnonzero(counts >= 2 * ExtractionOptions().min_points)
    assert len(ex.planes) == len(visible)
    for g in range(len(ex.planes)):
        lab = label[ex.point_index[ex.point_plane == g]]
        majority = np.bincount(lab[lab >= 0]).argmax()
        assert (
            lab == majority
        ).mean() > 0.97  # a clutter point or two inside a board's 3-sigma slab
    found = np.zeros(len(label), dtype=bool)
    found[ex.point_index] = True
    for k in visible:
        assert found[label == k].mean() > MIN_FOUND


def test_cli_on_a_real_scan(tmp_path, capsys):
    # An industrial room scanned by a real scanner (every 7th point of pye57's
    # pumpAVisualReferenceImage.e57, tests/data/README.md): the largest plane is the floor of the
    # levelled scan, about 1.9 m below the scanner, and every plane is a surface of mm RMS.
    from tlsjax._cli import main as cli

    src = DATA / "pump_every7th.e57"
    assert cli(["extract-planes", str(src), "--out", str(tmp_path / "p.npz")]) == 0
    out = capsys.readouterr().out
    assert "22172 of 22172 points" in out and "RMS [mm]" in out
    planes = read_extracted_planes(tmp_path / "p.npz")
    assert len(planes.planes) >= 5
    n, d = planes.planes[0, :3], planes.planes[0, 3]
    assert abs(n[2]) > np.cos(np.radians(1.0)) and 1.8 < abs(d) < 2.0
    for p in planes.to_dict()["planes"]:
        assert p["rms"] < ExtractionOptions().max_rms and p["n_scans"] == 1
