"""Monte Carlo runs the engine of calibrate: any design calibrate accepts (SPEC section 9).

Each realisation of :func:`tlsjax.monte_carlo` (the chord method on the design's factorisation)
must equal :func:`tlsjax.calibrate` of the same observations (:func:`tlsjax.monte_carlo_network`)
to 1e-9 sigma, with the design's covariance scaled by its own s0^2: a target design with partial
visibility, control points, a scale bar and two instruments; a plane design; and a combined
one. The reference is the public calibrate started from its own approximate values, so the
check covers the simulation (error-free observations of the truth, the fixed point with the
true APs, noise on levelling, control and bar lengths) and the batched engine at once.

Private imports: ``ap_corrections`` and the arc-second factor build the reference observations;
``distorted_observations``, the fixed point the draws run to, is checked against its definition.
"""

import numpy as np
import pytest

import tlsjax as tj
from tlsjax import MonteCarloOptions, SimulationTruth, monte_carlo, monte_carlo_network
from tlsjax._units import ARCSEC

pytestmark = pytest.mark.internal

DEG = np.pi / 180
RUNS = 3
APS = "A0 B6 B7 C0"


def _partial_target_truth():
    """24 targets; each scan misses a different quarter of them; 3 control points; 1 scale
    bar; scans S1-S3 from instrument "a", S4-S6 from "b" (same true scanner)."""
    sim = tj.simulate(tj.Room(n_targets=24), seed=11, aps=APS, scale_bars=1)
    net = sim.network
    rng = np.random.default_rng(0)
    keep = rng.random(len(net.target_index)) > 0.25
    bar_targets = set(net.scale_bar_targets.reshape(-1).tolist())
    keep |= np.isin(net.target_index, list(bar_targets))
    names = [net.targets[t] for t in net.target_index[keep]]
    scans = [net.scans[j] for j in net.scan_index[keep]]
    X = {f"T{t + 1:03d}": sim.true_targets[t] for t in range(len(sim.true_targets))}
    control = {t: (X[t], 2e-3) for t in ("T002", "T009", "T017")}
    bars = [
        (net.targets[a], net.targets[b], L, s)
        for (a, b), L, s in zip(net.scale_bar_targets, net.scale_bar_length, net.scale_bar_sigma)
    ]
    lev = {
        s: {"omega": 0.0, "phi": 0.0, "sigma_omega": 10 * ARCSEC, "sigma_phi": 10 * ARCSEC}
        for j, s in enumerate(net.scans)
        if np.isfinite(net.levelling_sigma[j]).all()
    }
    design = tj.make_network(
        scans,
        names,
        net.observations[keep],
        sigmas=net.sigmas[keep],
        instruments=["a" if s in ("S1", "S2", "S3") else "b" for s in scans],
        levelling=lev,
        control=control,
        scale_bars=bars,
    )
    assert len(design.observations) < len(net.observations)
    return SimulationTruth(
        design,
        (sim.scanner, sim.scanner),
        (sim.true_aps, sim.true_aps),
        sim.true_eops[[int(s[1:]) - 1 for s in design.scans]],
        np.array([X[t] for t in design.targets]),
    )


def _clouds():
    design = tj.CloudDesign(aps=APS, angular_step=4 * DEG, tilted=True)
    return tj.simulate_point_clouds(design, seed=4)


def _check(truth, model, seed=5):
    mc = monte_carlo(
        truth, model, MonteCarloOptions(runs=RUNS, chunk_size=RUNS, seed=seed, progress=False)
    )
    assert np.all(mc.result == 0), mc.failures()
    for k in range(RUNS):
        net, _ = monte_carlo_network(truth, k, seed=seed)
        ref = tj.calibrate(net, model, tj.SolverOptions(tolerance=1e-10))
        assert ref.result == 0, ref.message
        assert mc.ap_names == ref.ap_names
        # Each AP to 1e-9 of its own sigma.
        dev = np.abs(mc.ap_values[k] - ref.ap_values) / ref.ap_sigmas
        assert dev.max() < 1e-9, dev
        assert mc.sigma0_sq[k] == pytest.approx(ref.sigma0**2, rel=1e-8)
        assert mc.dof == ref.dof
        # The covariance is the design's (the normal matrix at the truth), scaled by the
        # realisation's s0^2: its own differs by about the noise-to-signal ratio.
        np.testing.assert_allclose(mc.ap_sigmas[k], ref.ap_sigmas, rtol=2e-3)
    design_sigmas = mc.ap_sigmas / np.sqrt(mc.sigma0_sq)[:, None]
    np.testing.assert_allclose(design_sigmas, design_sigmas[:1].repeat(RUNS, 0), rtol=1e-12)
    return mc


def test_partial_visibility_control_points_scale_bar_two_instruments():
    truth = _partial_target_truth()
    sc = truth.scanners[0]
    model = tj.CalibrationModel({"a": sc, "b": sc})  # datum "auto": the control points
    mc = _check(truth, model)
    assert mc.ap_names == tuple(f"{a}[{i}]" for i in "ab" for a in sc.aps)
    # The truth of each estimated AP is the simulated one, per instrument.
    np.testing.assert_array_equal(mc.true_aps[0], [truth.true_aps[0][a] for a in sc.aps] * 2)


def test_plane_design():
    truth = _clouds().truth(max_points=12, seed=0)
    assert truth.network.has_planes and not truth.network.has_targets
    _check(truth, tj.CalibrationModel(tj.Scanner(aps=APS)))


def test_combined_design():
    targets = tj.simulate(tj.Room(n_targets=24), seed=3, aps=APS).truth()
    truth = targets.combine(_clouds().truth(max_points=8, seed=1))
    assert truth.network.has_planes and truth.network.has_targets
    _check(truth, tj.CalibrationModel(tj.Scanner(aps=APS)))


def test_error_free_observations_reproduce_the_design():
    # Without noise the design's own observations are the fixed point of F + Delta(l).
    sim = tj.simulate(tj.Room(n_targets=24), seed=2, aps=APS, noise=False)
    F, _ = sim.truth().error_free()
    from tlsjax._model._aps import ap_corrections

    sc = sim.scanner
    l = sim.network.observations
    coeffs = np.array([sim.true_aps[a] for a in sc.aps])
    d = np.asarray(ap_corrections(coeffs, sc.aps, l, sc))
    res = F + d - l
    res[:, 1:] = (res[:, 1:] + np.pi) % (2 * np.pi) - np.pi
    assert np.abs(res).max() < 1e-9


def test_draws_stop_where_settled_at_the_fixed_point():
    """The Monte Carlo's draws stop once an iteration moves no observation by more than its
    rounding. Sources: the fixed point's definition ``l = base + Delta(l)`` (its residual at
    rounding) and the fixed-count loop run to a bound far beyond convergence; a contraction of
    0.5 (slow) must still reach it, and the cap must hold."""
    import jax.numpy as jnp

    from tlsjax._model._points import distorted_observations

    rng = np.random.default_rng(0)
    base = np.column_stack(
        [rng.uniform(1, 30, 500), rng.uniform(0, 6.2, 500), rng.uniform(-1.2, 1.2, 500)]
    )
    for q in (1e-3, 0.1, 0.5):
        # Amplitude 10 mm / 0.01 rad; the range's slope (the contraction) q.
        corr = lambda l, q=q: 1e-2 * jnp.sin(l * jnp.array([q / 1e-2, 1.0, 1.0]))
        settled = np.asarray(distorted_observations(base, corr, 200, until_settled=True))
        fixed = np.asarray(distorted_observations(base, corr, 200))
        scale = np.maximum(np.abs(fixed), 1.0)
        assert np.abs(settled - fixed).max() <= 4 * np.finfo(float).eps * scale.max()
        resid = settled - base - np.asarray(corr(jnp.asarray(settled)))
        resid[:, 1] = (resid[:, 1] + np.pi) % (2 * np.pi) - np.pi
        assert np.abs(resid).max() <= 8 * np.finfo(float).eps * scale.max()
    # The cap: two iterations of a slow contraction are not the fixed point.
    capped = np.asarray(distorted_observations(base, corr, 2, until_settled=True))
    assert np.abs(capped - fixed).max() > 1e-6
