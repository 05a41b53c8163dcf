"""A careless or hurried user (issue 28, issue 27 item 6): every case is a clear one-line error
(exit 2 naming the file, line, option or parameter), a result code with its reason, or a
warning naming the likely cause; never a traceback, never a plausible wrong number, and never a
modified input.

Each CLI case runs in a fresh folder holding copies of the fixture files; every file there is
hashed before and after, and only the outputs the case names may change.

Private imports: the console script's entry ``tlsjax._cli.main``, the cost estimate of
``state_cost`` and the atomic writer ``atomic_output`` (mechanisms of the command line and the
file writers), the pipeline's steps and the table reader's internals for the cases that patch
them.
"""

import csv
import hashlib
import json
import os
import re
import shutil

import jax
import numpy as np
import pytest
from helpers import tiny_planes
from strict_json import load_strict

import tlsjax as tj
from tlsjax._cli import main

N_TARGETS = 24


# --- fixtures ---------------------------------------------------------------------------------


def _write_csv(path, header, rows):
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        w.writerows(rows)


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """Fixture files: a simulated room (targets, scans, truth), its calibration JSON, other
    kinds of tlsjax JSON, corrupted variants, a point cloud and plane files."""
    # Deliberately broken JSON inputs live here (tests/strict_json.py skips the folder).
    d = tmp_path_factory.mktemp("hostile") / "not_written_by_tlsjax"
    d.mkdir()
    argv = ["simulate", "--out", str(d / "obs.csv"), "--scans-out", str(d / "scans.csv")]
    argv += ["--truth", str(d / "truth.json"), "--targets", str(N_TARGETS), "--seed", "4"]
    assert main(argv) == 0
    argv = ["calibrate", str(d / "obs.csv"), "--scans", str(d / "scans.csv"), "--no-vce"]
    assert main(argv + ["--json", str(d / "cal.json")]) == 0
    with open(d / "obs.csv", newline="") as fh:  # without the "# tlsjax ..." comment line
        rows = [r for r in csv.reader(fh) if r and not r[0].startswith("#")]
    head, body = rows[0], rows[1:]
    i_range = head.index("range_m")

    def scaled(factor, name, header="range_m"):
        new = [list(r) for r in body]
        for r in new:
            r[i_range] = repr(float(r[i_range]) * factor)
        _write_csv(d / name, [header if c == "range_m" else c for c in head], new)

    scaled(1.0, "obs_metres_as_mm.csv", "range_mm")  # ranges of 2-8 "mm"
    scaled(1000.0, "obs_mm_as_metres.csv")  # a 14 m room read as 14 km
    huge = [list(r) for r in body]
    huge[10][i_range] = "1e300"
    _write_csv(d / "obs_huge.csv", head, huge)
    five = [r for r in body if r[1] in {"T001", "T002", "T003", "T004", "T005"}]
    _write_csv(d / "obs5.csv", head, five)
    # A plane file (the targets as plane points) with a negative incidence angle.
    planes = [list(r) + ["12"] for r in body]
    planes[3][-1] = "-5"
    _write_csv(
        d / "planes_neg_incidence.csv", ["scan", "plane"] + head[2:] + ["incidence_deg"], planes
    )
    _write_csv(d / "poses.csv", ["scan", "x_m", "y_m", "z_m", "omega_deg", "phi_deg", "kappa_deg"],
               [["scan", 0, 0, 0, 0, 0, 0]])  # fmt: skip
    rng = np.random.default_rng(0)
    np.savetxt(d / "scan.xyz", rng.normal(size=(500, 3)) * 4.0 + [6.0, 0.0, 0.0])
    np.savetxt(d / "noise.xyz", rng.uniform(-5, 5, size=(3000, 3)))

    cal = json.loads((d / "cal.json").read_text())

    def variant(name, change):
        doc = json.loads(json.dumps(cal))
        change(doc)
        (d / name).write_text(json.dumps(doc))

    variant("cal_nonnumeric.json", lambda doc: doc["aps"]["B6"].update(value="abc"))
    variant("cal_aps_list.json", lambda doc: doc.update(aps=[1, 2]))
    variant("cal_impossible.json", lambda doc: (doc["aps"]["A0"].update(value=5.0),
                                                doc["aps"]["B6"].update(value=0.5)))  # fmt: skip
    variant("cal_large.json", lambda doc: doc["aps"]["A0"].update(value=0.3))

    def withhold(doc):
        doc["estimates"] = "withheld: the adjustment failed (did not converge)"
        for a in doc["aps"].values():
            a["value"] = None

    variant("cal_withheld.json", withhold)
    variant("cal_all_null.json", lambda doc: [a.update(value=None) for a in doc["aps"].values()])
    (d / "mc.json").write_text(
        json.dumps({"runs": 4, "successful": 4, "aps": {"A0": {"mean": 0.01}}})
    )
    (d / "compare.json").write_text(json.dumps({"p_value": 0.3, "compatible": True, "runs": 10}))
    (d / "garbage.json").write_text("{not json")
    # Plane files: one cut short, one whose arrays disagree.
    tj.write_extracted_planes(d / "planes.npz", tiny_planes(rng, 40))
    raw = (d / "planes.npz").read_bytes()
    (d / "planes_truncated.npz").write_bytes(raw[: len(raw) // 2])
    with np.load(d / "planes.npz") as z:
        arrays = {k: z[k] for k in z.files}
    arrays["point_patch"] = arrays["point_patch"] + 1000
    np.savez(d / "planes_inconsistent.npz", **arrays)
    return d


def _digest(folder):
    out = {}
    for root, _, files in os.walk(folder):
        for f in files:
            p = os.path.join(root, f)
            with open(p, "rb") as fh:
                out[os.path.relpath(p, folder)] = hashlib.sha256(fh.read()).hexdigest()
    return out


@pytest.fixture
def work(base, tmp_path):
    """A fresh copy of the fixture files."""
    d = tmp_path / "not_written_by_tlsjax"
    shutil.copytree(base, d)
    return d


def run(argv, capsys):
    try:
        code = main([str(a) for a in argv])
    except SystemExit as exc:  # argparse's errors
        code = exc.code
    out = capsys.readouterr()
    return code, out.out, out.err


def _one_error_line(err, command):
    # Progress lines ("[   0.0 s] reading ...") say what ran before the refusal; the refusal
    # itself is one line.
    lines = [x for x in err.splitlines() if x.strip() and not re.match(r"\[\s*[\d.]+ s\]", x)]
    assert len(lines) == 1, lines
    assert lines[0].startswith(f"tlsjax {command}: error:"), lines
    return lines[0]


# --- CLI cases: (id, argv with {d} for the work folder, outcome, pattern) -----------------------

ERRORS = [
    # Data lost (issue 28): an output over an input, two outputs on one path.
    ("json over observations", "calibrate {d}/obs.csv --scans {d}/scans.csv --json {d}/obs.csv",
     "is the input observations"),
    ("json over scans", "calibrate {d}/obs.csv --scans {d}/scans.csv --json {d}/scans.csv",
     "is the input --scans"),
    ("html over calibration", "report {d}/cal.json --html {d}/cal.json", "is the input calibration"),
    ("two outputs one path", "simulate --out {d}/x.csv --scans-out {d}/x.csv", "are the same file"),
    ("json and report one path", "calibrate {d}/obs.csv --json {d}/o.json --report {d}/o.json",
     "are the same file"),
    ("json through a symlink", "calibrate {d}/obs.csv --json {d}/link.json", "is the input"),
    ("json through a hard link", "calibrate {d}/obs.csv --json {d}/hard.json", "is the input"),
    ("correct into the input folder", "correct {d}/cal.json {d}/scan.xyz --out {d}",
     "is the input scan"),
    ("extract csv over poses",
     "extract-planes {d}/scan.xyz --out {d}/p.npz --poses {d}/poses.csv --csv {d}/poses.csv",
     "is the input --poses"),
    ("demo out is a file", "demo --out {d}/obs.csv", "is a file"),
    ("json empty name", "calibrate {d}/obs.csv --json=", "not a file name"),
    ("montecarlo png under a file", "montecarlo --runs 5 --png {d}/obs.csv/x.png", "is a file"),
    ("design json under a file", "design --json {d}/obs.csv/x.json", "is a file"),
    ("import-targets over its list", "import-targets {d}/scan.xyz --architecture hybrid "
     "--out {d}/scan.xyz", "is the input list"),
    ("check-targets json over the reference", "check-targets {d}/cal.json {d}/obs.csv "
     "--reference {d}/poses.csv --json {d}/poses.csv", "is the input --reference"),
    ("check-targets json over the calibration", "check-targets {d}/cal.json {d}/obs.csv "
     "--reference {d}/poses.csv --json {d}/cal.json", "is the input calibration"),
    ("extract-targets over a scan", "extract-targets {d}/scan.xyz --spheres 0.07 "
     "--out {d}/scan.xyz", "--out .*scan.xyz: is the input scan"),
    ("extract-targets table over poses", "extract-targets {d}/scan.xyz --spheres 0.07 "
     "--out {d}/t.csv --poses {d}/poses.csv --table {d}/poses.csv", "is the input --poses"),
    ("extract-targets default table over the list", "extract-targets {d}/scan.xyz --spheres "
     "0.07 --out {d}/t.csv --target-list {d}/t_table.csv", "--table .*t_table.csv: is the input"),
    ("extract-targets out and table one path", "extract-targets {d}/scan.xyz --spheres 0.07 "
     "--out {d}/t.csv --table {d}/t.csv", "are the same file"),
    ("extract-targets plots is a file", "extract-targets {d}/scan.xyz --spheres 0.07 "
     "--out {d}/t.csv --plots {d}/obs.csv", "--plots .*obs.csv: is a file"),
    ("extract-targets negative radius", "extract-targets {d}/scan.xyz --spheres -0.07 "
     "--out {d}/t.csv", "--spheres: -0.07 must be a positive number"),
    ("extract-targets coverage above one", "extract-targets {d}/scan.xyz --spheres 0.07 "
     "--min-coverage 2 --out {d}/t.csv", "--min-coverage: 2 must be between 0 and 1"),
    # Unit mix-ups and impossible values in the data.
    ("metres under range_mm", "calibrate {d}/obs_metres_as_mm.csv", "metres read as millimetres"),
    ("millimetres under range_m", "calibrate {d}/obs_mm_as_metres.csv",
     "millimetres read as metres"),
    ("range 1e300", "calibrate {d}/obs_huge.csv", "obs_huge.csv, line 12: range"),
    ("negative incidence", "calibrate --planes {d}/planes_neg_incidence.csv",
     r"incidence angle .* must be in \[0, 90\)"),
    # Tracebacks before (issue 28).
    ("empty aps", "calibrate {d}/obs.csv --aps=", "--aps '': no AP named"),
    ("report on a Monte Carlo JSON", "report {d}/mc.json --html {d}/r.html",
     "a Monte Carlo summary"),
    ("report on a compare JSON", "report {d}/compare.json --html {d}/r.html",
     "compatibility test"),
    ("report on a truth JSON", "report {d}/truth.json --html {d}/r.html", "truth of a simulation"),
    ("report non-numeric AP", "report {d}/cal_nonnumeric.json --html {d}/r.html",
     "AP B6: value is not a number"),
    ("report aps not an object", "report {d}/cal_aps_list.json --html {d}/r.html",
     "no 'aps' object"),
    ("report not JSON", "report {d}/garbage.json --html {d}/r.html", "not a readable result JSON"),
    ("correct a Monte Carlo JSON", "correct {d}/mc.json {d}/scan.xyz --out {d}/o",
     "a Monte Carlo summary"),
    ("correct withheld estimates", "correct {d}/cal_withheld.json {d}/scan.xyz --out {d}/o",
     "no calibration to apply: the estimates are withheld"),
    ("correct impossible APs", "correct {d}/cal_impossible.json {d}/scan.xyz --out {d}/o",
     "refusing to apply it: A0"),
    ("correct every AP null", "correct {d}/cal_all_null.json {d}/scan.xyz --out {d}/o",
     "no AP has a value"),
    ("planes npz cut short", "calibrate --planes {d}/planes_truncated.npz",
     "planes_truncated.npz: not a"),
    ("planes npz inconsistent", "calibrate --planes {d}/planes_inconsistent.npz",
     "point_patch indexes outside"),
    ("montecarlo a billion runs", "montecarlo --runs 1000000000 --targets 24",
     "--runs 1000000000: .* of results"),
    # Options that cannot take effect together, or at all.
    ("negative sigma", "calibrate {d}/obs.csv --sigma-range-mm -1",
     "--sigma-range-mm: -1 must be a positive number"),
    ("datum inner with a fixed scan", "calibrate {d}/obs.csv --datum inner --fixed-scan S1",
     "--fixed-scan takes effect only with --datum fixed-scan"),
    ("fixed scan unknown", "calibrate {d}/obs.csv --fixed-scan S99", "--fixed-scan S99: no such"),
    ("bonferroni without snoop", "calibrate {d}/obs.csv --bonferroni",
     "--bonferroni takes effect only with --snoop"),
    ("snoop alpha without snoop", "calibrate {d}/obs.csv --snoop-alpha 0.01",
     "--snoop-alpha takes effect only with --snoop"),
    ("select alpha without select", "calibrate {d}/obs.csv --select-alpha 0.05",
     "--select-alpha takes effect only with --select"),
    ("screen alpha without screening", "calibrate {d}/obs.csv --no-screen --screen-alpha 0.01",
     "--screen-alpha takes effect only with --screen"),
    ("screen alpha without vce", "calibrate {d}/obs.csv --no-vce --screen-alpha 0.01",
     "--screen-alpha takes effect only with --vce"),
    ("devices zero", "montecarlo --devices 0", "--devices: 0 must be at least 1"),
    ("alpha of one", "compare {d}/cal.json {d}/cal.json --alpha 1", "--alpha: 1 must be between"),
    ("negative seed", "simulate --out {d}/s.csv --seed -1", "--seed: -1 must be 0 or more"),
    ("unit length zero", "calibrate {d}/obs.csv --unit-length 0", "--unit-length: 0 must be"),
]  # fmt: skip


def _setup(d):
    os.symlink(d / "obs.csv", d / "link.json")
    os.link(d / "obs.csv", d / "hard.json")


@pytest.mark.parametrize("case", ERRORS, ids=[c[0] for c in ERRORS])
def test_refused_in_one_line_before_any_work(work, capsys, case):
    name, argv, pattern = case
    _setup(work)
    before = _digest(work)
    argv = argv.format(d=work).split()
    code, out, err = run(argv, capsys)
    assert code == 2, (name, out, err)
    line = _one_error_line(err, argv[0])
    assert re.search(pattern, line), line
    assert "wrote" not in out
    assert _digest(work) == before  # no input modified, no output written


def test_missing_parent_folders_are_created_by_every_command(work, capsys):
    """One rule for all commands: an output's missing folders are created."""
    d = work
    assert run(["simulate", "--out", d / "a/b/obs.csv", "--targets", 24], capsys)[0] == 0
    assert (d / "a/b/obs.csv").is_file() and (d / "a/b/obs_scans.csv").is_file()
    assert run(["report", d / "cal.json", "--html", d / "c/d/r.html"], capsys)[0] == 0
    assert (d / "c/d/r.html").read_text().startswith("<!DOCTYPE html>")
    argv = ["correct", d / "cal.json", d / "scan.xyz", "--out", d / "e/f"]
    assert run(argv, capsys)[0] == 0 and (d / "e/f/scan.xyz").is_file()
    argv = ["calibrate", d / "obs.csv", "--no-vce", "--json", d / "g/h/c.json"]
    code, _, _ = run(argv + ["--plots", d / "i/j", "--report", d / "k/r.html"], capsys)
    assert code == 0
    for p in ("g/h/c.json", "i/j/residuals.png", "i/j/ap_correlations.png", "k/r.html"):
        assert (d / p).is_file(), p
    assert not [p for p in _digest(d) if os.path.basename(p).startswith(".tlsjax-")]


def test_implausible_and_ignored_values_are_warned_about(work, capsys):
    d = work
    before = _digest(d)
    code, out, err = run(
        ["calibrate", d / "obs.csv", "--no-vce", "--sigma-range-mm", "0.3"], capsys
    )
    assert code == 0
    assert "warning: --sigma-range-mm 0.3 mm is ignored: every row of" in err
    argv = ["correct", d / "cal_large.json", d / "scan.xyz", "--out", d / "o"]
    code, out, err = run(argv, capsys)
    assert code == 0 and "applying A0 = 300 mm" in out
    assert "A0 (rangefinder offset) = 300 mm is beyond 100 mm" in err
    after = _digest(d)
    assert {k: v for k, v in after.items() if not k.startswith("o/")} == before


def test_a_not_estimable_ap_is_said_in_words(work, capsys):
    """A1 without scale (not estimable): no "nan" anywhere, no t, the JSON null with its
    reason."""
    d = work
    argv = ["calibrate", d / "obs.csv", "--scans", d / "scans.csv", "--aps", "A0 A1 B6"]
    code, out, err = run(argv + ["--json", d / "a1.json"], capsys)
    assert code == 0 and "nan" not in (out + err).lower()
    assert re.search(r"A1: not estimable \(scale is undefined.*\): no t", out)
    doc = load_strict(d / "a1.json")
    assert doc["aps"]["A1"]["t"] is None and "not estimable" in doc["aps"]["A1"]["note"]
    assert doc["aps"]["A0"]["note"] is None
    a1 = next(t for t in doc["ap_tests"] if t["name"] == "A1")
    assert a1["t"] is None and not a1["significant"] and "not estimable" in a1["note"]


def test_weakly_determined_aps_get_no_verdict(work, capsys):
    """23 APs from 5 targets (|corr| near 1): no "nan" anywhere, no "significant" for a weakly
    determined AP, the reason in the JSON and the likely cause named."""
    d = work
    argv = ["calibrate", d / "obs5.csv", "--aps", "chow2013-noscale", "--json", d / "c5.json"]
    code, out, err = run(argv, capsys)
    doc = load_strict(d / "c5.json")
    weak = {w["name"] for w in doc["weakly_determined"]}
    assert weak and "nan" not in (out + err).lower()
    for line in out.splitlines():
        m = re.match(r"\s+(\w+): t = ", line)
        if m and m.group(1) in weak:
            assert "significant" not in line.replace("significance", ""), line
            assert "no verdict" in line
    for name in weak:
        assert "weakly determined" in doc["aps"][name]["note"]
    assert "for 23 APs" in err or "for 23 APs" in out  # the likely cause is named


@pytest.mark.internal
def test_a_run_whose_vce_failed_writes_no_estimates(work, capsys, monkeypatch):
    """VCE that oscillates (forced): exit 1, and the text, the JSON and the exit code agree
    that there is no calibration (issue 28: it used to say "valid" and hold B6). Private:
    the group statistics of the VCE step are patched to force the failure."""
    from tlsjax._inference import _steps

    real = _steps.group_statistics
    calls = {"n": 0}

    def alternating(ctx, state):
        s2, r_g, n_g = real(ctx, state)
        calls["n"] += 1
        return np.where(np.arange(len(s2)) < 3, 4.0 if calls["n"] % 2 else 0.25, s2), r_g, n_g

    monkeypatch.setattr(_steps, "group_statistics", alternating)
    d = work
    argv = ["calibrate", d / "obs.csv", "--scans", d / "scans.csv", "--json", d / "v.json"]
    code, out, err = run(argv + ["--report", d / "v.html"], capsys)
    assert code == 1
    assert "no estimates: the variance components failed" in out
    assert not re.search(r"\b[A-C]\d+: t = ", out)
    doc = load_strict(d / "v.json")
    assert doc["estimates"].startswith("withheld: the variance components failed")
    assert doc["vce"]["status"] != "converged"
    assert all(a["value"] is None and a["note"].startswith("withheld") for a in doc["aps"].values())
    assert "No calibration:" in (d / "v.html").read_text()
    code, _, err = run(["correct", d / "v.json", d / "scan.xyz", "--out", d / "o"], capsys)
    assert code == 2 and "estimates are withheld" in err


def test_single_scan_planes_and_too_few_targets_are_named(work, capsys):
    d = work
    # The AP set of test_weakly_determined_aps_get_no_verdict: one compiled adjustment.
    argv = ["calibrate", d / "obs5.csv", "--no-vce", "--aps", "chow2013-noscale"]
    code, out, err = run(argv, capsys)
    assert code in (0, 1)
    assert "warning: 5 targets for 23 APs: fewer primitives than APs" in err
    design = tj.CloudDesign(architecture="hybrid", tilted=False, angular_step=np.radians(3.0))
    pc = tj.simulate_point_clouds(design, seed=0)
    table = pc.to_table()
    one = [i for i, s in enumerate(table.scans) if s == table.scans[0]][:600]
    tj.write_observations(
        d / "planes1.csv",
        type(table)(
            kind="plane",
            source="x",
            scans=tuple(table.scans[i] for i in one),
            primitives=tuple(table.primitives[i] for i in one),
            observations=table.observations[one],
            sigmas=None,
            incidence=None,
            instruments=None,
            rows=np.arange(len(one)),
        ),
    )
    code, out, err = run(["calibrate", "--planes", d / "planes1.csv", "--aps", "physical"], capsys)
    assert "warning: 1 scan for 4 AP(s)" in err
    assert code in (0, 1) and "nan" not in out.lower()


def test_extract_planes_that_finds_none_writes_nothing(work, capsys):
    code, out, err = run(["extract-planes", work / "noise.xyz", "--out", work / "p.npz"], capsys)
    assert code == 1 and "no plane found" in err
    assert not (work / "p.npz").exists()


# --- the API ------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def sim():
    return tj.simulate(tj.Room(n_targets=N_TARGETS), aps="A0 B6 B7 C0", seed=0)


@pytest.mark.parametrize("transform", ["jit", "grad", "vmap"])
def test_calibrate_under_a_transformation_names_what_to_call(sim, transform):
    import dataclasses

    model = tj.CalibrationModel(sim.scanner)

    def f(obs):
        return tj.calibrate(dataclasses.replace(sim.network, observations=obs), model).sigma0

    obs = sim.network.observations
    wrapped = {"jit": jax.jit(f), "grad": jax.grad(f), "vmap": jax.vmap(f)}[transform]
    with pytest.raises(ValueError, match="differentiable_adjustment") as e:
        wrapped(obs[None] if transform == "vmap" else obs)
    assert "\n" not in str(e.value)
    with pytest.raises(ValueError, match="make_network runs on the host"):
        jax.jit(lambda o: tj.make_network(["S1"] * 4, list("abcd"), o).sigmas)(obs[:4])
    # The network closed over, nothing traced reaches it: still one line naming the entry.
    outer = {"jit": jax.jit, "grad": jax.grad, "vmap": jax.vmap}[transform]
    arg = np.ones(2) if transform == "vmap" else 1.0
    for entry in (tj.calibrate, tj.self_calibrate):
        with pytest.raises(ValueError, match=f"{entry.__name__} runs on the host.*differentiable"):
            outer(lambda s, entry=entry: (entry(sim.network, model), s)[1])(arg)


def test_api_misuse_is_a_clear_error(base, sim):
    with pytest.raises(TypeError, match="planes must be a plane ObservationTable, got list"):
        tj.make_plane_network([1, 2, 3])
    cal = tj.Calibration.from_json(base / "cal.json")
    with pytest.raises(ValueError, match=r"points must have shape \(n, 3\).*\(5, 2\)"):
        tj.correct_points(np.ones((5, 2)), cal)
    with pytest.raises(ValueError, match="a Monte Carlo summary"):
        tj.Calibration.from_json(base / "mc.json")
    with pytest.raises(ValueError, match="AP B6: value is not a number"):
        tj.Calibration.from_json(base / "cal_nonnumeric.json")
    with pytest.raises(ValueError, match="estimates are withheld"):
        tj.Calibration.from_json(base / "cal_withheld.json")
    with pytest.raises(ValueError, match="takes effect only with datum='fixed-scan'"):
        tj.CalibrationModel(datum="inner", fixed_scan="S1")
    model = tj.CalibrationModel(sim.scanner)
    failed = tj.calibrate(sim.network, model, tj.SolverOptions(max_iterations=1))
    assert failed.result == tj.ResultCode.MAX_ITERATIONS
    with pytest.raises(ValueError, match="did not succeed .*its APs cannot be compared"):
        tj.APSet.from_result(failed)
    with pytest.raises(ValueError, match="not applied"):
        tj.Calibration.from_result(failed, sim.scanner)
    with pytest.raises(ValueError, match=r"did not succeed \(withheld: the adjustment"):
        tj.APSet.from_json(base / "cal_withheld.json")


def test_same_plausibility_rules_in_the_api():
    scanner = tj.Scanner(aps="A0 B6")
    with pytest.raises(ValueError, match=r"B6 \(collimation axis error\) = .* beyond 18,000"):
        tj.Calibration(scanner, [0.001, 0.5])
    with pytest.warns(tj.PlausibilityWarning, match="A0 .* = 300 mm is beyond 100 mm"):
        cal = tj.Calibration(scanner, [0.3, 0.0])
    assert any("300 mm" in n for n in cal.notes)
    obs = tj.simulate(tj.Room(n_targets=N_TARGETS), aps="none", noise=False).network
    with pytest.raises(ValueError, match="metres read as millimetres"):
        tj.make_network(
            [obs.scans[j] for j in obs.scan_index],
            [obs.targets[t] for t in obs.target_index],
            obs.observations * np.array([1e-3, 1.0, 1.0]),
        )
    with pytest.warns(tj.PlausibilityWarning, match="millimetres read as metres"):
        tj.make_network(
            [obs.scans[j] for j in obs.scan_index],
            [obs.targets[t] for t in obs.target_index],
            obs.observations * np.array([200.0, 1.0, 1.0]),
        )


def test_one_wrong_cell_in_a_point_list_is_named_not_rescaled(tmp_path):
    """A reference survey in metres with one coordinate typed as 50,000: its line is refused;
    the unit rule (median distance from the median point) is not flipped to millimetres by
    it, which would have scaled every other point by 1/1000 without a word."""
    rng = np.random.default_rng(3)
    xyz = rng.uniform(-6.0, 6.0, (12, 3))
    rows = [f"T{i:02d},{x:.4f},{y:.4f},{z:.4f}" for i, (x, y, z) in enumerate(xyz)]
    (tmp_path / "ok.csv").write_text("\n".join(["name,x,y,z", *rows]) + "\n")
    ref = tj.read_reference(tmp_path / "ok.csv")
    np.testing.assert_allclose(ref["T03"], np.round(xyz[3], 4))
    rows[5] = "T05,50000," + rows[5].split(",", 2)[2]
    (tmp_path / "bad.csv").write_text("\n".join(["name,x,y,z", *rows]) + "\n")
    with pytest.raises(ValueError, match=r"bad.csv, line 7: point T05 lies 5[.\d]*e\+04 m from"):
        tj.read_reference(tmp_path / "bad.csv")
    with pytest.raises(ValueError, match=r"bad.csv, line 7: point T05 lies .* from the scanner"):
        tj.read_target_list(tmp_path / "bad.csv", "hybrid", scan="S1")


def test_t_tests_give_no_verdict_where_none_is_defined(sim):
    net = tj.simulate(tj.Room(n_targets=N_TARGETS), aps="A0 B6 B7 C0", seed=1).network
    res = tj.calibrate(net, tj.CalibrationModel(tj.Scanner(aps="A0 A1 B6 B7 C0")))
    tests = {t.name: t for t in tj.ap_t_tests(res)}
    assert res.not_estimable and not tests["A1"].significant
    assert tests["A1"].describe().startswith("A1: not estimable")
    assert "nan" not in tests["A1"].describe()
    assert tests["A0"].note == "" and tests["A0"].significant
    table = res.summary()
    assert "nan" not in table.lower() and "A1       not estimable" in table
    d = res.to_dict()
    assert d["aps"]["A1"]["t"] is None and "not estimable" in d["aps"]["A1"]["note"]


# --- cost, Ctrl-C and atomic writes -------------------------------------------------------------


@pytest.mark.internal
def test_a_long_run_states_its_cost_first(capsys):
    from tlsjax._cli._checks import state_cost

    seconds = state_cost(
        "the Monte Carlo run", "--runs", 10**6, rows=2168, parameters=10, devices=2,
        result_bytes=224, usual="1,000 is usual",
    )  # fmt: skip
    out = capsys.readouterr().out
    assert seconds > 120 and out.startswith("cost: the Monte Carlo run (1,000,000 x 2,168")
    assert "Ctrl-C stops it cleanly" in out
    state_cost("x", "--runs", 10, rows=10, parameters=10, devices=1, result_bytes=1, usual="")
    assert capsys.readouterr().out == ""  # a short run says nothing


@pytest.mark.internal
def test_ctrl_c_leaves_no_half_written_file(tmp_path):
    from tlsjax._io._outputs import atomic_output

    target = tmp_path / "out.csv"
    target.write_text("previous\n")
    with pytest.raises(KeyboardInterrupt):
        with atomic_output(target) as tmp:
            with open(tmp, "w") as fh:
                fh.write("half")
            raise KeyboardInterrupt
    assert target.read_text() == "previous\n"
    assert sorted(os.listdir(tmp_path)) == ["out.csv"]


def test_ctrl_c_exits_130(work, capsys, monkeypatch):
    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(tj, "read_network", interrupted)  # what tlsjax calibrate calls
    code, out, err = run(["calibrate", work / "obs.csv", "--json", work / "c.json"], capsys)
    assert code == 130 and "interrupted" in err and not (work / "c.json").exists()
