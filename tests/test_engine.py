"""The engine's specialisations equal its general path, and there is one engine.

* The point family's Jacobians by the chain rule through a per-scan rotation (and on the grid,
  with the scan as an axis) equal ``jacfwd`` of the whole point model; so do the plane
  family's (one instrument or two, away from the approximate values).
* The grid layout of a family's sums (reshapes) gives the same adjustment as segment sums.
* One engine behind calibrate, the analysed adjustment and self_calibrate, and one
  cofactor function behind the quality of an adjustment and the design's prediction.
* The suite compiles without XLA's backend optimisations (tests/conftest.py); a calibration
  compiled at XLA's default level, what a user runs, agrees with it to rounding.

Private modules are imported for properties of private algorithms (the structured Jacobians,
the grid layout, the cofactor function), compared with their general paths.
"""

import dataclasses
import json
import os
import subprocess
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tlsjax as tj
from tlsjax import Adjustment, _jit
from tlsjax._adjustment import _families as F
from tlsjax._adjustment._calibrate import _replace
from tlsjax._adjustment._quality import pose_ap_cofactor
from tlsjax._model._planes import condition_variance, projection_step

pytestmark = pytest.mark.internal


def _compiled(method, spec, fi, **kwargs):
    """``method(fam, spec, problem, params, fi, **kwargs)`` as one compiled program of (fam,
    problem, params): run eagerly, the family code dispatches and compiles hundreds of small
    operations one by one (minutes of the suite), with the same arithmetic."""
    return eqx.filter_jit(
        lambda fam, problem, params, kw: method(fam, spec, problem, params, fi, **kw)
    )


EPS = np.finfo(np.float64).eps


def _whitened_scale(net):
    """The largest |observation| / sigma of a network's target rows."""
    return float(np.abs(np.asarray(net.observations) / np.asarray(net.sigmas)).max())


@pytest.mark.parametrize("architecture", ["hybrid", "panoramic"])
def test_structured_point_jacobian_equals_autodiff_of_the_model(architecture):
    sim = tj.simulate(tj.Room(n_targets=24), seed=0, architecture=architecture, scale_bars=2)
    adj = Adjustment(sim.network, tj.CalibrationModel(tj.Scanner(architecture=architecture)))
    spec, params = adj.plan.spec, adj.initial
    for problem in (adj.plan.problem, F.on_grid(adj.plan.problem)):
        for fi, fam in enumerate(problem.families):
            structured = _compiled(type(fam).linear_rows, spec, fi)
            e, Jp, Js, Ja, raw = structured(fam, problem, params, {})
            # The generic family method: vmap(jacfwd) of the whole residual.
            generic = _compiled(F.Family.linear_rows, spec, fi)
            e2, Jp2, Js2, Ja2, _ = generic(fam, problem, params, {})
            # Whitened misclosures are differences of terms of size |l| / sigma (up to 1e5):
            # two evaluation orders differ by ulps of that, not of the misclosure.
            np.testing.assert_allclose(e, e2, rtol=0, atol=64 * EPS * _whitened_scale(sim.network))
            for a, b in ((Jp, Jp2), (Js, Js2), (Ja, Ja2)):
                np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * float(jnp.abs(b).max()))


@pytest.mark.parametrize("two_instruments", [False, True])
def test_structured_plane_jacobian_equals_autodiff_of_the_model(two_instruments):
    clouds = tj.simulate_point_clouds(
        tj.CloudDesign(angular_step=4 * np.pi / 180, tilted=True), seed=1
    )
    net = clouds.to_network(max_points=20)
    scanner = tj.Scanner(aps="A0 B6 B7 C0 A2 B2 C2", architecture="hybrid")
    model = tj.CalibrationModel(scanner)
    if two_instruments:
        split = np.arange(len(net.scans)) % 2
        net = dataclasses.replace(net, instruments=("a", "b"), instrument_of_scan=split)
        other = tj.Scanner(aps="A0 B6 C0", architecture="hybrid")
        model = tj.CalibrationModel({"a": scanner, "b": other})
    adj = Adjustment(net, model)
    spec, params = adj.plan.spec, adj.initial
    # Away from the approximate values, with APs that bend the observations.
    rng = np.random.default_rng(0)
    params = F.Params(
        tuple(P * (1 + 1e-3 * rng.normal(size=P.shape)) for P in params.prims),
        params.eops + 1e-3 * rng.normal(size=params.eops.shape),
        params.aps + 1e-3 * rng.normal(size=params.aps.shape),
    )
    for problem in (adj.plan.problem, F.on_grid(adj.plan.problem)):
        for fi, fam in enumerate(problem.families):
            assert isinstance(fam, F.PlaneFamily)
            # Linearised at l + v (the Gauss-Helmert residuals of a previous step).
            sig = jnp.where(fam.weight > 0, 1 / jnp.where(fam.weight > 0, fam.weight, 1.0), 0.0)
            v = jnp.asarray(rng.normal(size=fam.obs.shape)) * sig
            got = _compiled(type(fam).linear_rows, spec, fi)(fam, problem, params, {"state": v})
            want = _compiled(F.Family.linear_rows, spec, fi)(fam, problem, params, {"state": v})
            for a, b in zip(got[:4], want[:4]):
                assert a.shape == b.shape
                np.testing.assert_allclose(a, b, rtol=0, atol=1e-11 * float(jnp.abs(b).max()))
            # B = dg/dl at l + v against the model's condition_variance (jax.grad per point),
            # and the step's cost against the model's whitened condition.
            args = eqx.filter_jit(lambda f, pr, pa, v: f.observation_args(pr, pa, fi, v))(
                fam, problem, params, v
            )
            sl = (spec.scanners, spec.ap_names, spec.ap_slices)
            _, B = jax.jit(
                jax.vmap(
                    lambda P, E, lv, s, i: condition_variance(
                        P, E, params.aps, lv[0] + lv[1], s, *sl, i
                    )
                )
            )(args[0], args[1], args[3], sig, args[6])
            np.testing.assert_allclose(got[5], B, rtol=0, atol=1e-11 * float(jnp.abs(B).max()))
            cost, v1, _ = _compiled(type(fam).cost_state, spec, fi)(
                fam, problem, params, {"state": v}
            )
            np.testing.assert_allclose(
                cost, want[0], rtol=0, atol=1e-11 * float(jnp.abs(cost).max())
            )
            # The next residuals: one Gauss-Helmert update at fixed unknowns.
            v_model = jax.jit(
                jax.vmap(
                    lambda P, E, lv, w, i: projection_step(
                        P, E, params.aps, lv[0], lv[1], w, *sl, i
                    )
                )
            )(args[0], args[1], args[3], fam.weight, args[6])
            np.testing.assert_allclose(v1, v_model, rtol=0, atol=1e-11 * float(jnp.abs(v1).max()))


def _without_layouts(adj):
    problem = adj.plan.problem
    return _replace(problem, layouts=(None,) * len(problem.families))


def test_grid_layout_equals_segment_sums():
    sim = tj.simulate(tj.Room(n_targets=24), seed=5, scale_bars=1)
    model = tj.CalibrationModel(tj.Scanner(aps="A0 B6 B7 C0"))
    adj = Adjustment(sim.network, model)
    assert all(lay is not None for lay in adj.plan.problem.layouts)
    s1, q1 = adj.run()
    s2, q2 = adj.run(_without_layouts(adj))
    assert int(s1.iteration) == int(s2.iteration)
    np.testing.assert_allclose(s1.params.aps, s2.params.aps, rtol=1e-10)
    np.testing.assert_allclose(q1.Qzz, q2.Qzz, rtol=1e-8, atol=1e-14)
    for a, b in zip(q1.residuals + q1.redundancy, q2.residuals + q2.redundancy):
        np.testing.assert_allclose(a, b, rtol=1e-8, atol=1e-12)


def test_grid_layout_is_chosen_from_the_structure():
    # Planes with few points per (plane, scan): a mostly full grid. Targets: every target in
    # every scan is a full grid; each seen in 2 of 6 scans fills a third of it (segment sums).
    clouds = tj.simulate_point_clouds(tj.CloudDesign(angular_step=4 * np.pi / 180), seed=1)
    adj = Adjustment(clouds.to_network(max_points=10), tj.CalibrationModel())
    assert adj.plan.problem.layouts[0] is not None
    sim = tj.simulate(tj.Room(n_targets=24), seed=5)
    fam = Adjustment(sim.network, tj.CalibrationModel()).plan.problem.families[0]
    lay = F.grid_layout(fam, 6)
    assert lay.shape == (24, 6, 1) and bool(jnp.all(lay.valid))
    # Slot (target i, scan s) holds the row of target i in scan s.
    np.testing.assert_array_equal(
        np.asarray(fam.prim)[np.asarray(lay.rows)], np.repeat(np.arange(24), 6)
    )
    np.testing.assert_array_equal(
        np.asarray(fam.scan)[np.asarray(lay.rows)], np.tile(np.arange(6), 24)
    )
    np.testing.assert_array_equal(np.asarray(lay.rows)[np.asarray(lay.pos)], np.arange(144))
    prim, scan = np.asarray(fam.prim), np.asarray(fam.scan)
    for keep, grid in (((prim + scan) % 3 != 0, True), ((prim + scan) % 3 == 0, False)):
        sub = _replace(fam, prim=jnp.asarray(prim[keep]), scan=jnp.asarray(scan[keep]))
        assert (F.grid_layout(sub, 6) is not None) == grid


def test_one_engine_behind_every_entry_point():
    """calibrate, the analysed adjustment re-solved with the network's own weights, and
    self_calibrate with nothing to test give the same estimates, sigmas and redundancy: one
    compiled adjustment behind them. (Monte Carlo against calibrate of the same realisation is
    tests/test_montecarlo*.py; the design's predicted covariance against calibrate is
    tests/test_design.py.) The quality path and the design path are one function: the
    cofactor predicted at the converged estimates equals the calibration's covariance over
    sigma0^2."""
    sim = tj.simulate(tj.Room(n_targets=24), seed=5, scale_bars=1)
    net = sim.network
    model = tj.CalibrationModel(tj.Scanner(aps="A0 B6 B7 C0"))
    res = tj.calibrate(net, model, tj.SolverOptions(full_covariance=True))
    again = tj.analyze(net, model, tj.SolverOptions(full_covariance=True)).solve(
        weights=1.0 / net.sigmas
    )
    nothing = tj.CalibrationOptions(cross_validation=None, vce=None, screening=None)
    tested = tj.self_calibrate(net, model, nothing).calibration
    for other in (again, tested):
        np.testing.assert_allclose(other.ap_values, res.ap_values, rtol=1e-10, atol=1e-15)
        np.testing.assert_allclose(other.ap_sigmas, res.ap_sigmas, rtol=1e-8)
        np.testing.assert_allclose(other.redundancy, res.redundancy, rtol=1e-8, atol=1e-12)
        assert other.dof == res.dof
    adj = Adjustment(net, model)
    state, _ = adj.run()
    spec = adj.plan.spec
    cofactor = eqx.filter_jit(lambda problem, params: pose_ap_cofactor(spec, problem, params, -1.0))
    Q = cofactor(adj.plan.problem, state.params)
    r = 6 * len(res.scans) + len(res.ap_names)
    want = np.asarray(res.covariance)[-r:, -r:] / res.sigma0**2
    np.testing.assert_allclose(np.asarray(Q), want, rtol=1e-6, atol=1e-12 * np.abs(want).max())


_AT_DEFAULT_LEVEL = """
import json, sys
import tlsjax as tj
sim = tj.simulate(tj.Room(n_targets=20), seed=11, aps="A0 B6 B7 C0 C3", tilted=True)
res = tj.calibrate(sim.network, tj.CalibrationModel(tj.Scanner(aps="A0 B6 B7 C0 C3")))
json.dump({"ok": bool(res.ok), "iterations": int(res.iterations),
           "aps": res.ap_values.tolist(), "sigmas": res.ap_sigmas.tolist()}, sys.stdout)
"""


def test_calibration_at_xla_default_level_agrees_with_the_suite():
    """The suite's programs are compiled at XLA backend optimisation level 0; a user's at the
    default level. Both must converge to the same estimates and sigmas (to rounding): a
    solver whose result depends on the compiler's summation order or contractions is fragile
    on ill-conditioned normal equations."""
    assert "--xla_backend_optimization_level=0" in os.environ.get("XLA_FLAGS", "")
    flags = " ".join(
        f
        for f in os.environ["XLA_FLAGS"].split()
        if not any(name in f for name in _jit.QUICK_COMPILE_FLAGS)
    )
    env = dict(os.environ, XLA_FLAGS=flags, JAX_PLATFORMS="cpu")
    proc = subprocess.run(
        [sys.executable, "-c", _AT_DEFAULT_LEVEL], env=env, capture_output=True, text=True
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    user = json.loads(proc.stdout)
    sim = tj.simulate(tj.Room(n_targets=20), seed=11, aps="A0 B6 B7 C0 C3", tilted=True)
    res = tj.calibrate(sim.network, tj.CalibrationModel(tj.Scanner(aps="A0 B6 B7 C0 C3")))
    assert user["ok"] and res.ok
    np.testing.assert_allclose(user["aps"], res.ap_values, rtol=1e-8, atol=1e-14)
    np.testing.assert_allclose(user["sigmas"], res.ap_sigmas, rtol=1e-8)
