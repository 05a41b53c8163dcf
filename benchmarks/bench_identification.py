"""Model identification by prediction (issue 41): each registered term planted in turn with a
near-equivalent alternative registered; how often stepwise selection chooses the planted term
over the alternative, whether a calibration is ever worse than none without a warning, and
whether a term the design cannot estimate is ever proposed.

For each term X of the Chow/Lichti registry (A1 with two scale bars, the only design that can
estimate it): simulate the room with the physical terms and X at its default true value
(SPEC section 8); register an alternative ``ALT`` = X's basis + lambda times the basis of the
built-in term Y of X's group whose effect after the start model is most correlated with X's,
lambda chosen so that X and ALT correlate at ``--corr`` (default 0.97) after the model: their
score statistics are then nearly equal, the case of issue 41 (C1 T = 370.6 vs C3 T = 367.0).
Then ``tj.select_aps`` from the physical model without X, candidates X and ALT; a draw counts
as correct when the selected set holds X and not ALT. Per draw also: the chosen set's
cross-validation code (a calibration worse than none must carry NOT_IMPROVED) and the score
tests' terms that the design cannot estimate (never among the significant).

    JAX_PLATFORMS=cpu python benchmarks/bench_identification.py --draws 10 --jobs 2
    python benchmarks/bench_identification.py --terms C3 B7 --draws 4 --out /tmp/ident.json

The room is drawn anew for every draw (target layout), so what the design can tell differs
between draws. Per draw the benchmark therefore also records what any selection at a
controlled level can reach there, from the noise-free design: the non-centrality
``lambda = a^2 S_xx`` of X at its planted value ``a`` after the start model, X's correlation
with ALT, the power of the selection's statistic at its critical value, X's minimal detectable
size at 90 % power (``mdb``), and ``expected_correct``: the probability that X's statistic is
the larger and passes (the rate of the rule "the larger statistic enters"). A term whose
planted value is below its MDB cannot be found in 90 % of draws by any test that keeps its
false alarms at the level; ``expected_share_correct`` and the share among the draws with
power >= 90 % separate that from the selection's own errors.

Writes benchmarks/results/identification.json (per term: draws, share correct, the statistics
of X and ALT, the CV of both when tried, the design's figures above, timings). Each term runs
in a fresh process, ``--jobs`` of them at once.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor

import numpy as np

sys.path.insert(0, os.path.dirname(__file__))
from _common import loadavg, write_results  # noqa: E402

PHYSICAL = ("A0", "B6", "B7", "C0")


def _design_schur(tj, score, room, term, names, seed):
    """The candidates ``names``' Schur complement ``S`` (whitened: ``c_i^T P Q_vv P c_j``)
    after the start model (the physical terms without ``term``), on the noise-free draw
    ``seed`` of the design with ``term`` in the data: the non-centrality of a term planted
    at ``a`` is ``a^2 S_ii``, the correlation of two after the model ``S_ij / sqrt(S_ii S_jj)``."""
    start = tuple(a for a in PHYSICAL if a != term)
    model = tj.CalibrationModel(tj.Scanner(aps=start))
    kw = {"scale_bars": 2} if term == "A1" else {}
    s = tj.simulate(room, seed=seed, aps=start + (term,), noise=False, **kw)
    res = tj.calibrate(s.network, model)
    tester = score.ScoreTester(s.network, model, list(names))
    from tlsjax._adjustment._plan import initial_params

    p = initial_params(s.network, tester.adjustment.plan, res.target_xyz, res.eops)
    aps = np.zeros(tester.adjustment.plan.spec.n_aps)
    aps[tester.model_index] = np.nan_to_num(res.ap_values)
    params = score.Params(
        score.jax.tree.map(score.jnp.asarray, p.prims),
        score.jnp.asarray(p.eops),
        score.jnp.asarray(aps),
    )
    adj = tester.adjustment
    problem = adj.problem(fixed_aps=adj.model.fixed_aps)
    out = score._score_system(
        adj.plan.spec,
        problem,
        params,
        score.jnp.asarray(score.station_positions(np.asarray(params.eops))),
    )
    K = np.asarray(out[0])
    labels = adj.plan.ap_labels
    cols = 6 * adj.plan.spec.n_scans + np.array([labels.index(n) for n in names])
    return score._schur(K, ~np.asarray(problem.fixed), cols)[2]


def _alternative(tj, score, room, term, corr, seed):
    """(name of Y, lambda): ALT = X + lambda Y with corr(X, ALT) = ``corr`` after the start
    model, on a noise-free draw of the design."""
    start = tuple(a for a in PHYSICAL if a != term)
    from tlsjax._model._aps import get_ap

    g = get_ap(term).group
    others = [
        n
        for n in tj.registered_aps()
        if n != term and get_ap(n).group == g and n in score._CHOW and n not in start and n != "A1"
    ]
    S = _design_schur(tj, score, room, term, [term] + others, seed)
    cols = range(len(others) + 1)
    a = S[0, 0]
    best, best_r = None, 0.0
    for k in range(1, len(cols)):
        r = abs(S[0, k]) / np.sqrt(a * S[k, k])
        if S[k, k] > 1e-12 * a and r > best_r and r < 0.999:
            best, best_r = k, r
    if best is None:
        return None, 0.0, 0.0
    b, c = S[0, best], S[best, best]
    # corr(X, X + lam Y) = (a + lam b) / sqrt(a (a + 2 lam b + lam^2 c)), decreasing in |lam|
    # from 1 along the sign that makes the two least alike; bisection on lam.
    sign = -1.0 if b > 0 else 1.0
    f = lambda lam: (a + lam * b) / np.sqrt(a * (a + 2 * lam * b + lam * lam * c)) - corr
    lo, hi = 0.0, np.sqrt(a / c)
    while f(sign * hi) > 0 and hi < 1e6 * np.sqrt(a / c):
        hi *= 2
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if f(sign * mid) > 0 else (lo, mid)
    return others[best - 1], sign * 0.5 * (lo + hi), best_r


#: A draw's design "detects" the planted term when the selection's test has this power at its
#: non-centrality (Baarda's beta0 = 80 % is the usual MDB; 90 % matches the criterion).
POWER = 0.9


def _expected(S, true, critical, seed, n=200_000):
    """What a level-controlled selection can reach in this draw's design (module docstring):
    the non-centrality ``lambda = a^2 S_xx`` of the planted term, its correlation ``rho`` with
    ALT after the start model, the ``power`` of the one statistic at the critical value, the
    minimal detectable size at that power (``mdb``, the term's unit, SI) and
    ``expected_correct``: the probability that the larger statistic is X's and passes the
    critical value (``z_x ~ N(sqrt(lambda), 1)``, ``z_alt = rho z_x + sqrt(1 - rho^2) e``;
    seeded Monte Carlo), i.e. the rate of entering X over ALT by the statistic."""
    from scipy import optimize, stats

    sxx, sxa, saa = S[0, 0], S[0, 1], S[1, 1]
    lam = float(true**2 * sxx)
    rho = float(sxa / np.sqrt(sxx * saa))
    rng = np.random.default_rng(seed)
    zx = rng.standard_normal(n) + np.sqrt(lam)
    za = rho * zx + np.sqrt(max(1 - rho * rho, 0.0)) * rng.standard_normal(n)
    lam0 = optimize.brentq(lambda x: stats.ncx2.sf(critical, 1, x) - POWER, 1e-6, 1e4)
    return {
        "noncentrality": lam,
        "corr_x_alt": rho,
        "power": float(stats.ncx2.sf(critical, 1, lam)),
        "mdb": float(np.sqrt(lam0 / sxx)),
        "true": float(true),
        "expected_correct": float(np.mean((zx * zx > critical) & (np.abs(zx) > np.abs(za)))),
    }


def run_term(args):
    term, draws, corr, n_targets, seed0 = args
    os.environ.setdefault("JAX_PLATFORMS", "cpu")
    import tlsjax as tj
    from tlsjax._inference import _score as score
    from tlsjax._model._aps import get_ap

    room = tj.Room(n_targets=n_targets)
    t0 = time.perf_counter()
    y, lam, r_xy = _alternative(tj, score, room, term, corr, seed0)
    out = {"term": term, "alternative_of": y, "lambda": lam, "corr_x_y": r_xy, "draws": []}
    if y is None:
        out["note"] = "no other term of its group to build an alternative from"
        return out
    bx, by = get_ap(term).basis, get_ap(y).basis
    tj.register_ap(
        "ALT",
        get_ap(term).group,
        lambda r, t, a, s: bx(r, t, a, s) + lam * by(r, t, a, s),
        get_ap(term).unit,
        f"{term} + {lam:.3g} {y}",
        overwrite=True,
    )
    start = tuple(a for a in PHYSICAL if a != term)
    model = tj.CalibrationModel(tj.Scanner(aps=start))
    # The selection as ``tlsjax calibrate --select`` runs it (robust start, screening, then
    # the selection on the screened observations), without VCE: a priori weights throughout.
    options = tj.CalibrationOptions(
        vce=None, selection=tj.SelectionOptions(candidates=(term, "ALT"))
    )
    kw = {"scale_bars": 2} if term == "A1" else {}
    for d in range(draws):
        t1 = time.perf_counter()
        s = tj.simulate(room, seed=seed0 + 1 + d, aps=start + (term,), **kw)
        result = tj.self_calibrate(s.network, model, options)
        sel = result.selection
        S = _design_schur(tj, score, room, term, [term, "ALT"], seed0 + 1 + d)
        expected = _expected(S, s.true_aps[term], sel.critical, seed0 + 1 + d)
        tried = {st.term: st for st in sel.steps if st.action in ("try", "add")}
        # The calibration's own cross-validation: what the user is told (NOT_IMPROVED).
        cv = result.cross_validation or sel.cross_validation
        tests = sel.score_tests
        out["draws"].append(
            {
                "seed": seed0 + 1 + d,
                "aps": list(sel.aps),
                "correct": term in sel.aps and "ALT" not in sel.aps,
                "statistic_x": getattr(tried.get(term), "statistic", None),
                "statistic_alt": getattr(tried.get("ALT"), "statistic", None),
                "cv_x_mm": getattr(tried.get(term), "cv_mm", None),
                "cv_alt_mm": getattr(tried.get("ALT"), "cv_mm", None),
                "cv_mm": None if cv is None else cv.rms_mm["xyz"],
                "cv_none_mm": None if cv is None else cv.rms_none_mm["xyz"],
                "cv_code": None if cv is None else int(cv.code),
                "worse_without_warning": bool(
                    cv is not None
                    and cv.ok
                    and cv.rms_mm["xyz"] > cv.rms_none_mm["xyz"]
                    and cv.code != tj.CrossValidationCode.NOT_IMPROVED
                ),
                "proposed_not_estimable": []
                if tests is None
                else [t.name for t in tests.significant if not t.testable],
                "end": sel.end,
                **expected,
                "seconds": time.perf_counter() - t1,
            }
        )
    ok = [d["correct"] for d in out["draws"]]
    out["share_correct"] = float(np.mean(ok)) if ok else None
    out["expected_share_correct"] = float(np.mean([d["expected_correct"] for d in out["draws"]]))
    detectable = [d["correct"] for d in out["draws"] if d["power"] >= POWER]
    out["detectable_draws"] = len(detectable)
    out["share_correct_detectable"] = float(np.mean(detectable)) if detectable else None
    out["seconds"] = time.perf_counter() - t0
    return json.loads(json.dumps(out, default=float))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--terms", nargs="*", default=None, help="default: every Chow/Lichti term")
    ap.add_argument("--draws", type=int, default=10)
    ap.add_argument("--corr", type=float, default=0.97)
    ap.add_argument("--targets", type=int, default=60)
    ap.add_argument("--seed", type=int, default=1000)
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument(
        "--out", default=os.path.join(os.path.dirname(__file__), "results", "identification.json")
    )
    args = ap.parse_args()
    if args.terms is None:
        from tlsjax._inference._score import _CHOW

        args.terms = list(_CHOW)
    work = [(t, args.draws, args.corr, args.targets, args.seed) for t in args.terms]
    t0 = time.perf_counter()
    load0 = loadavg()
    # Each term in a fresh process: every term registers its own ALT and compiles its programs,
    # and one process holding all of them ran out of memory (LLVM) on a shared machine.
    with ProcessPoolExecutor(args.jobs, max_tasks_per_child=1) as ex:
        results = list(ex.map(run_term, work))
    for r in results:
        print(
            f"{r['term']:4s} vs ALT ({r['term']} + {r.get('lambda', 0):.3g} {r.get('alternative_of')}): "
            f"{r.get('share_correct')} correct of {len(r['draws'])} (expected at the design's "
            f"power: {r.get('expected_share_correct', float('nan')):.2f}; "
            f"{r.get('detectable_draws')} draws with power >= {POWER:g}: "
            f"{r.get('share_correct_detectable')} correct)"
        )
    draws = [d for r in results for d in r["draws"]]
    summary = {
        "terms": len(results),
        "terms_at_least_90_percent": sum(
            1 for r in results if r.get("share_correct") is not None and r["share_correct"] >= 0.9
        ),
        "draws": len(draws),
        "share_correct": float(np.mean([d["correct"] for d in draws])) if draws else None,
        "expected_share_correct": float(np.mean([d["expected_correct"] for d in draws]))
        if draws
        else None,
        "detectable_draws": sum(d["power"] >= POWER for d in draws),
        "share_correct_detectable": float(
            np.mean([d["correct"] for d in draws if d["power"] >= POWER])
        )
        if any(d["power"] >= POWER for d in draws)
        else None,
        "worse_without_warning": sum(d["worse_without_warning"] for d in draws),
        "proposed_not_estimable": sum(bool(d["proposed_not_estimable"]) for d in draws),
    }
    print(json.dumps(summary))
    write_results(
        {
            "benchmark": "identification",
            "settings": vars(args),
            "loadavg_before": load0,
            "loadavg_after": loadavg(),
            "seconds": time.perf_counter() - t0,
            "summary": summary,
            "results": results,
        },
        args.out,
    )


if __name__ == "__main__":
    main()
