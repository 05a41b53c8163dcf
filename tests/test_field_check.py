"""Field checks (issue 38): the DVW guideline's distance differences and the ISO 17123-9-style
comparison, and matching across scans from 3 common targets."""

import json

import numpy as np
import pytest

import tlsjax as tj
from tlsjax._cli import main
from tlsjax._model._geometry import rotation_matrix

# The guideline's layout (DVW-Merkblatt 7-2014, figure 2): S1, T1, S2, T2 on one line, T3 at
# the far corner of the horizontal right triangle, T4 above T2.
T = {"T1": [6.0, 0, 0.0], "T2": [20.0, 0, 0.0], "T3": [20.0, 14.0, 0.0], "T4": [20.0, 0, 9.0]}
S = {"S1": np.array([0.0, 0.0, 0.0]), "S2": np.array([13.0, 0.0, 0.0])}


def _centres(a0=0.0, sigma=0.2e-3, repeats=3, seed=0):
    """Scanner-space centres of each station's repeats, with a range offset a0 [m]."""
    rng = np.random.default_rng(seed)
    out = {}
    for s, (name, pos) in enumerate(S.items()):
        R = rotation_matrix(0.01, -0.02, 1.0 + s, xp=np)
        out[name] = {}
        for t, X in T.items():
            x = R @ (np.asarray(X) - pos)
            x = x * (1 + a0 / np.linalg.norm(x))
            out[name][t] = x + rng.normal(0, sigma, (repeats, 3))
    return out


def test_dvw_check_finds_a_range_offset_and_then_leaves_the_angles_unjudged():
    ok = tj.field_check(_centres(), tj.FieldCheckOptions(u_t=0.5e-3))
    assert ok.passed and all(r["passed"] for r in ok.rows)
    # u_T = sqrt(u_A^2 + u_B^2) (DVW eq. 3), U = 4 u_T (eq. 7); u_A near the 0.2 mm drawn.
    assert abs(ok.u_t - np.hypot(ok.u_a, 0.5e-3)) < 1e-12 and 0.15e-3 < ok.u_a < 0.25e-3
    assert ok.rows[0]["limit_m"] == pytest.approx(4 * ok.u_t)
    # A 2 mm rangefinder offset: T1T2 is free of it from S1 (both on the same ray), doubled
    # from S2 (eq. 8): Delta 1,2 = -2 a0... whose sign follows the layout: |Delta| = 2 a0.
    bad = tj.field_check(_centres(a0=2e-3), tj.FieldCheckOptions(u_t=0.5e-3))
    d12 = bad.rows[0]
    assert d12["quantity"].startswith("Delta 1,2") and abs(abs(d12["value_m"]) - 4e-3) < 0.5e-3
    assert d12["passed"] is False and not bad.passed
    assert [r["passed"] for r in bad.rows[1:3]] == [None, None]  # section 2.6
    json.dumps(bad.to_dict(), allow_nan=False)
    assert "FAIL" in bad.summary()


def test_field_check_reports_what_it_cannot_form():
    c = _centres(repeats=1)
    del c["S2"]["T3"]
    with pytest.raises(ValueError, match="scan each target at least twice"):
        tj.field_check(c)
    r = tj.field_check(c, tj.FieldCheckOptions(u_t=0.5e-3))
    assert any("T3T4 is not seen from both stations" in m for m in r.messages)
    assert np.isnan(r.u_a) and r.to_dict()["u_a_m"] is None


def _patch(path, centre, rng, size=0.15, n=60, noise=0.5e-3):
    """A checkerboard patch (header //X Y Z R G B Intensity) facing the scanner at centre,
    the dark squares 4 times as noisy in range as the white ones."""
    c = np.asarray(centre, dtype=float)
    n_ = -c / np.linalg.norm(c)
    e1 = np.cross([0, 0, 1.0], n_)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(n_, e1)
    u, v = np.meshgrid(np.linspace(-size / 2, size / 2, n), np.linspace(-size / 2, size / 2, n))
    u, v = u.ravel(), v.ravel()
    white = 0.5 + 0.5 * np.tanh(u / 0.004) * np.tanh(v / 0.004)  # a footprint's blur
    P = c + np.outer(u, e1) + np.outer(v, e2)
    P += np.outer(rng.normal(0, noise * (1 + 3 * (1 - white))), c / np.linalg.norm(c))
    rgb = rng.integers(0, 255, (len(P), 3))
    inten = 300 + 3000 * white + rng.normal(0, 30, len(P))
    with open(path, "w") as fh:
        fh.write("//X Y Z R G B Intensity\n")
        np.savetxt(fh, np.column_stack([P, rgb, inten]), fmt="%.6f")


def test_cli_field_check_from_target_patches(tmp_path, capsys):
    # Patches as students crop them (one target per file, T1.1 and T1.2 its repeats), with
    # the red column before the intensity: read by name, every centre found, the check passes.
    rng = np.random.default_rng(3)
    c = _centres(sigma=0.0, repeats=2)
    args = ["field-check", "--checkerboards", "--u-t-mm", "0.5", "--json", str(tmp_path / "f.json")]
    for s in ("S1", "S2"):
        (tmp_path / s).mkdir()
        files = []
        for t, X in c[s].items():
            for k, x in enumerate(X):
                files.append(str(tmp_path / s / f"{t}.{k + 1}.txt"))
                _patch(files[-1], x, rng)
        args += [f"--{s.lower()}", *files]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert "overall: PASS" in out and "Delta 3,4" in out
    doc = json.load(open(tmp_path / "f.json"))
    assert doc["repeats"]["S1"] == {"T1": 2, "T2": 2, "T3": 2, "T4": 2}


def test_matching_from_three_common_targets_and_its_ambiguity():
    rng = np.random.default_rng(5)
    tri = np.array([[0.0, 0.0, 0.0], [7.0, 0.0, 0.0], [2.0, 3.0, 0.5]])
    R = rotation_matrix(0.05, -0.03, 2.1, xp=np)
    B = tri @ R.T + [1.0, -2.0, 0.3] + rng.normal(0, 1e-3, (3, 3))
    found = tj.ExtractedTargets.from_centres(("A", "B"), [0, 0, 0, 1, 1, 1], np.vstack([tri, B]))
    four = tj.match_targets(found)
    assert four.matching.status["B"] == "too few common targets"
    three = tj.match_targets(found, tj.TargetMatchingOptions(min_common=3))
    assert three.matching.status["B"] == "placed"
    assert list(three.names[:3]) == list(three.names[3:]) and all(three.names)
    # An isosceles triangle maps onto itself by a half turn about its axis: 3 cannot decide.
    iso = np.array([[0.0, 0, 0], [6.0, 0, 0], [3.0, 5.0, 0]])
    found = tj.ExtractedTargets.from_centres(
        ("A", "B"), [0] * 3 + [1] * 3, np.vstack([iso, iso @ R.T])
    )
    amb = tj.match_targets(found, tj.TargetMatchingOptions(min_common=3))
    assert amb.matching.status["B"] == "ambiguous" and not any(amb.names)
    assert "ambiguous" in amb.matching.summary()
