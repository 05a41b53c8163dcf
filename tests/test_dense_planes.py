"""Dense plane clouds (issue 27 item 7): thinning to independent points, the correlated noise
of the simulation, honest AP sigmas at two densities, and the CLI's progress lines.

Independent sources: brute-force voxel bookkeeping (every occupied voxel keeps its point nearest
the centre), the Gaussian covariance the correlated field must have (sampled over fields), and
Monte Carlo scatter of the AP estimates about the simulation's truth against the reported sigmas.

Private imports: ``tlsjax._cli.main`` is the console script's entry point (pyproject), called in
process; ``ObservationTable`` (the reader's table, built here with random rows);
``correlated_field`` (the simulation's random field, checked against its covariance)
and ``thin_indices``/``take_rows`` (the rows thinning keeps, to hold one thinned design fixed
over the realisations of a Monte Carlo run).
"""

import dataclasses

import numpy as np
import pytest

import tlsjax as tj
from tlsjax import ObservationTable
from tlsjax._cli import main
from tlsjax._clouds._thin import take_rows, thin_indices
from tlsjax._simulation._point_clouds import correlated_field

pytestmark = pytest.mark.internal

DEG = np.pi / 180


def _table(rng, n=3000, scans=("S1", "S2"), planes=("P1", "P2", "P3")):
    obs = np.stack(
        [rng.uniform(1.0, 4.0, n), rng.uniform(0.0, 2 * np.pi, n), rng.uniform(-0.6, 0.6, n)],
        axis=1,
    )
    return ObservationTable(
        kind="plane",
        source="<random>",
        scans=tuple(rng.choice(scans, n)),
        primitives=tuple(rng.choice(planes, n)),
        observations=obs,
        sigmas=None,
        incidence=rng.uniform(0.0, 1.0, n),
        instruments=None,
        rows=np.arange(2, n + 2),
    )


def _on_planes(table):
    """Brute force: each group's plane by SVD, each line of sight met with it."""
    _, theta, alpha = table.observations.T
    u = np.stack([np.cos(alpha) * np.cos(theta), np.cos(alpha) * np.sin(theta), np.sin(alpha)], 1)
    x = u * table.observations[:, :1]
    out = x.copy()
    groups = {}
    for i, key in enumerate(zip(table.scans, table.primitives)):
        groups.setdefault(key, []).append(i)
    for rows in groups.values():
        rows = np.asarray(rows)
        c = x[rows].mean(axis=0)
        n = np.linalg.svd(x[rows] - c)[2][-1]
        nu = u[rows] @ n
        ok = np.abs(nu) >= 0.02
        out[rows[ok]] = u[rows[ok]] * (n @ c / nu[ok])[:, None]
    return out


@pytest.mark.parametrize("spacing", [0.05, 0.3, 1.0])
def test_thinning_keeps_the_point_nearest_each_voxel_centre(spacing):
    rng = np.random.default_rng(int(spacing * 100))
    table = _table(rng)
    keep = thin_indices(table, spacing)
    x = _on_planes(table)
    best = {}
    for i, (s, p, xi) in enumerate(zip(table.scans, table.primitives, x)):
        v = tuple(np.floor(xi / spacing).astype(int))
        d = np.sum((xi - (np.asarray(v) + 0.5) * spacing) ** 2)
        key = (s, p, v)
        if key not in best or d < best[key][0]:
            best[key] = (d, i)
    assert sorted(i for _, i in best.values()) == keep.tolist()
    # The kept set does not depend on the order of the rows.
    perm = rng.permutation(len(table))
    again = thin_indices(take_rows(table, perm), spacing)
    assert sorted(perm[again].tolist()) == keep.tolist()
    thinned = tj.thin_planes(table, spacing)
    assert len(thinned) == len(keep) and thinned.rows.tolist() == table.rows[keep].tolist()
    if len(keep) < len(table):
        assert f"{len(keep)} of {len(table)} kept" in thinned.notes[-1]


def test_thinning_does_not_select_range_noise():
    """A wall parallel to a voxel face, at several offsets from it: the kept points' range
    errors average zero (a choice by the observed coordinates keeps the points whose error
    moves them towards the voxel centre, the same sign over the whole wall)."""
    rng = np.random.default_rng(7)
    t, a = np.meshgrid(np.radians(np.arange(-40, 40, 0.25)), np.radians(np.arange(-30, 30, 0.25)))
    u = np.stack([np.cos(a) * np.cos(t), np.cos(a) * np.sin(t), np.sin(a)], -1).reshape(-1, 3)
    sigma, errors = 1e-3, []
    for depth in 3.0 + np.linspace(0.005, 0.045, 5):  # x = depth, 0.1 m voxels centred at 3.05
        rho = depth / u[:, 0]
        e = rng.standard_normal(len(rho)) * sigma
        obs = np.stack([rho + e, np.arctan2(u[:, 1], u[:, 0]), np.arcsin(u[:, 2])], axis=1)
        table = dataclasses.replace(
            _table(rng, n=len(rho), scans=("S1",), planes=("P1",)), observations=obs
        )
        errors.append(e[thin_indices(table, 0.1)])
    errors = np.concatenate(errors)
    assert abs(errors.mean()) < 4 * sigma / np.sqrt(len(errors)), errors.mean() / sigma


def test_thinning_zero_keeps_all_and_bad_spacing_is_refused():
    table = _table(np.random.default_rng(0), n=50)
    assert tj.thin_planes(table, 0.0) is table
    for bad in (-0.1, float("nan"), float("inf")):
        with pytest.raises(ValueError, match="spacing"):
            tj.thin_planes(table, bad)
    with pytest.raises(ValueError, match="plane observations"):
        tj.thin_planes(dataclasses.replace(table, kind="target"), 0.1)


def test_correlated_field_has_the_gaussian_covariance():
    """Over independent fields, cov(f(X), f(Y)) = exp(-|X - Y|^2 / (2 L^2)), variance 1."""
    L, m = 0.2, 4000
    d = np.array([0.0, 0.1, 0.2, 0.4, 0.8])
    X = np.stack([d, np.zeros_like(d), np.zeros_like(d)], axis=1) + np.array([1.0, 2.0, 0.5])
    rng = np.random.default_rng(5)
    f = np.stack([correlated_field(X, L, rng) for _ in range(m)])
    cov = (f * f[:, :1]).mean(axis=0)
    # Monte Carlo error of a product moment of unit-variance fields: about sqrt(2 / m).
    np.testing.assert_allclose(cov, np.exp(-(d**2) / (2 * L**2)), atol=4 * np.sqrt(2.0 / m))


def test_correlated_noise_changes_only_the_range_and_states_the_total_sigma():
    base = tj.CloudDesign(angular_step=6 * DEG, aps=("A0",))
    corr = dataclasses.replace(base, correlated_sigma_range=1e-3, correlation_length=0.05)
    a, b = tj.simulate_point_clouds(base, seed=3), tj.simulate_point_clouds(corr, seed=3)
    assert b.sigma_range == pytest.approx(np.hypot(base.sigma_range, 1e-3))
    for oa, ob in zip(a.observations, b.observations):
        np.testing.assert_array_equal(oa[:, 1:], ob[:, 1:])  # the angles' noise is the same
        assert 2e-4 < np.std(ob[:, 0] - oa[:, 0]) < 5e-3
    with pytest.raises(ValueError, match="correlation_length"):
        dataclasses.replace(base, correlation_length=0.0)


# Monte Carlo of sigma against scatter. The physics depends on the ratio of the thinning
# spacing to the correlation length alone, so the small room below scales both up (L = 0.25 m,
# spacing 0.8 m: 3.2 L, the default's ratio for L = 3 cm) to stay at a few thousand points.
ROOM = dict(length=6.0, width=5.0, height=3.0, n_targets=12)
L_CORR, SPACING, RUNS = 0.25, 0.8, 10


def _design(step):
    return tj.CloudDesign(
        room=tj.Room(**ROOM, stations=((2.0, 2.0, 1.5), (4.0, 3.2, 1.5))),
        boards=(
            tj.Board.tilted((1.0, 4.0, 1.2), 1.0, 0.8, azimuth=-40 * DEG, tilt=25 * DEG),
            tj.Board.tilted((5.0, 1.0, 1.0), 1.0, 0.8, azimuth=150 * DEG, tilt=-20 * DEG),
        ),
        angular_step=step,
        correlated_sigma_range=0.5e-3,
        correlation_length=L_CORR,
    )


def _sigma_over_scatter(step, spacing, runs):
    """Reported sigma over the RMS error about the truth, pooled over the APs and runs:
    ``1 / sqrt(mean((estimate - truth)^2 / sigma^2))``. One thinned design (the rows of the
    first realisation; the geometry is the same in all) so that one compile serves them all."""
    design, keep, z = _design(step), None, []
    for seed in range(runs):
        pc = tj.simulate_point_clouds(design, seed=seed)
        table = pc.to_table()
        keep = thin_indices(table, spacing) if keep is None else keep
        net = tj.make_plane_network(
            take_rows(table, keep),
            sigma_range=pc.sigma_range,
            sigma_hz=pc.sigma_angle,
            sigma_el=pc.sigma_angle,
            levelling=pc.levelling,
        )
        res = tj.calibrate(net, tj.CalibrationModel(pc.scanner))
        assert res.ok, res.message
        truth = np.array([pc.true_aps[a] for a in res.ap_names])
        z.append((res.ap_values - truth) / res.ap_sigmas)
    return 1.0 / np.sqrt(np.mean(np.square(z))), len(keep)


def test_thinned_sigmas_match_monte_carlo_scatter_at_two_densities():
    """Thinned, the reported sigmas match the scatter at 4 and at 2 deg steps (4x the points);
    unthinned at 2 deg they are several times too small. The tolerance is the Monte Carlo error
    of the pooled ratio, 1 / sqrt(8 RUNS) per the 4 APs (the APs are correlated, so it is
    larger in truth), three times: 0.34 for 10 runs. The benchmark's statistics script holds the
    10 % figure with more runs."""
    tol = 3.0 / np.sqrt(8 * RUNS)
    coarse, n_coarse = _sigma_over_scatter(4 * DEG, SPACING, RUNS)
    fine, n_fine = _sigma_over_scatter(2 * DEG, SPACING, RUNS)
    raw, n_raw = _sigma_over_scatter(2 * DEG, 0.0, 3)
    assert n_raw > 20 * n_fine  # the dense cloud, and how much thinning took out
    assert abs(coarse - 1.0) < tol and abs(fine - 1.0) < tol, (coarse, fine)
    assert raw < 0.5, raw  # correlated points taken as independent: sigmas far too small


def test_cli_thins_by_default_and_shows_its_phases_on_stderr(tmp_path, capsys):
    pc = tj.simulate_point_clouds(
        tj.CloudDesign(angular_step=3 * DEG, aps=("A0", "B6", "B7", "C0")), seed=4
    )
    path, out = tmp_path / "planes.csv", tmp_path / "r.json"
    tj.write_observations(path, pc.to_table())
    n = len(pc.to_table())
    assert main(["calibrate", str(path), "--aps", "A0 C0", "--json", str(out)]) == 0
    printed = capsys.readouterr()
    kept = len(tj.thin_planes(pc.to_table(), tj.DEFAULT_PLANE_SPACING))
    assert kept < n and f"{kept} of {n} kept" in printed.out
    assert json_points(out) <= kept  # screening may remove a few more
    for phase in ("reading", "thinning", "screening the plane points", "adjusted:"):
        assert phase in printed.err, printed.err
    assert "iterations" in printed.err and " s]" in printed.err
    assert main(["calibrate", "--planes", str(path), "--aps", "A0 C0", "--quiet", "--no-screen",
                 "--plane-spacing", "0", "--json", str(out)]) == 0  # fmt: skip
    printed = capsys.readouterr()
    assert printed.err == "" and json_points(out) == n
    assert main(["calibrate", "--planes", str(path), "--plane-spacing", "-1"]) == 2
    assert "spacing" in capsys.readouterr().err


def json_points(path):
    import json

    return json.loads(path.read_text())["n_plane_points"]
