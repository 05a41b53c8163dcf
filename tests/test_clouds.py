"""Simulated point clouds: exact plane geometry, the SPEC section 4 AP condition, noise, faces.

The references are written out here: AP bases by hand, the box room's faces as coordinates,
ray-board intersections by the textbook formula.

Private import: ``simulate_point_observations``, the point model's simulation, as the reference
for the simulated clouds.
"""

import numpy as np
import pytest

import tlsjax  # noqa: F401  (x64)
from tlsjax import (
    Board,
    CloudDesign,
    PointClouds,
    Room,
    read_observations,
    simulate_point_clouds,
    write_observations,
)

DEG = np.pi / 180
ARCSEC = DEG / 3600


def _R(w, p, k):
    c, s = np.cos, np.sin
    R1 = np.array([[1, 0, 0], [0, c(w), s(w)], [0, -s(w), c(w)]])
    R2 = np.array([[c(p), 0, -s(p)], [0, 1, 0], [s(p), 0, c(p)]])
    R3 = np.array([[c(k), s(k), 0], [-s(k), c(k), 0], [0, 0, 1]])
    return R3 @ R2 @ R1


def _corrections(l, aps, architecture):
    """Delta(l) of A0, B6, B7, C0 written out by hand (Chow et al. 2013, eqs. 4-6)."""
    rho, th, al = l.T
    d = np.zeros_like(l)
    d[:, 0] += aps.get("A0", 0.0)
    b6 = 1 / np.cos(al) - (1.0 if architecture == "hybrid" else 0.0)
    d[:, 1] += aps.get("B6", 0.0) * b6 + aps.get("B7", 0.0) * np.tan(al)
    d[:, 2] += aps.get("C0", 0.0)
    return d


@pytest.fixture(scope="module", params=["hybrid", "panoramic"])
def noiseless(request):
    design = CloudDesign(angular_step=4 * DEG, architecture=request.param, noise=False)
    return simulate_point_clouds(design, seed=3)


def test_noiseless_points_satisfy_plane_condition(noiseless: PointClouds):
    # SPEC section 4: g = n . (R^T x + S) - d with x from the AP-reduced observations.
    pc = noiseless
    arch = pc.scanner.architecture
    worst = 0.0
    for j, l in enumerate(pc.observations):
        d = _corrections(l, pc.true_aps, arch)
        r, t, a = (l - d).T
        x = np.stack([r * np.cos(a) * np.cos(t), r * np.cos(a) * np.sin(t), r * np.sin(a)], axis=1)
        X = x @ _R(*pc.eops[j, 3:]) + pc.eops[j, :3]
        P = pc.planes[pc.plane_ids[j]]
        g = np.einsum("mi,mi->m", P[:, :3], X) - P[:, 3]
        worst = max(worst, np.abs(g).max())
        np.testing.assert_allclose(X, pc.true_points[j], atol=1e-10)
    assert worst < 1e-10
    # The APs are really in the data: without the reduction the same condition fails by mm.
    l = pc.observations[0]
    r, t, a = l.T
    X = (
        np.stack([r * np.cos(a) * np.cos(t), r * np.cos(a) * np.sin(t), r * np.sin(a)], axis=1)
        @ _R(*pc.eops[0, 3:])
        + pc.eops[0, :3]
    )
    P = pc.planes[pc.plane_ids[0]]
    assert np.abs(np.einsum("mi,mi->m", P[:, :3], X) - P[:, 3]).max() > 5e-3


def test_panoramic_faces(noiseless: PointClouds):
    pc = noiseless
    for j, l in enumerate(pc.observations):
        x = (pc.true_points[j] - pc.eops[j, :3]) @ _R(*pc.eops[j, 3:]).T
        back = x[:, 1] < 0  # hybrid theta >= pi
        if pc.scanner.architecture == "hybrid":
            assert np.all(np.abs(l[:, 2]) < np.pi / 2)
            assert np.all((l[:, 1] >= 0) & (l[:, 1] < 2 * np.pi))
        else:
            np.testing.assert_array_equal(l[:, 2] > np.pi / 2, back)
            # Face-2 directions have theta = theta' - pi in [0, pi) (a full turn up where the APs
            # push it just below zero).
            th = np.where(l[:, 1] > 1.5 * np.pi, l[:, 1] - 2 * np.pi, l[:, 1])
            assert np.all((th > -1e-2) & (th < np.pi + 1e-2))


def test_box_faces_and_nearest_board():
    # One board 1 m in front of the wall x = L, facing the station: rays through it stop on it.
    room = Room(8.0, 6.0, 3.0, stations=((3.0, 3.0, 1.5), (5.0, 2.0, 1.5)))
    board = Board((7.0, 2.0, 0.5), (0.0, 2.0, 0.0), (0.0, 0.0, 1.5))
    design = CloudDesign(
        room=room, boards=(board,), angular_step=2 * DEG, noise=False, aps=(), tilted=False
    )
    pc = simulate_point_clouds(design, seed=0)
    bounds = {0: (0, 0.0), 1: (0, 8.0), 2: (1, 0.0), 3: (1, 6.0), 4: (2, 0.0), 5: (2, 3.0)}
    for j, (X, ids) in enumerate(zip(pc.true_points, pc.plane_ids)):
        assert np.all((X > -1e-9) & (X < np.array([8, 6, 3]) + 1e-9))
        for k, (axis, value) in bounds.items():
            np.testing.assert_allclose(X[ids == k, axis], value, atol=1e-9)
        on_board = X[ids == 6]
        assert len(on_board) > 20
        np.testing.assert_allclose(on_board[:, 0], 7.0, atol=1e-9)
        assert np.all((on_board[:, 1] >= 2 - 1e-9) & (on_board[:, 1] <= 4 + 1e-9))
        assert np.all((on_board[:, 2] >= 0.5 - 1e-9) & (on_board[:, 2] <= 2 + 1e-9))
        # Rays that end on the far wall must pass the plane x = 7 outside the board.
        S = pc.eops[j, :3]
        far = X[ids == 1]
        t = (7.0 - S[0]) / (far[:, 0] - S[0])
        P = S + t[:, None] * (far - S)
        inside = (P[:, 1] > 2) & (P[:, 1] < 4) & (P[:, 2] > 0.5) & (P[:, 2] < 2)
        assert not inside.any()
    # Incidence against the true plane normal, from the geometry.
    X, ids, S = pc.true_points[0], pc.plane_ids[0], pc.eops[0, :3]
    los = (X - S) / np.linalg.norm(X - S, axis=1, keepdims=True)
    cosb = np.abs(np.einsum("mi,mi->m", los, pc.planes[ids, :3]))
    np.testing.assert_allclose(np.cos(pc.incidence[0]), cosb, atol=1e-12)


def test_noise_levels_and_seeds():
    # Without APs, l - F(X) is the noise: 0.5 mm sec(beta) in range, 20" in both angles.
    design = CloudDesign(angular_step=3 * DEG, aps=(), tilted=False)
    pc = simulate_point_clouds(design, seed=7)
    z = []
    for j, l in enumerate(pc.observations):
        x = (pc.true_points[j] - pc.eops[j, :3]) @ _R(*pc.eops[j, 3:]).T
        F = np.stack(
            [
                np.linalg.norm(x, axis=1),
                np.mod(np.arctan2(x[:, 1], x[:, 0]), 2 * np.pi),
                np.arctan2(x[:, 2], np.hypot(x[:, 0], x[:, 1])),
            ],
            axis=1,
        )
        e = l - F
        e[:, 1:] = np.arctan2(np.sin(e[:, 1:]), np.cos(e[:, 1:]))
        z.append(
            e
            / np.stack(
                [
                    0.5e-3 / np.cos(pc.incidence[j]),
                    np.full(len(l), 20 * ARCSEC),
                    np.full(len(l), 20 * ARCSEC),
                ],
                axis=1,
            )
        )
    z = np.concatenate(z)
    assert len(z) > 20000
    np.testing.assert_allclose(z.std(axis=0), 1.0, atol=0.03)
    np.testing.assert_allclose(z.mean(axis=0), 0.0, atol=0.03)
    again = simulate_point_clouds(design, seed=7)
    other = simulate_point_clouds(design, seed=8)
    np.testing.assert_array_equal(again.observations[2], pc.observations[2])
    assert np.abs(other.observations[2] - pc.observations[2]).max() > 1e-5


def test_grid_and_field_of_view():
    design = CloudDesign(
        angular_step=5 * DEG,
        elevation_limits=(-30 * DEG, 60 * DEG),
        noise=False,
        aps=(),
        tilted=False,
    )
    pc = simulate_point_clouds(design, seed=0)
    # 72 directions x 19 elevations per scan; all hit the closed box.
    assert [len(o) for o in pc.observations] == [72 * 19] * 6
    al = pc.observations[0][:, 2]
    assert al.min() == pytest.approx(-30 * DEG, abs=1e-12) and al.max() == pytest.approx(
        60 * DEG, abs=1e-12
    )


def test_to_table_round_trip(tmp_path, noiseless):
    table = noiseless.to_table()
    path = tmp_path / "planes.csv"
    write_observations(path, table, angle_unit="rad")
    back = read_observations(path)
    assert (
        back.kind == "plane" and back.scans == table.scans and back.primitives == table.primitives
    )
    np.testing.assert_allclose(back.observations, table.observations, rtol=0, atol=1e-12)
    assert set(back.primitives) == set(noiseless.plane_names)


def test_design_errors():
    with pytest.raises(ValueError, match="angular_step"):
        CloudDesign(angular_step=0.0)
    with pytest.raises(ValueError, match="elevation_limits"):
        CloudDesign(elevation_limits=(-40 * DEG, 90 * DEG))
    with pytest.raises(ValueError, match="parallel"):
        Board((0, 0, 0), (1, 0, 0), (2, 0, 0))
    with pytest.raises(ValueError, match="unknown AP"):
        CloudDesign(aps="A0 Z9")


@pytest.mark.internal
def test_fixed_point_matches_point_simulation():
    # The looped, chunked fixed point reproduces the target simulation's construction.
    import jax.numpy as jnp

    from tlsjax._model._points import simulate_point_observations

    design = CloudDesign(
        angular_step=6 * DEG, architecture="panoramic", noise=False, aps="A0 B6 B7 C0 B8"
    )
    pc = simulate_point_clouds(design, seed=5)
    j, names = 4, pc.scanner.aps
    coeffs = jnp.asarray([pc.true_aps[n] for n in names])
    for i in (0, len(pc.observations[j]) // 2, len(pc.observations[j]) - 1):
        l = pc.observations[j][i]
        ref = np.asarray(
            simulate_point_observations(
                jnp.asarray(pc.true_points[j][i]),
                jnp.asarray(pc.eops[j]),
                coeffs,
                (pc.scanner,),
                (names,),
                ((0, len(names)),),
                0,
                jnp.zeros(3),
                bool(l[2] > np.pi / 2),
            )
        )
        diff = ref - l
        diff[1:] = np.arctan2(np.sin(diff[1:]), np.cos(diff[1:]))
        assert np.abs(diff).max() < 1e-12
