"""Vendor target lists in (issue 27 item 4): layouts, units, the panoramic fold, exact round
trips, sigmas, refusals, and the file path ``import-targets`` -> ``calibrate``.

Private imports: ``tlsjax._cli.main`` (the console script), the polar sigma propagation
``polar_sigmas`` checked against its closed form, and the scans-file writers that build the
inputs.
"""

import pathlib

import numpy as np
import pytest

import tlsjax as tj
from tlsjax._cli import main

DATA = pathlib.Path(__file__).parent / "data" / "target_lists"

#: The fixtures hold the same two scans in the layouts of the common exports.
LAYOUTS = {
    "PTS-like (count line, name x y z intensity)": ["Station1.pts", "Station2.pts"],
    "Cyclone-style (tab, numeric ids, header TargetID X Y Z)": [
        "cyclone_Station1.txt",
        "cyclone_Station2.txt",
    ],
    "SCENE-style (semicolon, decimal comma, mm in the header)": [
        "scene_Station1.csv",
        "scene_Station2.csv",
    ],
    "RiSCAN TPL SOCS-style (X[m], Height[m] beside Z[m])": [
        "riscan_tpl_socs_Station1.csv",
        "riscan_tpl_socs_Station2.csv",
    ],
    "RealWorks-style (one file, station column, sigma)": ["realworks_all_stations.csv"],
    "CloudCompare-style (//Name,X,Y,Z)": [
        "cloudcompare_Station1.txt",
        "cloudcompare_Station2.txt",
    ],
}


def _cartesian(obs):
    """Independent inverse of SPEC section 1 (valid for both faces)."""
    r, t, a = obs.T
    return np.stack([r * np.cos(a) * np.cos(t), r * np.cos(a) * np.sin(t), r * np.sin(a)], 1)


def _points(seed=0, n=60):
    """Scanner-frame points in every direction, 0.5 to 80 m away, some near the zenith/nadir."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d[:4] = [[1e-4, 2e-4, 1.0], [0, -1e-3, -1.0], [-1.0, 1e-12, 0.2], [-1.0, -1e-12, 0.2]]
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return d * rng.uniform(0.5, 80.0, size=(n, 1))


def _write(path, names, xyz, *, header="name,x,y,z", sep=",", scale=1.0, scans=None):
    lines = [header] if header else []
    for i, n in enumerate(names):
        cells = ([scans[i]] if scans is not None else []) + [n]
        cells += [f"{v * scale:.17g}" for v in xyz[i]]
        lines.append(sep.join(cells))
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.parametrize("layout", list(LAYOUTS))
def test_every_export_layout_reads_the_same_observations(layout):
    base = tj.read_target_list(
        [DATA / f for f in LAYOUTS["PTS-like (count line, name x y z intensity)"]], "hybrid"
    )
    t = tj.read_target_list([DATA / f for f in LAYOUTS[layout]], "hybrid")
    assert len(t) == 20 and t.kind == "target" and t.architecture == "hybrid"
    np.testing.assert_allclose(t.observations, base.observations, rtol=0, atol=1e-12)
    assert len(set(t.scans)) == 2
    text = " ".join(t.notes)
    if "SCENE" in layout:
        assert "decimal comma" in text and "mm (from the header)" in text and "Typ" in text
        assert t.primitives[0] == "Kugel T001"
    if "RiSCAN" in layout:
        assert "ignored columns: Height[m], Reflectance[dB]" in text
    if "RealWorks" in layout:
        assert t.scans[0] == "Station1" and t.sigmas is not None
    if "PTS" in layout:
        assert "point count" in text and "detected" in text


@pytest.mark.parametrize("architecture", ["hybrid", "panoramic"])
def test_cartesian_polar_cartesian_is_exact_and_the_fold_is_spec_section_1(tmp_path, architecture):
    xyz = _points()
    names = [f"P{i}" for i in range(len(xyz))]
    t = tj.read_target_list(_write(tmp_path / "S1.csv", names, xyz), architecture)
    obs = t.observations
    np.testing.assert_allclose(_cartesian(obs), xyz, rtol=0, atol=1e-12)
    np.testing.assert_allclose(obs[:, 0], np.linalg.norm(xyz, axis=1), rtol=1e-15)
    hyb_t = np.mod(np.arctan2(xyz[:, 1], xyz[:, 0]), 2 * np.pi)
    hyb_a = np.arctan2(xyz[:, 2], np.hypot(xyz[:, 0], xyz[:, 1]))
    if architecture == "hybrid":
        assert np.all((obs[:, 1] >= 0) & (obs[:, 1] < 2 * np.pi))
        np.testing.assert_allclose(obs[:, 1:], np.stack([hyb_t, hyb_a], 1), atol=1e-15)
    else:
        face2 = hyb_t >= np.pi
        assert face2.sum() > 10 and (~face2).sum() > 10
        assert np.all((obs[:, 1] >= 0) & (obs[:, 1] < np.pi))
        assert np.array_equal(obs[:, 2] > np.pi / 2, face2)
        np.testing.assert_allclose(obs[face2, 1], hyb_t[face2] - np.pi, atol=1e-15)
        np.testing.assert_allclose(obs[face2, 2], np.pi - hyb_a[face2], atol=1e-15)
        np.testing.assert_allclose(obs[~face2, 1:], np.stack([hyb_t, hyb_a], 1)[~face2], atol=0)
    # Through the observation CSV (17 digits) and back: the network sees the same numbers.
    tj.write_observations(tmp_path / "obs.csv", t)
    back = tj.read_observations(tmp_path / "obs.csv")
    assert back.architecture == architecture
    np.testing.assert_allclose(_cartesian(back.observations), xyz, rtol=0, atol=1e-12)


def test_one_file_with_a_scan_column_equals_one_file_per_scan_in_m_and_mm(tmp_path):
    xyz = [_points(1, 12), _points(2, 12)]
    names = [f"T{i}" for i in range(12)]
    per_file = tj.read_target_list(
        [
            _write(tmp_path / "A.txt", names, xyz[0], header="", sep=" "),
            _write(tmp_path / "B.txt", names, xyz[1], header="", sep=" "),
        ],
        "panoramic",
    )
    both = np.concatenate(xyz)
    one = tj.read_target_list(
        _write(
            tmp_path / "all.csv",
            names * 2,
            both,
            header="Scan;Target;X [mm];Y [mm];Z [mm]",
            sep=";",
            scale=1e3,
            scans=["A"] * 12 + ["B"] * 12,
        ),
        "panoramic",
    )
    assert one.scans == per_file.scans and one.primitives == per_file.primitives
    np.testing.assert_allclose(one.observations, per_file.observations, rtol=0, atol=1e-12)
    mm = tj.read_target_list(
        _write(tmp_path / "A_mm.txt", names, xyz[0], header="", sep="\t", scale=1e3),
        "panoramic",
        length_unit="mm",
        scan="A",
    )
    np.testing.assert_allclose(mm.observations, per_file.observations[:12], atol=1e-12)


def test_units_explicit_detected_or_refused_with_the_fix(tmp_path):
    names = [f"T{i}" for i in range(8)]
    near = _points(3, 8) / 10.0  # median range a few metres
    m = tj.read_target_list(_write(tmp_path / "m.csv", names, near), "hybrid")
    mm = tj.read_target_list(_write(tmp_path / "mm.csv", names, near, scale=1e3), "hybrid")
    np.testing.assert_allclose(mm.observations, m.observations, atol=1e-12)
    assert "m (detected" in m.notes[0] and "mm (detected" in mm.notes[0]
    # A median range of 1,000 file units is 1 m in mm or 1 km in m: refused, naming the fix.
    amb = near / np.median(np.linalg.norm(near, axis=1)) * 1000.0
    with pytest.raises(ValueError, match="ambiguous.*--length-unit m\\|mm"):
        tj.read_target_list(_write(tmp_path / "amb.csv", names, amb), "hybrid")
    ok = tj.read_target_list(tmp_path / "amb.csv", "hybrid", length_unit="mm")
    np.testing.assert_allclose(ok.observations[:, 0], np.linalg.norm(amb, axis=1) / 1e3)
    # A header unit that contradicts the one given, and files detected in different units.
    _write(tmp_path / "h.csv", names, near, header="name,x[mm],y[mm],z[mm]")
    with pytest.raises(ValueError, match="the header says mm but length_unit m"):
        tj.read_target_list(tmp_path / "h.csv", "hybrid", length_unit="m")
    with pytest.raises(ValueError, match="detected length units differ"):
        tj.read_target_list([tmp_path / "m.csv", tmp_path / "mm.csv"], "hybrid")


@pytest.mark.internal
def test_sigmas_from_the_file_are_propagated_to_range_and_angles(tmp_path):
    xyz = _points(4, 10)
    names = [f"T{i}" for i in range(10)]
    lines = ["name,x,y,z,sigma_mm"] + [
        f"{n},{p[0]:.17g},{p[1]:.17g},{p[2]:.17g},0.7" for n, p in zip(names, xyz)
    ]
    (tmp_path / "s.csv").write_text("\n".join(lines) + "\n")
    t = tj.read_target_list(tmp_path / "s.csv", "panoramic")
    rho = np.linalg.norm(xyz, axis=1)
    cos_a = np.hypot(xyz[:, 0], xyz[:, 1]) / rho
    expect = np.stack([np.full(10, 7e-4), 7e-4 / (rho * cos_a), 7e-4 / rho], axis=1)
    np.testing.assert_allclose(t.sigmas, expect, rtol=1e-12)
    # Per-axis sigmas: the diagonal of J diag(s^2) J^T, J by central differences.
    from tlsjax._io._target_lists import polar_sigmas

    s = np.abs(np.random.default_rng(5).normal(1e-3, 3e-4, size=(10, 3)))

    def f(x):
        h = np.hypot(x[:, 0], x[:, 1])
        return np.stack(
            [np.linalg.norm(x, axis=1), np.arctan2(x[:, 1], x[:, 0]), np.arctan2(x[:, 2], h)], 1
        )

    J = np.zeros((10, 3, 3))
    for k in range(3):
        e = np.zeros(3)
        e[k] = 1e-6
        d = f(xyz + e) - f(xyz - e)
        J[:, :, k] = np.arctan2(np.sin(d), np.cos(d)) / 2e-6  # across the branch cut at 180 deg
        J[:, 0, k] = d[:, 0] / 2e-6
    fd = np.sqrt(np.einsum("nij,nj->ni", J**2, s**2))
    np.testing.assert_allclose(polar_sigmas(xyz, s), fd, rtol=1e-6)


@pytest.mark.parametrize(
    "text, match",
    [
        ("T1,1,2,3\nT1,2,3,4\nT2,1,1,1\nT3,2,2,2\n", "T1 of scan bad is listed twice.*line 1"),
        ("1.5 2 3 4\n2.5 3 4 5\n3.5 1 1 1\n", "decimal numbers"),
        ("name,x,y,z\nT1,0,0,0\nT2,1,2,3\n", "origin"),
        ("name,x,y,z\n", "no data lines"),
        ("Target 1 1.0 2.0 3.0\nT2 1.0 2.0 3.0\n", "no layout found.*--columns"),
    ],
)
def test_bad_lists_are_refused_in_one_line_naming_the_file(tmp_path, text, match):
    path = tmp_path / "bad.txt"
    path.write_text(text)
    with pytest.raises(ValueError, match=match) as err:
        tj.read_target_list(path, "hybrid")
    assert "\n" not in str(err.value) and ("bad.txt" in str(err.value) or "columns" in match)


def test_columns_override_and_two_files_of_one_scan_name(tmp_path):
    path = tmp_path / "odd.txt"
    path.write_text("1.0 2.0 3.0 T1 S9\n2.0 3.0 1.0 T2 S9\n4.0 1.0 2.0 T3 S9\n")
    t = tj.read_target_list(path, "hybrid", columns="x,y,z,name,scan")
    assert t.scans == ("S9",) * 3 and t.primitives == ("T1", "T2", "T3")
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    for d in ("a", "b"):
        (tmp_path / d / "S1.txt").write_text("T1 1 2 3\nT2 2 3 1\n")
    with pytest.raises(ValueError, match="scan 'S1' is also the scan of"):
        tj.read_target_list([tmp_path / "a" / "S1.txt", tmp_path / "b" / "S1.txt"], "hybrid")


@pytest.mark.internal
def test_import_targets_then_calibrate_equals_the_polar_file(tmp_path, capsys):
    """A panoramic simulation written as per-scan Cartesian lists in millimetres: import-targets
    gives the simulated observations back (to 1e-12), records the architecture, and calibrate
    reads it without --architecture to the same APs as the simulated network."""
    sim = tj.simulate(architecture="panoramic", tilted=True, aps="A0 B6 B7 C0", seed=3)
    net = sim.network
    xyz = _cartesian(np.asarray(net.observations))
    files = []
    for j, s in enumerate(net.scans):
        rows = np.flatnonzero(net.scan_index == j)
        files.append(
            _write(
                tmp_path / f"{s}.txt",
                [net.targets[t] for t in net.target_index[rows]],
                xyz[rows],
                header="Name X[mm] Y[mm] Z[mm]",
                sep=" ",
                scale=1e3,
            )
        )
    out = tmp_path / "obs.csv"
    assert (
        main(["import-targets", *map(str, files), "--out", str(out), "--architecture", "panoramic"])
        == 0
    )
    printed = capsys.readouterr().out
    assert "folded into the second face" in printed and "mm (from the header)" in printed
    table = tj.read_observations(out)
    assert table.architecture == "panoramic"
    np.testing.assert_allclose(table.observations[:, 0], net.observations[:, 0], atol=1e-12)
    d = table.observations[:, 1:] - net.observations[:, 1:]
    assert np.abs(np.arctan2(np.sin(d), np.cos(d))).max() < 1e-12
    scans = tmp_path / "scans.csv"
    from tlsjax._io._tables import levelling_of_network, write_scans

    write_scans(scans, levelling_of_network(net))
    cal = tmp_path / "cal.json"
    assert (
        main(
            [
                "calibrate",
                str(out),
                "--scans",
                str(scans),
                "--aps",
                "A0 B6 B7 C0",
                "--no-vce",
                "--no-screen",
                "--json",
                str(cal),
            ]
        )
        == 0
    )
    assert "panoramic scanner (recorded in the file)" in capsys.readouterr().out
    same = tj.make_network(  # the simulated arrays with the default sigmas the file implies
        [net.scans[j] for j in net.scan_index],
        [net.targets[t] for t in net.target_index],
        net.observations,
        levelling=levelling_of_network(net),
    )
    ref = tj.calibrate(same, tj.CalibrationModel(sim.scanner))
    got = tj.Calibration.from_json(cal)
    assert got.scanner.architecture == "panoramic"
    np.testing.assert_allclose(got.values, ref.ap_values, rtol=1e-7, atol=1e-12)
    # A file recorded for one architecture is refused for the other, with the fix named.
    assert main(["calibrate", str(out), "--architecture", "hybrid"]) == 2
    assert "give --architecture panoramic" in capsys.readouterr().err


def test_import_targets_refusals_are_one_line_before_writing(tmp_path, capsys):
    names = [f"T{i}" for i in range(6)]
    pts = _points(6, 6)
    amb = _write(tmp_path / "S1.txt", names, pts / np.median(np.linalg.norm(pts, axis=1)) * 1e3)
    out = tmp_path / "obs.csv"
    argv = ["import-targets", str(amb), "--out", str(out), "--architecture", "hybrid"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "S1.txt: the length unit is ambiguous" in err and "--length-unit" in err
    assert err.count("\n") == 1 and not out.exists()
    assert main(argv + ["--length-unit", "mm"]) == 0
    assert "units: mm (given)" in capsys.readouterr().out
    assert tj.read_observations(out).architecture == "hybrid"
