"""The papers' models as presets, estimability that does not depend on units, and calibration
without APs (issue 30, item 3).

* ``lichti2006`` is the final 17-term model of Lichti & Licht 2006 (Tables 1 and 2 without the
  median-wavelength cyclic pair a5, a6, which ``lichti2006-19`` keeps); on a simulated 8-scan
  room like the paper's (two stations 6.7 m apart, four scans each turned by 90 deg, 131 targets
  in a 12 x 9 x 3.3 m room, no inclinometer) it converges and recovers its truth within 3 sigma.
* A1 without an independent scale (the old preset's error) is named as not estimable with
  "scale" instead of diverging; so is a copy of A1 in other units (the test is unit-free).
* ``none`` (the papers' "without self-calibration") calibrates targets and planes, and its
  residuals show the systematic errors the calibrated model removes.

Private import: the registry's term lookup ``get_ap`` (its basis functions build the
reference corrections; there is no public accessor).
"""

import jax.numpy as jnp
import numpy as np
import pytest

import tlsjax as tj
from tlsjax._model._aps import get_ap  # the registry's term lookup (no public accessor)

pytestmark = pytest.mark.internal

DEG = np.pi / 180
#: Lichti & Licht 2006, section 3, Tables 1 and 2, in tlsjax's names (the mapping of
#: tlsjax/_model/_aps.py): a0 a2 a3 a4 a7 a8; b1 b2 b3 b4 b5 b6 b7; c0 c2 c3 c4.
PAPER_2006 = {
    "a0": "A0",
    "a2": "A2",
    "a3": "A3",
    "a4": "A4",
    "a7": "A7",
    "a8": "A8",
    "b1": "B6",
    "b2": "B7",
    "b3": "B4",
    "b4": "B5",
    "b5": "B1",
    "b6": "B11",
    "b7": "B12",
    "c0": "C0",
    "c2": "C2",
    "c3": "C9",
    "c4": "C10",
}


def test_presets_are_the_papers_models():
    assert len(tj.PRESETS["lichti2006"]) == 17
    assert set(tj.PRESETS["lichti2006"]) == set(PAPER_2006.values())
    assert "A1" not in tj.PRESETS["lichti2006"]  # "no scale term (a1) is included"
    assert set(tj.PRESETS["lichti2006-19"]) == set(PAPER_2006.values()) | {"A5", "A6"}
    assert tj.PRESETS["chow2013-fundamental"] == ("A0", "B6", "B7", "C0")
    assert set(tj.PRESETS["chow2013"]) - set(tj.PRESETS["chow2013-noscale"]) == {"A1"}
    assert tj.PRESETS["none"] == ()
    # The bases of the mapping, spot-checked against the paper's descriptions.
    r, t, a = jnp.asarray(5.0), jnp.asarray(0.3), jnp.asarray(0.2)
    sc = tj.Scanner(architecture="panoramic")
    b = lambda name: float(get_ap(name).basis(r, t, a, sc))
    assert b("B6") == pytest.approx(1 / np.cos(0.2))  # b1: collimation, sec(alpha)
    assert b("B1") == pytest.approx(0.3)  # b5: horizontal scale, theta
    assert b("B4") == pytest.approx(np.sin(0.6)) and b("B5") == pytest.approx(np.cos(0.6))
    assert b("B11") == pytest.approx(np.sin(0.6)) and b("B12") == pytest.approx(np.sin(0.8))
    assert b("C9") == pytest.approx(np.sin(0.9)) and b("C10") == pytest.approx(np.cos(0.9))
    assert b("A7") == pytest.approx(np.sin(1.2)) and b("A8") == pytest.approx(np.cos(1.2))
    assert b("C2") == pytest.approx(np.sin(0.2)) and b("A2") == pytest.approx(np.sin(0.2))


def _room_2006(seed=0):
    """Lichti & Licht 2006, sec. 4.1: eight scans at two stations 6.7 m apart, four per station
    turned by 90 deg, 131 targets on the walls, floor and ceiling of a 12 x 9 x 3.3 m room, a
    panoramic scanner, no inclinometer; the data hold the 17 terms of the final model."""
    stations = [(2.65, 4.5, 1.5), (9.35, 4.5, 1.5)]
    scans = tuple(
        (*st, 0.0, 0.0, (90 * k + 10 * i) * DEG) for i, st in enumerate(stations) for k in range(4)
    )
    design = tj.NetworkDesign(
        room=(12.0, 9.0, 3.3),
        scans=scans,
        n_targets=131,
        architecture="panoramic",
        aps=tj.PRESETS["lichti2006"],
        levelling=False,
        elevation_limits=(-70 * DEG, 89 * DEG),
    )
    return tj.simulate_design(design, seed=seed)


@pytest.fixture(scope="module")
def room_2006():
    return _room_2006()


def test_lichti2006_recovers_its_truth(room_2006):
    sim = room_2006
    res = tj.calibrate(
        sim.network, tj.CalibrationModel(tj.Scanner(architecture="panoramic", aps="lichti2006"))
    )
    assert res.result == 0 and res.converged, res.message
    truth = np.array([sim.true_aps[n] for n in res.ap_names])
    z = (res.ap_values - truth) / res.ap_sigmas
    assert np.all(np.abs(z) < 3), dict(zip(res.ap_names, np.round(z, 2)))
    assert abs(res.sigma0 - 1) < 5 / np.sqrt(2 * res.dof)


def test_none_gives_the_without_calibration_pattern(room_2006):
    """The papers' "without self-calibration" column (Lichti & Licht 2006, Table 3): every
    group's residual RMS is larger without the APs, and with them it is the noise."""
    sim = room_2006
    rms = {}
    for aps in ("none", "lichti2006"):
        res = tj.calibrate(
            sim.network, tj.CalibrationModel(tj.Scanner(architecture="panoramic", aps=aps))
        )
        assert res.ok, res.message
        assert len(res.ap_names) == (0 if aps == "none" else 17)
        rms[aps] = np.sqrt(np.mean(res.residuals**2, axis=0))
        assert res.to_dict()["redundancy"]["total"]["sum"] == pytest.approx(res.dof, rel=1e-9)
    noise = np.sqrt(np.mean(sim.noise_sigmas**2, axis=0))
    assert np.all(rms["none"] > 2 * rms["lichti2006"]), rms
    # With the model the residuals are the noise (a share, the redundancy, of it).
    assert np.all(np.abs(rms["lichti2006"] / noise - 1) < 0.3), (rms, noise)


def test_a1_without_scale_is_named_not_estimable():
    """The old 15-term preset (with A1, without scale bars) on the Chow room: A1 passed the
    in-order rank test (1 - R^2 3e-6..1e-5 against the columns before it) and the solve
    diverged. Against every other unknown its 1 - R^2 is below 1e-6: held and named."""
    old = "A0 A1 A3 A4 A5 A6 A7 A8 B6 B7 B11 B12 C0 C9 C10"
    sim = tj.simulate(tj.Room(n_targets=60), aps=old, seed=0)
    res = tj.calibrate(sim.network, tj.CalibrationModel(tj.Scanner(aps=old)))
    assert res.result == 2 and res.converged, res.message
    assert [(n, w) for n, w, _ in res.not_estimable] == [("A1", "scale")]
    assert "A1 is not estimable: scale is undefined" in res.message
    assert np.isnan(res.ap("A1")["value"])
    truth = np.array([sim.true_aps[n] for n in res.ap_names if n != "A1"])
    keep = [i for i, n in enumerate(res.ap_names) if n != "A1"]
    # A1 was simulated (10 ppm-level); without it the range terms absorb part of its effect, so
    # only the angular terms are compared with their truth.
    ang = [i for i in keep if res.ap_names[i][0] in "BC"]
    z = (res.ap_values[ang] - truth[[keep.index(i) for i in ang]]) / res.ap_sigmas[ang]
    assert np.all(np.abs(z) < 5), z
    # With scale bars the same model determines A1.
    sim_s = tj.simulate(tj.Room(n_targets=60), aps=old, seed=0, scale_bars=4)
    res_s = tj.calibrate(sim_s.network, tj.CalibrationModel(tj.Scanner(aps=old)))
    assert res_s.result == 0, res_s.message


def test_estimability_does_not_depend_on_units():
    """A copy of A1 in other units (kilometres of range per metre: basis rho / 1000) is as
    undeterminable as A1; a copy of C0 in other units is as determinable as C0."""
    tj.register_ap("Zkm", "range", lambda r, t, a, s: r / 1000.0, "1", "A1 per km", overwrite=True)
    tj.register_ap(
        "Zmdeg",
        "el",
        lambda r, t, a, s: jnp.full_like(a, 1e-3),
        "rad",
        "C0 in mdeg",
        overwrite=True,
    )
    sim = tj.simulate(tj.Room(n_targets=60), aps="A0 B6 B7 C0", seed=1)
    res = tj.calibrate(sim.network, tj.CalibrationModel(tj.Scanner(aps="A0 B6 B7 Zmdeg Zkm")))
    assert [(n, w) for n, w, _ in res.not_estimable] == [("Zkm", "scale")], res.message
    assert res.ap("Zmdeg")["value"] * 1e-3 == pytest.approx(sim.true_aps["C0"], rel=0.1)


def test_none_calibrates_planes_and_selection_starts_from_it():
    pc = tj.simulate_point_clouds(
        tj.CloudDesign(architecture="hybrid", tilted=True, angular_step=4 * DEG), seed=0
    )
    net = pc.to_network(max_points=30)
    res = tj.calibrate(net, tj.CalibrationModel(tj.Scanner(aps="none")))
    assert res.ok and res.ap_names == () and res.dof > 0, res.message
    assert res.to_dict()["redundancy"]["total"]["sum"] == pytest.approx(res.dof, rel=1e-9)
    sim = tj.simulate(tj.Room(n_targets=40), aps="A0 B7", seed=2)
    selection = tj.SelectionOptions(candidates="physical")
    sel = tj.self_calibrate(
        sim.network,
        tj.CalibrationModel(tj.Scanner(aps="none")),
        tj.CalibrationOptions(vce=None, selection=selection),
    ).selection
    assert set(sel.aps) >= {"A0", "B7"}, sel.aps
