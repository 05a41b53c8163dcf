"""Non-estimable and weakly determined APs come back by name, never as numbers (SPEC 7, issue 2.9).

Each case has an analytic reason for the defect, so the expected partner is known in advance.

Private imports: the AP registry (every registered term is tried) and geometry helpers to build
the designs.
"""

import jax.numpy as jnp
import numpy as np
import pytest

import tlsjax as tj
from tlsjax import rotation_matrix, spherical_from_cartesian
from tlsjax._model._aps import _REGISTRY

pytestmark = pytest.mark.internal


@pytest.fixture(scope="module", autouse=True)
def extra_terms():
    # The full collimation model sec(alpha) on a hybrid scanner, and a copy of B7's basis.
    tj.register_ap(
        "B6full",
        "hz",
        lambda r, t, a, s: 1.0 / jnp.cos(a),
        "rad",
        "full collimation",
        overwrite=True,
    )
    tj.register_ap(
        "B7copy", "hz", lambda r, t, a, s: jnp.tan(a), "rad", "same basis as B7", overwrite=True
    )
    yield
    for name in ("B6full", "B7copy"):
        _REGISTRY.pop(name, None)


def _flat_network(noise_seed=0):
    """Levelled scans whose centres and every target lie at one height: every elevation is 0,
    so sec(alpha) = 1 and the full collimation term is a constant hz offset, which is exactly a
    rotation of each scan about its vertical axis (kappa)."""
    rng = np.random.default_rng(noise_seed)
    ang = rng.uniform(0, 2 * np.pi, 30)
    X = np.stack([7 + 6 * np.cos(ang), 5.5 + 5 * np.sin(ang), np.full(30, 1.6)], axis=1)
    eops = np.array(
        [[4.5, 4.0, 1.6, 0, 0, 0.3], [9.5, 7.0, 1.6, 0, 0, 1.4], [6.0, 6.0, 1.6, 0, 0, 2.5]]
    )
    scans, targets, obs = [], [], []
    for j, e in enumerate(eops):
        R = np.asarray(rotation_matrix(*e[3:], xp=np))
        l = spherical_from_cartesian((X - e[:3]) @ R.T, xp=np)
        l = l + rng.standard_normal(l.shape) * [0.5e-3, 1e-4, 1e-4]
        l[:, 1] = np.mod(l[:, 1], 2 * np.pi)
        scans += [f"S{j + 1}"] * len(X)
        targets += [f"T{i}" for i in range(len(X))]
        obs.append(l)
    lev = {
        f"S{j + 1}": {"omega": 0.0, "phi": 0.0, "sigma_omega": 5e-5, "sigma_phi": 5e-5}
        for j in range(3)
    }
    return tj.make_network(
        scans, targets, np.concatenate(obs), levelling=lev, sigma_hz=1e-4, sigma_el=1e-4
    )


def test_full_collimation_at_one_elevation_is_confounded_with_kappa():
    res = tj.calibrate(_flat_network(), tj.CalibrationModel(tj.Scanner(aps="A0 B6full")))
    assert res.result == 2, res.message
    ((name, partner, reason),) = res.not_estimable
    assert name == "B6full" and partner.startswith("kappa[")
    assert "B6full is not estimable" in res.message and partner in res.message
    i = res.ap_names.index("B6full")
    assert np.isnan(res.ap_values[i]) and np.isnan(res.ap_sigmas[i])
    # The estimable AP is unaffected: A0 is still a number with a finite sigma.
    assert np.isfinite(res.ap_values[0]) and np.isfinite(res.ap_sigmas[0])


def test_two_terms_with_one_basis():
    sim = tj.simulate(tj.Room(n_targets=36), seed=2, aps="A0 B7 C0")
    res = tj.calibrate(sim.network, tj.CalibrationModel(tj.Scanner(aps="A0 B7 B7copy C0")))
    assert res.result == 2
    assert [(n, p) for n, p, _ in res.not_estimable] == [("B7copy", "B7")]
    # Holding the copy at zero leaves B7 with the whole effect.
    i = res.ap_names.index("B7")
    assert abs(res.ap_values[i] - sim.true_aps["B7"]) < 5 * res.ap_sigmas[i]


def test_range_scale_needs_an_independent_scale():
    sim = tj.simulate(tj.Room(n_targets=36), seed=1, aps="A0 A1 B6 C0")
    free = tj.calibrate(sim.network, tj.CalibrationModel(tj.Scanner(aps="A0 A1 B6 C0")))
    assert [(n, p) for n, p, _ in free.not_estimable] == [("A1", "scale")]
    assert "add scale bars or control" in free.message
    # The same room with two scale bars determines A1.
    bars = tj.simulate(tj.Room(n_targets=36), seed=1, aps="A0 A1 B6 C0", scale_bars=2)
    res = tj.calibrate(bars.network, tj.CalibrationModel(tj.Scanner(aps="A0 A1 B6 C0")))
    assert res.result == 0, res.message
    i = res.ap_names.index("A1")
    assert abs(res.ap_values[i] - bars.true_aps["A1"]) < 5 * res.ap_sigmas[i]


def test_full_collimation_with_levelled_hybrid_scans_is_weak_not_missing():
    sim = tj.simulate(seed=0, tilted=False, aps="A0 B7 C0")
    res = tj.calibrate(sim.network, tj.CalibrationModel(tj.Scanner(aps="A0 B6full B7 C0")))
    assert res.result == 0, res.message
    weak = {n: (p, c) for n, p, c in res.weakly_determined}
    assert "B6full" in weak
    partner, corr = weak["B6full"]
    assert partner.startswith("kappa[") and 0.99 < corr < 1.0
    # Tilted scans decorrelate it (Chow et al. 2013, sec. 4.1).
    tilted = tj.simulate(seed=0, tilted=True, aps="A0 B7 C0")
    res_t = tj.calibrate(tilted.network, tj.CalibrationModel(tj.Scanner(aps="A0 B6full B7 C0")))
    i = res_t.ap_names.index("B6full")
    assert res_t.ap_max_abs_corr[i] < corr
