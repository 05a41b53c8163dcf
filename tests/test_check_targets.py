"""Before and after from the API and the CLI (issue 27 item 5): adjusted targets with sigmas in
the JSON and a CSV, ``check-targets`` against a reference survey, and every JSON tlsjax writes
read back by ``Calibration.from_json`` with its architecture."""

import dataclasses
import json

import numpy as np
import pytest
from strict_json import load_strict

import tlsjax as tj
from tlsjax import rotation_matrix
from tlsjax._cli import main

APS = "A0 B6 B7 C0"
REF_NOISE = 3e-4  # reference survey, per coordinate [m]


@pytest.fixture(scope="module")
def room():
    noisy = tj.simulate(tilted=True, aps=APS, seed=11)
    exact = tj.simulate(tilted=True, aps=APS, seed=11, noise=False)
    assert np.array_equal(noisy.true_targets, exact.true_targets)
    cal = tj.Calibration(
        tj.Scanner(aps=tuple(noisy.true_aps)), np.array(list(noisy.true_aps.values()))
    )
    return noisy, exact, cal


def _reference(sim, noise, seed=0):
    """The true targets in a survey frame far away, with survey noise."""
    rng = np.random.default_rng(seed)
    R = rotation_matrix(0.002, -0.003, 2.1, xp=np)
    t = np.array([512_000.0, 5_400_000.0, 310.0])
    X = sim.true_targets @ R.T + t + rng.normal(0.0, noise, sim.true_targets.shape)
    return {n: X[i] for i, n in enumerate(sim.network.targets)}


def test_true_aps_give_noise_level_and_none_give_the_ap_effect(room):
    noisy, exact, cal = room
    # Noise-free scans and an exact reference: the corrected placement is the truth, and the
    # uncorrected one differs by the APs' effect alone.
    ex = tj.check_targets(exact.network, cal, _reference(exact, 0.0))
    assert ex.network["with"]["rms"]["xyz_mm"] < 1e-5
    assert ex.per_scan.with_correction["range_mm"] < 1e-5
    assert ex.per_scan.with_correction["hz_arcsec"] < 1e-4
    effect = ex.network["without"]["rms"]
    assert effect["xyz_mm"] > 3.0  # 10 mm and 3' APs move the targets by millimetres
    # Noisy scans and a noisy reference: with the true APs the differences are what the
    # targets' a posteriori sigmas and the survey noise predict; without, the AP effect on top.
    chk = tj.check_targets(noisy.network, cal, _reference(noisy, REF_NOISE))
    res = tj.calibrate(noisy.network, tj.CalibrationModel(noisy.scanner))
    predicted = np.sqrt(np.mean(res.target_sigmas**2, axis=0) + REF_NOISE**2) * 1e3
    got = chk.network["with"]["rms"]
    ratio = np.array([got["x_mm"], got["y_mm"], got["z_mm"]]) / predicted
    assert np.all((ratio > 0.7) & (ratio < 1.4)), ratio
    without = chk.network["without"]["rms"]
    for k in ("x_mm", "y_mm", "z_mm", "xyz_mm"):
        expect = np.hypot(effect[k], got[k])
        assert abs(without[k] - expect) < 0.15 * expect, (k, without[k], expect)
    assert chk.improvement()["xyz_mm"] > 80
    assert chk.per_scan.without["range_mm"] > 3 * chk.per_scan.with_correction["range_mm"]
    assert len(chk.names) == len(noisy.network.targets) and "with calibration" in chk.summary()
    # A 7-parameter fit reports its scale; leaving out targets leaves them out.
    sim7 = tj.check_targets(
        noisy.network, cal, _reference(noisy, REF_NOISE), transform="7-parameter", exclude=["T001"]
    )
    assert abs(sim7.network["with"]["scale_ppm"]) < 50 and "T001" not in sim7.names
    assert sim7.network["with"]["rms"]["xyz_mm"] <= got["xyz_mm"] * 1.01


def test_a_reference_in_other_units_is_named_not_fitted(room):
    noisy, _, cal = room
    ref = {k: v * 1e3 for k, v in _reference(noisy, REF_NOISE).items()}  # mm read as m
    with pytest.raises(ValueError, match="unit mix-up"):
        tj.check_targets(noisy.network, cal, ref)


def test_targets_in_the_json_are_the_dense_covariance_blocks(room):
    noisy, _, _ = room
    res = tj.calibrate(
        noisy.network,
        tj.CalibrationModel(noisy.scanner),
        tj.SolverOptions(full_covariance=True),
    )
    doc = res.to_dict()
    names = list(res.parameter_names)
    for t in ("T001", "T050", "T120"):
        idx = [names.index(f"{c}[{t}]") for c in "XYZ"]
        dense = res.covariance[np.ix_(idx, idx)]
        k = res.targets.index(t)
        np.testing.assert_allclose(res.target_covariance[k], dense, rtol=1e-8, atol=1e-16)
        axes = np.array(doc["targets"][t]["ellipsoid_axes"])
        np.testing.assert_allclose(np.sort(axes**2), np.linalg.eigvalsh(dense), rtol=1e-8)
        np.testing.assert_allclose(doc["targets"][t]["sigma"], np.sqrt(np.diag(dense)), rtol=1e-8)
        np.testing.assert_allclose(doc["targets"][t]["xyz"], res.target_xyz[k], rtol=0, atol=0)
    assert doc["targets"]["T001"]["n_scans"] == len(
        set(noisy.network.scan_index[noisy.network.target_index == 0].tolist())
    )
    assert "inner constraints" in doc["targets_frame"]
    failed = dataclasses.replace(res, result=3, message="rank defect").to_dict()
    assert failed["targets"]["T001"]["xyz"] == [None, None, None]


def test_every_result_json_keeps_the_architecture(tmp_path):
    sim = tj.simulate(architecture="panoramic", tilted=True, aps=APS, seed=4)
    res = tj.calibrate(sim.network, tj.CalibrationModel(sim.scanner))
    tj.write_json(res, tmp_path / "api.json")
    cal = tj.Calibration.from_json(tmp_path / "api.json")
    assert cal.scanner.architecture == "panoramic" and not cal.notes
    np.testing.assert_array_equal(cal.values, res.ap_values)
    # The CLI path: simulate --architecture panoramic, calibrate with no architecture given.
    obs, truth = tmp_path / "pan.csv", tmp_path / "truth.json"
    assert (
        main(["simulate", "--architecture", "panoramic", "--out", str(obs), "--truth", str(truth)])
        == 0
    )
    out = tmp_path / "cal.json"
    assert (
        main(
            ["calibrate", str(obs), "--scans", str(tmp_path / "pan_scans.csv"), "--json", str(out)]
        )
        == 0
    )
    for path in (out, truth):
        c = tj.Calibration.from_json(path)
        assert c.scanner.architecture == "panoramic" and c.scanner.aps == ("A0", "B6", "B7", "C0")
        # A simulation's truth is applied, and named as such (issue 39 item 7).
        assert [n for n in c.notes if "true APs of a simulation" not in n] == [], c.notes
        assert (path == truth) == bool(c.notes)
    true = load_strict(truth)["aps"]
    np.testing.assert_allclose(tj.Calibration.from_json(truth).values, list(true.values()))
    # `tlsjax compare` takes the architecture from the JSONs it compares (APSet.from_json).
    for path in (out, tmp_path / "api.json"):
        assert tj.APSet.from_json(path).scanner.architecture == "panoramic"


def test_check_targets_cli_calibrate_targets_out_and_held_out_scans(tmp_path, capsys):
    obs, scans, truth = tmp_path / "obs.csv", tmp_path / "scans.csv", tmp_path / "truth.json"
    argv = ["simulate", "--out", str(obs), "--scans-out", str(scans), "--truth", str(truth)]
    assert main(argv + ["--aps", APS, "--seed", "5"]) == 0
    doc = load_strict(truth)
    sim = tj.simulate(tilted=True, aps=APS, seed=5)
    ref = _reference(sim, REF_NOISE, seed=3)
    lines = ["Point;E [mm];N [mm];H [mm]"] + [
        f"{n};{x[0] * 1e3:.3f};{x[1] * 1e3:.3f};{x[2] * 1e3:.3f}".replace(".", ",")
        for n, x in ref.items()
    ]
    (tmp_path / "survey.csv").write_text("\n".join(lines) + "\n")
    out = tmp_path / "check.json"
    argv = ["check-targets", str(truth), str(obs), "--reference", str(tmp_path / "survey.csv")]
    assert (
        main(argv + ["--scans", str(scans), "--transform", "7-parameter", "--json", str(out)]) == 0
    )
    printed = capsys.readouterr().out
    assert "without calibration" in printed and "largest 3D differences" in printed
    got = load_strict(out)
    api = tj.check_targets(
        tj.read_observations(obs),
        tj.Calibration.from_json(truth),
        tj.read_reference(tmp_path / "survey.csv"),
        transform="7-parameter",
        levelling=tj.read_scans(scans),
    )
    for case in ("without", "with"):
        for k, v in api.network[case]["rms"].items():
            assert got["network"][case]["rms"][k] == pytest.approx(v, rel=1e-6, abs=1e-6)
    assert got["network"]["with"]["scale_ppm"] is not None
    assert got["per_scan"]["with"]["range_mm"] < got["per_scan"]["without"]["range_mm"]
    back = tj.Calibration.from_json(out)  # the check records the calibration it applied
    np.testing.assert_allclose(back.values, list(doc["aps"].values()))
    # calibrate writes the targets (JSON and CSV); its own scans placed with its own APs give
    # its targets back: the cross-validation of held-out scans runs on the same command.
    cal, tg = tmp_path / "cal.json", tmp_path / "targets.csv"
    argv = ["calibrate", str(obs), "--scans", str(scans), "--aps", APS, "--no-vce"]
    assert main(argv + ["--json", str(cal), "--targets-out", str(tg)]) == 0
    t_json = load_strict(cal)["targets"]
    t_csv = tj.read_reference(tg)
    assert set(t_csv) == set(t_json)
    for n in ("T001", "T077"):
        np.testing.assert_allclose(t_csv[n], t_json[n]["xyz"], rtol=0, atol=1e-12)
    out2 = tmp_path / "self.json"
    argv = ["check-targets", str(cal), str(obs), "--reference", str(cal), "--scans", str(scans)]
    assert main(argv + ["--json", str(out2)]) == 0
    assert load_strict(out2)["network"]["with"]["rms"]["xyz_mm"] < 1e-4
    # A reference in millimetres declared as metres is refused in one line with the fix.
    capsys.readouterr()
    plain = tmp_path / "survey_no_units.csv"
    plain.write_text((tmp_path / "survey.csv").read_text().replace(" [mm]", ""))
    bad = ["check-targets", str(truth), str(obs), "--reference", str(plain)]
    assert main(bad + ["--length-unit", "m"]) == 2
    err = capsys.readouterr().err.splitlines()
    assert "true APs of a simulation" in err[0]  # the truth given as the calibration, named
    assert "unit mix-up" in err[-1] and len(err) == 2
    assert json.loads(cal.read_text())["scanner"]["architecture"] == "hybrid"
