"""The AP-set compatibility test of SPEC section 9: size, power, visibility, inputs and the CLI.

Why the sizes suffice. The null of T is exact (to first order in the sets' errors) for any number of
simulations and check points: given the simulated noise, which is known, T_obs and the null T(e) are
the same quadratic function of the sets' errors e. So a level study needs many independent pairs of
AP sets, not many simulations per pair: 300-400 pairs of 2 simulations each (180 check points; 20
with 10 check points) give the rejection rate at 5 % to a Monte Carlo standard error of 1.1-1.3 %,
and the check fails only when the rate is off by more than that error allows (two-sided binomial
test at 0.1 %). Many pairs run as one batch through the one compiled function of a design
(``tj.compatibility_batch``), and every test uses one chunk size so that the tests of a design share
that compilation. Power is compared on the same kind of batches.

Private import: ``tlsjax._cli.main`` is the ``tlsjax`` console script's entry point
(pyproject), called in process.
"""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import stats

import tlsjax as tj
from tlsjax._cli import main

APS4 = "A0 B6 B7 C0"
CHUNK = 20  # one chunk size everywhere: the tests of a design share one compiled function
DRAWS = 4000  # null draws per pair in the batches (p resolution 2.5e-4, far below alpha)


def options(**kw):
    kw.setdefault("chunk_size", CHUNK)
    kw.setdefault("progress", False)
    return tj.CompatibilityOptions(**kw)


def _full_collimation():
    """A user-registered full collimation term, sec(alpha) (B6 of a hybrid scanner is the
    reduced sec(alpha) - 1)."""
    if "B6full" not in tj.registered_aps():
        tj.register_ap("B6full", "hz", lambda r, t, a, s: 1.0 / jnp.cos(a), "rad", "sec(alpha)")
    return "B6full"


def _calibrated(aps, seed=3):
    sim = tj.simulate(seed=seed, aps=aps)
    res = tj.calibrate(sim.network, tj.CalibrationModel(tj.Scanner(aps=aps)))
    assert res.ok, res.message
    return tj.APSet.from_result(res), res


@pytest.fixture(scope="module")
def cal4():
    return _calibrated(APS4)


@pytest.fixture(scope="module")
def set4(cal4):
    return cal4[0]


@pytest.fixture(scope="module")
def set23():
    return _calibrated("chow2013-noscale")[0]


def _sqrt(C):
    w, V = np.linalg.eigh(C)
    return (V * np.sqrt(np.clip(w, 0, None))) @ V.T


def _pairs(s1, s2, n, seed, shift=None):
    """``n`` pairs of values, both sets drawn around one truth with their own covariances
    (H0), set 1 moved by ``shift`` (H1)."""
    rng = np.random.default_rng(seed)
    V1 = s1.values + rng.standard_normal((n, len(s1.names))) @ _sqrt(s1.covariance)
    V2 = s2.values + rng.standard_normal((n, len(s2.names))) @ _sqrt(s2.covariance)
    return (V1 if shift is None else V1 + shift), V2


def _assert_size(p, alpha=0.05):
    k = int(np.sum(p < alpha))
    test = stats.binomtest(k, p.size, alpha)
    assert test.pvalue > 1e-3, f"rejection rate {k / p.size:.3f} over {p.size} pairs"


# ------------------------------------------------------------------------------------------
# Size under H0


def _design(case, set4, set23):
    """(set 1, set 2, room-and-target options) of each design of the level study."""
    if case == "4 APs":
        return set4, set4, {}
    if case == "23 APs":
        return set23, set23, {}
    if case == "10 check points":
        return set4, set4, {"n_targets": 20, "n_control": 10}
    # Different basis functions of one term: reduced against full collimation. The same
    # collimation c is c (sec - 1) in set 1 and c sec in set 2; their difference, c, is a
    # rotation about the vertical axis, which the rigid fit absorbs: both draw around one truth.
    full = _full_collimation()
    s2 = tj.APSet(("A0", full, "B7", "C0"), set4.values, set4.covariance)
    return set4, s2, {}


@pytest.mark.parametrize("case", ["4 APs", "23 APs", "10 check points", "different basis"])
def test_size_under_h0(case, set4, set23):
    s1, s2, design = _design(case, set4, set23)
    n = 300 if case == "23 APs" else 400
    V1, V2 = _pairs(s1, s2, n, seed=29)
    r = tj.compatibility_batch(
        s1, s2, V1, V2, options=options(runs=2, null_draws=DRAWS, seed=1, **design)
    )
    assert np.all(np.isfinite(r["p_value"]))
    _assert_size(r["p_value"])
    # Under H0 the p-values are uniform, not only right at 5 %.
    assert stats.kstest(r["p_value"], "uniform").pvalue > 1e-3


def test_size_at_zero_noise_with_imhof(set4):
    # Zero noise: the pure object-space test; p from Imhof's formula.
    V1, V2 = _pairs(set4, set4, 200, seed=7)
    r = tj.compatibility_batch(
        set4, set4, V1, V2, options=options(runs=4, seed=2), sigma_range=0.0, sigma_angle=0.0
    )
    _assert_size(r["p_value"])


# ------------------------------------------------------------------------------------------
# Power


def _shifts(s, ref, rng, n_random, kappa=3.0):
    """Single-AP and random directions of a difference a1 - a2, each scaled so that its
    object-space effect ``mu^T (L^T G L) mu`` is ``kappa`` times the null's 95 % quantile above
    its mean: far enough out that neither rule has power near 5 %, not so far that both have 1."""
    sd = np.sqrt(2.0 * np.diag(s.covariance))
    dirs = [np.eye(len(s.names))[k] * sd[k] for k in range(len(s.names))]
    dirs += [_sqrt(s.covariance) @ rng.standard_normal(len(s.names)) for _ in range(n_random)]
    w, V = np.linalg.eigh(s.covariance)
    whiten = (V / np.sqrt(w)) @ V.T
    room = ref.critical_value - ref.null_constant - ref.null_eigenvalues.sum()
    out = []
    for d in dirs:
        mu = np.concatenate([whiten @ d, np.zeros(len(s.names))])
        out.append(d * np.sqrt(kappa * room / (mu @ ref.null_matrix @ mu)))
    labels = list(s.names) + [f"random {k}" for k in range(n_random)]
    return labels, out


def _power_study(s, n_h0, n_alt, runs, n_random, seed):
    ref = tj.compatibility_test(s, s, options=options(runs=40, seed=seed))
    labels, shifts = _shifts(s, ref, np.random.default_rng(seed), n_random)
    V1, V2 = _pairs(s, s, n_h0, seed=seed)
    for k, d in enumerate(shifts):
        W1, W2 = _pairs(s, s, n_alt, seed=seed + 1 + k, shift=d)
        V1, V2 = np.vstack([V1, W1]), np.vstack([V2, W2])
    r = tj.compatibility_batch(s, s, V1, V2, options=options(runs=runs, null_draws=DRAWS))
    h0 = slice(0, n_h0)
    # The median-share rule at the same noise: its critical value is the 95 % quantile of the
    # median share over the H0 pairs (its null has no closed form).
    q = np.quantile(r["median_share"][h0], 0.95)
    _assert_size(r["p_value"][h0])
    rows = []
    for k, label in enumerate(labels):
        sel = slice(n_h0 + k * n_alt, n_h0 + (k + 1) * n_alt)
        rows.append((label, np.mean(r["p_value"][sel] < 0.05), np.mean(r["median_share"][sel] > q)))
    return rows


def _assert_power(rows, n_alt):
    # Per direction: no worse than the median-share rule beyond the Monte Carlo error of a
    # difference of two rates (at most 2 * sqrt(0.25 / n_alt) at 2 sigma, plus a margin).
    tol = 2.0 * np.sqrt(2 * 0.25 / n_alt)
    for label, power, share in rows:
        assert power >= share - tol, (label, power, share)
    powers, shares = np.array([r[1] for r in rows]), np.array([r[2] for r in rows])
    assert powers.mean() >= shares.mean() + 0.2, rows  # and clearly better on the whole
    assert powers.min() >= 0.3, rows  # the shifts are meant to be detectable


def test_power_at_least_the_median_share_rule_4_aps(set4):
    # Every single AP and four random directions; 80 pairs each, 6 simulations per pair (the
    # gap is wide: about 0.7-0.85 against 0.05-0.2 when this was written).
    rows = _power_study(set4, n_h0=200, n_alt=80, runs=6, n_random=4, seed=40)
    _assert_power(rows, 80)


def test_power_at_least_the_median_share_rule_23_aps(set23):
    # Every single AP of 23 and four random directions; 30 pairs each, 4 simulations per pair
    # (about 0.55-0.9 against 0.03-0.25 when this was written).
    rows = _power_study(set23, n_h0=150, n_alt=30, runs=4, n_random=4, seed=60)
    _assert_power(rows, 30)


def test_zero_noise_power_close_to_the_naive_test_where_visible(set4):
    """At zero noise T = sum lambda_m (y_m + mu_m)^2: along a direction object space sees fully
    (lambda near 1) it decides as the naive chi-square test does."""
    ref = tj.compatibility_test(
        set4, set4, options=options(runs=40), sigma_range=0.0, sigma_angle=0.0
    )
    visible = np.flatnonzero(ref.eigenvalues > 0.8)
    assert visible.size >= 2
    n = len(set4.names)
    Cd = 2.0 * set4.covariance
    ncp = 10.0  # naive power about 0.7 for chi2(4)
    V1, V2, groups = [], [], []
    for k in visible:
        d = ref.directions[:n, k] - ref.directions[n:, k]
        d = d * np.sqrt(ncp / (d @ np.linalg.solve(Cd, d)))
        W1, W2 = _pairs(set4, set4, 150, seed=100 + int(k), shift=d)
        V1.append(W1)
        V2.append(W2)
        groups += [k] * 150
    r = tj.compatibility_batch(
        set4,
        set4,
        np.vstack(V1),
        np.vstack(V2),
        options=options(runs=4, null_draws=DRAWS, null_method="draws"),
        sigma_range=0.0,
        sigma_angle=0.0,
    )
    groups = np.array(groups)
    for k in visible:
        sel = groups == k
        power, naive = np.mean(r["p_value"][sel] < 0.05), np.mean(r["naive_p_value"][sel] < 0.05)
        assert abs(power - naive) <= 0.12, (k, ref.eigenvalues[k], power, naive)


# ------------------------------------------------------------------------------------------
# The null's eigenvalues, the pure object-space test, Imhof against the draws


@pytest.mark.parametrize("case", ["4 APs", "23 APs", "different basis"])
def test_zero_noise_eigenvalues_in_unit_interval_sum_to_three(case, set4, set23):
    """L^T G L is a mean of orthogonal projectors of rank 3 (module docstring of _compatibility)."""
    s1, s2, _ = _design(case, set4, set23)
    r = tj.compatibility_test(s1, s2, options=options(runs=20), sigma_range=0, sigma_angle=0)
    lam = r.null_eigenvalues
    assert lam.min() > -1e-9 and lam.max() < 1 + 1e-9
    assert lam.sum() == pytest.approx(3.0, abs=1e-6)
    # The difference directions carry all of it (the common moves are exact zeros).
    assert r.eigenvalues.sum() == pytest.approx(3.0, abs=1e-6)
    assert r.p_method == "imhof"


def test_identical_sets_at_zero_noise_differ_by_nothing(set4):
    r = tj.compatibility_test(set4, set4, options=options(runs=20), sigma_range=0, sigma_angle=0)
    assert r.statistic < 1e-12 and r.p_value > 0.999 and r.compatible
    assert r.rms_mm[3] < 1e-9 and r.naive_chi2 == pytest.approx(0.0, abs=1e-12)


def test_clearly_different_sets_and_the_report(set4):
    v = set4.values.copy()
    v[1] += 30 * np.sqrt(set4.covariance[1, 1])  # collimation B6 moved by 30 sigma
    r = tj.compatibility_test(set4, set4.with_values(v), options=options(runs=40))
    assert not r.compatible and r.p_value < 0.01
    assert not r.naive_compatible
    d = set4.values - v
    chi2 = d @ np.linalg.solve(2 * set4.covariance, d)
    assert r.naive_chi2 == pytest.approx(chi2, rel=1e-9)
    assert r.naive_p_value == pytest.approx(stats.chi2.sf(chi2, 4), rel=1e-9)
    assert r.ap_names == set4.names and r.naive_meaningful
    assert len(r.eigenvalues) == 4 and r.least_visible.startswith("lambda")
    q1, q3 = r.share_quartiles
    assert 0 <= q1 <= r.median_share <= q3 <= 1
    text = r.summary()
    assert "NOT compatible" in text and "naive chi-square" in text and "descriptive" in text
    json.dumps(r.to_dict(), allow_nan=False)


def test_imhof_and_draws_agree_with_noise(set4):
    # Two independent evaluations of one null: seeded draws and Imhof's noncentral formula.
    v = set4.values + 2.5 * np.sqrt(np.diag(set4.covariance))
    opts = dict(runs=40, seed=3)
    a = tj.compatibility_test(set4, set4.with_values(v), options=options(**opts))
    b = tj.compatibility_test(
        set4, set4.with_values(v), options=options(null_method="imhof", **opts)
    )
    assert a.statistic == b.statistic and (a.p_method, b.p_method) == ("draws", "imhof")
    se = np.sqrt(b.p_value * (1 - b.p_value) / a.null_draws)
    assert abs(a.p_value - b.p_value) < 4 * se + 2 / a.null_draws
    assert abs(a.critical_value - b.critical_value) < 0.01 * (b.critical_value - b.null_constant)


def test_difference_object_space_cannot_see_is_reported(set4):
    # Reduced against full collimation with one coefficient: the corrections differ by a
    # constant horizontal direction, a rotation about the vertical axis.
    s1, s2, _ = _design("different basis", set4, None)
    r = tj.compatibility_test(s1, s2, options=options(runs=20))
    assert len(r.invisible) == 1 and "B6" in r.invisible[0] and "B6full" in r.invisible[0]
    assert r.seen_share.min() < 1e-6 and r.eigenvalues.min() < 1e-8
    assert r.compatible  # the two sets describe one instrument
    assert "object space cannot see" in r.summary()


def test_statistic_gradient_matches_finite_differences(set4):
    T = tj.compatibility_statistic(set4, set4, options=options(runs=2, seed=5))
    a1 = set4.values + np.sqrt(np.diag(set4.covariance))
    value_and_grad = jax.jit(jax.value_and_grad(T))
    t0, g = value_and_grad(a1, set4.values)
    sd = np.sqrt(np.diag(set4.covariance))
    for k in range(len(a1)):
        h = np.zeros_like(a1)
        h[k] = 0.1 * sd[k]
        fd = (value_and_grad(a1 + h, set4.values)[0] - value_and_grad(a1 - h, set4.values)[0]) / (
            2 * h[k]
        )
        assert float(g[k]) == pytest.approx(float(fd), rel=1e-4, abs=1e-6 * abs(float(t0)) / sd[k])
    # The function is the statistic of the test with the same settings (through the compiled
    # function above: T traced op by op costs more than its compilation).
    r = tj.compatibility_test(set4, set4.with_values(a1), options=options(runs=2, seed=5))
    assert float(value_and_grad(set4.values, a1)[0]) == pytest.approx(r.statistic, rel=1e-10)


# ------------------------------------------------------------------------------------------
# AP sets: full covariance, refusals, JSON


def test_from_result_uses_the_full_ap_covariance(cal4):
    s, res = cal4
    np.testing.assert_allclose(s.covariance, res.ap_covariance, rtol=1e-14, atol=0)
    corr = s.covariance / np.outer(s.sigmas, s.sigmas)
    assert np.abs(corr - np.eye(4)).max() > 0.05  # correlated: not the diagonal
    assert s.noise is not None and s.noise[1] > 0 and s.scanner.architecture == "hybrid"


def test_from_result_refuses_a_failed_calibration(cal4):
    _, res = cal4
    failed = dataclasses.replace(res, converged=False, result=1, message="no convergence")
    with pytest.raises(ValueError, match="did not succeed.*no convergence"):
        tj.APSet.from_result(failed)
    missing = dataclasses.replace(res, ap_covariance=None)
    with pytest.raises(ValueError, match="no AP covariance"):
        tj.APSet.from_result(missing)


def test_json_round_trip(set4, tmp_path):
    s = tj.APSet(
        set4.names,
        set4.values,
        set4.covariance,
        scanner=tj.Scanner(architecture="panoramic", unit_length=0.9),
        noise=(0.4e-3, 1e-4, 2e-4),
    )
    doc = tj.write_json(s, tmp_path / "set.json")
    assert doc["scanner"]["basis"]["B6"].startswith("sec(alpha) (full")
    back = tj.APSet.from_json(tmp_path / "set.json")
    assert back.names == s.names and back.noise == s.noise
    np.testing.assert_array_equal(back.values, s.values)
    np.testing.assert_array_equal(back.covariance, s.covariance)
    assert back.scanner == s.scanner
    # A basis this tlsjax would evaluate differently is refused, naming the file and term.
    doc["scanner"]["basis"]["B6"] = "sec(alpha) - 1 (reduced collimation, hybrid)"
    (tmp_path / "bad.json").write_text(json.dumps(doc))
    with pytest.raises(ValueError, match=r"bad\.json.*B6"):
        tj.APSet.from_json(tmp_path / "bad.json")
    for text, match in (("{", "not a readable JSON"), ('{"x": 1}', "not an AP set")):
        (tmp_path / "bad.json").write_text(text)
        with pytest.raises(ValueError, match=match):
            tj.APSet.from_json(tmp_path / "bad.json")


def test_result_json_without_covariance_or_with_a_non_estimable_ap(set4, tmp_path):
    aps = {
        n: {"value": float(v), "sigma": float(s)}
        for n, v, s in zip(set4.names, set4.values, set4.sigmas)
    }
    (tmp_path / "r.json").write_text(json.dumps({"aps": aps}))
    s = tj.APSet.from_json(tmp_path / "r.json")
    np.testing.assert_allclose(s.covariance, np.diag(set4.sigmas**2))
    assert any("uncorrelated" in n for n in s.notes)
    aps["B7"]["value"] = None
    (tmp_path / "r.json").write_text(json.dumps({"aps": aps}))
    with pytest.raises(ValueError, match="B7 is not estimable"):
        tj.APSet.from_json(tmp_path / "r.json")


# ------------------------------------------------------------------------------------------
# The command line


def _strict(path):
    def refuse(c):
        raise ValueError(f"not strict JSON: {c}")

    return json.loads(path.read_text(), parse_constant=refuse)


def test_cli_compare_calibrate_json_and_ap_set_json(tmp_path, capsys):
    obs, scans, cal = tmp_path / "obs.csv", tmp_path / "scans.csv", tmp_path / "cal.json"
    assert main(["simulate", "--out", str(obs), "--scans-out", str(scans), "--seed", "1"]) == 0
    assert main(["calibrate", str(obs), "--scans", str(scans), "--json", str(cal), "--no-vce"]) == 0
    doc = _strict(cal)
    assert doc["ap_covariance_names"] and doc["scanner"]["architecture"] == "hybrid"
    fast = ["--runs", "20", "--draws", "2000", "--no-progress", "--devices", "1"]
    out = tmp_path / "same.json"
    assert main(["compare", str(cal), str(cal), "--json", str(out), *fast]) == 0
    same = _strict(out)
    assert same["compatible"] and same["naive_chi2_test"]["meaningful"]
    # The same calibration with the collimation moved by 30 sigma, as an AP-set JSON.
    s = tj.APSet.from_json(cal)
    v = s.values.copy()
    v[s.names.index("B6")] += 30 * s.sigmas[s.names.index("B6")]
    tj.write_json(s.with_values(v), tmp_path / "moved.json")
    out = tmp_path / "moved_out.json"
    assert main(["compare", str(cal), str(tmp_path / "moved.json"), "--json", str(out), *fast]) == 1
    moved = _strict(out)
    assert not moved["compatible"] and moved["p_value"] < 0.05
    assert "NOT compatible" in capsys.readouterr().out
    # The same values as a panoramic scanner's set: B6 is then the full sec(alpha); the naive
    # test is marked not meaningful and the constant difference is one object space cannot see.
    pano = tj.APSet(s.names, s.values, s.covariance, scanner=tj.Scanner(architecture="panoramic"))
    tj.write_json(pano, tmp_path / "pano.json")
    out = tmp_path / "pano_out.json"
    rc = main(["compare", str(cal), str(tmp_path / "pano.json"), "--json", str(out), *fast])
    result = _strict(out)
    assert rc == (0 if result["compatible"] else 1)
    assert not result["naive_chi2_test"]["meaningful"] and "B6" in result["naive_chi2_test"]["note"]
    assert any("B6[1]" in t and "B6[2]" in t for t in result["invisible"])
    assert "NOT MEANINGFUL" in capsys.readouterr().out


def test_cli_compare_bad_input_is_exit_code_2(tmp_path, capsys):
    (tmp_path / "x.json").write_text('{"aps": {"Q9": {"value": 1.0, "sigma": 1.0}}}')
    assert main(["compare", str(tmp_path / "x.json"), str(tmp_path / "x.json")]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "x.json" in err and "Q9" in err
