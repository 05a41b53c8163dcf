"""Applying a calibration to point clouds: round trip against the simulation's error-free points,
every format through the CLI, attributes kept, chunking, and precision vs Monte Carlo.

Private imports: ``tlsjax._cli.main`` is the ``tlsjax`` console script's entry point
(pyproject), called in process; the chunk sizes of ``_correct``, ``_correct_files`` and
``_las`` are set small to exercise chunking; geometry helpers and
``observations_from_points``/``to_object`` build the reference points.
"""

import json

import numpy as np
import pytest
from pyquaternion import Quaternion

import tlsjax as tj
from tlsjax import (
    Calibration,
    CloudDesign,
    cartesian_from_spherical,
    correct_points,
    read_point_clouds,
    rotation_matrix,
    simulate_point_clouds,
)
from tlsjax._cli import main
from tlsjax._io import _correct, _correct_files, _las
from tlsjax._io._point_clouds import observations_from_points, to_object

pytestmark = pytest.mark.internal

DEG = np.pi / 180
APS = ("A0", "A3", "B6", "B7", "B8", "C0", "C6")
J = 4  # a tilted scan


@pytest.fixture(scope="module", params=["hybrid", "panoramic"])
def sim(request):
    pc = simulate_point_clouds(
        CloudDesign(angular_step=3 * DEG, architecture=request.param, noise=False, aps=APS),
        seed=5,
    )
    pose = pc.eops[J]
    R = rotation_matrix(*pose[3:], xp=np)
    truth = (pc.true_points[J] - pose[:3]) @ R.T  # error-free scanner-space points
    x = cartesian_from_spherical(pc.observations[J], xp=np)  # what the scanner delivers
    return pc, x, truth, pose


def _cal_json(path, pc, cov_scale=1e-10):
    names = list(pc.true_aps)
    doc = {
        "aps": {n: {"value": pc.true_aps[n], "sigma": 1e-5, "unit": "m"} for n in names},
        "ap_covariance_names": names,
        "ap_covariance": (np.eye(len(names)) * cov_scale).tolist(),
        "scanner": {"architecture": pc.scanner.architecture, "unit_length": 1.2},
    }
    path.write_text(json.dumps(doc))
    return path


def _away_from_face_boundary(truth, arch):
    """Panoramic: a point within the AP shift of the face boundary (hybrid theta 0 or pi) is
    ambiguous from its Cartesian coordinates alone (either face gives the same point)."""
    if arch == "hybrid":
        return np.ones(len(truth), dtype=bool)
    th = observations_from_points(truth, "hybrid")[:, 1]
    d = np.minimum(np.abs(np.mod(th + np.pi / 2, np.pi) - np.pi / 2), np.pi)
    return d > 0.2 * DEG


def test_in_memory_round_trip_equals_error_free_points(sim):
    pc, x, truth, _ = sim
    cal = Calibration(tj.Scanner(pc.scanner.architecture, aps=APS), list(pc.true_aps.values()))
    xc, sig = correct_points(x, cal)
    ok = _away_from_face_boundary(truth, pc.scanner.architecture)
    assert ok.mean() > 0.99
    err = np.linalg.norm(xc - truth, axis=1)[ok]
    assert err.max() < 1e-10  # l = F + Delta(l) exactly, so l - Delta(l) = F
    assert np.linalg.norm(x - truth, axis=1).max() > 0.01  # the APs move points by centimetres
    assert not sig.any()


# Tolerance of each format's coordinates: LAS 0.1 mm grid, E57 (pye57) single precision, PTX
# and XYZ 1 micrometre, PLY float64.
FORMATS = {"las": 1e-4, "laz": 1e-4, "e57": 5e-6, "ptx": 2e-6, "xyz": 2e-6, "ply": 1e-9}


def _write(path, fmt, x, pose):
    n = len(x)
    inten = (np.arange(n) % 251).astype(np.float32)
    if fmt in ("las", "laz"):
        _las.write_las(path, to_object(x, pose), pose, attributes={"intensity": np.arange(n) % 999})
    elif fmt == "ply":
        tj.write_ply(
            path, x, attributes={"intensity": inten, "red": (np.arange(n) % 256).astype("u1")}
        )
    elif fmt == "e57":
        import pye57

        e57 = pye57.E57(str(path), mode="w")
        A = rotation_matrix(*pose[3:], xp=np).T
        data = {"cartesianX": x[:, 0], "cartesianY": x[:, 1], "cartesianZ": x[:, 2]}
        e57.write_scan_raw(
            data | {"intensity": inten},
            rotation=Quaternion(matrix=A).elements,
            translation=pose[:3],
            name="scan J",
        )
        e57.close()
    elif fmt == "ptx":
        # One "no return" line among the points: it must stay as written.
        xx = np.concatenate([x[:5], np.zeros((1, 3)), x[5:]])
        from tlsjax._io._point_clouds import write_ptx

        write_ptx(path, [(xx, pose)])
    else:
        np.savetxt(path, np.column_stack([x, inten]), fmt="%.9f")


@pytest.mark.parametrize("fmt", sorted(FORMATS))
def test_cli_round_trip_every_format(tmp_path, sim, fmt, capsys):
    pc, x, truth, pose = sim
    src = tmp_path / f"scan.{fmt}"
    _write(src, fmt, x, pose)
    cal = _cal_json(tmp_path / "cal.json", pc)
    out = tmp_path / "out"
    assert main(["correct", str(cal), str(src), "--out", str(out), "--precision"]) == 0
    text = capsys.readouterr().out
    assert f"{len(x)} of {len(x) + (fmt == 'ptx')} points corrected" in text
    (scan,) = read_point_clouds(out / src.name, architecture=pc.scanner.architecture)
    assert len(scan.points) == len(x)
    ok = _away_from_face_boundary(truth, pc.scanner.architecture)
    err = np.linalg.norm(scan.points - truth, axis=1)[ok]
    assert err.max() < FORMATS[fmt] * 1.8  # well below the 0.5 mm noise
    if fmt in ("las", "laz"):
        import laspy

        np.testing.assert_array_equal(pose, scan.pose)
        las = laspy.read(out / src.name)
        np.testing.assert_array_equal(las.intensity, np.arange(len(x)) % 999)
        assert np.all(las["calibration_sigma"] > 0)
    elif fmt == "ply":
        import plyfile

        v = plyfile.PlyData.read(str(out / src.name))["vertex"].data
        np.testing.assert_array_equal(v["red"], np.arange(len(x)) % 256)
        assert v["calibration_sigma"].min() > 0
    elif fmt == "e57":
        np.testing.assert_allclose(scan.pose, pose, atol=1e-12)
        import pye57

        data = pye57.E57(str(out / src.name)).read_scan_raw(0)
        np.testing.assert_array_equal(data["intensity"], (np.arange(len(x)) % 251))
    elif fmt == "ptx":
        lines = (out / src.name).read_text().splitlines()
        assert lines[:10] == src.read_text().splitlines()[:10]  # header and pose unchanged
        assert lines[15] == src.read_text().splitlines()[15] == "0 0 0 0.5"
        np.testing.assert_allclose(scan.pose, pose, atol=1e-12)
    if fmt in ("ptx", "xyz", "e57"):
        sig = np.loadtxt(str(out / src.name) + ".sigma_mm.txt")
        assert len(sig) == len(x) + (fmt == "ptx") and sig.max() > 0


def test_chunk_boundaries_do_not_matter(tmp_path, sim, monkeypatch):
    pc, x, truth, pose = sim
    cal = Calibration(
        tj.Scanner(pc.scanner.architecture, aps=APS), list(pc.true_aps.values()), np.eye(7) * 1e-9
    )
    whole, s_whole = correct_points(x, cal, precision=True)
    monkeypatch.setattr(_correct, "CHUNK", 1000)
    parts, s_parts = correct_points(x, cal, precision=True)
    # Another compiled size may round differently in the last bit, nothing more.
    np.testing.assert_allclose(parts, whole, rtol=0, atol=1e-12)
    np.testing.assert_allclose(s_parts, s_whole, rtol=1e-12, atol=0)
    # Text files in chunks of 700 lines, LAS files in chunks of 999 points.
    monkeypatch.setattr(_correct_files, "_TEXT_CHUNK", 700)
    monkeypatch.setattr(_las, "LAS_CHUNK", 999)
    for fmt in ("ptx", "las"):
        _write(tmp_path / f"s.{fmt}", fmt, x, pose)
        _correct_files.correct_point_cloud(tmp_path / f"s.{fmt}", cal, tmp_path / f"c.{fmt}")
        (scan,) = read_point_clouds(tmp_path / f"c.{fmt}", architecture=pc.scanner.architecture)
        assert np.abs(scan.points - whole).max() < 2 * FORMATS[fmt]  # in and out rounded


def test_precision_matches_monte_carlo_of_the_aps(sim):
    pc, x, truth, pose = sim
    rng = np.random.default_rng(0)
    k = len(APS)
    A = rng.standard_normal((k, k)) * 1e-4
    C = A @ A.T + np.eye(k) * 1e-9  # a full, correlated AP covariance [SI^2]
    values = np.array(list(pc.true_aps.values()))
    scanner = tj.Scanner(pc.scanner.architecture, aps=APS)
    pts = x[::40]
    _, sig = correct_points(pts, Calibration(scanner, values, C), precision=True)
    draws = rng.multivariate_normal(values, C, size=400)
    outs = np.stack([correct_points(pts, Calibration(scanner, d))[0] for d in draws])
    empirical = np.sqrt(np.sum(outs.var(axis=0, ddof=1), axis=1))
    # The correction is linear in the APs: the scatter matches up to sampling (7 % for 400).
    np.testing.assert_allclose(sig, empirical, rtol=0.2)
    assert np.median(np.abs(sig / empirical - 1)) < 0.08


def test_bad_inputs_one_line(tmp_path, sim, capsys):
    pc, x, truth, pose = sim
    src = tmp_path / "s.xyz"
    np.savetxt(src, x[:50])
    cal = _cal_json(tmp_path / "cal.json", pc)
    junk = tmp_path / "not_written_by_tlsjax" / "junk.json"
    junk.parent.mkdir()
    junk.write_text("{not json")
    (tmp_path / "multi.json").write_text(
        json.dumps({"aps": {"A0[a]": {"value": 0.001}, "A0[b]": {"value": 0.002}}})
    )
    cases = [
        ([str(junk), str(src)], "junk.json: not a readable result JSON"),
        ([str(tmp_path / "multi.json"), str(src)], "choose one with --instrument"),
        ([str(cal), str(tmp_path / "s.foo")], "unknown point-cloud format"),
        ([str(cal), str(tmp_path / "missing.ptx")], "missing.ptx: no such file"),
        ([str(cal), str(src), "--out", str(tmp_path)], "never writes over its inputs"),
    ]
    for argv, pattern in cases:
        if "--out" not in argv:
            argv = argv + ["--out", str(tmp_path / "o")]
        assert main(["correct", *argv]) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and pattern in err[0], err
    # A multi-instrument JSON with --instrument picks that block.
    cal_b = Calibration.from_json(tmp_path / "multi.json", instrument="b")
    assert cal_b.scanner.aps == ("A0",) and cal_b.values[0] == 0.002
    assert any("no scanner architecture" in n for n in cal_b.notes)


def test_from_a_target_calibration_end_to_end(tmp_path, capsys):
    # Calibrate the simulated room from targets, then correct a point cloud of the same scanner:
    # the corrected points lie within a few AP sigmas of the error-free ones.
    obs = tmp_path / "obs.csv"
    assert (
        main(
            ["simulate", "--out", str(obs), "--scans-out", str(tmp_path / "sc.csv"), "--seed", "3"]
        )
        == 0
    )
    cal = tmp_path / "cal.json"
    args = [
        "calibrate",
        str(obs),
        "--scans",
        str(tmp_path / "sc.csv"),
        "--no-vce",
        "--json",
        str(cal),
    ]
    assert main(args) == 0
    doc = json.loads(cal.read_text())
    assert doc["scanner"]["architecture"] == "hybrid" and doc["provenance"]["inputs"]
    pc = simulate_point_clouds(CloudDesign(angular_step=3 * DEG, noise=False), seed=5)
    x = cartesian_from_spherical(pc.observations[J], xp=np)
    R = rotation_matrix(*pc.eops[J, 3:], xp=np)
    truth = (pc.true_points[J] - pc.eops[J, :3]) @ R.T
    np.savetxt(tmp_path / "s.xyz", x, fmt="%.9f")
    capsys.readouterr()
    assert main(["correct", str(cal), str(tmp_path / "s.xyz"), "--out", str(tmp_path / "o")]) == 0
    (scan,) = read_point_clouds(tmp_path / "o" / "s.xyz")
    before = np.sqrt(np.mean(np.sum((x - truth) ** 2, axis=1)))
    after = np.sqrt(np.mean(np.sum((scan.points - truth) ** 2, axis=1)))
    assert before > 0.005 and after < 0.1 * before


def test_map_coordinates_are_refused_not_corrected(tmp_path, sim, capsys):
    # A public LAS file in UTM coordinates (PDAL's simple.laz) has no scan pose: applying scanner
    # APs to map coordinates would give a plausible but wrong cloud, so it is refused.
    import pathlib

    pc, *_ = sim
    cal = _cal_json(tmp_path / "cal.json", pc)
    src = pathlib.Path(__file__).parent / "data" / "simple.laz"
    assert main(["correct", str(cal), str(src), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "simple.laz" in err[0] and "map coordinates" in err[0]
    assert not (tmp_path / "o" / "simple.laz").exists()
