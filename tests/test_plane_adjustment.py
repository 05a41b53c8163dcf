"""The structured Gauss-Helmert plane adjustment against a dense bordered solve (SPEC 4, 6, 7).

The plane family of the solver (one whitened condition per point linearised at l + v, planes
eliminated by Schur complement with the unit normal as a hard constraint, inner constraints on
the planes) is compared with the dense rigorous Gauss-Helmert adjustment of
``helpers.dense_gauss_helmert`` (conditions written out by hand, full A and B, the unit-normal
constraints and the datum as hard constraints in a bordered system).

Private imports: the plane family, the solver and the quality pass are compared with the dense
oracle directly.
"""

import types

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import dense_gauss_helmert

import tlsjax as tj
from tlsjax._adjustment._families import Params, PlaneFamily, Problem, Spec
from tlsjax._adjustment._quality import quality
from tlsjax._adjustment._solver import adjust

pytestmark = pytest.mark.internal

DEG = np.pi / 180
APS = ("A0", "B6", "B7", "C0")


def _network():
    design = tj.CloudDesign(architecture="hybrid", tilted=True, aps=APS, angular_step=3 * DEG)
    pc = tj.simulate_point_clouds(design, seed=4)
    rng = np.random.default_rng(0)
    obs, plane, scan, inc = [], [], [], []
    for j in range(len(pc.scans)):
        for k in range(len(pc.planes)):
            idx = np.flatnonzero(pc.plane_ids[j] == k)
            if len(idx) < 8:
                continue
            take = rng.choice(idx, size=min(12, len(idx)), replace=False)
            obs.append(pc.observations[j][take])
            inc.append(pc.incidence[j][take])
            plane += [k] * len(take)
            scan += [j] * len(take)
    obs, inc = np.concatenate(obs), np.concatenate(inc)
    plane, scan = np.array(plane), np.array(scan)
    sig = np.stack(
        [
            pc.sigma_range / np.cos(inc),
            np.full(len(inc), pc.sigma_angle),
            np.full(len(inc), pc.sigma_angle),
        ],
        1,
    )
    return pc, obs, sig, plane, scan


@pytest.fixture(scope="module")
def network():
    return _network()


def _structured(pc, obs, sig, plane, scan, x0_planes, x0_eops):
    n_pl, n_s = len(pc.planes), len(pc.eops)
    pairs, pair = np.unique(np.stack([plane, scan], 1), axis=0, return_inverse=True)
    fam = PlaneFamily(
        obs=jnp.asarray(obs),
        weight=jnp.asarray(1 / sig),
        prim=jnp.asarray(plane),
        point=jnp.zeros(len(obs), int),
        scan=jnp.asarray(scan),
        pair=jnp.asarray(pair.reshape(-1)),
        pair_prim=jnp.asarray(pairs[:, 0]),
        pair_scan=jnp.asarray(pairs[:, 1]),
        n_planes=n_pl,
    )
    problem = Problem(
        (fam,),
        jnp.zeros(n_s, int),
        jnp.zeros((n_s, 2)),
        jnp.zeros((n_s, 2)),
        jnp.zeros(6 * n_s + 4, bool),
    )
    spec = Spec((pc.scanner,), (APS,), ((0, 4),), n_s, tuple(range(6)), True)
    p0 = Params((jnp.asarray(x0_planes),), jnp.asarray(x0_eops), jnp.zeros(4))
    # One compiled program each (run eagerly, the engine's code compiles op by op: minutes).
    opts = tj.SolverOptions(tolerance=1e-8).arrays()
    state = eqx.filter_jit(lambda pr, p, o: adjust(spec, pr, p, o))(problem, p0, opts)
    q = eqx.filter_jit(lambda pr, p, tol: quality(spec, pr, p, tol, full_covariance=False))(
        problem, state.params, jnp.asarray(1e-6)
    )
    return state, q


def _dense(obs, sig, plane, scan, x0, n_pl, n_s):
    """The rigorous dense Gauss-Helmert adjustment of ``helpers.dense_gauss_helmert``: (x, Q,
    redundancy numbers, residuals, v^T P v, dof)."""
    net = types.SimpleNamespace(
        planes=tuple(range(n_pl)),
        scans=tuple(range(n_s)),
        plane_index=plane,
        plane_scan_index=scan,
        plane_observations=obs,
        plane_sigmas=sig,
        levelling=np.zeros((n_s, 2)),
        levelling_sigma=np.full((n_s, 2), np.inf),
    )
    ref = dense_gauss_helmert(net, APS, x0)
    m = len(obs)
    return (
        ref["x"],
        ref["Q"],
        ref["r"].reshape(m, 3),
        ref["v"].reshape(m, 3),
        ref["vtpv"],
        ref["dof"],
    )


def test_plane_adjustment_equals_dense_gauss_helmert(network):
    pc, obs, sig, plane, scan = network
    n_pl, n_s = len(pc.planes), len(pc.eops)
    rng = np.random.default_rng(1)
    P0 = pc.planes + rng.normal(scale=[1e-3, 1e-3, 1e-3, 5e-3], size=pc.planes.shape)
    P0[:, :3] /= np.linalg.norm(P0[:, :3], axis=1, keepdims=True)
    E0 = pc.eops + rng.normal(scale=[5e-3] * 3 + [5e-4] * 3, size=pc.eops.shape)
    state, q = _structured(pc, obs, sig, plane, scan, P0, E0)
    assert bool(state.converged)
    x0 = np.concatenate(
        [
            np.asarray(state.params.prims[0]).reshape(-1) * (1 + 1e-7),
            np.asarray(state.params.eops).reshape(-1) + 1e-5,
            np.zeros(4),
        ]
    )
    x, Q, redund, v, vtpv, dof = _dense(obs, sig, plane, scan, x0, n_pl, n_s)
    a = 4 * n_pl + 6 * n_s
    assert float(q.dof) == dof
    assert np.isclose(float(q.vtpv), vtpv, rtol=1e-9)
    np.testing.assert_allclose(np.asarray(state.params.aps), x[a:], rtol=1e-7, atol=1e-12)
    # AP cofactors are datum invariant: the reduced system's AP block equals the dense one.
    np.testing.assert_allclose(np.diag(np.asarray(q.Qzz))[6 * n_s :], np.diag(Q)[a:], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(q.redundancy[0]), redund, atol=1e-8)
    np.testing.assert_allclose(np.asarray(q.residuals[0]), v, rtol=1e-6, atol=1e-10)
    # Redundancy numbers of a point sum to at most 1, and all of them to the dof.
    assert np.all(np.asarray(q.redundancy[0]).sum(axis=1) <= 1 + 1e-9)
    total = float(np.asarray(q.redundancy[0]).sum())
    assert np.isclose(total, dof, rtol=1e-9)
    # Noise-level estimate of the APs: within a few sigma of the simulated truth.
    s0 = np.sqrt(vtpv / dof)
    z = (x[a:] - np.array([pc.true_aps[n] for n in APS])) / (s0 * np.sqrt(np.diag(Q)[a:]))
    assert np.all(np.abs(z) < 5), z


def test_calibrate_of_a_plane_network_equals_dense_gauss_helmert(network):
    """The public path (make_plane_network, approximate values, calibrate) against the oracle:
    AP estimates and a posteriori sigmas, per-observation redundancy numbers and residuals."""
    from tlsjax import ObservationTable

    pc, obs, sig, plane, scan = network
    n_pl, n_s = len(pc.planes), len(pc.eops)
    table = ObservationTable(
        kind="plane",
        source="<test>",
        scans=tuple(pc.scans[j] for j in scan),
        primitives=tuple(pc.plane_names[k] for k in plane),
        observations=obs,
        sigmas=sig,
        incidence=None,
        instruments=None,
        rows=np.arange(len(obs)),
    )
    net = tj.make_plane_network(table)
    res = tj.calibrate(
        net, tj.CalibrationModel(scanner=pc.scanner), tj.SolverOptions(tolerance=1e-8)
    )
    assert res.ok and res.converged, res.message
    # The oracle starts at calibrate's solution, mapped back to the oracle's plane order.
    order = [net.planes.index(name) for name in pc.plane_names]
    scan_order = [net.scans.index(s) for s in pc.scans]
    x0 = np.concatenate(
        [
            res.plane_params[order].reshape(-1) * (1 + 1e-7),
            res.eops[scan_order].reshape(-1) + 1e-5,
            np.zeros(4),
        ]
    )
    x, Q, redund, v, vtpv, dof = _dense(obs, sig, plane, scan, x0, n_pl, n_s)
    a = 4 * n_pl + 6 * n_s
    assert res.dof == dof
    np.testing.assert_allclose(res.sigma0, np.sqrt(vtpv / dof), rtol=1e-8)
    np.testing.assert_allclose(res.ap_values, x[a:], rtol=1e-7, atol=1e-12)
    np.testing.assert_allclose(res.ap_sigmas, np.sqrt(vtpv / dof * np.diag(Q)[a:]), rtol=1e-6)
    np.testing.assert_allclose(res.plane_redundancy, redund, atol=1e-8)
    np.testing.assert_allclose(res.plane_residuals, v, rtol=1e-6, atol=1e-10)
    # Plane sigmas: the oracle's bordered inverse is the inner-constraint cofactor matrix (the
    # hard constraint leaves no variance along the normal: 0 for a normal on an axis).
    s_pl = np.sqrt(np.clip(vtpv / dof * np.diag(Q)[: 4 * n_pl], 0, None)).reshape(n_pl, 4)
    np.testing.assert_allclose(res.plane_sigmas[order], s_pl, rtol=1e-6, atol=1e-12)
    _check_plane_precision(res, order, x, vtpv / dof * Q, pc.plane_names)
    # Three observations per point: n counts them, the dof counts one condition per point and
    # one unit-normal constraint per plane; four unknowns per plane.
    assert res.n_observations == 3 * len(obs)
    assert res.n_conditions == len(obs) and res.n_constraints == n_pl
    assert res.n_unknowns == 4 * n_pl + 6 * n_s + len(APS)


def _check_plane_precision(res, order, x, C, names):
    """The planes' 4 x 4 covariance blocks and the precision measures of the result JSON
    (issue 31) against the dense oracle's covariance ``C`` by other routes: the tilt sigmas as
    the two nonzero eigenvalues of the normal block under the projector ``I - n n^T``, the foot
    point's ellipsoid through the autodiff Jacobian of ``(n / |n|) d``."""
    k_pl = len(names)
    B = np.stack([C[4 * k : 4 * k + 4, 4 * k : 4 * k + 4] for k in range(k_pl)])
    for k in range(k_pl):
        np.testing.assert_allclose(
            res.plane_covariance[order[k]], B[k], rtol=1e-5, atol=1e-6 * np.abs(B[k]).max()
        )
    doc = res.to_dict()
    for k, name in enumerate(names):
        p, P = doc["planes"][name], x[4 * k : 4 * k + 4]
        n = P[:3] / np.linalg.norm(P[:3])
        proj = np.eye(3) - np.outer(n, n)
        tilt = np.sqrt(np.linalg.eigvalsh(proj @ B[k, :3, :3] @ proj)[::-1][:2])
        np.testing.assert_allclose(p["tilt_sigmas"], tilt, rtol=1e-5)
        U = np.array(p["tilt_directions"])  # unit columns in the plane, orthogonal
        np.testing.assert_allclose(U.T @ U, np.eye(2), atol=1e-9)
        np.testing.assert_allclose(n @ U, 0.0, atol=1e-9)
        J = np.asarray(jax.jacfwd(lambda q: q[:3] / jnp.linalg.norm(q[:3]) * q[3])(P))
        foot = np.sqrt(np.clip(np.linalg.eigvalsh(J @ B[k] @ J.T)[::-1], 0, None))
        np.testing.assert_allclose(p["foot_point_ellipsoid_axes"], foot, rtol=1e-5)
        np.testing.assert_allclose(p["foot_point"], n * P[3], rtol=1e-6, atol=1e-9)
        np.testing.assert_allclose(p["sigma"]["d"], np.sqrt(B[k, 3, 3]), rtol=1e-6)
