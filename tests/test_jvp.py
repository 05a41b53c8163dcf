"""Forward-mode derivatives of the converged adjustment (SPEC section 12) against central finite
differences of the full forward computation: ``tj.calibrate`` re-run on a perturbed network
(new approximate values, new plan). Tolerance: 1e-4 of the largest component of each
derivative (the re-run converges to 1e-6 of a sigma; FD steps of 1e-3 sigma).

Private imports: the datum's null space and S-transformation, to compare tangents in one datum.
"""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import DELTA0

import tlsjax as tj
from tlsjax._adjustment._normal import null_space

pytestmark = pytest.mark.internal

ROOM = tj.Room(n_targets=16)
RTOL = 1e-4


@pytest.fixture(scope="module")
def setup():
    sim = tj.simulate(ROOM, tilted=True, aps="A0 B6 B7 C0", seed=1)
    model = tj.CalibrationModel(sim.scanner, datum="inner")
    adj = tj.analyze(sim.network, model)
    f = tj.differentiable_adjustment(adj)
    theta = tj.network_inputs(adj)
    jvp = jax.jit(lambda t, v: jax.jvp(f, (t,), (v,)))
    return sim, model, adj, f, theta, jvp


def _summary(aps, sig, s0, corr, red, mdb):
    return np.concatenate(
        [aps, sig, [s0], corr[np.triu_indices(4, 1)], red[:12].ravel(), mdb[:12].ravel()]
    )


def _calibrated(net, model):
    r = tj.calibrate(net, model)
    assert r.ok
    C = r.ap_covariance / np.outer(r.ap_sigmas, r.ap_sigmas)
    mdb = DELTA0 * net.sigmas / np.sqrt(r.redundancy)
    return r, _summary(r.ap_values, r.ap_sigmas, r.sigma0, C, r.redundancy, mdb)


def _assert_close(analytic, fd, rtol=RTOL):
    scale = np.max(np.abs(fd))
    assert scale > 0
    np.testing.assert_allclose(analytic, fd, rtol=0, atol=rtol * scale)


def _datum_free(adj, x, dx_prims, dx_eops):
    """S-transform a finite-difference tangent onto the inner constraints at x (the datum of a
    re-run is fixed by its own path)."""
    from tlsjax._model._datum import s_transform_vector

    spec = adj.plan.spec

    @eqx.filter_jit  # one program (eagerly, each operation compiles on its own: a minute)
    def transform(families, x, dx_prims, dx_eops):
        Hp, Hz = null_space(spec, families, x)
        dz = jnp.concatenate([dx_eops.reshape(-1), jnp.zeros(spec.n_aps)])
        return s_transform_vector(Hp, Hz, (dx_prims,), dz)

    dps, dz = transform(adj.plan.problem.families, x, jnp.asarray(dx_prims), jnp.asarray(dx_eops))
    return np.asarray(dps[0]), np.asarray(dz[: 6 * spec.n_scans]).reshape(-1, 6)


@pytest.mark.parametrize("kind", ["observations", "sigmas", "levelling"])
def test_jvp_matches_finite_differences_of_calibrate(setup, kind):
    sim, model, adj, f, theta, jvp = setup
    rng = np.random.default_rng({"observations": 0, "sigmas": 1, "levelling": 2}[kind])
    zero = jax.tree.map(jnp.zeros_like, theta)
    if kind == "observations":
        v = rng.standard_normal(theta.observations.shape) * np.asarray(theta.sigmas)
    elif kind == "sigmas":
        v = rng.uniform(-1, 1, theta.sigmas.shape) * np.asarray(theta.sigmas)
    else:
        v = rng.standard_normal(theta.levelling.shape) * 10 * np.pi / 180 / 3600
    v = dataclasses.replace(zero, **{kind: jnp.asarray(v)})
    est, d = jvp(theta, v)
    net = sim.network
    h = 1e-3
    runs = []
    for s in (1, -1):
        t = jax.tree.map(lambda a, b, s=s: np.asarray(a + s * h * b), theta, v)
        pert = dataclasses.replace(
            net, observations=t.observations, sigmas=t.sigmas, levelling=t.levelling
        )
        runs.append(_calibrated(pert, model))
    fd = (runs[0][1] - runs[1][1]) / (2 * h)
    an = _summary(d.aps, d.ap_sigmas, d.sigma0, np.asarray(d.ap_correlation), d.redundancy, d.mdb)
    _assert_close(an, fd)
    # Datum-dependent estimates (scan poses, targets) after S-transforming the FD tangent.
    x = est.params
    dX = (runs[0][0].target_xyz - runs[1][0].target_xyz) / (2 * h)
    dE = (runs[0][0].eops - runs[1][0].eops) / (2 * h)
    dX, dE = _datum_free(adj, x, dX, dE)
    _assert_close(np.asarray(d.params.eops), dE, 1e-3)
    _assert_close(np.asarray(d.params.prims[0]), dX, 1e-3)


def test_tangent_respects_the_datum_and_zero_direction(setup):
    """``G^T dx = 0`` (inner constraints), and a zero input tangent gives a zero tangent."""
    sim, model, adj, f, theta, jvp = setup
    v = dataclasses.replace(
        jax.tree.map(jnp.zeros_like, theta),
        observations=jnp.ones_like(theta.observations) * 1e-4,
    )
    est, d = jvp(theta, v)
    Hp, _ = null_space(adj.plan.spec, adj.plan.problem.families, est.params)
    Gtdx = np.einsum("npd,np->d", np.asarray(Hp[0]), np.asarray(d.params.prims[0]))
    scale = np.abs(np.asarray(Hp[0])).max() * np.abs(np.asarray(d.params.prims[0])).sum()
    assert np.all(np.abs(Gtdx) <= 1e-10 * scale)
    _, d0 = jvp(theta, jax.tree.map(jnp.zeros_like, theta))
    assert np.all(np.asarray(d0.aps) == 0) and float(d0.sigma0) == 0.0


def test_design_derivatives_match_calibrate(setup):
    """d estimates / d design (station position, tilt, target position, range noise) of a noisy
    simulated network with fixed noise draws, against calibrate of re-simulated networks."""
    sim = setup[0]
    design = tj.TargetDesign.from_simulation(sim)
    dn = tj.DesignProblem.targets(design, sim.scanner)
    rng = np.random.default_rng(5)
    n, s = dn.scan_index.shape[0], design.eops.shape[0]
    z, zl = jnp.asarray(rng.standard_normal((n, 3))), jnp.asarray(rng.standard_normal((s, 2)))
    f = tj.differentiable_adjustment(dn.template)

    def estimate(d):
        e = f(dn.inputs(d, z, zl), dn.truth(d))
        return jnp.concatenate([e.aps, e.ap_sigmas, e.sigma0[None]])

    zero = jax.tree.map(jnp.zeros_like, design)
    directions = {
        "station": dataclasses.replace(zero, eops=zero.eops.at[3:, 0].set(1.0)),
        "tilt": dataclasses.replace(zero, eops=zero.eops.at[4, 3].set(1.0)),
        "target": dataclasses.replace(zero, targets=zero.targets.at[2, 1].set(1.0)),
        "noise": dataclasses.replace(zero, sigma_range=jnp.asarray(1e-4)),
    }
    jvp = jax.jit(lambda d, v: jax.jvp(estimate, (d,), (v,))[1])

    def calibrated(d):
        net = _network_with_noise(dn, d, z, zl)
        r = tj.calibrate(net, dn.model)
        assert r.ok
        return np.concatenate([r.ap_values, r.ap_sigmas, [r.sigma0]])

    for name, v in directions.items():
        h = 1e-3 if name != "noise" else 1e-2  # noise: sigma_range +- 1e-6 m
        plus = calibrated(jax.tree.map(lambda a, b: a + h * b, design, v))
        minus = calibrated(jax.tree.map(lambda a, b: a - h * b, design, v))
        _assert_close(np.asarray(jvp(design, v)), (plus - minus) / (2 * h), 2e-4)


def _network_with_noise(dn, design, z, zl):
    """A network of ``design`` with the given standard-normal draws (the host path of
    DesignProblem.network, with the draws fixed across the perturbed designs)."""
    th = dn.inputs(design, z, zl)
    net = dn.template.network
    return dataclasses.replace(
        net,
        observations=np.asarray(th.observations),
        sigmas=np.asarray(th.sigmas),
        levelling=np.asarray(th.levelling),
    )
