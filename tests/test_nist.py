"""The NIST geometric error model (Muralikrishnan et al. 2015, 2017) as registered APs, and the
two-face design of one panoramic station.

Private import: ``ap_corrections``, compared with the NIST equations written out here.
"""

import numpy as np
import pytest

import tlsjax as tj

NAMES = ("x1n", "x1z", "x2", "x3", "x4", "x5n", "x5z", "x6", "x7", "x8x", "x8y", "x9n", "x9z",
         "x10", "x11a", "x11b", "x12a", "x12b")  # fmt: skip


def _nist(x, R, H, V):
    """The published model in its own variables (zenith angle V): errors of R, H and V."""
    dR = x["x2"] * np.sin(V) + x["x10"]
    dH = (
        x["x1z"] / (R * np.tan(V)) + x["x3"] / (R * np.sin(V)) + x["x5z"] / np.tan(V)
        + 2 * x["x6"] / np.sin(V) + x["x7"] / np.tan(V) + x["x8x"] * np.sin(H)
        - x["x8y"] * np.cos(H) + x["x11a"] * np.cos(2 * H) - x["x11b"] * np.sin(2 * H)
    )  # fmt: skip
    dV = (
        x["x1n"] * np.cos(V) / R + x["x4"] + x["x5n"] * np.cos(V) + x["x9n"] * np.cos(V)
        - x["x9z"] * np.sin(V) + x["x12a"] * np.cos(2 * V) - x["x12b"] * np.sin(2 * V)
    )  # fmt: skip
    return dR, dH, dV


@pytest.mark.internal
def test_registered_terms_reproduce_the_published_equations_in_both_faces():
    from tlsjax._model._aps import ap_corrections

    rng = np.random.default_rng(0)
    values = dict(zip(NAMES, rng.normal(size=len(NAMES)) * 1e-3))
    n = 200
    rho = rng.uniform(1, 30, n)
    theta = rng.uniform(0, np.pi, n)
    alpha = np.concatenate([rng.uniform(-1.2, 1.2, n // 2), rng.uniform(1.95, 4.3, n // 2)])
    l = np.stack([rho, theta, alpha], axis=1)  # panoramic: second half in face 2
    scanner = tj.Scanner("panoramic", aps=NAMES)
    got = np.asarray(ap_corrections(np.array([values[k] for k in NAMES]), NAMES, l, scanner))
    dR, dH, dV = _nist(values, rho, theta, np.pi / 2 - alpha)  # V = 90 deg - alpha, both faces
    np.testing.assert_allclose(got[:, 0], dR, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(got[:, 1], dH, rtol=1e-10, atol=1e-15)
    # The elevation is 90 deg minus the zenith angle; x2's elevation part is carried by x1n.
    np.testing.assert_allclose(got[:, 2], -dV, rtol=1e-10, atol=1e-15)
    assert set(tj.PRESETS["nist"]) == set(NAMES) - {"x7", "x9n"}


def test_two_face_design_observes_each_target_in_both_faces():
    sim = tj.simulate(architecture="panoramic", two_face=True, aps=(), noise=False, seed=1)
    net = sim.network
    obs = net.observations
    assert len(sim.true_eops) == 2 and len(obs) == 2 * len(sim.true_targets)
    np.testing.assert_allclose(sim.true_eops[0, :3], sim.true_eops[1, :3])
    assert np.isclose(sim.true_eops[1, 5] - sim.true_eops[0, 5], np.pi)
    a, b = obs[net.scan_index == 0], obs[net.scan_index == 1]
    ta, tb = net.target_index[net.scan_index == 0], net.target_index[net.scan_index == 1]
    a, b = a[np.argsort(ta)], b[np.argsort(tb)]
    face2_a = a[:, 2] > np.pi / 2
    assert np.all(face2_a != (b[:, 2] > np.pi / 2))  # each target once in each face
    np.testing.assert_allclose(b[:, 0], a[:, 0], atol=1e-12)
    np.testing.assert_allclose(b[:, 1], a[:, 1], atol=1e-9)
    np.testing.assert_allclose(b[:, 2], np.pi - a[:, 2], atol=1e-9)
    assert np.all((obs[:, 1] >= 0) & (obs[:, 1] < np.pi))  # SPEC 1: panoramic hz in [0, 180)
    with pytest.raises(ValueError, match="panoramic"):
        tj.simulate(architecture="hybrid", two_face=True)


def test_two_face_calibration_recovers_the_face_dependent_terms():
    # Terms whose sign flips between the faces are determined from one station (NIST two-face
    # method); the scan is held fixed (one station gives no other datum for the targets).
    # (x8x, x8y, sin/cos of H, flip with the face only when H runs over the full circle; in the
    # panoramic convention of SPEC section 1 both faces report the same hz, so one station cannot
    # separate them from the targets.)
    aps = "x1z x3 x4 x6"
    sim = tj.simulate(architecture="panoramic", two_face=True, aps=aps, seed=3)
    model = tj.CalibrationModel(
        tj.Scanner("panoramic", aps=aps), datum="fixed-scan", fixed_scan="S1"
    )
    res = tj.calibrate(sim.network, model)
    assert res.ok, res.message
    z = (
        np.asarray(res.ap_values) - np.array([sim.true_aps[n] for n in res.ap_names])
    ) / np.asarray(res.ap_sigmas)
    assert np.abs(z).max() < 4.5
    assert np.abs(np.asarray(res.ap_values) / np.asarray(res.ap_sigmas)).min() > 10
