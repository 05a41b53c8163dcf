"""The HTML calibration report: contents from the result JSON, "not computed" where the run did
not compute a field, provenance hashes, and a render in a real headless browser."""

import hashlib
import json
import os
import shutil
import subprocess

import numpy as np
import pytest

from tlsjax._cli import main


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    d = tmp_path_factory.mktemp("report")
    obs, scans = d / "obs.csv", d / "scans.csv"
    assert main(["simulate", "--out", str(obs), "--scans-out", str(scans), "--seed", "4"]) == 0
    args = ["calibrate", str(obs), "--scans", str(scans), "--aps", "A0 A1 B6 B7 C0", "--snoop"]
    args += ["--json", str(d / "cal.json"), "--report", str(d / "report.html")]
    assert main(args) == 0
    plain = ["calibrate", str(obs), "--scans", str(scans), "--no-vce", "--json", str(d / "p.json")]
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
        "Global test",
        "Additional parameters",
        "Variance components",
        "Redundancy numbers",
        "Reliability",
        "Outliers",
        "Plots",
        "Scan poses",
        "Produced by",
    ):
        assert f">{heading}" in page, heading
    # A1 has no independent scale: named as not estimable, never given a number.
    assert "not estimable" in page and "A1</b>: scale is undefined" in page
    # Every AP's sigma as in the JSON, in report units (mm and arc seconds).
    for name, a in doc["aps"].items():
        if a["sigma"] is not None:
            f = 1e3 if a["unit"] == "m" else 180 * 3600 / np.pi
            assert f"{a['sigma'] * f:.3f}" in page, name
    assert NOT_COMPUTED_OUTLIERS not in page
    assert "not computed" not in page.split("Outliers")[1].split("Plots")[0]
    # Provenance: the SHA-256 of the observation file, computed here independently.
    digest = hashlib.sha256((calibrated / "obs.csv").read_bytes()).hexdigest()
    assert digest in page and doc["provenance"]["inputs"][0]["sha256"] == digest


NOT_COMPUTED_OUTLIERS = "data snooping: not computed"


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


def test_report_renders_in_headless_chromium(calibrated, tmp_path):
    exe = _chromium()
    if exe is None:
        pytest.skip(
            "chromium is not installed (./scripts/setup installs it: apt-get install chromium)"
        )
    shot = tmp_path / "report.png"
    cmd = [
        exe,
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        f"--user-data-dir={tmp_path / 'profile'}",
        "--window-size=1200,3000",
        f"--screenshot={shot}",
        (calibrated / "report.html").as_uri(),
    ]
    subprocess.run(cmd, capture_output=True, timeout=120, check=False)
    assert shot.exists() and shot.stat().st_size > 20_000
    from PIL import Image

    img = np.asarray(Image.open(shot).convert("L"), dtype=float)
    assert img.shape == (3000, 1200)
    # Text and plots, not a blank or error page: many dark pixels, spread down the page.
    dark = img < 128
    assert dark.mean() > 0.01
    rows_with_ink = np.flatnonzero(dark.any(axis=1))
    assert rows_with_ink.max() - rows_with_ink.min() > 2000
    if os.environ.get("TLSJAX_KEEP_SCREENSHOT"):
        shutil.copy(shot, os.environ["TLSJAX_KEEP_SCREENSHOT"])
