"""The documentation site builds, and what it says runs.

``docs/build.py`` (what ``./scripts/docs`` runs) builds the Sphinx site and then runs every
example of the pages and docstrings (``sphinx.ext.doctest``, command lines included), with
warnings as errors: a broken link or reference, a public name of ``tlsjax`` without a docstring
or on no API page, a help text that is not valid reST, a benchmark figure whose JSON key is gone
and an example whose output changed all fail this test. The cheap tests below check the
extension's own rules against independent sources.
"""

import json
import os
import pathlib
import subprocess
import sys

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "docs" / "_ext"))

import tlsjax_docs  # noqa: E402


def test_docs_build_and_examples(tmp_path):
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    proc = subprocess.run(
        [sys.executable, str(ROOT / "docs" / "build.py"), str(tmp_path)],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
    )
    assert proc.returncode == 0, proc.stdout[-6000:] + proc.stderr[-6000:]
    html = tmp_path / "html"
    pages = ("index", "getting-started/demo", "howto/choose-model", "howto/field-check", "cli")
    for page in (*pages, "howto/speed", "api/calibrate"):
        assert (html / f"{page}.html").is_file(), page
    api = (html / "api" / "calibrate.html").read_text()
    assert 'id="tlsjax.calibrate"' in api and 'id="tlsjax.self_calibrate"' in api
    # settings classes show their inherited to_dict/from_dict
    assert 'id="tlsjax.CalibrationOptions.from_dict"' in api
    cli = (html / "cli.html").read_text()
    assert "check-targets" in cli and "--aps" in cli
    speed = (html / "concepts" / "speed.html").read_text()
    point = json.loads((ROOT / "benchmarks/results/point.json").read_text())
    run_ms = point["cases"]["physical"]["run_s"]["median"] * 1000
    assert f"{run_ms:.1f} ms" in speed


def test_public_names_are_those_of_the_package():
    import tlsjax

    names = set(tlsjax_docs.public_names())
    assert names == {n for n in dir(tlsjax) if not n.startswith("_")}


def test_every_public_name_is_on_one_api_page():
    placed = []
    for page in (ROOT / "docs" / "api").glob("*.rst"):
        for line in page.read_text().splitlines():
            if line.startswith(".. tlsjax-api::"):
                placed += line.split("::", 1)[1].split()
    assert sorted(placed) == sorted(tlsjax_docs.public_names())


def test_bench_figure_reads_the_json():
    point = json.loads((ROOT / "benchmarks/results/point.json").read_text())
    value = point["cases"]["physical"]["compile_s"]
    spec = "point.json:cases.physical.compile_s:.2f s"
    assert tlsjax_docs.bench_value(spec) == f"{value:.2f} s"
    spec = "point.json:cases.physical.run_s.median*1000:.1f ms"
    assert (
        tlsjax_docs.bench_value(spec)
        == f"{point['cases']['physical']['run_s']['median'] * 1e3:.1f} ms"
    )
    with pytest.raises(KeyError):
        tlsjax_docs.bench_value("point.json:cases.nothing")
    # "?": a field that an older version of a benchmark did not write reads "not measured"
    assert tlsjax_docs.bench_value("point.json:?cases.nothing:.1f s") == "not measured"
    spec = "point.json:?cases.physical.compile_s:.2f s"
    assert tlsjax_docs.bench_value(spec) == f"{value:.2f} s"


def test_bench_median_of_a_list(tmp_path, monkeypatch):
    monkeypatch.setattr(tlsjax_docs, "RESULTS", tmp_path)
    (tmp_path / "cli.json").write_text(json.dumps({"cli": {"rerun_s": [3.0, 1.0, 2.0, 10.0]}}))
    assert tlsjax_docs.bench_value("cli.json:cli.rerun_s.median:.2f s") == "2.50 s"
    assert tlsjax_docs.bench_value("cli.json:cli.rerun_s.1") == "1.0"


def test_provenance_says_what_was_not_measured(tmp_path, monkeypatch):
    monkeypatch.setattr(tlsjax_docs, "RESULTS", tmp_path)
    (tmp_path / "bare.json").write_text(json.dumps({"run_s": 1.0}))
    text = tlsjax_docs.provenance("bare.json")
    assert "date not measured" in text and "machine not measured" in text
    assert "load average not measured" in text
    (tmp_path / "full.json").write_text(
        json.dumps(
            {"date": "2026-11-27", "machine": {"cpu_model": "X", "cpu_count": 2}, "loadavg": [1.5]}
        )
    )
    text = tlsjax_docs.provenance("full.json")
    assert "measured 2026-11-27" in text and "X, 2 CPU cores" in text and "load average 1.5" in text
    # bench_ceres.py: date_utc, versions, and the load each round started at under a limit
    rounds = [{"loadavg_before": 0.8}, {"loadavg_before": 2.1}, {"wall_s": 1.0}]
    (tmp_path / "ceres.json").write_text(
        json.dumps(
            {
                "date_utc": "2026-11-28T10:00:00+00:00",
                "tlsjax_version": "0.1.0",
                "max_load": 2.5,
                "machine": {"cpu_model": "X", "cpu_count": 2},
                "loadavg_start": [9.0],
                "rounds": rounds,
            }
        )
    )
    text = tlsjax_docs.provenance("ceres.json")
    assert "measured 2026-11-28T10:00:00+00:00" in text and "tlsjax 0.1.0" in text
    assert "load average 0.8-2.1 at the start of its 2 rounds (at most 2.5 allowed)" in text


def test_absolute_values_escaped_outside_literals():
    line = "largest |correlation| and ``|t|`` beside |x|"
    out = tlsjax_docs._escape_bars(line)
    assert out == r"largest \|correlation\| and ``|t|`` beside \|x\|"


def _readme_section(title):
    text = (ROOT / "README.md").read_text()
    start = text.index(f"\n## {title}\n")
    end = text.find("\n## ", start + 1)
    return text[start : end if end > 0 else None]


def _code_blocks(section, language):
    return [b.split("\n", 1)[1] for b in section.split("```")[1::2] if b.startswith(language)]


def test_readme_is_a_front_page():
    assert len((ROOT / "README.md").read_text().splitlines()) < 150
    image = ROOT / "docs" / "img" / "demo_residuals.png"
    assert image.is_file() and "docs/img/demo_residuals.png" in (ROOT / "README.md").read_text()


def test_readme_test_command_is_what_ci_runs():
    commands = [
        line.split("#")[0].strip()
        for block in _code_blocks(_readme_section("Two commands"), "bash")
        for line in block.splitlines()
    ]
    ci = [x.strip() for x in (ROOT / ".ci" / "run").read_text().splitlines()]
    assert "./scripts/test" in commands and "./scripts/test" in ci
    assert "./scripts/demo" in commands


def test_readme_python_example_runs(capsys):
    (block,) = _code_blocks(_readme_section("Python in five lines"), "python")
    assert len([x for x in block.splitlines() if x.strip()]) <= 5
    exec(compile(block, "README.md", "exec"), {})
    out = capsys.readouterr().out.splitlines()
    assert out[0] == "testing: converged; variance components converged"
    head = next(i for i, line in enumerate(out) if line.split()[:3] == ["AP", "estimate", "sigma"])
    assert [line.split()[0] for line in out[head + 2 : head + 6]] == ["A0", "B6", "B7", "C0"]
