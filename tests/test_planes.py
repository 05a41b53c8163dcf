"""The plane-based condition model (SPEC section 4) against independent references.

Private imports: the plane condition model and the datum's rigid-motion actions, tested against
independent references.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tlsjax as tj
from tlsjax._model._datum import move_eop, move_plane, null_space_columns
from tlsjax._model._planes import (
    observation_residuals,
    plane_condition,
    plane_step_basis,
    projection_step,
    unit_normal_constraint,
    whitened_condition,
)

pytestmark = pytest.mark.internal

DEG = np.pi / 180


@pytest.fixture(scope="module", params=["hybrid", "panoramic"])
def clouds(request):
    design = tj.CloudDesign(
        architecture=request.param,
        angular_step=4 * DEG,
        noise=False,
        aps=("A0", "B6", "B7", "C0", "A3"),
    )
    return tj.simulate_point_clouds(design, seed=1)


def _rows(pc, scan=1, k=200):
    l = pc.observations[scan][:k]
    ids = pc.plane_ids[scan][:k]
    names = pc.scanner.aps
    coeffs = jnp.asarray([pc.true_aps[n] for n in names])
    return l, ids, names, coeffs


def _g(pc, names, coeffs):
    sc = (pc.scanner,)
    return jax.vmap(
        lambda P, e, l: plane_condition(P, e, coeffs, l, sc, (names,), ((0, len(names)),), 0)
    )


def test_noiseless_points_close_the_condition(clouds):
    l, ids, names, coeffs = _rows(clouds)
    g = _g(clouds, names, coeffs)(
        jnp.asarray(clouds.planes[ids]),
        jnp.tile(jnp.asarray(clouds.eops[1]), (len(l), 1)),
        jnp.asarray(l),
    )
    assert np.abs(np.asarray(g)).max() < 1e-10
    # Without the AP correction the same points miss their planes by millimetres.
    g0 = _g(clouds, names, jnp.zeros_like(coeffs))(
        jnp.asarray(clouds.planes[ids]),
        jnp.tile(jnp.asarray(clouds.eops[1]), (len(l), 1)),
        jnp.asarray(l),
    )
    assert np.abs(np.asarray(g0)).max() > 1e-3


def test_autodiff_jacobians_match_finite_differences(clouds):
    l, ids, names, coeffs = _rows(clouds, k=5)
    sc, sl = (clouds.scanner,), ((0, len(names)),)
    f = lambda P, e, a, obs: plane_condition(P, e, a, obs, sc, (names,), sl, 0)
    for i in range(len(l)):
        args = [
            jnp.asarray(clouds.planes[ids[i]]) * 1.0,
            jnp.asarray(clouds.eops[1]),
            coeffs,
            jnp.asarray(l[i]),
        ]
        grads = jax.grad(f, argnums=(0, 1, 2, 3))(*args)
        for k, G in enumerate(grads):
            fd = np.zeros(G.shape)
            for j in range(G.shape[0]):
                h = 1e-6
                up = [a for a in args]
                dn = [a for a in args]
                up[k] = up[k].at[j].add(h)
                dn[k] = dn[k].at[j].add(-h)
                fd[j] = (float(f(*up)) - float(f(*dn))) / (2 * h)
            np.testing.assert_allclose(np.asarray(G), fd, rtol=1e-6, atol=1e-8)


def test_rigid_motion_is_a_null_direction(clouds):
    """Moving planes and scan poses together by the same rigid motion leaves every condition
    unchanged: ``dg/dplane H_plane + dg/deop H_eop = 0`` (the plane datum defect)."""
    l, ids, names, coeffs = _rows(clouds, k=50)
    sc, sl = (clouds.scanner,), ((0, len(names)),)
    P = jnp.asarray(clouds.planes[ids])
    E = jnp.tile(jnp.asarray(clouds.eops[1]), (len(l), 1))
    Jp, Je = jax.vmap(
        jax.grad(
            lambda p, e, obs: plane_condition(p, e, coeffs, obs, sc, (names,), sl, 0),
            argnums=(0, 1),
        )
    )(P, E, jnp.asarray(l))
    Hp = null_space_columns(move_plane, P, range(6))
    He = null_space_columns(move_eop, E, range(6))
    total = jnp.einsum("np,npd->nd", Jp, Hp) + jnp.einsum("np,npd->nd", Je, He)
    assert np.abs(np.asarray(total)).max() < 1e-10
    # Each part alone is not zero: the test can fail.
    assert np.abs(np.asarray(jnp.einsum("np,npd->nd", Jp, Hp))).max() > 1e-3
    # The action keeps the normal a unit vector to first order.
    dc = jax.vmap(jax.grad(unit_normal_constraint))(P)
    assert np.abs(np.asarray(jnp.einsum("np,npd->nd", dc, Hp))).max() < 1e-12


def test_gauss_helmert_residuals_close_the_linearised_condition(clouds):
    """The first Gauss-Helmert update from v = 0 closes the condition linearised at l; its
    fixed point (``observation_residuals``) closes the condition itself, ``g(l + v) = 0``, with
    ``v^T P v = w^2 / m`` of the row linearised at ``l + v``."""
    l, ids, names, coeffs = _rows(clouds, k=30)
    sc, sl = (clouds.scanner,), ((0, len(names)),)
    rng = np.random.default_rng(0)
    sigma = np.array([0.5e-3, 1e-4, 1e-4])
    noisy = jnp.asarray(l + rng.standard_normal(l.shape) * sigma)
    P = jnp.asarray(clouds.planes[ids])
    E = jnp.tile(jnp.asarray(clouds.eops[1]), (len(l), 1))
    w = jnp.tile(jnp.asarray(1 / sigma), (len(l), 1))
    g_of = jax.vmap(lambda p, e_, obs: plane_condition(p, e_, coeffs, obs, sc, (names,), sl, 0))
    g = g_of(P, E, noisy)
    B = jax.vmap(
        jax.grad(
            lambda p, e_, obs: plane_condition(p, e_, coeffs, obs, sc, (names,), sl, 0), argnums=2
        )
    )(P, E, noisy)
    step = jax.vmap(
        lambda p, e_, obs, v_, ww: projection_step(p, e_, coeffs, obs, v_, ww, sc, (names,), sl, 0)
    )
    v1 = step(P, E, noisy, jnp.zeros_like(noisy), w)
    np.testing.assert_allclose(
        np.sum(np.asarray(B * v1), axis=1), -np.asarray(g), rtol=1e-10, atol=1e-15
    )
    v = jax.vmap(
        lambda p, e_, obs, ww: observation_residuals(p, e_, coeffs, obs, ww, sc, (names,), sl, 0)
    )(P, E, noisy, w)
    # Closed to rounding: g = n . x(l) - d evaluates terms of the size of the range.
    floor = 16 * np.finfo(np.float64).eps * float(np.abs(np.asarray(noisy[:, 0])).max())
    closed = np.abs(np.asarray(g_of(P, E, noisy + v))).max()
    assert closed < 1e-12 * np.abs(np.asarray(g)).max() + floor
    # A fixed point: one more update leaves v where it is.
    np.testing.assert_allclose(
        step(P, E, noisy, v, w), v, rtol=0, atol=1e-12 * float(np.abs(v).max()) + floor
    )
    e = jax.vmap(
        lambda p, e_, obs, v_, ww: whitened_condition(
            p, e_, coeffs, obs, v_, ww, sc, (names,), sl, 0
        )
    )(P, E, noisy, v, w)[:, 0]
    np.testing.assert_allclose(
        np.sum(np.asarray(v) ** 2 / sigma**2, axis=1), np.asarray(e) ** 2, rtol=1e-9
    )
    # The first-order residual is not the projection: the test can fail.
    assert np.abs(np.asarray(v - v1)).max() > 1e-9 * np.abs(np.asarray(v)).max()


def test_plane_step_basis_spans_the_tangent_space():
    """``E`` of a plane: orthonormal columns, orthogonal to the normal, d free; for normals on
    the axes and oblique ones."""
    rng = np.random.default_rng(2)
    normals = np.concatenate([np.eye(3), -np.eye(3), rng.normal(size=(20, 3))])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    for n in normals:
        E = np.asarray(plane_step_basis(jnp.asarray(np.append(n, 2.0))))
        np.testing.assert_allclose(E.T @ E, np.eye(3), atol=1e-14)
        np.testing.assert_allclose(n @ E[:3], 0.0, atol=1e-14)
        np.testing.assert_allclose(E[3], [0.0, 0.0, 1.0], atol=0)
