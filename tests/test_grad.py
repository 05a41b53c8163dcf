"""Reverse-mode derivatives of the converged adjustment (SPEC section 12): grad agrees with the
forward mode and with finite differences of ``tj.calibrate``; ``vmap(grad)`` equals a loop of
``grad``; ``d AP / d l`` agrees with finite differences and with the quality pass's external
reliability.

Private import: the compiled function behind ``differentiable_adjustment``, to count its
compilations.
"""

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tlsjax as tj

ROOM = tj.Room(n_targets=16)


def scalar(est):
    # A mix of what a calibration scientist differentiates: an AP, an AP sigma, sigma0, a
    # correlation and a redundancy number.
    return (
        est.aps[1] / est.ap_sigmas[1] + est.sigma0 + est.ap_correlation[1, 2] + est.redundancy[3, 1]
    )


@pytest.fixture(scope="module")
def setup():
    sim = tj.simulate(ROOM, tilted=True, aps="A0 B6 B7 C0", seed=1)
    model = tj.CalibrationModel(sim.scanner, datum="inner")
    adj = tj.analyze(sim.network, model)
    f = tj.differentiable_adjustment(adj)
    theta = tj.network_inputs(adj)
    grad = jax.jit(jax.grad(lambda t: scalar(f(t))))
    return sim, model, adj, f, theta, grad


def test_grad_matches_calibrate_and_forward_mode(setup):
    sim, model, adj, f, theta, grad = setup
    g = grad(theta)
    rng = np.random.default_rng(3)
    v = dataclasses.replace(
        jax.tree.map(jnp.zeros_like, theta),
        observations=jnp.asarray(rng.standard_normal(theta.observations.shape)) * theta.sigmas,
        sigmas=jnp.asarray(rng.uniform(-0.5, 0.5, theta.sigmas.shape)) * theta.sigmas,
    )
    dot = sum(float(jnp.sum(a * b)) for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(v)))

    def calibrated(t):
        net = dataclasses.replace(
            sim.network, observations=np.asarray(t.observations), sigmas=np.asarray(t.sigmas)
        )
        r = tj.calibrate(net, model)
        c = r.ap_covariance[1, 2] / (r.ap_sigmas[1] * r.ap_sigmas[2])
        return r.ap_values[1] / r.ap_sigmas[1] + r.sigma0 + c + r.redundancy[3, 1]

    h = 1e-3
    fd = (
        calibrated(jax.tree.map(lambda a, b: a + h * b, theta, v))
        - calibrated(jax.tree.map(lambda a, b: a - h * b, theta, v))
    ) / (2 * h)
    assert abs(dot - fd) <= 1e-4 * abs(fd)
    _, fwd = jax.jvp(lambda t: scalar(f(t)), (theta,), (v,))
    assert abs(dot - float(fwd)) <= 1e-9 * abs(float(fwd))


def test_vmap_grad_equals_loop(setup):
    sim, model, adj, f, theta, grad = setup
    rng = np.random.default_rng(4)
    batch = [
        dataclasses.replace(
            theta,
            observations=theta.observations
            + jnp.asarray(rng.standard_normal(theta.observations.shape)) * theta.sigmas,
        )
        for _ in range(3)
    ]
    stacked = jax.tree.map(lambda *a: jnp.stack(a), *batch)
    vg = jax.jit(jax.vmap(jax.grad(lambda t: scalar(f(t)))))(stacked)
    for k, t in enumerate(batch):
        one = grad(t)
        for a, b in zip(jax.tree.leaves(vg), jax.tree.leaves(one)):
            # The batched and the single program sum in different orders: an entry far below
            # the gradient's largest ones differs by rounding of those (2e-10 at 0.2 beside
            # 500, seen), so the floor is relative to the leaf's scale; a batch member mixed
            # up with another differs by O(1).
            b = np.asarray(b)
            floor = 1e-11 * float(np.abs(b).max(initial=0.0))
            np.testing.assert_allclose(np.asarray(a[k]), b, rtol=1e-9, atol=max(floor, 1e-12))


def test_sensitivity_matches_calibrate_and_external_reliability(setup):
    sim, model, adj, f, theta, grad = setup
    s = tj.ap_sensitivity(adj)
    assert s.values.shape == (sim.network.observations.shape[0], 3, 4)
    # External reliability of the quality pass: the linear formula, equal up to the dependence
    # of the AP corrections on the observation itself (module docstring); 2 % of the largest.
    scale = np.abs(s.influence).max()
    np.testing.assert_allclose(s.values, s.influence, rtol=0, atol=0.02 * scale)
    assert np.abs(s.values[:, :2] - s.influence[:, :2]).max() <= 1e-3 * scale
    # One observation by finite differences of calibrate (the one where the two differ most).
    i, g, _ = np.unravel_index(np.argmax(np.abs(s.values - s.influence)), s.values.shape)
    res = tj.calibrate(sim.network, model)
    sa = res.ap_sigmas / res.sigma0
    h, out = 1e-2, []
    for sign in (1, -1):
        o = sim.network.observations.copy()
        o[i, g] += sign * h * sim.network.sigmas[i, g]
        out.append(tj.calibrate(dataclasses.replace(sim.network, observations=o), model).ap_values)
    fd = (out[0] - out[1]) / (2 * h) / sa
    np.testing.assert_allclose(s.values[i, g], fd, rtol=0, atol=1e-4 * np.abs(fd).max())
    assert "d AP / d l" in s.summary(5) and set(s.largest()) == set(s.ap_names)


@pytest.mark.internal
def test_no_recompilation_for_new_values(setup):
    """Other observation values, sigmas or a new wrapper of the same adjustment reuse the
    compiled function (the spec and shapes are the only static parts)."""
    from tlsjax._adjustment._implicit import _estimates

    sim, model, adj, f, theta, grad = setup
    f(theta)
    n = _estimates._cache_size()
    other = dataclasses.replace(theta, sigmas=theta.sigmas * 1.5)
    tj.differentiable_adjustment(adj)(other)
    f(dataclasses.replace(theta, observations=theta.observations + 1e-4))
    assert _estimates._cache_size() == n
