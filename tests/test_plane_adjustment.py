"""The structured Gauss-Helmert plane adjustment against a dense bordered solve (SPEC 4, 6, 7).

The plane family of the solver (one whitened condition per point, planes eliminated by Schur
complement, the unit-normal constraint as a heavy pseudo-observation, inner constraints on the
planes) is compared with a dense Gauss-Newton of the same conditions written out by hand,
with the unit-normal constraints and the datum as hard constraints in a bordered system.

Private imports: the plane family, the solver and the quality pass are compared with the dense
oracle directly.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import _R

import tlsjax as tj
from tlsjax._adjustment._families import Params, PlaneFamily, Problem, Spec
from tlsjax._adjustment._quality import quality
from tlsjax._adjustment._solver import adjust

DEG = np.pi / 180
APS = ("A0", "B6", "B7", "C0")


def _g_by_hand(plane, eop, aps, l):
    """g = n.(R^T x + S) - d with the hybrid AP corrections A0, B6 (sec - 1), B7, C0."""
    rho, th, al = (
        l[0] - aps[0],
        l[1] - aps[1] * (1 / jnp.cos(l[2]) - 1) - aps[2] * jnp.tan(l[2]),
        l[2] - aps[3],
    )
    x = rho * jnp.array([jnp.cos(al) * jnp.cos(th), jnp.cos(al) * jnp.sin(th), jnp.sin(al)])
    return plane[:3] @ (_R(*eop[3:]).T @ x + eop[:3]) - plane[3]


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
        unit_weight=jnp.full(n_pl, 1e7),
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
    state = adjust(spec, problem, p0, tj.SolverOptions(tolerance=1e-8).arrays())
    q = quality(spec, problem, state.params, jnp.asarray(1e-6), full_covariance=False)
    return state, q


def _dense(obs, sig, plane, scan, x0, n_pl, n_s, iterations=10):
    """Dense Gauss-Newton: rows g_i / sqrt(m_i) (m_i = B Sigma B^T held per iteration), hard
    unit-normal constraints and inner constraints on the planes in a bordered system."""
    l = jnp.asarray(obs)
    pl, sc = jnp.asarray(plane), jnp.asarray(scan)

    def unpack(x):
        x = jnp.asarray(x)
        return (
            x[: 4 * n_pl].reshape(n_pl, 4),
            x[4 * n_pl : 4 * n_pl + 6 * n_s].reshape(n_s, 6),
            x[4 * n_pl + 6 * n_s :],
        )

    def g_all(x):
        P, E, A = unpack(x)
        return jax.vmap(lambda i: _g_by_hand(P[pl[i]], E[sc[i]], A, l[i]))(jnp.arange(len(obs)))

    def m_all(x):
        P, E, A = unpack(x)
        B = jax.vmap(lambda i: jax.grad(lambda li: _g_by_hand(P[pl[i]], E[sc[i]], A, li))(l[i]))(
            jnp.arange(len(obs))
        )
        return jnp.sum((B * sig) ** 2, axis=1), B

    def constraints(x):
        P = unpack(x)[0]
        return jnp.sum(P[:, :3] ** 2, axis=1) - 1.0

    def datum(x):
        # Rows of G^T: translation t changes d by n.t, rotation w changes n by w x n.
        P = unpack(x)[0]
        G = np.zeros((6, x.size))
        for k in range(n_pl):
            n = np.asarray(P[k, :3])
            G[:3, 4 * k + 3] = n
            G[3:, 4 * k : 4 * k + 3] = np.array(
                [[0, -n[2], n[1]], [n[2], 0, -n[0]], [-n[1], n[0], 0]]
            ).T
        return G

    x = np.asarray(x0, dtype=float)
    Jg, Jc = jax.jit(jax.jacfwd(g_all)), jax.jit(jax.jacfwd(constraints))
    for it in range(iterations + 1):
        m, B = (np.asarray(a) for a in jax.jit(m_all)(x))
        w = 1 / np.sqrt(m)
        J = np.asarray(Jg(x)) * w[:, None]
        e = np.asarray(jax.jit(g_all)(x)) * w
        C = np.asarray(Jc(x))
        c = np.asarray(constraints(x))
        G = datum(x)
        K = np.vstack([C, G])
        u, nk = x.size, K.shape[0]
        M = np.block([[J.T @ J, K.T], [K, np.zeros((nk, nk))]])
        if it == iterations:
            break
        sol = np.linalg.solve(M, np.concatenate([-J.T @ e, -c, np.zeros(6)]))
        x = x + sol[:u]
    Q = np.linalg.inv(M)[:u, :u]
    r_c = 1 - np.einsum("ij,jk,ik->i", J, Q, J)
    share = (sig * B) ** 2 / m[:, None]
    v = -(sig**2) * B * (np.asarray(g_all(x)) / m)[:, None]
    dof = len(obs) + n_pl - u + 6
    return x, Q, r_c[:, None] * share, v, float(e @ e), dof


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
    # The unit-normal constraint is a heavy pseudo-observation (weight 1e7), the oracle's a
    # hard one; |n|^2 - 1 ends near 1e-13.
    assert np.isclose(float(q.vtpv), vtpv, rtol=1e-9)
    np.testing.assert_allclose(np.asarray(state.params.aps), x[a:], rtol=1e-7, atol=1e-12)
    # AP cofactors are datum invariant: the reduced system's AP block equals the dense one.
    np.testing.assert_allclose(np.diag(np.asarray(q.Qzz))[6 * n_s :], np.diag(Q)[a:], rtol=1e-6)
    np.testing.assert_allclose(np.asarray(q.redundancy[0]), redund, atol=1e-8)
    np.testing.assert_allclose(np.asarray(q.residuals[0]), v, rtol=1e-6, atol=1e-10)
    # Redundancy numbers of a point sum to at most 1, and all of them to the dof.
    assert np.all(np.asarray(q.redundancy[0]).sum(axis=1) <= 1 + 1e-9)
    total = float(np.asarray(q.redundancy[0]).sum() + np.asarray(q.redundancy_prior[0]).sum())
    assert np.isclose(total, dof, rtol=1e-7)
    # Noise-level estimate of the APs: within a few sigma of the simulated truth.
    s0 = np.sqrt(vtpv / dof)
    z = (x[a:] - np.array([pc.true_aps[n] for n in APS])) / (s0 * np.sqrt(np.diag(Q)[a:]))
    assert np.all(np.abs(z) < 5), z


def test_calibrate_of_a_plane_network_equals_dense_gauss_helmert(network):
    """The public path (make_plane_network, approximate values, calibrate) against the oracle:
    AP estimates and a posteriori sigmas, per-observation redundancy numbers and residuals."""
    from tlsjax._adjustment._network import ObservationTable

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
    # Plane sigmas: the oracle's bordered inverse is the inner-constraint cofactor matrix. Along
    # its own normal a component keeps the soft constraint's sigma 1/(2 w) = 5e-8 where the
    # hard one has 0; every other sigma is 1e-5 or more.
    s_pl = np.sqrt(vtpv / dof * np.diag(Q)[: 4 * n_pl]).reshape(n_pl, 4)
    np.testing.assert_allclose(res.plane_sigmas[order], s_pl, rtol=1e-5, atol=1e-7)
    # Three observations per point: n counts them, the dof counts one condition per point.
    assert res.n_observations == 3 * len(obs) + n_pl
