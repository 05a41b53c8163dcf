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


_LAYOUTS = [
    # (file name, header, columns written, where x y z and intensity are)
    ("cc.txt", "//X Y Z R G B Intensity", "xyzrgbi", "by the header"),
    ("cc_comma.asc", "//X,Y,Z,Rf,Gf,Bf,Intensity", "xyzrgbi", "by the header"),
    ("plain.csv", "X,Y,Z,Intensity", "xyzi", "by the header"),
    (
        "riscan.txt",
        "X[m] Y[m] Z[m] Amplitude[dB] Reflectance[dB] Deviation",
        "xyzaid",
        "by the header",
    ),
    ("pcl.xyz", "# x y z intensity", "xyzi", "by the header"),
    ("cyclone.pts", "{n}", "xyzirgb", "by the column count"),
    ("four.xyz", None, "xyzi", "by the column count"),
]


def _write_columns(path, header, layout, P, inten):
    rng = np.random.default_rng(0)
    cols = {"x": P[:, 0], "y": P[:, 1], "z": P[:, 2], "i": inten}
    cols |= {k: rng.integers(0, 255, len(P)).astype(float) for k in "rgbad"}
    sep = "," if path.suffix == ".csv" or (header and "," in header) else " "
    with open(path, "w") as fh:
        if header:
            fh.write(header.format(n=len(P)) + "\n")
        np.savetxt(fh, np.stack([cols[c] for c in layout], 1), fmt="%.6f", delimiter=sep)


@pytest.mark.parametrize("name, header, layout, how", _LAYOUTS)
def test_text_columns_by_name(tmp_path, name, header, layout, how):
    # Intensity by its name (never the red column of "//X Y Z R G B Intensity"; RiSCAN's
    # reflectance, not its amplitude), PTS by its format; the streamed reader and the whole-file
    # reader agree on x y z.
    from tlsjax._io._point_clouds import text_layout
    from tlsjax._io._scan_chunks import open_scans

    rng = np.random.default_rng(1)
    P, inten = rng.uniform(-5, 5, (50, 3)), rng.uniform(100, 2000, 50)
    path = tmp_path / name
    _write_columns(path, header, layout, P, inten)
    lines = path.read_text().splitlines()
    assert text_layout(lines, str(path), pts=name.endswith(".pts")).how == how
    ((pts, got, _),) = list(open_scans(path)[0].chunks())
    np.testing.assert_allclose(pts, P, atol=1e-6)
    np.testing.assert_allclose(got, inten, atol=1e-6)
    (scan,) = read_point_clouds(path)
    np.testing.assert_allclose(scan.points, P, atol=1e-6)


def test_unnamed_columns_are_refused_with_the_fix(tmp_path):
    from tlsjax._io._scan_chunks import open_scans

    rng = np.random.default_rng(2)
    P, inten = rng.uniform(-5, 5, (20, 3)), rng.uniform(100, 2000, 20)
    path = tmp_path / "seven.txt"
    _write_columns(path, None, "xyzrgbi", P, inten)
    with pytest.raises(ValueError, match=r"seven.txt: 7 unnamed columns.*--columns x,y,z"):
        open_scans(path)
    ((_, got, _),) = list(open_scans(path, columns="x,y,z,r,g,b,intensity")[0].chunks())
    np.testing.assert_allclose(got, inten, atol=1e-6)
    (scan,) = read_point_clouds(path)  # x y z only: the first three in every convention
    np.testing.assert_allclose(scan.points, P, atol=1e-6)
