"""Result tables as JAG3D files them (``tlsjax calibrate --tables DIR`` and the JSON's
``observation_table`` / ``group_table``), checked against independent identities: redundancy
numbers sum to the degrees of freedom, ``w = v / (sigma sqrt(r))``, ``MDB = delta0 sigma /
sqrt(r)``, every ``line`` points at the input file's line with that scan and target, and a
planted blunder is removed on its own line. Also ``tlsjax --version``.

Private import: ``tlsjax._cli.main`` is the console script's entry point, called in process.
"""

import csv
import json

import numpy as np
import pytest
from strict_json import load_strict

import tlsjax as tj
from tlsjax._cli import main


def _read_csv(path):
    with open(path, newline="") as fh:
        rows = [r for r in csv.reader(fh) if r and not r[0].startswith("#")]
    return [dict(zip(rows[0], r)) for r in rows[1:]]


def _num(text):
    return float(text) if text else np.nan


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """A simulated target file (comment lines before the header) with blank lines inserted among the data (so line !=
    row + 1) and one range blunder; calibrated with snooping, tables and JSON."""
    d = tmp_path_factory.mktemp("tables")
    sim, scans = d / "sim.csv", d / "scans.csv"
    args = ["simulate", "--out", str(sim), "--scans-out", str(scans), "--seed", "3"]
    assert main([*args, "--aps", "A0 B6 B7 C0", "--room", "14x11x3", "--targets", "36"]) == 0
    text = sim.read_text().splitlines()
    header = next(i for i, t in enumerate(text) if t.startswith("scan,"))
    out = text[: header + 1]
    for k, line in enumerate(text[header + 1 :]):
        if k in (5, 40):
            out += ["", "  "]  # blank lines among the data (comments only before the header)
        out.append(line)
    # Plant a 5 cm range blunder on the 60th data row (four blank lines before it).
    blunder_line = header + 1 + 60 + 4 + 1  # 1-based line number in the new file
    cells = out[blunder_line - 1].split(",")
    cells[2] = repr(float(cells[2]) + 0.05)
    out[blunder_line - 1] = ",".join(cells)
    obs = d / "obs.csv"
    obs.write_text("\n".join(out) + "\n")
    res_json, tables = d / "r.json", d / "tab"
    rc = main(
        [
            "calibrate",
            str(obs),
            "--scans",
            str(scans),
            "--aps",
            "A0 B6 B7 C0",
            "--snoop",
            "--json",
            str(res_json),
            "--tables",
            str(tables),
            "--report",
            str(d / "report.html"),
        ]
    )
    assert rc == 0
    return {
        "lines": out,
        "scans_lines": scans.read_text().splitlines(),
        "blunder_line": blunder_line,
        "doc": load_strict(res_json),
        "obs": _read_csv(tables / "observations.csv"),
        "groups": _read_csv(tables / "groups.csv"),
        "targets": _read_csv(tables / "targets.csv"),
        "page": (d / "report.html").read_text(),
    }


TARGET_GROUPS = ("range", "hz", "el")


def test_lines_point_at_the_input_rows(run):
    lines = run["lines"]
    for r in (r for r in run["obs"] if r["group"] in TARGET_GROUPS):
        cells = lines[int(r["line"]) - 1].split(",")
        assert (cells[0], cells[1]) == (r["scan"], r["target"])
        if r["group"] == "range" and r["line"] != str(run["blunder_line"]):
            assert float(r["observed"]) == pytest.approx(float(cells[2]), abs=1e-8)
    rows = [int(r["row"]) for r in run["obs"] if r["group"] in TARGET_GROUPS]
    assert rows[0] == 1 and rows[-1] == len(rows) // 3
    # The levelling rows point at their scan's row of the scans CSV.
    scans = run["scans_lines"]
    levelling = [r for r in run["obs"] if r["group"] == "levelling"]
    assert levelling and all(r["row"] == "" for r in levelling)
    for r in levelling:
        assert scans[int(r["line"]) - 1].split(",")[0] == r["scan"]


def test_planted_blunder_is_removed_on_its_line(run):
    removed = [r for r in run["obs"] if r["decision"].startswith("removed")]
    assert {(r["line"], r["group"]) for r in removed} >= {(str(run["blunder_line"]), "range")}
    outlier_lines = {o["line"] for o in run["doc"]["outliers"]}
    assert run["blunder_line"] in outlier_lines


def test_redundancy_numbers_sum_to_dof(run):
    doc = run["doc"]
    # Every row (target observations and levelling readings) has its redundancy number.
    r_obs = sum(_num(r["redundancy"]) for r in run["obs"])
    assert r_obs == pytest.approx(doc["dof"], rel=1e-6)
    r_lev = sum(g["redundancy"] for g in doc["group_table"] if g["group"] == "levelling")
    levelling = sum(_num(r["redundancy"]) for r in run["obs"] if r["group"] == "levelling")
    assert levelling == pytest.approx(r_lev, rel=1e-6)
    groups = {g["group"]: float(g["redundancy"]) for g in run["groups"]}
    for name in ("range", "hz", "el"):
        assert groups[name] == pytest.approx(
            sum(_num(r["redundancy"]) for r in run["obs"] if r["group"] == name), rel=1e-6
        )


def test_normalised_residual_and_mdb_identities(run):
    delta0 = 4.13  # alpha0 = 0.001, power 0.80 (Baarda)
    for r in run["obs"]:
        red, v, s = _num(r["redundancy"]), _num(r["residual"]), _num(r["sigma"])
        if r["decision"].startswith("removed"):
            assert r["w"] == "" and red == 0
            continue
        assert _num(r["w"]) == pytest.approx(v / (s * np.sqrt(red)), rel=1e-6)
        assert _num(r["mdb"]) == pytest.approx(delta0 * s / np.sqrt(red), rel=2e-3)
        assert _num(r["external"]) == pytest.approx(delta0 * np.sqrt((1 - red) / red), rel=2e-3)
        assert (abs(_num(r["w"])) > _num(r["critical_value"])) == (r["decision"] == "rejected")


def test_json_tables_match_the_csv(run):
    table = run["doc"]["observation_table"]
    rows = [dict(zip(table["columns"], row)) for row in table["rows"]]
    assert len(rows) == len(run["obs"])
    for a, b in zip(rows[::97], run["obs"][::97]):
        assert (a["line"], a["scan"], a["primitive"], a["group"]) == (
            int(b["line"]),
            b["scan"],
            b["target"],
            b["group"],
        )
        f = 1e3 if a["group"] == "range" else 648000 / np.pi
        if a["residual"] is not None:
            assert a["residual"] * f == pytest.approx(float(b["residual"]), rel=1e-8)
    assert set(run["doc"]["targets"]) == {t["target"] for t in run["targets"]}


def test_report_shows_the_test_sequence_and_each_removal_with_its_stage(run):
    from test_report_html import _tables

    doc, tables = run["doc"], _tables(run["page"])
    tests = tables["tests"]
    stages = [(r[0].split(" ")[0], r[1]) for r in tests[1:]]
    # The a priori global test first, then one group test per group: for all observations, or
    # for those the robust start kept when it removed the blunder already.
    assert stages[0][0] == "global"
    assert stages[0][1] in (
        "a priori sigmas, all observations",
        "a priori sigmas, after the robust start (1 removed)",
    )
    first = doc["a_priori_tests"][0]
    assert float(tests[1][2]) == pytest.approx(first["global"]["statistic"], abs=0.06)
    groups = [r[0] for r in tests[1:] if r[1] == stages[0][1]][1:]
    assert groups == [f"group {g} (factor)" for g in first["groups"]]
    # sigma0 after VCE is printed as not a test, outside the table of tests.
    assert "not a test" in run["page"].split(">Tests")[1].split("<h2>")[0]
    assert not any("sigma0" in r[0] for r in tests)
    removals = tables["removals"]
    rows = {(r[2], r[5]): r[1] for r in removals[1:]}
    stage = "robust start" if "robust start" in stages[0][1] else "screening (before VCE)"
    assert rows[(str(run["blunder_line"]), "range")] == stage
    groups = {r[0]: r for r in tables["groups"][1:]}
    for g in doc["group_table"]:
        assert float(groups[g["group"]][2]) == pytest.approx(g["redundancy"], abs=0.06)


@pytest.mark.internal
def test_plain_calibration_tables_from_the_api():
    from tlsjax._report._tables import group_records, observation_records

    sim = tj.simulate(seed=2, aps="A0 B6", tilted=False)
    res = tj.calibrate(sim.network, tj.CalibrationModel(sim.scanner))
    recs = observation_records(res)
    assert len(recs) == 3 * sim.network.observations.shape[0]
    assert all(r["line"] is None for r in recs)  # arrays: no file lines
    total = sum(r["redundancy"] for r in recs) + float(np.sum(res.redundancy_levelling))
    assert total == pytest.approx(res.dof, rel=1e-6)
    groups = {g["group"]: g for g in group_records(res)}
    omega = sum((r["residual"] / r["sigma"]) ** 2 for r in recs)
    r_g = sum(g["redundancy"] for g in groups.values())
    assert sum(g["variance_factor"] * g["redundancy"] for g in groups.values()) == pytest.approx(
        omega, rel=1e-9
    )
    assert r_g == pytest.approx(sum(r["redundancy"] for r in recs), rel=1e-9)


@pytest.mark.internal
def test_every_confounding_is_named_once_and_alike_everywhere():
    from tlsjax._adjustment._text import confoundings, summary

    not_est = (("A1", "scale", "scale is undefined; add scale bars or control points"),)
    weak = (("C0", "C3", 0.9993), ("C3", "C0", 0.9993), ("C4", "C2", 0.9977), ("A1", "scale", 1.0))
    found = confoundings(not_est, weak)
    assert [c["parameters"] for c in found] == [["A1", "scale"], ["C0", "C3"], ["C4", "C2"]]
    # The JSON form of the same lists gives the same sentences.
    as_json = confoundings(
        [{"name": n, "confounded_with": w, "reason": r} for n, w, r in not_est],
        [{"name": n, "correlated_with": w, "max_abs_corr": c} for n, w, c in weak],
    )
    assert as_json == found
    sim = tj.simulate(seed=1, aps="A0 B6 B7 C0", tilted=False)
    scanner = tj.Scanner(architecture="hybrid", aps="A0 A1 B6 B7 C0")
    res = tj.calibrate(sim.network, tj.CalibrationModel(scanner))
    doc = res.to_dict()
    text = summary(res)
    assert doc["confoundings"] and all(f"warning: {c['text']}" in text for c in doc["confoundings"])
    assert text.count("warning:") == len(doc["confoundings"])


def test_version(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--version"])
    assert e.value.code == 0
    assert capsys.readouterr().out.strip() == f"tlsjax {tj.__version__}"
    json.dumps(tj.__version__)


@pytest.mark.internal
def test_dense_residual_panel_is_a_density_and_removed_points_never_set_the_scale():
    """Private import: ``tlsjax._report._plots._residual_panel`` draws one panel of
    ``tj.plot_residuals``; a plane network of 100k points is too slow to adjust in a unit test."""
    import types

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from tlsjax._report._plots import _residual_panel

    rng = np.random.default_rng(0)
    n = 100_000
    x = rng.uniform(1.0, 12.0, n)
    v = rng.normal(0.0, 0.5e-3, n)  # range residuals [m]
    used = np.ones(n, bool)
    used[:40] = False
    v[:40] = 0.2  # removed blunders of 200 mm
    stub = types.SimpleNamespace(ap_names=("A0",))
    fig, (a, b) = plt.subplots(1, 2)
    _residual_panel(a, stub, x, v, used, None, 0, 1.0)
    lo, hi = a.get_ylim()
    assert lo < -1.5 and hi > 1.5 and hi < 5.0  # mm: the used residuals, not the 200 mm
    assert any(type(c).__name__ == "PolyCollection" for c in a.collections)  # hexbin
    a.legend()
    labels = [t.get_text() for t in a.get_legend().get_texts()]
    assert any("40, 40 beyond the axis" in t for t in labels), labels
    _residual_panel(b, stub, x[:500], v[:500], used[:500], None, 0, 1.0)
    assert not b.collections  # few points: one marker each
    plt.close(fig)


@pytest.mark.internal
def test_plane_point_tables(tmp_path):
    """Plane points through a plane CSV: one row per point and component, lines of that file,
    redundancy numbers summing (with the levelling) to the degrees of freedom."""
    from tlsjax._units import ARCSEC

    design = tj.CloudDesign(angular_step=4 * np.pi / 180, aps=("A0", "B6", "B7", "C0"))
    pc = tj.simulate_point_clouds(design, seed=1)
    path = tmp_path / "planes.csv"
    tj.write_observations(path, pc.to_table(max_points=25, seed=0))
    net = tj.read_network(None, planes=path)
    res = tj.calibrate(net, tj.CalibrationModel(pc.scanner))
    assert res.ok
    written = tj.write_tables(res, tmp_path / "tab")
    names = sorted(p.rsplit("/", 1)[-1] for p in written)
    assert names == ["groups.csv", "plane_points.csv", "planes.csv"]
    rows = _read_csv(tmp_path / "tab" / "plane_points.csv")
    assert len(rows) == 3 * net.plane_observations.shape[0]
    lines = path.read_text().splitlines()
    for r in rows[::151]:
        cells = lines[int(r["line"]) - 1].split(",")
        assert (cells[0], cells[1]) == (r["scan"], r["plane"])
    total = sum(_num(r["redundancy"]) for r in rows) + float(np.sum(res.redundancy_levelling))
    assert total == pytest.approx(res.dof, rel=1e-6)
    groups = {g["group"]: g for g in tj.group_records(res)}
    assert set(groups) == {"plane range", "plane hz", "plane el"}
    # planes.csv carries the JSON's plane precision in its display units (mm, arc seconds).
    doc = res.to_dict()
    for r in _read_csv(tmp_path / "tab" / "planes.csv"):
        p = doc["planes"][r["plane"]]
        tilt = [_num(r[f"tilt_sigma_{i}_arcsec"]) * ARCSEC for i in (1, 2)]
        np.testing.assert_allclose(tilt, p["tilt_sigmas"], rtol=1e-9)
        axes = [_num(r[f"foot_axis_{i}_mm"]) / 1e3 for i in (1, 2, 3)]
        np.testing.assert_allclose(axes, p["foot_point_ellipsoid_axes"], rtol=1e-9)
        assert _num(r["sigma_d_mm"]) / 1e3 == pytest.approx(p["sigma"]["d"], rel=1e-9)


@pytest.mark.internal
def test_every_weighted_constraint_has_its_row():
    """Tilt readings, headings and an AP prior get rows with the target observations (JSON
    ``observation_table``): all redundancy numbers sum to the degrees of freedom, and each
    levelling or heading residual is the adjusted orientation minus the reading."""
    from tlsjax._model._geometry import wrap_angle
    from tlsjax._model._levelling import orientation_reading
    from tlsjax._report._tables import observation_records, pseudo_records, table_json
    from tlsjax._units import ARCSEC

    sim = tj.simulate(seed=5, aps="A0 B6 B7 C0", sigma_tilt=5 * ARCSEC, sigma_heading=30 * ARCSEC)
    model = tj.CalibrationModel(sim.scanner, ap_priors={"A0": (0.0, 2e-3)})
    res = tj.calibrate(sim.network, model)
    assert res.ok, res.message
    net, pseudo = sim.network, pseudo_records(res)
    assert {r["group"] for r in pseudo} == {"levelling", "heading", "ap prior"}
    total = sum(r["redundancy"] for r in observation_records(res) + pseudo)
    assert total == pytest.approx(res.dof, rel=1e-9)
    read = np.asarray([orientation_reading(e) for e in res.eops])
    observed = np.column_stack([net.levelling, net.heading_values])
    for r in pseudo:
        if r["group"] == "ap prior":
            assert r["residual"] == pytest.approx(res.ap("A0")["value"], abs=1e-12)
            continue
        j, c = net.scans.index(r["scan"]), ("omega", "phi", "kappa").index(r["primitive"])
        expected = float(wrap_angle(read[j, c] - observed[j, c]))
        assert r["residual"] == pytest.approx(expected, abs=1e-12)
        assert r["w"] == pytest.approx(
            r["residual"] / (r["sigma"] * np.sqrt(r["redundancy"])), rel=1e-9
        )
        assert r["line"] is None  # from memory: no scans CSV
    rows = table_json(res)["observation_table"]["rows"]
    assert len(rows) == 3 * net.observations.shape[0] + len(pseudo)
