"""The HTML calibration report: contents from the result JSON, "not computed" where the run did
not compute a field, provenance hashes, and a render in a real headless browser.

Private import: ``tlsjax._cli.main`` is the ``tlsjax`` console script's entry point
(pyproject), called in process.
"""

import hashlib
import html
import html.parser
import json
import os
import shutil
import subprocess
import tempfile

import numpy as np
import pytest

from tlsjax._cli import main


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    d = tmp_path_factory.mktemp("report")
    obs, scans = d / "obs.csv", d / "scans.csv"
    assert main(["simulate", "--out", str(obs), "--scans-out", str(scans), "--seed", "4"]) == 0
    args = [
        "calibrate",
        "--no-cross-validation",
        str(obs),
        "--scans",
        str(scans),
        "--aps",
        "A0 A1 B6 B7 C0",
        "--snoop",
    ]
    args += ["--json", str(d / "cal.json"), "--report", str(d / "report.html")]
    assert main(args) == 0
    plain = [
        "calibrate",
        "--no-cross-validation",
        str(obs),
        "--scans",
        str(scans),
        "--no-vce",
        "--no-screen",
    ]
    plain += ["--json", str(d / "p.json")]
    assert main(plain) == 0
    return d


def test_report_holds_every_section(calibrated):
    page = (calibrated / "report.html").read_text()
    doc = json.loads((calibrated / "cal.json").read_text())
    # Self-contained: no external resource of any kind.
    assert "http://" not in page and "https://" not in page and "<script" not in page
    assert page.count("data:image/png;base64,") == 2  # residuals and AP correlations
    for heading in (
        "Design and adjustment",
        "Tests",
        "Additional parameters",
        "Variance components",
        "Redundancy numbers",
        "Reliability",
        "Removals",
        "Plots",
        "Scan poses",
        "Produced by",
    ):
        assert f">{heading}" in page, heading
    # A1 has no independent scale: named as not estimable, never given a number.
    assert "not estimable" in page and "<li>A1 is not estimable: scale is undefined" in page
    # Every confounding in the HTML with the JSON's own sentence (the text summary prints it too).
    assert doc["confoundings"] and all(
        f"<li>{html.escape(c['text'], quote=True)}</li>" in page for c in doc["confoundings"]
    )
    # The AP table, parsed: one row per AP of the JSON, value and sigma in report units (mm
    # and arc seconds, converted here), |t| and the correlation partner; A1 without numbers.
    table = _tables(page)["aps"]
    assert [r[0] for r in table[1:]] == list(doc["aps"])
    for row in table[1:]:
        a = doc["aps"][row[0]]
        if a["value"] is None:
            assert row[2] == row[3] == "\u2013" and row[8].startswith("not estimable"), row
            continue
        f = 1e3 if a["unit"] == "m" else 180 * 3600 / np.pi
        assert float(row[2]) == pytest.approx(a["value"] * f, abs=1e-3), row
        assert float(row[3]) == pytest.approx(a["sigma"] * f, abs=1e-3), row
        assert row[4] == ("mm" if a["unit"] == "m" else '"')
        assert float(row[5]) == pytest.approx(abs(a["t"]), abs=0.05)
        assert row[7] == a["max_corr_with"]
    assert NOT_COMPUTED_OUTLIERS not in page
    assert "not computed" not in page.split(">Removals")[1].split("Plots")[0]
    # Provenance: the SHA-256 of the observation file, computed here independently.
    digest = hashlib.sha256((calibrated / "obs.csv").read_bytes()).hexdigest()
    assert digest in page and doc["provenance"]["inputs"][0]["sha256"] == digest


NOT_COMPUTED_OUTLIERS = "screening and data snooping: not computed"


class _TableParser(html.parser.HTMLParser):
    """The text of every cell of every ``<table class=...>``, by class: {class: [rows]}."""

    def __init__(self):
        super().__init__()
        self.tables, self.cls, self.row, self.cell = {}, None, None, None

    def handle_starttag(self, tag, attrs):
        if tag == "table":
            self.cls = dict(attrs).get("class", "")
            self.tables.setdefault(self.cls, [])
        elif tag == "tr" and self.cls is not None:
            self.row = []
        elif tag in ("td", "th") and self.row is not None:
            self.cell = ""

    def handle_endtag(self, tag):
        if tag in ("td", "th") and self.cell is not None:
            self.row.append(self.cell.strip())
            self.cell = None
        elif tag == "tr" and self.row is not None:
            self.tables[self.cls].append(self.row)
            self.row = None
        elif tag == "table":
            self.cls = None

    def handle_data(self, data):
        if self.cell is not None:
            self.cell += data


def _tables(page):
    parser = _TableParser()
    parser.feed(page)
    return parser.tables


def test_report_from_plain_json_says_not_computed(calibrated, capsys):
    out = calibrated / "plain.html"
    assert main(["report", str(calibrated / "p.json"), "--html", str(out)]) == 0
    page = out.read_text()
    assert NOT_COMPUTED_OUTLIERS in page
    assert "variance components: not computed" in page
    assert "residual plots: not computed" in page  # the JSON has no residuals
    assert page.count("data:image/png;base64,") == 1  # correlations from ap_covariance
    # Errors in one line, exit code 2.
    (calibrated / "bad.json").write_text("[1, 2]")
    assert main(["report", str(calibrated / "bad.json"), "--html", str(out)]) == 2
    assert capsys.readouterr().err.strip().count("\n") == 0


def _chromium():
    for exe in ("chromium", "chromium-browser", "google-chrome"):
        if shutil.which(exe):
            return shutil.which(exe)
    return None


def _screenshot(exe, page, shot, profile):
    """Render ``page`` into ``shot``; returns chromium's exit code and the tail of its stderr."""
    cmd = [
        exe,
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-dev-shm-usage",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        f"--user-data-dir={profile}",
        "--window-size=1200,5000",
        f"--screenshot={shot}",
        page.as_uri(),
    ]
    # Chromium puts its singleton socket under TMPDIR, and a Unix socket path has at most 107
    # bytes: pytest's tmp_path under xdist can be longer, so TMPDIR is a short folder that the
    # context manager removes.
    with tempfile.TemporaryDirectory(prefix="tj") as short:
        env = {**os.environ, "TMPDIR": short}
        try:
            run = subprocess.run(cmd, capture_output=True, timeout=180, check=False, env=env)
        except subprocess.TimeoutExpired:
            return None, "timed out after 180 s"
    return run.returncode, run.stderr.decode(errors="replace")[-2000:]


def test_report_renders_in_headless_chromium(calibrated, tmp_path):
    exe = _chromium()
    if exe is None:
        pytest.skip(
            "chromium is not installed (./scripts/setup installs it: apt-get install chromium)"
        )
    shot = tmp_path / "report.png"
    # A browser that starts but dies before it draws (a machine without the shared memory, fonts
    # or namespaces it needs) says nothing about the report: up to three tries, then a control
    # page of plain text decides between "this chromium cannot draw here" (skip, with its stderr)
    # and "it draws a page but not our report" (fail, with its stderr).
    for attempt in range(3):
        rc, err = _screenshot(exe, calibrated / "report.html", shot, tmp_path / f"profile{attempt}")
        if shot.exists():
            break
    if not shot.exists():
        control = tmp_path / "control.html"
        control.write_text("<html><body><h1>control</h1><p>plain text</p></body></html>")
        crc, cerr = _screenshot(exe, control, tmp_path / "control.png", tmp_path / "pc")
        if not (tmp_path / "control.png").exists():
            pytest.skip(f"{exe} cannot take a screenshot on this machine (rc {crc}): {cerr}")
        pytest.fail(f"chromium drew a control page but not the report (rc {rc}): {err}")
    assert shot.stat().st_size > 20_000
    from PIL import Image

    rgb = np.asarray(Image.open(shot).convert("RGB"), dtype=float)
    assert rgb.shape == (5000, 1200, 3)
    gray = rgb.mean(axis=2)
    # Not a blank or an error page: text lines down the whole page (rows with dark ink,
    # separated by white ones: many separate runs of ink) ...
    ink = (gray < 128).any(axis=1)
    runs = np.count_nonzero(ink[1:] & ~ink[:-1])
    assert runs > 60, runs
    assert np.flatnonzero(ink).max() - np.flatnonzero(ink).min() > 2000
    # ... and the two embedded plots drawn: coloured pixels (the text is black on white; the
    # residual and correlation plots are in colour) in at least two separate bands of rows.
    colour = (rgb.max(axis=2) - rgb.min(axis=2)) > 60
    bands = colour.sum(axis=1) > 20
    starts = np.count_nonzero(bands[1:] & ~bands[:-1])
    assert colour.sum() > 20_000 and starts >= 2, (colour.sum(), starts)
    if os.environ.get("TLSJAX_KEEP_SCREENSHOT"):
        shutil.copy(shot, os.environ["TLSJAX_KEEP_SCREENSHOT"])
