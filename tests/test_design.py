"""Network design (SPEC section 13): predicted covariance against calibrate, criterion gradient
against finite differences, plane designs, the optimiser beats its start (checked by an
independent calibrate), the CLI.

Private imports: ``tlsjax._cli.main`` is the ``tlsjax`` console script's entry point
(pyproject), called in process.
"""

import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from dispatch import executed_programs

import tlsjax as tj
from tlsjax._cli import main

ROOM = tj.Room(n_targets=16)


@pytest.fixture(scope="module")
def room():
    sim = tj.simulate(ROOM, tilted=True, aps="A0 B6 B7 C0", seed=1, noise=False)
    design = tj.TargetDesign.from_simulation(sim)
    return sim, design, tj.DesignProblem.targets(design, sim.scanner)


def test_predicted_covariance_equals_calibrate(room):
    sim, design, dn = room
    Q = np.asarray(jax.jit(lambda d: tj.predicted_cofactor(dn, d))(design))
    res = tj.calibrate(dn.network(design, seed=2), dn.model, tj.SolverOptions(full_covariance=True))
    assert res.ok
    r = Q.shape[0]
    Qc = np.asarray(res.covariance)[-r:, -r:] / res.sigma0**2
    # The prediction linearises at the truth, calibrate at its noisy estimate.
    np.testing.assert_allclose(np.sqrt(np.diag(Q)), np.sqrt(np.diag(Qc)), rtol=1e-3)
    for kind in ("max_sigma", "trace", "max_correlation"):
        c = tj.DesignCriterion(kind, with_poses=kind == "max_correlation")
        pred = tj.design_criterion(dn, design, c, smooth=False)
        assert pred == pytest.approx(tj.criterion_of_result(c, res), rel=2e-3)
    # A report's criterion is one compiled program, not hundreds of operations dispatched one
    # by one (each compiled on its first call).
    with executed_programs() as counts:
        again = tj.design_criterion(dn, design, c, smooth=False)
    assert counts == {"jit(value)": 1}, dict(counts)
    assert again == pred


def test_criterion_gradient_matches_finite_differences(room):
    sim, design, dn = room
    crit = tj.DesignCriterion("max_sigma", tolerances={"B6": 1e-5})
    f = jax.jit(lambda d: tj.design_criterion(dn, d, crit))
    g = jax.jit(jax.grad(lambda d: tj.design_criterion(dn, d, crit)))(design)
    rng = np.random.default_rng(0)
    zero = jax.tree.map(jnp.zeros_like, design)
    v = dataclasses.replace(
        zero,
        eops=jnp.asarray(rng.standard_normal(design.eops.shape)),
        targets=jnp.asarray(rng.standard_normal(design.targets.shape)),
        sigma_angle=jnp.asarray(1e-6),
    )
    an = sum(float(jnp.sum(a * b)) for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(v)))
    h = 1e-5
    fd = (
        f(jax.tree.map(lambda a, b: a + h * b, design, v))
        - f(jax.tree.map(lambda a, b: a - h * b, design, v))
    ) / (2 * h)
    assert an == pytest.approx(float(fd), rel=1e-6)


@pytest.mark.internal
def test_optimiser_beats_its_start_verified_by_calibrate(room):
    from tlsjax._design._criteria import criterion_of_result

    sim, design, dn = room
    levelled = tj.simulate(ROOM, tilted=False, aps="A0 B6 B7 C0", noise=False, seed=1)
    start = tj.TargetDesign.from_simulation(levelled)
    mask = np.array([True, True, True, True, False, False])
    dnl = tj.DesignProblem.targets(start, levelled.scanner, levelled=mask)
    crit = tj.DesignCriterion("max_sigma", aps="B6", tolerances={"B6": 4.848e-6})
    out = tj.optimize_design(
        dnl, crit, tj.DesignSpace(room=ROOM), starts=2, steps=25, progress=False, seed=1
    )
    assert out.value < out.start_value and out.history.shape == (25, 2)
    json.dumps(out.to_dict(), allow_nan=False)
    assert "criterion" in out.summary() and "kappa [deg]" in out.summary()
    # Independent calibrate of noisy networks of both designs.
    opts = tj.SolverOptions(full_covariance=True)
    before = tj.calibrate(dnl.network(start, seed=3), dnl.model, opts)
    after = tj.calibrate(dnl.network(out.design, seed=3), dnl.model, opts)
    assert after.ok
    assert criterion_of_result(crit, after) == pytest.approx(out.value, rel=1e-2)
    assert criterion_of_result(crit, after) < criterion_of_result(crit, before)
    # Bounds: stations inside the room minus the clearance, tilts within the limit.
    e = np.asarray(out.design.eops)
    assert np.all(e[:, 0] >= 0.5) and np.all(e[:, 0] <= ROOM.length - 0.5)
    assert np.all(np.abs(e[4:, 3:5]) <= 60 * np.pi / 180) and np.all(e[:4, 3:5] == 0)


def test_plane_design_derivative_matches_calibrate():
    """d estimate / d plane parameter and d / d station of a plane network (Gauss-Helmert,
    variances as functions of the solution), against calibrate of re-simulated networks."""
    pc = tj.simulate_point_clouds(tj.CloudDesign(angular_step=4 * np.pi / 180, noise=False), seed=0)
    dn = tj.DesignProblem.from_point_clouds(pc, max_points=12, seed=0)
    design = dn.design
    n = dn.scan_index.shape[0]
    z = jnp.asarray(np.random.default_rng(1).standard_normal((n, 3)))
    f = tj.differentiable_adjustment(dn.template)

    def estimate(d):
        e = f(dn.inputs(d, z), dn.truth(d))
        return jnp.concatenate([e.aps, e.ap_sigmas, e.sigma0[None]])

    def calibrated(d):
        th = dn.inputs(d, z)
        net = dataclasses.replace(
            dn.template.network,
            plane_observations=np.asarray(th.plane_observations),
            plane_sigmas=np.asarray(th.plane_sigmas),
            levelling=np.asarray(th.levelling),
        )
        r = tj.calibrate(net, dn.model)
        assert r.ok
        return np.concatenate([r.ap_values, r.ap_sigmas, [r.sigma0]])

    zero = jax.tree.map(jnp.zeros_like, design)
    jvp = jax.jit(lambda d, v: jax.jvp(estimate, (d,), (v,))[1])
    for v in (
        dataclasses.replace(zero, planes=zero.planes.at[1, 3].set(1.0)),  # a wall's distance
        dataclasses.replace(zero, eops=zero.eops.at[0, 1].set(1.0)),  # a station
    ):
        h = 1e-3
        fd = (
            calibrated(jax.tree.map(lambda a, b: a + h * b, design, v))
            - calibrated(jax.tree.map(lambda a, b: a - h * b, design, v))
        ) / (2 * h)
        an = np.asarray(jvp(design, v))
        np.testing.assert_allclose(an, fd, rtol=0, atol=2e-4 * np.abs(fd).max())


def test_design_cli(tmp_path, capsys):
    out = tmp_path / "design.json"
    code = main(
        [
            "design",
            "--targets",
            "16",
            "--criterion-aps",
            "B6",
            "--tolerance",
            "B6=1",
            "--starts",
            "2",
            "--steps",
            "5",
            "--no-progress",
            "--json",
            str(out),
        ]
    )
    assert code == 0
    text = capsys.readouterr().out
    assert "independent calibrate (optimised)" in text
    data = json.loads(out.read_text())
    assert data["verified_optimised"]["criterion"] == pytest.approx(data["value"], rel=1e-2)
    assert main(["design", "--targets", "16", "--tolerance", "Z9=1", "--steps", "1"]) == 2


def test_criterion_errors():
    with pytest.raises(ValueError, match="not one of"):
        tj.DesignCriterion("volume")
    with pytest.raises(ValueError, match="positive"):
        tj.DesignCriterion(tolerances={"B6": 0.0})
    with pytest.raises(ValueError, match="tilts"):
        tj.DesignSpace(tilts="some")


def test_visibility_smooth_and_hard(room):
    """Field of view and incidence limit: a smooth weight in (0, 1] for the optimiser that
    agrees with the hard cut of network() away from the edges."""
    sim, design, _ = room
    fov, inc = (-40 * np.pi / 180, 60 * np.pi / 180), 70 * np.pi / 180
    dn = tj.DesignProblem.targets(
        design, sim.scanner, fov=fov, max_incidence=inc, smooth_visibility=True
    )
    v = np.asarray(dn.visibility(design))
    hard = dn.hard_visibility(design)
    assert 0 < hard.sum() < hard.size
    assert np.all((v > 0) & (v <= 1))
    # Each limit is a sigmoid 1 deg wide: above 1/2 inside it, below 1/2 outside.
    assert np.all(v[hard] > 0.5**3) and np.median(v[hard]) > 0.99
    assert np.all(v[~hard] < 0.5)
    net = dn.network(design)
    assert net.observations.shape[0] <= hard.sum()
    # Hidden rows carry (almost) no information in the smooth inputs.
    th = dn.inputs(design)
    ratio = np.asarray(th.sigmas[:, 1]) / float(design.sigma_angle)
    assert np.all(ratio[~hard & (v < 1e-4)] > 100)
