"""Point-cloud readers on public files written by other software, their broken variants, LAS/LAZ
round trips with the scan pose, and the messages for missing libraries.

Private imports: ``tlsjax._cli.main`` is the ``tlsjax`` console script's entry point
(pyproject), called in process; the optional-library loader's messages; geometry helpers and
``to_object`` build the reference points.
"""

import os
import pathlib
import warnings

import numpy as np
import pytest

import tlsjax  # noqa: F401  (x64)
from tlsjax import (
    CloudDesign,
    PointCloudWarning,
    cartesian_from_spherical,
    read_point_clouds,
    simulate_point_clouds,
    write_las,
    write_ply,
)
from tlsjax._cli import main

DATA = pathlib.Path(__file__).parent / "data"
DEG = np.pi / 180


@pytest.mark.internal
def test_optional_libraries_import():
    # CI must fail, not skip, when a library of the point-cloud formats cannot be imported
    # (e.g. open3d without the system library libusb-1.0-0).
    from tlsjax._optional import require

    for module in ("open3d", "pye57", "laspy", "lazrs", "plyfile"):
        require(module, "the test suite")


@pytest.mark.internal
def test_missing_library_messages_name_the_fix():
    from tlsjax._optional import missing_library_message, require

    err = OSError("libusb-1.0.so.0: cannot open shared object file: No such file or directory")
    msg = missing_library_message("open3d", "plane extraction", err)
    assert "libusb-1.0.so.0" in msg and "apt-get install -y libusb-1.0-0" in msg
    assert "pip" not in msg
    msg = missing_library_message("laspy", "reading LAS", ModuleNotFoundError("No module 'laspy'"))
    assert "pip install 'tlsjax[las]'" in msg
    with pytest.raises(ImportError, match="needs the Python package no_such_module_xyz"):
        require("no_such_module_xyz", "a test")


# (file, [(scan name, kept points, stored points, pose or None, number of notes)]); counts and
# poses read off the files' headers and text (tests/data/README.md).
PUBLIC = [
    ("simple.laz", [("simple", 1065, 1065, None, 1)]),  # UTM coordinates: map-scale note
    ("100-points.las", [("100-points", 100, 100, None, 1)]),
    ("A_B.e57", [("A_B_1", 2, 2, None, 0), ("A_B_2", 4, 4, None, 0)]),
    # One of four points is exactly (0, 0, 0); pose: translation (4, 5, 6), no rotation.
    ("translationWithoutRotation.e57", [("translationWithoutRotation", 3, 4, [4, 5, 6, 0, 0, 0], 1)]),
    ("testWithNormals.e57", [("testWithNormals", 2, 2, None, 0)]),
    ("utm17_space.pcd", [("utm17_space", 10, 10, None, 1)]),
    ("utm17_comma.pcd", [("utm17_comma", 10, 10, None, 1)]),
    ("simple_text.ply", [("simple_text", 3, 3, None, 0)]),
    # Eight "0 0 0" (no return) of 12 points; the pose is the PTX transform.
    ("complex-transform.ptx", [("complex-transform", 4, 12, "ptx", 1)]),
]  # fmt: skip


@pytest.mark.parametrize("name,expected", PUBLIC, ids=[p[0] for p in PUBLIC])
def test_public_files_counts_and_poses(name, expected):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        scans = read_point_clouds(DATA / name)
    assert len(scans) == len(expected)
    for scan, (sname, n, stored, pose, n_notes) in zip(scans, expected):
        assert (scan.name, len(scan.points), scan.n_stored) == (sname, n, stored)
        assert len(scan.notes) == n_notes
        assert len(scan.index) == n and scan.index.max() < stored
        if pose is None:
            assert scan.pose is None
        elif pose == "ptx":
            lines = (DATA / name).read_text().splitlines()
            M = np.array([[float(v) for v in ln.split()] for ln in lines[6:10]])
            R_file = M[:3, :3]  # rows: the scanner's axes in object space, R = M[:3, :3]
            from tlsjax import rotation_matrix

            R = rotation_matrix(*scan.pose[3:], xp=np)
            np.testing.assert_allclose(R, R_file, atol=2e-5)  # the file's matrix has 6 digits
            np.testing.assert_allclose(scan.pose[:3], M[3, :3], atol=1e-12)
        else:
            np.testing.assert_allclose(scan.pose, pose, atol=1e-12)
    assert [str(w.message) for w in caught if w.category is PointCloudWarning] == [
        n for s in scans for n in s.notes
    ]


REFUSED = [
    ("garbage_nVariableLength.las", r"claims 1069128089 variable-length records"),
    ("no-points.las", r"holds no points"),
    ("sized_dims.ply", r"PLY vertex element has no z property"),
    ("multiple-and-transform.ptx", r"line 7: PTX transform's rotation part is not a rotation"),
]


@pytest.mark.parametrize("name,pattern", REFUSED, ids=[r[0] for r in REFUSED])
def test_public_broken_files_refused_in_one_line(name, pattern, capsys, tmp_path):
    with pytest.raises(ValueError, match=pattern) as info:
        read_point_clouds(DATA / name)
    msg = str(info.value)
    assert "\n" not in msg and name in msg
    # Through the CLI: exit code 2 and one line on stderr.
    assert main(["extract-planes", str(DATA / name), "--out", str(tmp_path / "p.npz")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and name in err[0]


def _variants(raw: bytes):
    """Truncations and overwritten bytes of a file."""
    n = len(raw)
    for cut in sorted({8, 60, 240, n // 3, n // 2, n - 100, n - 7}):
        if 0 < cut < n:
            yield f"cut{cut}", raw[:cut]
    for start in sorted({50, 100, 230, n // 2, n - 300}):
        if 0 < start < n - 16:
            b = bytearray(raw)
            b[start : start + 16] = b"\xff" * 16
            yield f"ff{start}", bytes(b)


BROKEN_SOURCES = ["simple.laz", "100-points.las", "A_B.e57", "translationWithoutRotation.e57"]


@pytest.mark.parametrize("name", BROKEN_SOURCES)
def test_broken_variants_read_or_refused_in_one_line(tmp_path, name):
    raw = (DATA / name).read_bytes()
    stem, ext = os.path.splitext(name)
    for tag, data in _variants(raw):
        path = tmp_path / f"{stem}_{tag}{ext}"
        path.write_bytes(data)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", PointCloudWarning)
            try:
                scans = read_point_clouds(path)
            except ValueError as err:
                msg = str(err)
                assert "\n" not in msg and str(path) in msg, (tag, msg)
                continue
        for s in scans:  # read: then with finite points and consistent counts
            assert np.all(np.isfinite(s.points)) and len(s.points) <= s.n_stored


def test_ply_binary_and_text_round_trip(tmp_path):
    rng = np.random.default_rng(0)
    x = rng.uniform(-20, 20, size=(50, 3))
    for text in (False, True):
        path = tmp_path / f"s{int(text)}.ply"
        write_ply(path, x, attributes={"intensity": np.arange(50, dtype=np.float32)}, text=text)
        (scan,) = read_point_clouds(path)
        np.testing.assert_array_equal(scan.points, x)
        assert scan.notes == () and scan.n_stored == 50


@pytest.fixture(scope="module")
def scan():
    pc = simulate_point_clouds(CloudDesign(angular_step=4 * DEG, noise=False), seed=3)
    j = 4  # a tilted scan
    return pc.observations[j], pc.eops[j]


@pytest.mark.internal
@pytest.mark.parametrize("ext", ["las", "laz"])
def test_las_round_trip_with_pose_in_header(tmp_path, scan, ext):
    from tlsjax._io._point_clouds import to_object

    l, pose = scan
    x = cartesian_from_spherical(l, xp=np)
    X = to_object(x, pose)  # a LAS file holds object-space coordinates
    path = tmp_path / f"s.{ext}"
    write_las(path, X, pose, attributes={"intensity": np.arange(len(X)) % 65535})
    (got,) = read_point_clouds(path)
    np.testing.assert_array_equal(got.pose, pose)
    assert got.frame == "object" and got.notes == ()
    # 0.1 mm coordinate resolution: half a step per axis at most.
    assert np.abs(got.points - x).max() <= 0.5e-4 * np.sqrt(3) + 1e-9
    # Without the pose record, the poses argument supplies it.
    write_las(path, X)
    (plain,) = read_point_clouds(path)
    assert plain.pose is None and plain.frame == "scanner"
    (given,) = read_point_clouds(path, poses={"s": pose})
    np.testing.assert_allclose(given.points, got.points, atol=1e-12)


@pytest.mark.internal
def test_map_coordinates_without_pose_are_reported(tmp_path, scan):
    from tlsjax._io._point_clouds import to_object

    l, pose = scan
    x = cartesian_from_spherical(l, xp=np)
    shifted = dict(pose=np.r_[pose[:3] + [4.5e5, 5.2e6, 300.0], pose[3:]])
    X = to_object(x, shifted["pose"])
    write_las(tmp_path / "utm.las", X)
    with pytest.warns(PointCloudWarning, match=rf"{len(X)} point\(s\) have a median range of 5\.2"):
        (s,) = read_point_clouds(tmp_path / "utm.las")
    assert len(s.notes) == 1
    with warnings.catch_warnings():
        warnings.simplefilter("error", PointCloudWarning)
        (s,) = read_point_clouds(tmp_path / "utm.las", poses={"utm": shifted["pose"]})
    assert np.abs(np.linalg.norm(s.points, axis=1) - l[:, 0]).max() < 1e-3


def test_e57_invalid_points_are_dropped_and_counted(tmp_path):
    import pye57

    x = np.array([[1.0, 2.0, 3.0], [5.0, 5.0, 5.0], [0.0, 0.0, 0.0], [2.0, -1.0, 0.5]])
    state = np.array([0, 2, 1, 0], dtype=np.int8)
    e57 = pye57.E57(str(tmp_path / "inv.e57"), mode="w")
    e57.write_scan_raw(
        {
            "cartesianX": x[:, 0],
            "cartesianY": x[:, 1],
            "cartesianZ": x[:, 2],
            "cartesianInvalidState": state,
        }
    )
    e57.close()
    with pytest.warns(PointCloudWarning, match=r"dropped 2 point\(s\) flagged invalid"):
        (s,) = read_point_clouds(tmp_path / "inv.e57")
    assert list(s.index) == [0, 3] and s.n_stored == 4
    np.testing.assert_allclose(s.points, x[[0, 3]], atol=1e-6)
