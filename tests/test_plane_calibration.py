"""Plane-based self-calibration through the public API (SPEC sections 4-8).

Independent sources: the simulation's truth (noiseless recovery, up to the free network's rigid
motion), Gauss-Helmert identities (redundancy sums, 1/3 per plane observation), the a priori
sigmas (sigma0 against its sampling scatter) and the target-only and plane-only adjustments of the
same room (a combined network can only be better determined than either part).

Private imports: ``tlsjax._cli.main`` is the ``tlsjax`` console script's entry point
(pyproject), called in process; ``approximate_network`` (approximate values, a private
algorithm); ``rotation_matrix`` for the reference motion.
"""

import dataclasses
import json

import numpy as np
import pytest

import tlsjax as tj
from tlsjax import rotation_matrix, write_observations
from tlsjax._cli import main

DEG = np.pi / 180
APS = ("A0", "B6", "B7", "C0")
MAX_POINTS = 60  # per plane and scan: a few thousand plane points in all


def _invariants(eops, planes):
    """Quantities a rigid motion of the world frame leaves unchanged: scanner-to-scanner
    distances, relative rotations R_i R_j^T, angles between plane normals and each scanner's
    signed distance to each plane (d - n . S)."""
    S = eops[:, :3]
    R = np.stack([rotation_matrix(*e[3:], xp=np) for e in eops])
    dist = np.linalg.norm(S[:, None] - S[None], axis=-1)
    rel = np.einsum("iab,jcb->ijac", R, R)
    n, d = planes[:, :3], planes[:, 3]
    return dist, rel, n @ n.T, d[None, :] - S @ n.T


def _compare(est_eops, est_planes, true_eops, true_planes, length_tol, angle_tol):
    de, dr, dn, dd = (
        a - b
        for a, b in zip(_invariants(est_eops, est_planes), _invariants(true_eops, true_planes))
    )
    assert np.abs(de).max() < length_tol and np.abs(dd).max() < length_tol
    assert np.abs(dr).max() < angle_tol and np.abs(dn).max() < angle_tol


def _true_planes(pc, names):
    return pc.planes[[pc.plane_names.index(n) for n in names]]


@pytest.fixture(scope="module", params=["hybrid", "panoramic"])
def noiseless(request):
    design = tj.CloudDesign(architecture=request.param, angular_step=3 * DEG, noise=False, aps=APS)
    pc = tj.simulate_point_clouds(design, seed=2)
    net = pc.to_network(MAX_POINTS, seed=0)
    return pc, net, tj.calibrate(net, tj.CalibrationModel(pc.scanner))


def test_noiseless_recovery_of_the_truth(noiseless):
    pc, net, res = noiseless
    assert res.ok and res.converged, res.message
    truth = np.array([pc.true_aps[n] for n in res.ap_names])
    # A0 in m, B6/B7/C0 in rad: 1e-8 is 0.01 micrometre and 0.002".
    np.testing.assert_allclose(res.ap_values, truth, rtol=0, atol=1e-8)
    assert res.sigma0 < 1e-4
    assert sorted(res.planes) == sorted(pc.plane_names)
    _compare(res.eops, res.plane_params, pc.eops, _true_planes(pc, res.planes), 1e-7, 1e-8)
    np.testing.assert_allclose(np.linalg.norm(res.plane_params[:, :3], axis=1), 1, atol=1e-9)


@pytest.mark.internal
def test_approximate_values_are_within_centimetres(noiseless):
    from tlsjax._adjustment._approx import approximate_network

    pc, net, _ = noiseless
    _, eops, planes = approximate_network(net)
    assert np.isfinite(eops).all() and np.isfinite(planes).all()
    # The APs (10 mm, 180") are not in the approximate values: a centimetre and a fifth of a degree.
    _compare(eops, planes, pc.eops, _true_planes(pc, net.planes), 0.02, 0.2 * DEG)


@pytest.fixture(scope="module")
def noisy():
    design = tj.CloudDesign(architecture="hybrid", tilted=True, angular_step=3 * DEG, aps=APS)
    pc = tj.simulate_point_clouds(design, seed=5)
    net = pc.to_network(MAX_POINTS, seed=1)
    return pc, net, tj.calibrate(net, tj.CalibrationModel(pc.scanner))


def test_gauss_helmert_redundancy_identities(noisy):
    pc, net, res = noisy
    assert res.ok, res.message
    summary = res.to_dict()["redundancy"]
    # Sum over plane observations and levelling equals the degrees of freedom.
    assert summary["total"]["sum"] == pytest.approx(res.dof, abs=1e-6)
    r = res.plane_redundancy
    assert r.min() > -1e-10
    # One condition per point: the point's three numbers share a redundancy of at most 1.
    assert r.sum(axis=1).max() < 1 + 1e-9
    planes = summary["planes"]
    assert planes["all"]["mean"] <= 1 / 3 + 1e-12
    # The condition measures distance along the normal: the range carries almost all of it.
    assert planes["hz"]["mean"] < 0.3 * planes["range"]["mean"]
    assert planes["el"]["mean"] < 0.3 * planes["range"]["mean"]
    # Observations as the papers count them: 3 per plane point and 2 per levelled scan; the
    # dof count conditions and the hard unit-normal constraints (Gauss-Helmert):
    # m conditions + 2 per levelled scan - unknowns (4 per plane) + k constraints + 4 datum
    # defects.
    m, k, lev = len(net.plane_observations), len(net.planes), 2 * int(net.is_levelled.sum())
    assert res.n_observations == 3 * m + lev
    assert res.n_conditions == m + lev and res.n_constraints == k
    assert res.dof == m + lev - res.n_unknowns + k + 4


def test_noisy_plane_calibration_matches_its_sigmas(noisy):
    pc, net, res = noisy
    # sigma0 within five of its sampling standard deviations (1 / sqrt(2 dof)) of 1.
    assert abs(res.sigma0 - 1) < 5 / np.sqrt(2 * res.dof)
    truth = np.array([pc.true_aps[n] for n in res.ap_names])
    assert (np.abs(res.ap_values - truth) / res.ap_sigmas).max() < 4
    # Angular residuals are near zero: only the range direction is constrained by a plane.
    v = res.plane_residuals
    rho = net.plane_observations[:, 0]
    rms = np.sqrt((v**2).mean(axis=0))
    assert rms[1] * rho.mean() < 0.3 * rms[0] and rms[2] * rho.mean() < 0.3 * rms[0]


def test_scan_with_planes_of_two_directions_is_refused():
    # S2 keeps only the floor, the ceiling and the two x walls: its rotation is determined, but
    # nothing fixes its position along y.
    pc = tj.simulate_point_clouds(tj.CloudDesign(angular_step=3 * DEG, noise=False), seed=0)
    t = pc.to_table(MAX_POINTS)
    keep = np.array(
        [
            s != "S2" or p in ("floor", "ceiling", "wall_x0", "wall_xL")
            for s, p in zip(t.scans, t.primitives)
        ]
    )
    t = dataclasses.replace(
        t,
        scans=tuple(np.array(t.scans)[keep]),
        primitives=tuple(np.array(t.primitives)[keep]),
        observations=t.observations[keep],
        sigmas=t.sigmas[keep],
        incidence=t.incidence[keep],
        rows=t.rows[keep],
    )
    net = tj.make_plane_network(t)
    with pytest.raises(ValueError, match="scan S2: its position is not determined"):
        tj.calibrate(net, tj.CalibrationModel(pc.scanner))


def test_combined_network_is_better_determined_than_either_part():
    # The target room and the plane room share the stations (SPEC 8), the true APs and the
    # compensator readings, so one network may hold both.
    sim = tj.simulate(tj.Room(n_targets=48), seed=3, aps=" ".join(APS))
    pc = tj.simulate_point_clouds(tj.CloudDesign(angular_step=3 * DEG, aps=APS), seed=3)
    assert sim.true_aps == pytest.approx(pc.true_aps)
    np.testing.assert_allclose(sim.true_eops, pc.eops)
    tn = sim.network
    scans = [tn.scans[j] for j in tn.scan_index]
    targets = [tn.targets[i] for i in tn.target_index]
    table = pc.to_table(MAX_POINTS, seed=2)
    model = tj.CalibrationModel(pc.scanner)
    both = tj.calibrate(
        tj.make_network(
            scans, targets, tn.observations, sigmas=tn.sigmas, planes=table, levelling=pc.levelling
        ),
        model,
    )
    alone_t = tj.calibrate(
        tj.make_network(scans, targets, tn.observations, sigmas=tn.sigmas, levelling=pc.levelling),
        model,
    )
    alone_p = tj.calibrate(tj.make_plane_network(table, levelling=pc.levelling), model)
    for r in (both, alone_t, alone_p):
        assert r.ok, r.message
    assert both.to_dict()["redundancy"]["total"]["sum"] == pytest.approx(both.dof, abs=1e-6)
    assert both.n_observations == alone_t.n_observations + alone_p.n_observations - 2 * len(
        pc.levelling
    )
    # A priori AP standard deviations (cofactors): adding observations never loosens them.
    q = lambda r: r.ap_sigmas / r.sigma0
    assert (q(both) <= q(alone_t) * (1 + 1e-9)).all() and (q(both) <= q(alone_p) * (1 + 1e-9)).all()
    truth = np.array([pc.true_aps[n] for n in both.ap_names])
    assert (np.abs(both.ap_values - truth) / both.ap_sigmas).max() < 4


def test_cli_calibrate_plane_csv(tmp_path, noisy, capsys):
    pc, net, res = noisy
    path = tmp_path / "planes.csv"
    write_observations(path, pc.to_table(MAX_POINTS, seed=1))
    out = tmp_path / "r.json"
    # All points (no thinning): the same rows as the network of the API below.
    args = ["--planes", str(path), "--aps", " ".join(APS), "--json", str(out)]
    assert main(["calibrate", *args, "--plane-spacing", "0"]) == 0
    printed = capsys.readouterr().out
    assert "plane" in printed and "mm" in printed
    js = json.loads(out.read_text())
    assert {"planes", "plane_residual_rms", "n_plane_points"} <= set(js)
    assert js["n_plane_points"] == len(net.plane_observations)
    assert len(js["planes"]) == len(pc.plane_names)
    # The CSV has no compensator readings: the same network through the API, without them.
    api = tj.calibrate(
        tj.make_plane_network(pc.to_table(MAX_POINTS, seed=1)), tj.CalibrationModel(pc.scanner)
    )
    assert js["dof"] == api.dof and js["n_observations"] == api.n_observations
    for name, value, sigma in zip(api.ap_names, api.ap_values, api.ap_sigmas):
        assert js["aps"][name]["value"] == pytest.approx(value, rel=1e-6)
        assert js["aps"][name]["sigma"] == pytest.approx(sigma, rel=1e-6)
    # VCE and snooping belong to target networks: refused with the bad-input exit code.
    assert main(["calibrate", "--planes", str(path), "--vce"]) == 2
    assert "target networks" in capsys.readouterr().err
