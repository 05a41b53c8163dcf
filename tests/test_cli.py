"""The command line and the result JSON contract (SPEC section 11).

Private import: ``tlsjax._cli.main`` is what the ``tlsjax`` console script
(``tlsjax._cli.console``, pyproject) runs, called in process; ``console`` itself runs in a
subprocess, since it ends the process.
"""

import json
import re
import subprocess
import sys

import numpy as np
import pytest
import scipy.stats
from helpers import printed_is_summary, same_run
from networks import NumpyDrawer, point_case
from strict_json import load_strict

import tlsjax as tj
from tlsjax._cli import main

ROOM = ["--room", "14x11x3", "--targets", "36"]
CONTRACT = {
    "sigma0",
    "dof",
    "n_observations",
    "n_unknowns",
    "converged",
    "iterations",
    "aps",
    "eops",
    "redundancy",
    "outliers",
    "variance_components",
    "not_estimable",
}


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    d = tmp_path_factory.mktemp("sim")
    obs, scans, truth = d / "obs.csv", d / "scans.csv", d / "truth.json"
    assert (
        main(
            [
                "simulate",
                "--out",
                str(obs),
                "--scans-out",
                str(scans),
                "--truth",
                str(truth),
                "--seed",
                "4",
                "--aps",
                "A0 B6 B7 C0",
                *ROOM,
            ]
        )
        == 0
    )
    return d, obs, scans, truth


def test_calibrate_json_matches_the_api(simulated, capsys):
    d, obs, scans, truth = simulated
    out = d / "res.json"
    assert (
        main(
            [
                "calibrate",
                "--no-cross-validation",
                str(obs),
                "--scans",
                str(scans),
                "--aps",
                "A0 B6 B7 C0",
                "--no-vce",
                "--json",
                str(out),
            ]
        )
        == 0
    )
    printed = capsys.readouterr().out
    assert "B6" in printed and "mm" in printed and '"' in printed
    js = json.loads(out.read_text())
    assert CONTRACT <= set(js)
    # The same network through the Python API, built from the simulation in memory.
    sim = tj.simulate(tj.Room(n_targets=36), seed=4, aps="A0 B6 B7 C0")
    res = tj.calibrate(sim.network, tj.CalibrationModel(tj.Scanner(aps="A0 B6 B7 C0")))
    assert js["dof"] == res.dof and js["n_observations"] == res.n_observations
    assert js["n_unknowns"] == res.n_unknowns
    assert np.isclose(js["sigma0"], res.sigma0, rtol=1e-9)
    for i, name in enumerate(res.ap_names):
        a = js["aps"][name]
        # The CSV holds 17 significant digits, so the file path reproduces the API to rounding.
        assert abs(a["value"] - res.ap_values[i]) < 1e-6 * res.ap_sigmas[i]
        assert np.isclose(a["sigma"], res.ap_sigmas[i], rtol=1e-8)
        assert a["unit"] == res.ap_units[i] and a["max_corr_with"] == res.ap_max_corr_with[i]
    cov = np.array(js["ap_covariance"])
    np.testing.assert_allclose(
        np.sqrt(np.diag(cov)),
        [js["aps"][n]["sigma"] for n in js["ap_covariance_names"]],
        rtol=1e-12,
    )
    assert np.isclose(js["redundancy"]["total"]["sum"], js["dof"], rtol=1e-9)
    assert set(js["eops"]) == set(res.scans) and js["not_estimable"] == []
    true = json.loads(truth.read_text())["aps"]
    for name, v in true.items():
        assert abs(js["aps"][name]["value"] - v) < 5 * js["aps"][name]["sigma"]


def test_vce_and_snooping_through_the_cli(simulated, tmp_path, capsys):
    d, obs, scans, _ = simulated
    # One 30-sigma blunder in the range of the 10th row.
    lines = obs.read_text().splitlines()
    cells = lines[10].split(",")
    cells[2] = repr(float(cells[2]) + 30 * 0.5e-3)
    lines[10] = ",".join(cells)
    bad = tmp_path / "blunder.csv"
    bad.write_text("\n".join(lines) + "\n")
    out = tmp_path / "tested.json"
    assert (
        main(
            [
                "calibrate",
                "--no-cross-validation",
                str(bad),
                "--scans",
                str(scans),
                "--snoop",
                "--bonferroni",
                "--json",
                str(out),
            ]
        )
        == 0
    )
    js = json.loads(out.read_text())
    scan, target = cells[0], cells[1]
    assert [(o["scan"], o["target"], o["group"]) for o in js["outliers"]] == [
        (scan, target, "range")
    ]
    vc = js["variance_components"]
    assert {"range", "hz", "el"} <= set(vc if isinstance(vc, dict) else [v["group"] for v in vc])
    # The removed observation leaves the degrees of freedom.
    assert np.isclose(js["redundancy"]["total"]["sum"], js["dof"], rtol=1e-9)
    assert "removed" in capsys.readouterr().out


@pytest.mark.parametrize("length_unit,angle_unit", [("mm", "gon"), ("m", "arcsec"), ("m", "rad")])
def test_units_do_not_change_the_result(simulated, tmp_path, length_unit, angle_unit):
    d, obs, scans, _ = simulated
    other = tmp_path / "obs.csv"
    tj.write_observations(
        other, tj.read_observations(obs), length_unit=length_unit, angle_unit=angle_unit
    )
    comment, header = other.read_text().splitlines()[:2]
    assert comment == "# tlsjax target observations: architecture=hybrid"  # recorded, read back
    assert f"range_{length_unit}" in header
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    assert (
        main(
            [
                "calibrate",
                "--no-cross-validation",
                str(obs),
                "--scans",
                str(scans),
                "--json",
                str(a),
            ]
        )
        == 0
    )
    assert (
        main(
            [
                "calibrate",
                "--no-cross-validation",
                str(other),
                "--scans",
                str(scans),
                "--json",
                str(b),
            ]
        )
        == 0
    )
    ja, jb = json.loads(a.read_text()), json.loads(b.read_text())
    for name in ja["aps"]:
        assert (
            abs(ja["aps"][name]["value"] - jb["aps"][name]["value"])
            < 1e-6 * ja["aps"][name]["sigma"]
        )


def test_not_estimable_scale_is_named_not_numbered(simulated, tmp_path):
    _, obs, scans, _ = simulated
    out = tmp_path / "a1.json"
    # A1 without scale bars or control: a result, not a number (exit 0: the rest is estimated).
    assert (
        main(
            [
                "calibrate",
                "--no-cross-validation",
                str(obs),
                "--scans",
                str(scans),
                "--aps",
                "A0 A1 B6 B7 C0",
                "--json",
                str(out),
            ]
        )
        == 0
    )
    js = json.loads(out.read_text())
    assert js["aps"]["A1"]["value"] is None and js["aps"]["A1"]["sigma"] is None
    assert [e["name"] for e in js["not_estimable"]] == ["A1"]
    assert "scale" in js["not_estimable"][0]["reason"]
    assert js["aps"]["A0"]["value"] is not None


def test_bad_input_names_file_and_line(tmp_path, capsys):
    bad = tmp_path / "bad.csv"
    bad.write_text("scan,target,range_m,hz_deg,el_furlong\nS1,T1,5,10,3\n")
    assert main(["calibrate", "--no-cross-validation", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "bad.csv" in err and "el_furlong" in err
    assert main(["calibrate", "--no-cross-validation", str(tmp_path / "missing.csv")]) == 2
    assert "missing.csv" in capsys.readouterr().err


def test_target_seen_once_is_refused_then_dropped_on_request(simulated, tmp_path, capsys):
    _, obs, scans, _ = simulated
    lines = obs.read_text().splitlines()
    # Keep target T001 in its first scan only.
    keep = [lines[0]] + [
        ln for ln in lines[1:] if not (",T001," in ln and not ln.startswith("S1,"))
    ]
    f = tmp_path / "once.csv"
    f.write_text("\n".join(keep) + "\n")
    assert main(["calibrate", "--no-cross-validation", str(f), "--scans", str(scans)]) == 2
    assert "T001" in capsys.readouterr().err
    assert (
        main(
            [
                "calibrate",
                "--no-cross-validation",
                str(f),
                "--scans",
                str(scans),
                "--drop-single-targets",
            ]
        )
        == 0
    )
    assert "dropped 1 target(s) seen in one scan only: T001" in capsys.readouterr().out


def test_demo_writes_report_and_plots(tmp_path):
    assert main(["demo", "--out", str(tmp_path), "--aps", "physical"]) == 0
    for name in (
        "report.json",
        "residuals.png",
        "ap_correlations.png",
        "observations.csv",
        "scans.csv",
        "truth.json",
    ):
        assert (tmp_path / name).stat().st_size > 0
    js = json.loads((tmp_path / "report.json").read_text())
    assert set(js["aps"]) == {"A0", "B6", "B7", "C0"} and js["converged"]


def test_global_test_against_scipy():
    for dof in (3, 40, 1753):
        g = tj.global_test(1.0, dof, level=0.05)
        assert np.isclose(g["lower"], scipy.stats.chi2.ppf(0.025, dof), rtol=1e-9)
        assert np.isclose(g["upper"], scipy.stats.chi2.ppf(0.975, dof), rtol=1e-9)
    # s0 = 1.05 with r = 1000: T = 1102.5 beyond the 97.5 % quantile 1089.5, rejected;
    # s0 = 1.02: T = 1040.4 inside the interval [914.3, 1089.5], accepted.
    g = tj.global_test(1.05, 1000)
    assert np.isclose(g["statistic"], 1102.5)
    assert np.isclose(g["p_value"], 2 * scipy.stats.chi2.sf(1102.5, 1000), rtol=1e-8)
    assert g["accepted"] is False
    assert tj.global_test(1.02, 1000)["accepted"] is True
    assert tj.global_test(0.9, 1000)["accepted"] is False  # too small: two-sided


def test_room_parse_of_the_default_room_is_the_default_room():
    assert tj.Room.parse("14x11x3") == tj.Room()


# --------------------------------------------------------------------------------------------
# Issue 13: never a plausible wrong answer through the CLI


def _edit(src, dst, edits):
    """Copy a CSV with cells replaced: edits = {(line index, column index): text}."""
    lines = src.read_text().splitlines()
    for (i, c), text in edits.items():
        cells = lines[i].split(",")
        cells[c] = text(cells[c]) if callable(text) else text
        lines[i] = ",".join(cells)
    dst.write_text("\n".join(lines) + "\n")
    return dst


def test_default_calibrate_finds_gross_errors(simulated, tmp_path, capsys):
    d, obs, scans, truth = simulated
    bad = _edit(
        obs,
        tmp_path / "blunders.csv",
        {
            (10, 2): lambda v: repr(float(v) + 1.0),  # 1 m in the range
            (50, 3): lambda v: repr(float(v) + 10.0),  # 10 deg in hz
            (90, 4): lambda v: repr(float(v) + 10.0),  # 10 deg in el
        },
    )
    out = tmp_path / "res.json"
    code = main(
        ["calibrate", "--no-cross-validation", str(bad), "--scans", str(scans), "--json", str(out)]
    )
    printed = capsys.readouterr().out
    assert code == 0
    js = load_strict(out)
    rows = obs.read_text().splitlines()
    expected = {
        (rows[i].split(",")[0], rows[i].split(",")[1], g)
        for i, g in ((10, "range"), (50, "hz"), (90, "el"))
    }
    assert {(o["scan"], o["target"], o["group"]) for o in js["outliers"]} == expected
    assert js["a_priori_tests"][0]["stage"] == "after the robust start (3 removed)"
    assert js["screening"]["n_removed_robust_start"] == 3
    assert "score_tests" in js and js["score_tests"]["significant"] == []
    assert (
        js["global_test"]["stage"] == "a priori"
        and "not a test" in js["global_test_after_vce"]["note"]
    )
    assert js["vce"]["status"] == "converged"
    true = load_strict(truth)["aps"]
    for name, v in true.items():
        assert abs(js["aps"][name]["value"] - v) < 5 * js["aps"][name]["sigma"]
    assert "robust start" in printed
    assert ": accepted" not in printed.split("variance components:")[1].split("AP ")[0]


def test_implausible_input_is_refused_with_one_line(simulated, tmp_path, capsys):
    _, obs, scans, _ = simulated
    cases = {
        "el95.csv": ({(20, 4): "95"}, "el of scan .* = 95 deg .*hybrid scanner"),
        "elm120.csv": ({(20, 4): "-120"}, "column el_deg: el = -120 .*below -90 deg"),
        "hz720.csv": ({(20, 3): "720"}, "column hz_deg: hz = 720 .*two turns"),
    }
    for name, (edits, message) in cases.items():
        assert (
            main(
                [
                    "calibrate",
                    "--no-cross-validation",
                    str(_edit(obs, tmp_path / name, edits)),
                    "--scans",
                    str(scans),
                ]
            )
            == 2
        )
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and re.search(
            f"{name}, line 21.*{message}", err
        ), err
    rad = tmp_path / "rad.csv"
    rad.write_text(obs.read_text().replace("hz_deg,el_deg", "hz_rad,el_rad", 1))
    assert main(["calibrate", "--no-cross-validation", str(rad)]) == 2
    assert "column hz_rad" in capsys.readouterr().err
    nosig = tmp_path / "scans_nosig.csv"
    nosig.write_text("scan,omega_arcsec,phi_arcsec\nS1,1,2\n")
    assert main(["calibrate", "--no-cross-validation", str(obs), "--scans", str(nosig)]) == 2
    assert "no sigma columns" in capsys.readouterr().err


def test_file_system_failures_are_one_line_before_any_work(simulated, tmp_path, capsys):
    _, obs, scans, _ = simulated
    afile = tmp_path / "afile"
    afile.write_text("x")
    cases = [
        ([str(tmp_path), "--scans", str(scans)], "is a directory, not a CSV file"),
        ([str(obs), "--scans", str(tmp_path)], "is a directory, not a CSV file"),
        ([str(obs), "--json", str(tmp_path)], "--json .*is a directory"),
        ([str(obs), "--json", str(afile / "r.json")], "--json .*afile is a file, not a directory"),
        ([str(obs), "--plots", str(afile)], "--plots .*is a file, not a directory"),
        ([str(obs), "--plots", str(afile / "p")], "--plots .*afile is a file"),
    ]
    for args, message in cases:
        assert main(["calibrate", "--no-cross-validation", *args]) == 2, args
        captured = capsys.readouterr()
        assert "scans," not in captured.out  # refused before the network was even read
        assert len(captured.err.strip().splitlines()) == 1 and re.search(message, captured.err)
    assert main(["montecarlo", "--runs", "5", "--json", str(tmp_path)]) == 2
    assert "--json" in capsys.readouterr().err
    assert main(["simulate", "--out", str(afile / "obs.csv")]) == 2
    assert "--out" in capsys.readouterr().err
    assert main(["extract-planes", str(tmp_path / "none.ply"), "--out", str(tmp_path)]) == 2
    assert "--out" in capsys.readouterr().err  # before the (missing) scan is read
    assert main(["compare", str(obs), str(obs), "--json", str(afile / "c.json")]) == 2
    assert "--json" in capsys.readouterr().err


def test_drop_single_targets_that_empty_a_scan_is_a_message(simulated, tmp_path, capsys):
    _, obs, scans, _ = simulated
    lines = obs.read_text().splitlines()
    # Scan S6 keeps only its own renamed targets: all of them single.
    kept = [lines[0]] + [
        ln if not ln.startswith("S6,") else ln.replace(",T", ",X", 1) for ln in lines[1:]
    ]
    f = tmp_path / "lonely.csv"
    f.write_text("\n".join(kept) + "\n")
    assert main(["calibrate", "--no-cross-validation", str(f), "--drop-single-targets"]) == 2
    err = capsys.readouterr().err
    assert "scan(s) S6 observe only targets seen in no other scan" in err and "Traceback" not in err


def test_montecarlo_json_is_strict_and_failures_explained(tmp_path, capsys):
    assert main(["montecarlo", "--runs", "1", "--no-progress"]) == 2
    assert "at least 2 realisations" in capsys.readouterr().err
    out = tmp_path / "mc.json"
    args = ["montecarlo", "--runs", "4", "--targets", "24", "--aps", "A0 A1 B6", "--no-progress"]
    assert main([*args, "--json", str(out)]) == 1
    printed = capsys.readouterr().out
    js = load_strict(out)
    assert js["successful"] == 0 and js["aps"]["A1"]["mean"] is None
    assert "A1 is not estimable" in js["diagnosis"] and "scale" in js["diagnosis"]
    assert "A1 is not estimable" in printed


def test_screening_without_vce_and_score_tests_on_every_path(simulated, tmp_path, capsys):
    """Screening does not depend on VCE (issue 27): --no-vce still finds the blunder; only
    --no-screen turns it off; the score tests of the missing terms are in the JSON either way."""
    d, obs, scans, _ = simulated
    bad = _edit(obs, tmp_path / "bad.csv", {(20, 2): lambda v: repr(float(v) + 2.0)})
    row = obs.read_text().splitlines()[20].split(",")
    on, off = tmp_path / "on.json", tmp_path / "off.json"
    assert (
        main(
            [
                "calibrate",
                "--no-cross-validation",
                str(bad),
                "--scans",
                str(scans),
                "--no-vce",
                "--json",
                str(on),
            ]
        )
        == 0
    )
    js = load_strict(on)
    assert [(o["scan"], o["target"], o["group"]) for o in js["outliers"]] == [
        (row[0], row[1], "range")
    ]
    assert js["screening"]["enabled"] and "score_tests" in js
    args = [
        "calibrate",
        "--no-cross-validation",
        str(bad),
        "--scans",
        str(scans),
        "--no-vce",
        "--no-screen",
    ]
    main([*args, "--json", str(off)])
    printed = capsys.readouterr().out
    js = load_strict(off)
    assert js["outliers"] == [] and "score_tests" in js
    assert "missing terms (score tests" in printed


def test_select_with_a_gross_error_ends_as_on_the_clean_file(simulated, tmp_path, capsys):
    d, obs, scans, _ = simulated
    bad = _edit(obs, tmp_path / "bad.csv", {(30, 2): lambda v: repr(float(v) + 2.0)})
    chosen = []
    for name, path in (("clean", obs), ("bad", bad)):
        out = tmp_path / f"{name}.json"
        args = [
            "calibrate",
            "--no-cross-validation",
            str(path),
            "--scans",
            str(scans),
            "--aps",
            "A0 B6 C0",
            "--select",
        ]
        assert main([*args, "--select-candidates", "A3 B7 C2", "--json", str(out)]) == 0
        js = load_strict(out)
        chosen.append(set(js["selection"]["aps"]))
        assert js["selection"]["n_screened"] == (name == "bad")
    assert chosen[0] == chosen[1] == {"A0", "B6", "B7", "C0"}
    assert "largest score statistic" in capsys.readouterr().out


# --------------------------------------------------------------------------------------------
# Issue 39: the command prints and writes the one library call's result


def _cli_and_api(obs, scans, out, capsys, cli_args, model, options):
    """``tlsjax calibrate`` with ``cli_args`` and ``tj.self_calibrate`` of the same files with
    ``model`` and ``options``: (exit code, stdout, CLI JSON, API result)."""
    code = main(["calibrate", str(obs), "--scans", str(scans), "--json", str(out), *cli_args])
    printed = capsys.readouterr().out
    net = tj.read_network(str(obs), str(scans))
    return code, printed, load_strict(out), tj.self_calibrate(net, model, options)


@pytest.mark.parametrize(
    "cli_args, options",
    [
        ([], tj.CalibrationOptions()),
        (
            [
                "--no-vce",
                "--snoop",
                "--bonferroni",
                "--snoop-alpha",
                "0.05",
                "--no-cross-validation",
            ],
            tj.CalibrationOptions(
                vce=None,
                snooping=tj.SnoopingOptions(w_test_level=0.05, bonferroni=True),
                cross_validation=None,
            ),
        ),
        (
            [
                "--aps",
                "A0 B6 C0",
                "--select",
                "--select-candidates",
                "A3 B7 C2",
                "--no-cross-validation",
            ],
            tj.CalibrationOptions(
                selection=tj.SelectionOptions(candidates="A3 B7 C2"), cross_validation=None
            ),
        ),
    ],
    ids=["defaults", "snooping", "selection"],
)
def test_cli_prints_and_writes_the_self_calibration(simulated, tmp_path, capsys, cli_args, options):
    d, obs, scans, _ = simulated
    aps = cli_args[cli_args.index("--aps") + 1] if "--aps" in cli_args else "physical"
    model = tj.CalibrationModel(tj.Scanner(aps=aps))
    code, printed, doc, result = _cli_and_api(
        obs, scans, tmp_path / "r.json", capsys, cli_args, model, options
    )
    assert code == 0 and result.ok
    same_run(doc, result.to_dict())
    printed_is_summary(printed, result.summary())
    assert doc["settings"]["options"] == options.to_dict()
    assert doc["settings"]["inputs"]["command"].startswith("tlsjax calibrate ")
    if options.selection is not None:
        assert doc["selection"]["aps"] == list(result.model.scanner.aps)
        assert set(result.model.scanner.aps) == {"A0", "B6", "B7", "C0"}


def test_cli_prints_and_writes_the_self_calibration_of_a_drawn_network(tmp_path, capsys):
    """A network drawn at random (tests/networks.py: four scans from one to three stations,
    levelled or tilted, hybrid or panoramic, any sigma scale), written as ``tlsjax simulate``
    writes it; whatever the run ends in, the command's JSON and text are the entry's."""
    case = point_case(NumpyDrawer(7))
    sim = tj.simulate_design(case.design, seed=case.seed)
    obs, scans = tmp_path / "obs.csv", tmp_path / "scans.csv"
    tj.write_network(obs, sim.network, scans_path=scans, architecture=sim.scanner.architecture)
    model = tj.CalibrationModel(tj.Scanner(architecture=sim.scanner.architecture))
    code, printed, doc, result = _cli_and_api(
        obs,
        scans,
        tmp_path / "r.json",
        capsys,
        ["--no-cross-validation"],
        model,
        tj.CalibrationOptions(cross_validation=None),
    )
    assert code == (0 if result.ok else 1)
    same_run(doc, result.to_dict())
    printed_is_summary(printed, result.summary())


def test_from_json_reruns_the_recorded_calibration(simulated, tmp_path, capsys):
    """Issue 40 item 5: the JSON records its inputs, how they were read, the model and the
    options; ``--from-json`` re-runs it and reproduces it; only output options go with it."""
    d, obs, scans, _ = simulated
    first, again = tmp_path / "first.json", tmp_path / "again.json"
    given = ["--aps", "A0 B6 B7 C0", "--no-vce", "--snoop", "--sigma-range-mm", "0.6"]
    assert (
        main(
            [
                "calibrate",
                "--no-cross-validation",
                str(obs),
                "--scans",
                str(scans),
                *given,
                "--json",
                str(first),
            ]
        )
        == 0
    )
    assert main(["calibrate", "--from-json", str(first), "--json", str(again)]) == 0
    a, b = load_strict(first), load_strict(again)
    same_run(a, b)
    assert (
        a["settings"]["inputs"]["sigma_range_mm"] == 0.6 and a["settings"]["options"]["vce"] is None
    )
    assert b["settings"]["inputs"] == {
        **a["settings"]["inputs"],
        "command": b["provenance"]["command"],
    }
    capsys.readouterr()
    assert main(["calibrate", "--from-json", str(first), "--no-vce"]) == 2
    assert "--vce: not with --from-json" in capsys.readouterr().err
    # Issue 39 item 7: a simulation's truth where a calibration is expected is named.
    truth = d / "truth.json"
    assert main(["calibrate", "--from-json", str(truth)]) == 2
    assert "the truth of a simulation" in capsys.readouterr().err
    assert main(["calibrate", "--no-cross-validation", str(obs), "--ap-priors", str(truth)]) == 2
    assert "the truth of a simulation" in capsys.readouterr().err


# --------------------------------------------------------------------------------------------
# Issue 41: prediction judges the calibration; the architecture of Cartesian lists from the data

#: The room of tests/test_identification.py (its compiled programs serve both).
SMALL_ROOM = tj.Room(n_targets=24)


def _cartesian_lists(net, folder):
    """One vendor-style list per scan (name x y z in the scanner's frame, no header)."""
    x = np.asarray(tj.cartesian_from_spherical(net.observations))
    paths = []
    for j, scan in enumerate(net.scans):
        path = folder / f"{scan}.txt"
        rows = np.flatnonzero(net.scan_index == j)
        path.write_text(
            "".join(
                f"{net.targets[net.target_index[i]]} {x[i, 0]:.7f} {x[i, 1]:.7f} {x[i, 2]:.7f}\n"
                for i in rows
            )
        )
        paths.append(str(path))
    return paths


def test_a_calibration_no_better_than_none_exits_4_and_says_so(tmp_path, capsys):
    """Data without systematic errors: the physical model's APs fit noise, and its held-out
    scans are placed worse with them than without (seed 0): the command writes the result,
    prints the warning and exits 4 (a script that applies what exits 0 does not apply it);
    --no-cross-validation runs no folds and exits 0."""
    sim = tj.simulate(SMALL_ROOM, seed=0, aps=())
    obs, scans, out = tmp_path / "obs.csv", tmp_path / "scans.csv", tmp_path / "r.json"
    tj.write_network(obs, sim.network, scans_path=scans, architecture="hybrid")
    args = ["calibrate", str(obs), "--scans", str(scans), "--no-vce", "--quiet"]
    assert main([*args, "--json", str(out)]) == 4
    printed = capsys.readouterr().out
    cv = load_strict(out)["cross_validation"]
    assert cv["code"] == int(tj.CrossValidationCode.NOT_IMPROVED) and not cv["improves"]
    assert cv["rms_mm"]["xyz"] > cv["rms_none_mm"]["xyz"]
    assert "warning: cross-validation: the calibration does not improve" in printed
    assert f"{cv['rms_mm']['xyz']:.3f} mm with the APs" in printed
    assert "architecture_check" not in load_strict(out)  # the file records it: no check
    assert main([*args, "--no-cross-validation", "--json", str(out)]) == 0
    assert "cross_validation" not in load_strict(out)


def test_cartesian_lists_imported_as_the_wrong_architecture_are_named(tmp_path, capsys):
    """A hybrid scanner's Cartesian lists with the physical errors, imported as panoramic:
    the imported file says the architecture was only declared, so calibrate fits both
    (default on for such files) and warns naming hybrid, in the output and the JSON."""
    sim = tj.simulate(SMALL_ROOM, seed=0, aps="A0 B6 B7 C0")
    _, scans, _ = tj.write_network(
        tmp_path / "o.csv", sim.network, scans_path=tmp_path / "s.csv"
    ) or (None, tmp_path / "s.csv", None)
    imported, out = tmp_path / "imported.csv", tmp_path / "r.json"
    lists = _cartesian_lists(sim.network, tmp_path)
    assert (
        main(["import-targets", *lists, "--architecture", "panoramic", "--out", str(imported)]) == 0
    )
    assert "declared for Cartesian target lists" in imported.read_text().splitlines()[0]
    capsys.readouterr()
    code = main(
        [
            "calibrate",
            str(imported),
            "--scans",
            str(scans),
            "--no-vce",
            "--quiet",
            "--json",
            str(out),
        ]
    )
    printed = capsys.readouterr().out
    check = load_strict(out)["architecture_check"]
    assert check["given"] == "panoramic" and check["best"] == "hybrid" and check["clearly"]
    assert "read as panoramic, but hybrid explains them clearly better" in printed
    assert check["warning"] in load_strict(out)["warnings"]
    assert code in (0, 4)
    # Given explicitly, the architecture is the user's: no check.
    assert (
        main(
            [
                "calibrate",
                str(imported),
                "--scans",
                str(scans),
                "--no-vce",
                "--quiet",
                "--architecture",
                "panoramic",
                "--no-cross-validation",
                "--json",
                str(out),
            ]
        )
        == 0
    )
    assert "architecture_check" not in load_strict(out)


def test_calibrate_help_names_the_recommended_path(capsys):
    with pytest.raises(SystemExit):
        main(["calibrate", "--help"])
    text = capsys.readouterr().out
    assert "recommended path for a scanner owner" in text and "--select" in text
    assert "exit 4" in text and "--no-cross-validation" in text


def test_the_console_script_exits_with_mains_code_and_its_whole_output(tmp_path, capsys):
    """``tlsjax`` ends the process without the interpreter's teardown (:func:`console`): its
    exit codes, printed lines and written files are those of ``main`` in process."""
    run = "import sys; from tlsjax._cli import console; sys.argv[0] = 'tlsjax'; console()"

    def console(*args):
        return subprocess.run(
            [sys.executable, "-c", run, *args], capture_output=True, text=True, timeout=300
        )

    args = ["simulate", "--scans-out", str(tmp_path / "s.csv"), "--aps", "A0 B6"]
    done = console(*args, "--out", str(tmp_path / "o.csv"))
    assert main([*args, "--out", str(tmp_path / "o2.csv")]) == 0
    printed = capsys.readouterr().out
    assert done.returncode == 0 and done.stderr == ""
    assert done.stdout == printed.replace("o2.csv", "o.csv") and done.stdout.endswith("\n")
    assert (tmp_path / "o.csv").read_text() == (tmp_path / "o2.csv").read_text()
    missing = console("calibrate", str(tmp_path / "missing.csv"))
    assert missing.returncode == 2 and missing.stderr.strip().endswith("missing.csv: no such file")
    assert console().returncode == 2  # argparse's usage error: SystemExit(2) inside main


class _GoneReader:
    """A standard stream whose reader has gone (``tlsjax ... | head``): every write fails."""

    def write(self, text):
        raise BrokenPipeError(32, "Broken pipe")

    def flush(self):
        raise BrokenPipeError(32, "Broken pipe")


def test_a_reader_that_goes_away_ends_only_the_printing(tmp_path, monkeypatch):
    """``tlsjax simulate ... | head``: the command completes, writes every file as without the
    pipe and exits with its own code (Python would end it at the first print, exit code 2
    "Broken pipe", files not written); the streams are restored after."""
    args = ["simulate", "--scans-out", str(tmp_path / "s.csv"), "--aps", "A0 B6", *ROOM]
    assert main([*args, "--out", str(tmp_path / "ref.csv")]) == 0
    gone = _GoneReader()
    monkeypatch.setattr(sys, "stdout", gone)
    monkeypatch.setattr(sys, "stderr", gone)
    code = main([*args, "--out", str(tmp_path / "o.csv"), "--truth", str(tmp_path / "t.json")])
    assert sys.stdout is gone and sys.stderr is gone
    monkeypatch.undo()
    assert code == 0
    assert (tmp_path / "o.csv").read_text() == (tmp_path / "ref.csv").read_text()
    assert load_strict(tmp_path / "t.json")["aps"]
