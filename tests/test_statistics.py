"""VCE, data snooping, reliability and AP tests (SPEC sections 5, 7) against independent
references: the dense oracle, direct re-adjustment with an injected bias, counting.

Private imports: the re-weighted adjustment and the rule for targets left without redundancy
(private steps of the pipeline), the residual plot's AP curves, the constants of _stats; no
recompilation is counted with tests/dispatch.py.
"""

import dataclasses

import numpy as np
import pytest
from dispatch import compiled_programs

import tlsjax as tj

APS = ("A0", "B6", "B7", "C0")
MODEL = tj.CalibrationModel(tj.Scanner(aps=APS))


@pytest.fixture(scope="module")
def sim():
    return tj.simulate(tj.Room(n_targets=36), seed=11, aps=" ".join(APS))


@pytest.mark.internal
def test_constants():
    from scipy import stats

    from tlsjax._stats import confidence_scale, non_centrality, normal_critical_value

    # tlsjax._stats keeps scipy.stats out of ``import tlsjax``: the normal quantiles from the
    # standard library, the 95 % ellipsoid factors as scipy gives them.
    assert normal_critical_value(0.001) == pytest.approx(stats.norm.ppf(1 - 0.0005), rel=1e-15)
    assert non_centrality() == pytest.approx(
        stats.norm.ppf(0.9995) + stats.norm.ppf(0.8), rel=1e-15
    )
    for dim in (1, 2, 3):
        assert confidence_scale(dim) == np.sqrt(stats.chi2.ppf(0.95, dim))
    assert confidence_scale(3, 0.99) == pytest.approx(np.sqrt(stats.chi2.ppf(0.99, 3)), rel=1e-15)
    # The distribution functions (scipy.special, imported faster than scipy.stats) are
    # scipy.stats' own, to the last bit, over random degrees of freedom and arguments.
    from tlsjax._stats import chi2_cdf, chi2_quantile, chi2_sf, t_critical_value

    rng = np.random.default_rng(7)
    for dof, x, p in zip(rng.uniform(1, 5000, 50), rng.uniform(0, 3, 50), rng.uniform(0, 1, 50)):
        x *= dof
        assert chi2_cdf(x, dof) == stats.chi2.cdf(x, dof)
        assert chi2_sf(x, dof) == stats.chi2.sf(x, dof)
        assert chi2_quantile(p, dof) == stats.chi2.ppf(p, dof)
        assert t_critical_value(1 - p, dof) == stats.t.ppf(1 - (1 - p) / 2, dof)
    assert np.isclose(normal_critical_value(0.001), 3.2905, atol=1e-4)
    assert np.isclose(non_centrality(0.001, 0.8), 4.1321, atol=1e-3)
    with pytest.raises(ValueError, match="w_test_level"):
        tj.SnoopingOptions(w_test_level=1.5)
    with pytest.raises(ValueError, match="removal"):
        tj.SnoopingOptions(removal="scan")


@pytest.mark.internal
def test_mdb_and_external_reliability_by_direct_readjustment(sim):
    """An error of one MDB in observation i shifts its w-test by delta0 and the APs by the
    reported external reliability (linear model: exact up to linearisation)."""
    from tlsjax._stats import non_centrality

    net = sim.network
    base = tj.self_calibrate(
        net, MODEL, tj.CalibrationOptions(cross_validation=None, screening=None, vce=None)
    )
    delta0 = non_centrality()
    for i, g in ((5, 0), (40, 1), (77, 2)):
        obs = net.observations.copy()
        obs[i, g] += base.mdb[i, g]
        r2 = tj.self_calibrate(
            net.with_observations(obs),
            MODEL,
            tj.CalibrationOptions(cross_validation=None, screening=None, vce=None),
        )
        assert np.isclose(abs(r2.w[i, g] - base.w[i, g]), delta0, rtol=2e-3)
        s0 = base.calibration.sigma0
        sig_a = base.calibration.ap_sigmas / s0  # a priori AP sigmas
        shift = np.abs(r2.calibration.ap_values - base.calibration.ap_values) / sig_a
        # Looser than the w shift: Delta(l) is evaluated at the (biased) observation.
        assert np.isclose(shift.max(), base.external[i, g], rtol=1e-2)
        assert base.external_ap[i, g] == APS[int(np.argmax(shift))]


def test_vce_fixed_point_and_recovery(sim):
    net = sim.network
    wrong = dataclasses.replace(net, sigmas=net.sigmas * np.array([2.0, 0.5, 1.0]))
    r = tj.self_calibrate(
        wrong,
        MODEL,
        tj.CalibrationOptions(cross_validation=None, vce=tj.VCEOptions(tolerance=1e-4)),
    )
    res = r.calibration
    # Fixed point: with the re-estimated sigmas every group's v^T P v / r_g is 1.
    for g, name in enumerate(("range", "hz", "el")):
        e2 = np.sum((res.residuals[:, g] / r.sigmas[:, g]) ** 2)
        assert np.isclose(e2 / res.redundancy[:, g].sum(), 1.0, atol=2e-4), name
    f = {vc.group: vc.factor for vc in r.variance_components}
    # Simulated sigmas are the a priori ones: factors undo the deliberate error (loose: 36 targets).
    assert 0.2 < f["range"] < 0.32 and 3.2 < f["hz"] < 4.9 and 0.8 < f["el"] < 1.25
    assert np.isclose(res.sigma0, 1.0, atol=2e-3)


def test_reweighting_and_masking_do_not_recompile(sim):
    net = sim.network
    obs = net.observations.copy()
    obs[10, 0] += 30 * net.sigmas[10, 0]
    obs[50, 2] -= 30 * net.sigmas[50, 2]
    bad = net.with_observations(obs)
    tj.self_calibrate(
        bad, MODEL, tj.CalibrationOptions(cross_validation=None, snooping=tj.SnoopingOptions())
    )  # compiles this (spec, shapes) once
    with compiled_programs() as compiled:
        r = tj.self_calibrate(
            bad,
            MODEL,
            tj.CalibrationOptions(
                cross_validation=None, snooping=tj.SnoopingOptions(w_test_level=0.0001)
            ),
        )
    assert r.n_adjustments > 3  # VCE iterations and removals all ran the compiled adjustment
    assert sum(compiled.values()) == 0, dict(compiled)
    found = {(o.row, o.group) for o in r.outliers}
    assert {(10, "range"), (50, "el")} <= found
    for o in r.outliers:
        assert not r.mask[o.row, ("range", "hz", "el").index(o.group)]
        assert np.isnan(r.w[o.row, ("range", "hz", "el").index(o.group)])
    # The removed blunders' residuals are still reported, about the injected size.
    o = next(o for o in r.outliers if (o.row, o.group) == (10, "range"))
    assert abs(o.residual) > 15 * net.sigmas[10, 0] * 1e3
    res = r.calibration
    total = res.redundancy.sum() + res.redundancy_levelling.sum() + res.redundancy_prior_sum
    assert np.isclose(total, res.dof, rtol=1e-9)
    assert res.n_observations == net.n_observations + res.redundancy_levelling.astype(
        bool
    ).sum() - len(r.outliers) or res.n_observations == net.n_observations + int(
        np.isfinite(net.levelling_sigma).sum()
    ) - len(r.outliers)


@pytest.mark.parametrize("seed", [1, 2])
def test_snooping_finds_blunders_without_false_removals(seed):
    s = tj.simulate(tj.Room(n_targets=36), seed=seed, aps=" ".join(APS))
    net = s.network
    rng = np.random.default_rng(seed)
    rows = rng.choice(len(net.observations), 3, replace=False)
    cols = rng.integers(0, 3, 3)
    obs = net.observations.copy()
    for i, c in zip(rows, cols):
        obs[i, c] += 20 * net.sigmas[i, c]
    r = tj.self_calibrate(
        net.with_observations(obs),
        MODEL,
        tj.CalibrationOptions(
            cross_validation=None, snooping=tj.SnoopingOptions(w_test_level=0.05, bonferroni=True)
        ),
    )
    removed = {(o.row, ("range", "hz", "el").index(o.group)) for o in r.outliers}
    assert removed == set(zip(rows.tolist(), cols.tolist()))
    assert r.calibration.ok


@pytest.mark.internal
def test_target_removal_and_undetermined_target(sim):
    from tlsjax._inference._pipeline import Reweighter, _undetermined_targets

    net = sim.network
    rw = Reweighter(net, MODEL, tj.SolverOptions(full_covariance=False))
    w = 1.0 / net.sigmas
    lw = np.where(np.isfinite(net.levelling_sigma), 1.0 / net.levelling_sigma, 0.0)
    full = rw.run(w, lw, {}).result
    mask = np.ones_like(w, dtype=bool)
    rows = np.flatnonzero(net.target_index == 0)
    mask[rows[:-1]] = False  # target 0 is left in one scan only
    extra, mask, pinned = _undetermined_targets(net, full, mask, {}, 1)
    assert len(extra) == 3 and 0 in pinned and not mask[rows].any()
    res = rw.run(np.where(mask, w, 0.0), lw, pinned).result
    assert res.ok, res.message
    # The target's 3 x n_scans observations and its 3 unknowns leave; the pin adds 3 and 3.
    assert res.dof == full.dof - 3 * len(rows) + 3
    assert np.isclose(
        res.redundancy.sum() + res.redundancy_levelling.sum() + res.redundancy_prior_sum, res.dof
    )
    np.testing.assert_allclose(res.target_xyz[0], full.target_xyz[0], atol=1e-6)


def test_ap_t_tests_and_insignificant_term():
    s = tj.simulate(tj.Room(n_targets=36), seed=4, aps="A0 B7 C0")
    r = tj.self_calibrate(s.network, MODEL, tj.CalibrationOptions(cross_validation=None, vce=None))
    t = {a.name: a for a in r.ap_tests}
    assert t["A0"].significant and t["B7"].significant and t["C0"].significant
    assert not t["B6"].significant  # B6 is not in the data
    assert np.isclose(t["B6"].critical, 1.96, atol=0.01)


def test_checkpoints_noiseless_identity_and_improvement():
    from tlsjax import assess_checkpoints

    for noise in (False, True):
        s = tj.simulate(
            tj.Room(n_targets=24), seed=3, aps=" ".join(APS), noise=noise, architecture="panoramic"
        )
        cp = {t: s.true_targets[i] for i, t in enumerate(s.network.targets)}
        r = assess_checkpoints(
            s.network, cp, s.true_aps, scanner=tj.Scanner(architecture="panoramic")
        )
        assert r.n_points == len(s.network.observations)
        if not noise:
            # True APs on noiseless data: the corrected scans coincide with the check points.
            assert max(r.with_correction.values()) < 1e-6
        else:
            assert r.with_correction["range_mm"] < 1.5 and r.with_correction["hz_arcsec"] < 30
        assert r.without["range_mm"] > 8 and r.without["hz_arcsec"] > 100
    with pytest.raises(ValueError, match="check_points"):
        assess_checkpoints(s.network, {"nope": (0, 0, 0)}, s.true_aps)


def test_testing_fields_are_strict_json(sim):
    import json

    net = sim.network
    obs = net.observations.copy()
    obs[3, 1] += 40 * net.sigmas[3, 1]
    r = tj.self_calibrate(
        net.with_observations(obs),
        MODEL,
        tj.CalibrationOptions(
            cross_validation=None,
            snooping=tj.SnoopingOptions(removal="target", w_test_level=0.05, bonferroni=True),
        ),
    )
    d = r.testing_fields()
    text = json.dumps(d, allow_nan=False)
    assert len(d["outliers"]) == 3 and {o["group"] for o in d["outliers"]} == {"range", "hz", "el"}
    assert set(d["variance_components"]) == {"range", "hz", "el", "levelling"}
    assert "critical_value" in text


def test_stepwise_selection_adds_the_true_term_and_rejects_a_spurious_one():
    s = tj.simulate(tj.Room(n_targets=24), seed=5, aps="A0")
    selection = tj.SelectionOptions(candidates=("A0", "B7"), test_level=0.01)
    sel = tj.self_calibrate(
        s.network,
        tj.CalibrationModel(tj.Scanner(aps=())),
        tj.CalibrationOptions(cross_validation=None, vce=None, selection=selection),
    ).selection
    assert sel.aps == ("A0",)
    actions = [(st.action, st.term) for st in sel.steps if st.action != "try"]
    assert actions == [("start", ""), ("add", "A0"), ("final", "")]
    # B7 is not in the data: its score test at the final set is not significant, and it was
    # never refitted (terms enter by their score test, no trial fit per candidate).
    b7 = next(t for t in sel.score_tests.tests if t.name == "B7")
    assert not b7.significant
    assert sel.n_fits == 2  # (), (A0): one fit per distinct set
    assert sel.steps[1].sigma0 < sel.steps[0].sigma0


@pytest.mark.internal
def test_residual_plot_ap_curves(sim, tmp_path):
    from tlsjax import plot_residuals
    from tlsjax._report._plots import _ap_curves

    res = tj.calibrate(sim.network, MODEL)
    curves = _ap_curves(res, tj.Scanner())
    # B6 (sec(alpha) - 1) and B7 (tan alpha) depend on the elevation angle only; A0 and C0 are
    # constants, drawn against range (first column) only.
    assert sorted(curves) == [(0, 0), (1, 2), (2, 0)]
    assert curves[(1, 2)]["terms"] == ["B6", "B7"]
    l = sim.network.observations
    b6, b7 = 1 / np.cos(l[:, 2]) - 1, np.tan(l[:, 2])
    np.testing.assert_allclose(
        curves[(1, 2)]["at_obs"], res.ap_values[1] * b6 + res.ap_values[2] * b7, rtol=1e-12
    )
    np.testing.assert_allclose(curves[(0, 0)]["y"], res.ap_values[0])
    for ext in ("png", "svg"):
        p = plot_residuals(
            res,
            str(tmp_path / f"r.{ext}"),
            scanner=tj.Scanner(),
            compare=res,
            mask=np.ones_like(l, dtype=bool),
        )
        assert (tmp_path / f"r.{ext}").stat().st_size > 10_000 and p.endswith(ext)


def test_removed_observation_is_left_out_of_the_redundancy_means():
    sim = tj.simulate(tj.Room(n_targets=36), seed=21, aps="A0 B6 B7 C0")
    net = sim.network
    obs = net.observations.copy()
    obs[7, 0] += 40 * net.sigmas[7, 0]
    tested = tj.self_calibrate(
        net.with_observations(obs),
        tj.CalibrationModel(sim.scanner),
        tj.CalibrationOptions(
            cross_validation=None,
            vce=None,
            snooping=tj.SnoopingOptions(bonferroni=True, w_test_level=0.05),
        ),
    )
    res = tested.calibration
    assert [(o.row, o.group) for o in tested.outliers] == [(7, "range")]
    assert not res.used[7, 0] and res.used.sum() == res.used.size - 1 and res.redundancy[7, 0] == 0
    summary = res.to_dict()["redundancy"]
    assert np.isclose(
        summary["range"]["mean"], np.delete(res.redundancy[:, 0], 7).mean(), rtol=1e-12
    )
    assert np.isclose(summary["total"]["sum"], res.dof, rtol=1e-9)
