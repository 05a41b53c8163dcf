"""Model identification (issue 41; SPEC section 7, "candidates the design can estimate, and
alternatives", "prediction"): score tests only of the terms the design can estimate, groups of
alternatives whose correlation after the model is checked against a dense projector, a one-step
estimate beyond the plausibility bounds flagged.

Small rooms (24 targets, six scans) so that each adjustment compiles once for the module.
Private imports: the hand-written dense point model of ``tests/helpers.py`` (the oracle); the
AP registry (``tlsjax._model._aps``), to take a term registered for one test out again; and
``tlsjax._inference._architecture``, whose calibration a test makes fail.
"""

import dataclasses
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import BASES, dense_residuals

import tlsjax as tj

ARCSEC = np.pi / 180 / 3600
PHYSICAL = "A0 B6 B7 C0"
MODEL = tj.CalibrationModel(tj.Scanner(aps=PHYSICAL))
ROOM = tj.Room(n_targets=24)
#: A small room (1-4 m ranges), where a large range misfit is far from a change of scale.
SMALL = tj.Room(
    length=5, width=4, height=2.5, n_targets=24, stations=((1.5, 1.5, 1.2), (3.5, 2.5, 1.2))
)


@pytest.fixture(scope="module")
def c3_room():
    """The room with C3 (cos alpha, vertical circle eccentricity) in the data, the physical
    model without it; its score tests."""
    s = tj.simulate(ROOM, seed=0, aps=PHYSICAL + " C3")
    res = tj.calibrate(s.network, MODEL)
    return s, res, tj.score_tests(s.network, MODEL, res)


def test_a_range_scale_is_never_proposed_to_a_free_network():
    """A 20 mm range term and a 200 mm offset that the model lacks make the residuals large:
    at the observations A1's column then passes the engine's rank test (its distance from a
    change of scale is the residuals), at the adjusted observations it is exactly a change of
    scale. It is listed as not estimable with that reason, never significant; with two scale
    bars it is a candidate again. A0's one-step estimate (~200 mm) is flagged as implausible."""
    none = tj.CalibrationModel(tj.Scanner(aps="none"))
    true = {"A2": 0.02, "C3": 0.003, "A0": 0.2}
    s = tj.simulate(SMALL, seed=1, aps="A0 A2 C0 B7 C3", true_aps=true)
    # The built-in terms written out: another test of the same process may have registered
    # its own (a user's term in km would be a change of scale too, and listed beside A1).
    builtin = tuple(dict.fromkeys(tj.PRESETS["chow2013"] + tj.PRESETS["lichti2006"]))
    options = tj.CalibrationOptions(tests=tj.TestOptions(candidates=builtin))
    tests = tj.score_tests(s.network, none, tj.calibrate(s.network, none), options)
    a1 = tests.test("A1")
    assert not a1.testable and not a1.significant and "scale" in a1.note
    assert "A1" not in [t.name for t in tests.significant] and tests.best().name != "A1"
    assert [t.name for t in tests.not_estimable] == ["A1"]
    assert "not estimable in this design" in tests.summary() and "A1" in tests.summary()
    doc = tests.to_dict()
    assert doc["not_estimable"][0]["name"] == "A1"
    a0 = tests.test("A0")
    assert a0.significant and a0.plausibility == "warning" and "A0" in a0.plausibility_note
    assert "[warning" in a0.summary()
    bars = tj.simulate(SMALL, seed=1, aps="A0 A2 C0 B7 C3", true_aps=true, scale_bars=2)
    tests = tj.score_tests(bars.network, none, tj.calibrate(bars.network, none))
    assert tests.test("A1").testable


def test_alternatives_are_grouped_by_their_correlation_after_the_model(c3_room):
    """The correlation of two candidates' whitened columns after the model, ``c_i^T Q_vv c_j``
    normalised, from a dense Jacobian of the hand-written model (``Q_vv = I - A A^+``): the
    group's correlation matches it; a pair beyond 0.9 is in one group."""
    s, res, tests = c3_room
    net = s.network
    assert tests.groups and all(len(g) > 1 for g in tests.groups)
    c3 = tests.test("C3")
    assert c3.significant and c3.alternatives  # C3 is in a group (with C5: cos 2 alpha)
    aps = PHYSICAL.split()
    x = np.concatenate([res.target_xyz.reshape(-1), res.eops.reshape(-1), res.ap_values])
    f = lambda x: dense_residuals(x, net, aps, len(net.targets), len(net.scans))
    A = np.asarray(jax.jacfwd(f)(jnp.asarray(x)))
    l = net.observations
    bases = {
        "C3": lambda a: np.cos(a),
        "C5": lambda a: np.cos(2 * a),
        "C1": lambda a: a,
        "C2": lambda a: np.sin(a),
        "C4": lambda a: np.sin(2 * a),
    }
    cols = {}
    for name, b in bases.items():
        c = np.zeros((len(l), 3))
        c[:, 2] = b(l[:, 2]) / net.sigmas[:, 2]
        cols[name] = np.concatenate([c.reshape(-1), np.zeros(A.shape[0] - c.size)])
    proj = lambda c: c - A @ np.linalg.lstsq(A, c, rcond=None)[0]
    r = {n: proj(c) for n, c in cols.items()}
    corr = lambda a, b: abs(r[a] @ r[b]) / np.sqrt((r[a] @ r[a]) * (r[b] @ r[b]))
    group = tests.group_of("C3")
    (other,) = [n for n in group if n != "C3"]
    assert np.isclose(c3.alternative_correlation, corr("C3", other), atol=1e-4)
    names = [n for n in bases if tests.test(n).testable]
    for a in names:
        for b in names:
            if a < b:
                assert corr(a, b) < 0.9 + 1e-4 or b in tests.group_of(a), (a, b, corr(a, b))
    # The summary shows the group with each one's T, and the JSON lists it.
    assert "alternatives" in tests.summary() and f"{other} T = " in tests.summary()
    assert list(group) in tests.to_dict()["alternatives"]


# --- Cross-validation by scan groups (issue 41.1) ---------------------------------------------


@pytest.fixture(scope="module")
def physical_room():
    """The room with the physical terms in the data; the physical model's cross-validation with
    rigid and with automatic (levelled where there are tilt readings) placement."""
    s = tj.simulate(ROOM, seed=0, aps=PHYSICAL)
    rigid_folds = tj.CrossValidationOptions(placement="rigid")
    rigid = tj.cross_validate(s.network, MODEL, tj.CalibrationOptions(cross_validation=rigid_folds))
    auto = tj.cross_validate(s.network, MODEL)
    return s, rigid, auto


def _reduced(net, held):
    """The network without the scans ``held``: a fresh network, calibrated from scratch."""
    keep = ~np.isin(np.asarray(net.scans)[net.scan_index], held)
    lev = {
        s: dict(omega=net.levelling[j, 0], phi=net.levelling[j, 1], sigma_omega=net.levelling_sigma[j, 0], sigma_phi=net.levelling_sigma[j, 1])
        for j, s in enumerate(net.scans)
        if s not in held and np.isfinite(net.levelling_sigma[j, 0])
    }  # fmt: skip
    return tj.make_network(
        list(np.asarray(net.scans)[net.scan_index][keep]),
        list(np.asarray(net.targets)[net.target_index][keep]),
        net.observations[keep],
        sigmas=net.sigmas[keep],
        levelling=lev,
        drop_single_targets=True,
    )


def _cartesian(l):
    r, t, a = l.T
    return np.stack([r * np.cos(a) * np.cos(t), r * np.cos(a) * np.sin(t), r * np.sin(a)], 1)


def _procrustes(x, X):
    """Rigid least-squares fit of x onto X by the SVD of the cross-covariance (Arun 1987)."""
    cx, cX = x.mean(0), X.mean(0)
    U, _, Vt = np.linalg.svd((x - cx).T @ (X - cX))
    D = np.diag([1, 1, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ D @ U.T
    return (x - cx) @ R.T + cX - X


def _levelled(x, X, reading):
    """Heading and position fitted by scipy with the tilt of the readings held:
    ``X = (R2(phi) R1(omega) Rz(k))^T x + S`` (the compensator senses R e3)."""
    from helpers import _R
    from scipy.optimize import least_squares

    B = np.asarray(_R(reading[0], reading[1], 0.0))

    def f(p):
        R = B @ np.asarray(_R(0.0, 0.0, p[0]))
        return (x @ R + p[1:] - X).reshape(-1)

    p0 = np.concatenate([[0.0], X.mean(0) - x.mean(0)])
    best = min(
        (
            least_squares(f, p0 + [k, 0, 0, 0], xtol=1e-14, ftol=1e-14)
            for k in np.arange(0, 6.3, 0.5)
        ),
        key=lambda r: r.cost,
    )
    return f(best.x).reshape(-1, 3)


def test_cross_validation_matches_fresh_calibrations_of_the_rest(physical_room):
    """Two folds recomputed independently: the rest as a network of its own calibrated from
    scratch (tj.calibrate), the held-out scan corrected with its APs by the hand-written bases
    and placed by an SVD Procrustes fit (rigid) or a scipy fit of heading and position with the
    tilt readings held (levelled); the misfit RMS per fold, 3D and per axis, with and without
    the APs."""
    s, rigid, auto = physical_room
    net = s.network
    assert rigid.code == tj.CrossValidationCode.IMPROVED and all(f.ok for f in rigid.folds)
    assert [f.held_out for f in rigid.folds] == [(sc,) for sc in net.scans]
    aps = PHYSICAL.split()
    for held in ("S2", "S6"):  # a levelled and a tilted scan
        reduced = _reduced(net, [held])
        ref = tj.calibrate(reduced, MODEL)
        # No calibration: the rest adjusted with the APs held at zero (absent, issue 41.4).
        ref0 = tj.calibrate(reduced, tj.CalibrationModel(MODEL.scanner, fixed_aps=PHYSICAL))
        fold = next(f for f in rigid.folds if f.held_out == (held,))
        np.testing.assert_allclose([fold.aps[a] for a in aps], ref.ap_values, rtol=1e-5)
        j = net.scans.index(held)
        rows = np.flatnonzero(net.scan_index == j)
        l = net.observations[rows]
        corrected = l.copy()
        for k, name in enumerate(aps):
            g, basis = BASES[name]
            corrected[:, g] -= ref.ap_values[k] * np.asarray(basis(l[:, 0], l[:, 1], l[:, 2]))
        order = [ref.targets.index(net.targets[t]) for t in net.target_index[rows]]
        X, X0 = ref.target_xyz[order], ref0.target_xyz[order]
        for placed, cv in ((_procrustes, rigid), (_levelled, auto)):
            f = next(f for f in cv.folds if f.held_out == (held,))
            levelled = np.isfinite(net.levelling_sigma[j]).all()
            place = placed if placed is _procrustes or levelled else _procrustes
            args = (net.levelling[j],) if place is _levelled else ()
            for obs, Y, rms in ((corrected, X, f.rms_mm), (l, X0, f.rms_none_mm)):
                e = place(_cartesian(obs), Y, *args)
                mine = [rms[k] for k in ("xyz", "x", "y", "z")]
                theirs = [np.sqrt(np.mean(np.sum(e**2, 1))), *np.sqrt(np.mean(e**2, 0))]
                np.testing.assert_allclose(mine, np.array(theirs) * 1e3, rtol=1e-4, atol=1e-5)
    # Pooled over the folds.
    n = np.array([f.n for f in rigid.folds])
    pooled = np.sqrt(sum(f.n * f.rms_mm["xyz"] ** 2 for f in rigid.folds) / n.sum())
    assert np.isclose(rigid.rms_mm["xyz"], pooled)
    doc = rigid.to_dict()
    assert doc["improves"] and len(doc["folds"]) == len(net.scans)
    assert "with the APs" in rigid.summary()


def test_a_calibration_that_does_not_improve_prediction_says_so():
    """Data without systematic errors: the physical model's APs fit noise, its held-out scans
    are placed no better than uncorrected ones on targets adjusted without APs."""
    s = tj.simulate(ROOM, seed=0, aps=())
    cv = tj.cross_validate(s.network, MODEL)
    assert cv.code in (tj.CrossValidationCode.NOT_IMPROVED, tj.CrossValidationCode.NOT_SIGNIFICANT)
    assert cv.code != tj.CrossValidationCode.IMPROVED and "not" in cv.message
    # One station: no fold leaves scans from two stations, and that is the result, not NaN.
    one = tj.simulate(tj.Room(n_targets=24, stations=((4.5, 4.0, 1.6),)), seed=0, aps=PHYSICAL)
    cv = tj.cross_validate(one.network, MODEL)
    assert cv.code == tj.CrossValidationCode.NO_FOLDS and not cv.ok
    assert "one station" in cv.summary() and cv.to_dict()["rms_mm"]["xyz"] is None


def test_the_pipeline_step_reuses_the_adjustment_and_leaves_gross_errors_out(physical_room):
    """The cross-validation step of tj.self_calibrate (on by default): with a priori weights
    (no VCE) it equals tj.cross_validate; a 2 m range error that the robust start removed is
    left out of its scan's placement (one target fewer, the misfit unchanged in size); the
    result's summary, JSON and warnings carry it."""
    s, rigid, auto = physical_room
    options = tj.CalibrationOptions(vce=None, tests=tj.TestOptions(score_tests=False))
    clean = tj.self_calibrate(s.network, MODEL, options)
    cv = clean.cross_validation
    np.testing.assert_allclose(cv.rms_mm["xyz"], auto.rms_mm["xyz"], rtol=1e-5)
    assert cv.code == tj.CrossValidationCode.IMPROVED and not clean.not_improved
    assert clean.to_dict()["cross_validation"]["rms_mm"]["xyz"] == cv.rms_mm["xyz"]
    assert "cross-validation by scan groups" in clean.summary()
    obs = s.network.observations.copy()
    row = int(np.flatnonzero(s.network.scan_index == 1)[3])
    obs[row, 0] += 2.0
    result = tj.self_calibrate(s.network.with_observations(obs), MODEL, options)
    assert not result.mask[row].all()
    fold = next(f for f in result.cross_validation.folds if f.held_out == ("S2",))
    assert fold.n == 23 and fold.rms_mm["xyz"] < 2 * auto.rms_mm["xyz"]
    # Off: no folds, no section.
    off = tj.self_calibrate(s.network, MODEL, dataclasses.replace(options, cross_validation=None))
    assert off.cross_validation is None and "cross_validation" not in off.to_dict()

    # A removal without a test statistic (a target the removals leave without redundancy) is
    # never printed as nan (issue 41.6).
    extra = dataclasses.replace(result.outliers[0], w=float("nan"))
    text = dataclasses.replace(result, outliers=result.outliers + (extra,)).summary()
    assert "no w-test" in text and not re.search(r"\bnan\b", text, re.IGNORECASE)


def test_a_calibration_that_does_not_improve_prediction_has_its_own_code_and_warning():
    """Data without systematic errors, the physical model: its APs fit noise, and its held-out
    scans (seed 0) are placed worse with them than without. The result is a calibration
    (``ok``) that is ``not_improved``, with a warning naming both figures (``tlsjax
    calibrate`` exits with code 4 then: tests/test_cli.py)."""
    s = tj.simulate(ROOM, seed=0, aps=())
    options = tj.CalibrationOptions(vce=None, tests=tj.TestOptions(score_tests=False))
    result = tj.self_calibrate(s.network, MODEL, options)
    cv = result.cross_validation
    assert result.ok and result.not_improved
    assert (
        cv.code == tj.CrossValidationCode.NOT_IMPROVED and cv.rms_mm["xyz"] > cv.rms_none_mm["xyz"]
    )
    (warning,) = [w for w in result.warnings if w.startswith("cross-validation:")]
    assert f"{cv.rms_mm['xyz']:.3f} mm with" in warning and "do not apply it" in warning
    assert result.to_dict()["cross_validation"]["code"] == int(tj.CrossValidationCode.NOT_IMPROVED)


# --- Selection that ends where prediction is best (issue 41.3) --------------------------------


def test_selection_tries_alternatives_and_ends_no_worse_than_the_start(c3_room):
    """C3 in the data, C5 (cos 2 alpha) its alternative after the physical model: both are
    fitted and cross-validated, C3 enters; terms enter and leave by one statistic in one
    variance factor (T / s0^2 and t^2 against one critical value), the final score tests are
    judged in the same units (none significant where the selection stopped), and the end
    point predicts held-out scans no worse than the start."""
    s, _, tests = c3_room
    assert "C5" in tests.group_of("C3")
    selection = tj.SelectionOptions(candidates=("C3", "C5"))
    options = tj.CalibrationOptions(vce=None, selection=selection)
    result = tj.self_calibrate(s.network, MODEL, options)
    sel = result.selection
    assert result.model.scanner.aps == sel.aps
    assert "C3" in sel.aps and "C5" not in sel.aps
    tried = {st.term: st for st in sel.steps if st.action == "try"}
    assert set(tried) == {"C3", "C5"} and all(np.isfinite(t.cv_mm) for t in tried.values())
    added = next(st for st in sel.steps if st.action == "add")
    assert added.term == "C3" and "alternatives" in added.reason
    before = sel.steps[0]
    assert np.isclose(added.statistic, added.score / before.sigma0**2)
    assert added.statistic > sel.critical
    for st in sel.steps:
        if st.action == "remove" and np.isfinite(st.statistic):
            assert st.statistic < sel.critical  # leaving: t^2 below the same critical value
    assert sel.cross_validation.cv_mm <= sel.start_cross_validation.cv_mm
    final = sel.score_tests
    assert np.isclose(final.variance_factor, result.calibration.sigma0**2, rtol=1e-6)
    assert not final.significant
    doc = sel.to_dict()
    assert doc["aps"] == list(sel.aps) and doc["cross_validation"]["folds"]
    assert "CV" in sel.summary() and "CV" in result.summary()
    assert result.to_dict()["selection"]["steps"][0]["cv_mm"] == sel.steps[0].cv_mm


@pytest.mark.internal
def test_a_near_equivalent_of_a_term_in_the_model_enters_only_if_it_predicts_better(c3_room):
    """C3 in the data; a registered C3W = C3 + 0.05 sin(5 alpha), after C3 its near-equivalent
    (|r| > 0.9 between the two estimates) whose extra effect is noise. At a lenient level
    (test_level 0.9, so that its statistic passes) it used to enter beside C3; now it is tried
    and, predicting held-out scans no better than the model without it, not entered."""
    from tlsjax._model._aps import _REGISTRY

    s, _, _ = c3_room
    basis = lambda r, t, a, sc: jnp.cos(a) + 0.05 * jnp.sin(5 * a)
    tj.register_ap("C3W", "el", basis, "rad", "C3 and a little sin(5 alpha)", overwrite=True)
    selection = tj.SelectionOptions(candidates=("C3", "C3W"), test_level=0.9)
    try:
        options = tj.CalibrationOptions(vce=None, selection=selection)
        sel = tj.self_calibrate(s.network, MODEL, options).selection
    finally:  # every registered term is a default candidate: none left for later tests
        _REGISTRY.pop("C3W", None)
    assert "C3" in sel.aps and "C3W" not in sel.aps
    (late,) = [st for st in sel.steps if st.action == "try" and st.aps[-2:] == ("C3", "C3W")]
    assert late.statistic > sel.critical and late.max_abs_corr > 0.9
    without = next(st for st in sel.steps if st.action == "add" and st.term == "C3")
    assert late.cv_mm >= without.cv_mm and "not entered" in late.reason


# --- The architecture from the data (issue 41.5) ----------------------------------------------


def test_hybrid_data_read_as_panoramic_are_named(physical_room):
    """Hybrid data imported as panoramic (the back half folded into a second face): both
    representations are fitted; hybrid explains the data clearly better (held-out misfit and
    sigma0), the comparison warns naming it, and its APs are the truth within 3 sigma while the
    panoramic reading's collimation is far off."""
    s, rigid, auto = physical_room
    l = s.network.observations.copy()
    back = l[:, 1] >= np.pi  # the back half in the second face: (theta - pi, pi - alpha)
    l[back, 1] -= np.pi
    l[back, 2] = np.pi - l[back, 2]
    pano = s.network.with_observations(l)
    cmp = tj.compare_architectures(pano, MODEL)
    assert cmp.given == "panoramic" and cmp.best == "hybrid" and cmp.clearly
    assert "hybrid" in cmp.warning and "read as panoramic" in cmp.warning
    h, p = cmp.fits["hybrid"], cmp.fits["panoramic"]
    assert h.cv_mm < p.cv_mm and h.sigma0 < p.sigma0
    np.testing.assert_allclose(h.cv_mm, auto.cv_mm, rtol=1e-3)  # the same data, as hybrid
    res = tj.calibrate(s.network, MODEL)
    for k, name in enumerate(res.ap_names):
        assert abs(h.aps[name] - s.true_aps[name]) < 3 * res.ap_sigmas[k], name
    assert abs(p.aps["B6"] - s.true_aps["B6"]) > 5 * res.ap_sigmas[1]
    assert cmp.to_dict()["best"] == "hybrid" and "warning" in cmp.summary()


@pytest.mark.internal
def test_a_failed_fit_is_reported_as_failed_and_not_compared(physical_room, monkeypatch, tmp_path):
    """The hybrid calibration of hybrid data made to fail (one Gauss-Newton step: it does not
    converge): the comparison reports it as failed with its reason and draws no conclusion
    from it (no architecture called better, not "clearly", a warning that the architecture
    was not checked), where it used to call panoramic clearly better."""
    from tlsjax._inference import _architecture

    s, _, _ = physical_room
    run = _architecture.run_tests

    def hybrid_fails(network, model, options):
        if model.scanner.architecture == "hybrid":
            options = dataclasses.replace(options, solver=tj.SolverOptions(max_iterations=1))
        return run(network, model, options)

    monkeypatch.setattr(_architecture, "run_tests", hybrid_fails)
    cmp = tj.compare_architectures(s.network, MODEL)
    h, p = cmp.fits["hybrid"], cmp.fits["panoramic"]
    assert not h.ok and h.message and p.ok
    assert cmp.given == "hybrid" and cmp.best is None and not cmp.clearly
    assert "no comparison drawn" in cmp.reason and h.message in cmp.reason
    assert "not checked" in cmp.warning and "clearly" not in cmp.warning
    text = cmp.summary()
    assert f"hybrid: failed: {h.message}" in text and "explains the data better" not in text
    doc = cmp.to_dict()
    assert doc["best"] is None and not doc["clearly"] and not doc["fits"]["hybrid"]["ok"]
    page = open(tj.write_html_report({"architecture_check": doc}, tmp_path / "r.html")).read()
    assert "no comparison drawn" in page and "Explains the data better" not in page


def test_score_test_summary_prints_a_header_only_with_content():
    """Score tests with no testable candidate (none at all, or only terms the design cannot
    estimate) say so in one line; no "missing terms (score tests of 0 candidate(s) ...)"
    header over nothing. With a testable candidate, the header has it (or the largest) under
    or beside it."""
    note = "a change of the network's scale"
    a1 = tj.ScoreTest("A1", "range", *(np.nan,) * 5, "1", False, False, note)
    c3 = tj.ScoreTest("C3", "el", 30.0, 1e-7, 0.2, 1e-4, 1e-5, "rad", True, True)
    texts = {
        "empty": tj.ScoreTests((), 100.0, 0.001, 10.83).summary(),
        "not estimable": tj.ScoreTests((a1,), 100.0, 0.001, 10.83).summary(),
        "significant": tj.ScoreTests((c3, a1), 100.0, 0.001, 10.83).summary(),
    }
    assert texts["empty"] == "missing terms: no candidate could be tested (no candidate terms)"
    assert texts["not estimable"] == f"missing terms: no candidate could be tested (A1: {note})"
    lines = texts["significant"].splitlines()
    assert lines[0].startswith("missing terms (score tests of 1 candidate(s)")
    assert lines[1].strip().startswith("C3 (el) T = 30.0") and "A1: " + note in lines[2]
    for text in texts.values():
        assert "0 candidate(s)" not in text and "none significant" not in text
        rows = text.splitlines()
        for i, row in enumerate(rows):  # a line ending with ':' has an indented line under it
            if row.endswith(":"):
                assert i + 1 < len(rows) and rows[i + 1].startswith("  "), text


# --- The HTML report reads the parts' to_dict() (issue 41.7) ----------------------------------


def test_report_sections_for_score_tests_and_cross_validation(c3_room, physical_room, tmp_path):
    _, _, tests = c3_room
    _, rigid, _ = physical_room
    doc = {"score_tests": tests.to_dict(), "cross_validation": rigid.to_dict()}
    page = open(tj.write_html_report(doc, tmp_path / "r.html")).read()
    assert ">Missing terms (score tests)" in page and "Groups of alternatives" in page
    group = ", ".join(tests.group_of("C3"))
    assert f"<li>{group}</li>" in page
    assert "Not estimable in this design" in page and "A1: a change of the network" in page
    assert ">Prediction of held-out scans (cross-validation)" in page
    assert f"{rigid.rms_mm['xyz']:.3f}" in page and f"{rigid.rms_none_mm['xyz']:.3f}" in page
    assert page.count("<td>S") >= len(rigid.folds)  # one row per fold
    assert not re.search(r"\bnan\b", page, re.IGNORECASE)
    # Without them, the report says they were not computed.
    bare = open(tj.write_html_report({}, tmp_path / "bare.html")).read()
    assert "score tests of the terms not in the model" in bare
