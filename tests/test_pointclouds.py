"""Point-cloud readers: round trips through files against the simulated observations.

Private imports: the PTX/XYZ writers and ``observations_from_points`` make the fixtures;
geometry helpers build the reference points.
"""

import numpy as np
import pytest

import tlsjax  # noqa: F401  (x64)
from tlsjax import (
    CloudDesign,
    PointCloudWarning,
    cartesian_from_spherical,
    read_point_clouds,
    simulate_point_clouds,
)

DEG = np.pi / 180


@pytest.fixture(scope="module", params=["hybrid", "panoramic"])
def clouds(request):
    # Noise-free: every observation's face follows from its own direction (SPEC section 1).
    return simulate_point_clouds(
        CloudDesign(angular_step=4 * DEG, architecture=request.param, noise=False), seed=2
    )


def _write_pcd_double(path, x):
    header = (
        "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z\nSIZE 8 8 8\nTYPE F F F\nCOUNT 1 1 1\n"
        f"WIDTH {len(x)}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(x)}\nDATA ascii\n"
    )
    with open(path, "w") as fh:
        fh.write(header)
        np.savetxt(fh, x, fmt="%.17g")


@pytest.mark.internal
@pytest.mark.parametrize("fmt", ["xyz", "ptx", "ply", "pcd"])
def test_round_trip_equals_simulated_observations(tmp_path, clouds, fmt):
    from tlsjax._io._point_clouds import write_ptx, write_xyz

    arch = clouds.scanner.architecture
    j = 4  # a tilted scan
    l = clouds.observations[j]
    x = cartesian_from_spherical(l, xp=np)
    path = tmp_path / f"scan.{fmt}"
    if fmt == "xyz":
        write_xyz(path, x)
    elif fmt == "ptx":
        write_ptx(path, [(x, clouds.eops[j])])
    elif fmt == "pcd":
        _write_pcd_double(path, x)
    else:
        import open3d as o3d

        o3d.io.write_point_cloud(str(path), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(x)))
    (scan,) = read_point_clouds(path, architecture=arch)
    assert scan.name == "scan" and scan.architecture == arch
    np.testing.assert_allclose(scan.observations, l, rtol=0, atol=1e-9)
    if fmt == "ptx":
        np.testing.assert_allclose(scan.pose, clouds.eops[j], rtol=0, atol=1e-12)
    else:
        assert scan.pose is None


def test_open3d_pcd_is_single_precision(tmp_path, clouds):
    # open3d writes PCD coordinates as float32: a 10 m range keeps about 1e-6 m.
    import open3d as o3d

    l = clouds.observations[0]
    x = cartesian_from_spherical(l, xp=np)
    o3d.io.write_point_cloud(
        str(tmp_path / "s.pcd"), o3d.geometry.PointCloud(o3d.utility.Vector3dVector(x))
    )
    (scan,) = read_point_clouds(tmp_path / "s.pcd", architecture=clouds.scanner.architecture)
    err = np.abs(scan.observations - l).max()
    assert 1e-12 < err < 2e-6


@pytest.mark.internal
def test_ptx_several_scans_and_zero_points(tmp_path, clouds):
    from tlsjax._io._point_clouds import write_ptx

    arch = clouds.scanner.architecture
    scans = [
        (cartesian_from_spherical(clouds.observations[j], xp=np), clouds.eops[j]) for j in (0, 5)
    ]
    # A "no return" point in the middle of the first scan.
    x0 = scans[0][0]
    scans[0] = (np.concatenate([x0[:10], np.zeros((1, 3)), x0[10:]]), scans[0][1])
    write_ptx(tmp_path / "two.ptx", scans)
    a, b = read_point_clouds(tmp_path / "two.ptx", architecture=arch)
    assert (a.name, b.name) == ("two_1", "two_2")
    np.testing.assert_allclose(a.observations, clouds.observations[0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(b.observations, clouds.observations[5], rtol=0, atol=1e-9)
    np.testing.assert_allclose(b.pose, clouds.eops[5], rtol=0, atol=1e-12)
    # The pose maps the scanner-space points onto the simulation's object-space points.
    from tlsjax import rotation_matrix

    R = rotation_matrix(*b.pose[3:], xp=np)
    X = b.points @ R + b.pose[:3]
    if clouds.scanner.aps == ():  # pragma: no cover - the fixture has APs
        np.testing.assert_allclose(X, clouds.true_points[5], atol=1e-9)
    else:
        assert np.abs(X - clouds.true_points[5]).max() < 0.05


def test_e57_round_trip(tmp_path, clouds):
    import pye57
    from pyquaternion import Quaternion

    from tlsjax import rotation_matrix

    j = 3
    x = cartesian_from_spherical(clouds.observations[j], xp=np)
    A = rotation_matrix(*clouds.eops[j, 3:], xp=np).T  # X = A x + S
    e57 = pye57.E57(str(tmp_path / "s.e57"), mode="w")
    e57.write_scan_raw(
        {"cartesianX": x[:, 0], "cartesianY": x[:, 1], "cartesianZ": x[:, 2]},
        rotation=Quaternion(matrix=A).elements,
        translation=clouds.eops[j, :3],
    )
    e57.close()
    (scan,) = read_point_clouds(tmp_path / "s.e57", architecture=clouds.scanner.architecture)
    np.testing.assert_allclose(scan.pose, clouds.eops[j], rtol=0, atol=1e-12)
    # pye57 writes coordinates in single precision.
    np.testing.assert_allclose(scan.observations, clouds.observations[j], rtol=0, atol=2e-6)


@pytest.mark.internal
def test_panoramic_convention_by_hand():
    from tlsjax._io._point_clouds import observations_from_points

    x = np.array([[1.0, 1.0, 0.0], [-1.0, -1.0, 0.0], [0.0, -2.0, 2.0]])
    hyb = observations_from_points(x, "hybrid")
    pan = observations_from_points(x, "panoramic")
    np.testing.assert_allclose(hyb[:, 1], [np.pi / 4, 5 * np.pi / 4, 3 * np.pi / 2])
    np.testing.assert_allclose(pan[:, 1], [np.pi / 4, np.pi / 4, np.pi / 2])
    np.testing.assert_allclose(pan[:, 2], [0.0, np.pi, np.pi - np.pi / 4])
    np.testing.assert_allclose(pan[:, 0], [np.sqrt(2), np.sqrt(2), np.sqrt(8)])
    np.testing.assert_allclose(cartesian_from_spherical(pan, xp=np), x, atol=1e-15)


@pytest.mark.internal
def test_bad_input_names_file_and_line(tmp_path):
    from tlsjax._io._point_clouds import write_ptx

    p = tmp_path / "bad.xyz"
    p.write_text("# comment\n1 2 3\n\n4 five 6\n")
    with pytest.raises(ValueError, match=r"bad\.xyz, line 4: not a number"):
        read_point_clouds(p)
    p.write_text("1 2 3\n4 5\n")
    with pytest.raises(ValueError, match=r"bad\.xyz, line 2: expected at least 3 numbers"):
        read_point_clouds(p)
    p.write_text("1 2 3\n0 0 0\n")
    with pytest.warns(
        PointCloudWarning, match=r"bad\.xyz: scan bad: dropped 1 point\(s\) at exactly"
    ):
        (scan,) = read_point_clouds(p)
    assert len(scan.points) == 1 and scan.n_stored == 2 and list(scan.index) == [0]

    good = tmp_path / "good.ptx"
    write_ptx(good, [(np.array([[1.0, 2.0, 3.0], [2.0, 1.0, 0.5]]), None)])
    lines = good.read_text().splitlines()
    bad = tmp_path / "bad.ptx"
    bad.write_text("\n".join(lines[:-1]) + "\n")
    with pytest.raises(
        ValueError, match=r"bad\.ptx, line 11: PTX scan at line 1 needs 2 point lines"
    ):
        read_point_clouds(bad)
    bad.write_text("\n".join(["two"] + lines[1:]) + "\n")
    with pytest.raises(ValueError, match=r"bad\.ptx, line 1: PTX scan must start"):
        read_point_clouds(bad)
    rot = lines[:6] + ["2 0 0 0"] + lines[7:]
    bad.write_text("\n".join(rot) + "\n")
    with pytest.raises(ValueError, match=r"bad\.ptx, line 7: .*not a rotation"):
        read_point_clouds(bad)
    short = lines[:8] + ["1 2"] + lines[9:]
    bad.write_text("\n".join(short) + "\n")
    with pytest.raises(ValueError, match=r"bad\.ptx, line 9: PTX header line needs 4 numbers"):
        read_point_clouds(bad)
    pts = lines[:11] + ["1 2 x 0.5"]
    bad.write_text("\n".join(pts) + "\n")
    with pytest.raises(ValueError, match=r"bad\.ptx, line 12: not a number"):
        read_point_clouds(bad)

    with pytest.raises(ValueError, match=r"unknown point-cloud format '\.foo'"):
        (tmp_path / "a.foo").write_text("x")
        read_point_clouds(tmp_path / "a.foo")
    with pytest.raises(ValueError, match="architecture"):
        read_point_clouds(good, architecture="mirror")
    with pytest.raises(FileNotFoundError):
        read_point_clouds(tmp_path / "missing.ply")
    (tmp_path / "junk.ply").write_text("not a ply\n")
    with pytest.raises(ValueError, match=r"junk\.ply: not a readable PLY file"):
        read_point_clouds(tmp_path / "junk.ply")


def test_ptx_transform_convention_by_hand(tmp_path):
    # Leica PTX: [X Y Z 1] = [x y z 1] M, translation in M's last row. A scanner turned by
    # kappa = 90 deg (R = R3(90 deg) maps object to scanner space) at S = (10, 20, 30).
    text = "2\n1\n10 20 30\n0 1 0\n-1 0 0\n0 0 1\n0 1 0 0\n-1 0 0 0\n0 0 1 0\n10 20 30 1\n1 0 0 0.5\n0 0 2 0.5\n"
    (tmp_path / "hand.ptx").write_text(text)
    (scan,) = read_point_clouds(tmp_path / "hand.ptx")
    np.testing.assert_allclose(scan.pose, [10, 20, 30, 0, 0, np.pi / 2], atol=1e-15)
    from tlsjax import rotation_matrix

    X = scan.points @ rotation_matrix(*scan.pose[3:], xp=np) + scan.pose[:3]
    np.testing.assert_allclose(X, [[10, 21, 30], [10, 20, 32]], atol=1e-14)
    np.testing.assert_allclose(scan.observations, [[1, 0, 0], [2, 0, np.pi / 2]], atol=1e-15)
