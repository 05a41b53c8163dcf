"""Weighted constraints with observed values (Chow et al. 2013, eq. 7; SPEC section 6; issue 30
item 2): tilt readings of levelled and tilted scans, an observed kappa, AP priors.

* Against the dense rigorous Gauss-Helmert oracle (tests/helpers.py) of a plane network with
  oblique planes: the constraints' residuals and redundancy numbers, the APs, sigma0 and the
  degrees of freedom agree; the redundancy numbers sum to the dof.
* The same for a target network (redundancy sum), the files (scans CSV kappa columns, AP priors
  as text, CSV and result JSON) and the command line.

Private imports: ``tlsjax._cli.main`` (the console script) and the compensator model
``compensator_reading``, which builds the tilt readings of the reference networks.
"""

import dataclasses
import json

import jax.numpy as jnp
import numpy as np
import pytest
from helpers import dense_gauss_helmert
from networks import APS, NumpyDrawer, oblique_case

import tlsjax as tj
from tlsjax._cli import main
from tlsjax._model._levelling import compensator_reading

pytestmark = pytest.mark.internal

ARCSEC = np.pi / 180 / 3600


def _with_orientation(sim, sigma_tilt, sigma_heading, seed=0):
    """The simulated network with tilt readings of its tilted scans and a heading of every
    scan, drawn from the truth (the levelled scans keep their compensator readings)."""
    net, E = sim.network, sim.true_eops
    rng = np.random.default_rng(seed)
    lev, lev_sig = net.levelling.copy(), net.levelling_sigma.copy()
    for j in np.flatnonzero(~net.is_levelled):
        lev[j] = (
            np.asarray(compensator_reading(jnp.asarray(E[j]))) + rng.normal(size=2) * sigma_tilt
        )
        lev_sig[j] = sigma_tilt
    heading = E[:, 5] + rng.normal(size=len(E)) * sigma_heading
    return dataclasses.replace(
        net,
        levelling=lev,
        levelling_sigma=lev_sig,
        heading=heading,
        heading_sigma=np.full(len(E), sigma_heading),
    )


@pytest.fixture(scope="module")
def plane_case():
    # A drawn design with levelled and tilted scans (tests/test_gauss_helmert.py).
    for seed in range(50):
        design, sim_seed = oblique_case(NumpyDrawer(seed))
        if design.levelling and design.sigma_scale == 1.0:
            sim = tj.simulate_design(design, seed=sim_seed)
            if (~sim.network.is_levelled).any() and sim.network.is_levelled.any():
                return sim
    raise AssertionError("no design with levelled and tilted scans drawn")


def test_constraints_equal_the_dense_gauss_helmert_oracle(plane_case):
    sim = plane_case
    net = _with_orientation(sim, 10 * ARCSEC, 30 * ARCSEC)
    b6 = (sim.true_aps["B6"] + 3 * ARCSEC, 5 * ARCSEC)
    model = tj.CalibrationModel(sim.scanner, ap_priors={"B6": b6})
    res = tj.calibrate(net, model, tj.SolverOptions(tolerance=1e-10))
    assert res.result == 0, res.message
    n_pl, n_s = len(net.planes), len(net.scans)
    kappa = [
        (lambda x, j=j: x[4 * n_pl + 6 * j + 5], net.heading[j], net.heading_sigma[j])
        for j in range(n_s)
    ]
    prior = [(lambda x: x[-len(APS) + 1], *b6)]
    x0 = np.concatenate(
        [sim.true_planes.reshape(-1), sim.true_eops.reshape(-1), np.zeros(len(APS))]
    )
    # A heading fixes the rotation about the vertical: the datum is the translations.
    ref = dense_gauss_helmert(net, APS, x0, pseudo=kappa + prior, datum=(0, 1, 2))
    assert res.dof == ref["dof"]
    s0 = np.sqrt(ref["vtpv"] / ref["dof"])
    np.testing.assert_allclose(res.sigma0, s0, rtol=1e-6)
    a = slice(-len(APS), None)
    sig = s0 * np.sqrt(np.diag(ref["Q"])[a])
    np.testing.assert_allclose((res.ap_values - ref["x"][a]) / sig, 0.0, atol=1e-6)
    np.testing.assert_allclose(res.ap_sigmas, sig, rtol=1e-6)
    # The pseudo-observations follow the points in the oracle: tilt readings (scan, axis) in
    # order, then the headings, then the prior.
    m = ref["n_points"]
    v, r = ref["v"][3 * m :], ref["r"][3 * m :]
    tilt = np.isfinite(net.levelling_sigma)
    n_t = int(tilt.sum())
    np.testing.assert_allclose(
        res.orientation_residuals[:, :2][tilt] / net.levelling_sigma[tilt],
        v[:n_t] / net.levelling_sigma[tilt],
        atol=1e-6,
    )
    np.testing.assert_allclose(res.redundancy_orientation[:, :2][tilt], r[:n_t], atol=1e-6)
    np.testing.assert_allclose(
        res.orientation_residuals[:, 2] / net.heading_sigma,
        v[n_t : n_t + n_s] / net.heading_sigma,
        atol=1e-6,
    )
    np.testing.assert_allclose(res.redundancy_orientation[:, 2], r[n_t : n_t + n_s], atol=1e-6)
    np.testing.assert_allclose(res.ap_prior_residuals[1] / b6[1], v[-1] / b6[1], atol=1e-6)
    np.testing.assert_allclose(res.redundancy_ap_prior[1], r[-1], atol=1e-6)
    assert np.isnan(res.ap_prior_residuals[[0, 2, 3]]).all()
    # Every redundancy number of the network sums to the dof, the constraints' included.
    np.testing.assert_allclose(ref["r"].sum(), ref["dof"], rtol=1e-9)
    summary = res.to_dict()["redundancy"]
    np.testing.assert_allclose(summary["total"]["sum"], res.dof, rtol=1e-9)
    assert summary["heading"]["sum"] == pytest.approx(r[n_t : n_t + n_s].sum(), abs=1e-6)
    # Their tests: w = v / (sigma sqrt(r)).
    tests = {(c["kind"], c["name"]): c for c in res.weighted_constraints()}
    c = tests[("ap", "B6")]
    assert c["w"] == pytest.approx(v[-1] / (b6[1] * np.sqrt(r[-1])), rel=1e-5)
    assert len(tests) == n_t + n_s + 1


def test_target_network_with_constraints_sums_to_its_dof():
    sim = tj.simulate(
        tj.Room(n_targets=48),
        aps="physical",
        seed=5,
        sigma_tilt=10 * ARCSEC,
        sigma_heading=20 * ARCSEC,
    )
    net = sim.network
    # The tilted scans carry the tilt sensor's readings, every scan a heading.
    assert net.is_levelled.all() and np.isfinite(net.heading_sigma).all()
    for j in np.flatnonzero(np.abs(sim.true_eops[:, 3]) > 0):
        true = np.asarray(compensator_reading(jnp.asarray(sim.true_eops[j])))
        assert np.all(np.abs(net.levelling[j] - true) < 5 * 10 * ARCSEC)
    model = tj.CalibrationModel(
        tj.Scanner(aps="physical"), ap_priors={"C0": (180 * ARCSEC, 5 * ARCSEC)}
    )
    res = tj.calibrate(net, model)
    assert res.result == 0, res.message
    assert res.to_dict()["redundancy"]["total"]["sum"] == pytest.approx(res.dof, rel=1e-9)
    # Counting: three per target observation, two tilt readings and one heading per scan, one
    # prior; the datum defect is 3 (the heading fixes the rotation about the vertical).
    n_s = len(net.scans)
    assert res.n_observations == 3 * net.observations.shape[0] + 3 * n_s + 1
    assert res.dof == res.n_observations - res.n_unknowns + 3
    assert all(0 < c["redundancy"] < 1 for c in res.weighted_constraints())


def test_heading_without_tilt_readings_is_refused():
    sim = tj.simulate(tj.Room(n_targets=36), seed=1, levelling=False, sigma_heading=20 * ARCSEC)
    with pytest.raises(ValueError, match="observed kappa but no scan has tilt readings"):
        tj.calibrate(sim.network, tj.CalibrationModel(tj.Scanner()))


def test_orientation_argument_is_checked():
    sim = tj.simulate(tj.Room(n_targets=36), seed=1)
    t = tj.read_observations  # noqa: F841  (public reader exists)
    net = sim.network
    args = ([net.scans[j] for j in net.scan_index], [net.targets[t] for t in net.target_index])
    with pytest.raises(ValueError, match="kappa has no sigma_kappa"):
        tj.make_network(*args, net.observations, orientation={"S1": {"kappa": 0.1}})
    with pytest.raises(ValueError, match="both omega and phi"):
        tj.make_network(
            *args, net.observations, orientation={"S1": {"omega": 0.1, "sigma_omega": 1e-4}}
        )
    with pytest.raises(ValueError, match="within 90 deg"):
        tj.make_network(
            *args,
            net.observations,
            orientation={"S1": {"omega": 2.0, "phi": 0.0, "sigma_omega": 1e-4, "sigma_phi": 1e-4}},
        )
    with pytest.raises(ValueError, match="levelling and orientation"):
        tj.make_network(
            *args,
            net.observations,
            levelling={"S1": {"sigma_omega": 1e-4, "sigma_phi": 1e-4}},
            orientation={"S1": {"omega": 0.5, "phi": 0.0, "sigma_omega": 1e-4, "sigma_phi": 1e-4}},
        )
    ok = tj.make_network(
        *args,
        net.observations,
        orientation={
            "S5": {
                "omega": -0.78,
                "phi": 0.01,
                "sigma_omega": 1e-4,
                "sigma_phi": 1e-4,
                "kappa": 1.4,
                "sigma_kappa": 2e-4,
            }
        },
    )
    j = ok.scans.index("S5")
    assert ok.levelling[j, 0] == -0.78 and ok.heading[j] == 1.4 and ok.heading_sigma[j] == 2e-4
    with pytest.raises(ValueError, match="AP prior 'B6'"):
        tj.calibrate(
            sim.network, tj.CalibrationModel(tj.Scanner(aps="A0"), ap_priors={"B6": (0.0, 1e-5)})
        )
    with pytest.raises(ValueError, match="sigma positive"):
        tj.CalibrationModel(ap_priors={"B6": (0.0, 0.0)})


def test_priors_from_text_csv_and_result_json(tmp_path):
    name, v, s = tj.parse_ap_prior("B6=40arcsec+-5arcsec")
    assert name == "B6" and v == pytest.approx(40 * ARCSEC) and s == pytest.approx(5 * ARCSEC)
    assert tj.parse_ap_prior("A0 = -0.6mm ± 0.05")[1:] == pytest.approx((-0.6e-3, 0.05e-3))
    assert tj.parse_ap_prior("A1=12ppm+-3ppm")[1:] == pytest.approx((12e-6, 3e-6))
    assert tj.parse_ap_prior("B6[inst1]=0.001+-0.0001")[0] == "B6[inst1]"
    for bad, msg in (
        ("B6=40mm+-5mm", "does not fit B6"),
        ("B6=40", "expected NAME"),
        ("Q9=1+-1", "unknown AP"),
    ):
        with pytest.raises(ValueError, match=msg):
            tj.parse_ap_prior(bad)
    csv = tmp_path / "priors.csv"
    csv.write_text("ap,value,sigma,unit\nB6,40,5,arcsec\nA0,-0.6,0.05,mm\n")
    got = tj.read_ap_priors(csv)
    assert set(got) == {"B6", "A0"}
    assert got["B6"] == pytest.approx((40 * ARCSEC, 5 * ARCSEC))
    assert got["A0"] == pytest.approx((-0.6e-3, 0.05e-3))
    csv.write_text("ap,value,sigma,unit\nB6,40,5,mm\n")
    with pytest.raises(ValueError, match="priors.csv, line 2: unit 'mm' does not fit B6"):
        tj.read_ap_priors(csv)
    res_json = tmp_path / "cal.json"
    res_json.write_text(
        json.dumps(
            {"aps": {"B6": {"value": 1e-4, "sigma": 2e-5}, "A1": {"value": None, "sigma": None}}}
        )
    )
    assert tj.read_ap_priors(res_json) == {"B6": (1e-4, 2e-5)}


def test_scans_csv_kappa_columns(tmp_path):
    path = tmp_path / "scans.csv"
    path.write_text(
        "scan,omega_deg,phi_deg,sigma_omega_arcsec,sigma_phi_arcsec,kappa_deg,sigma_kappa_arcsec\n"
        "S1,0.01,-0.02,10,10,,\n"
        "S2,-45,0.5,10,10,80,30\n"
        "S3,,,,,120,30\n"
    )
    scans = tj.read_scans(path)
    assert "kappa" not in scans["S1"]
    assert scans["S2"]["omega"] == pytest.approx(-45 * np.pi / 180)
    assert scans["S2"]["kappa"] == pytest.approx(80 * np.pi / 180)
    assert scans["S3"] == pytest.approx({"kappa": 120 * np.pi / 180, "sigma_kappa": 30 * ARCSEC})
    path.write_text("scan,kappa_deg\nS1,1\n")
    with pytest.raises(ValueError, match="sigma_kappa"):
        tj.read_scans(path)
    path.write_text("scan,kappa_deg,sigma_kappa_arcsec\nS1,1,\n")
    with pytest.raises(ValueError, match="kappa but no sigma_kappa"):
        tj.read_scans(path)


def test_constraints_through_the_command_line(tmp_path, capsys):
    obs, scans, out = tmp_path / "obs.csv", tmp_path / "scans.csv", tmp_path / "cal.json"
    args = [
        "simulate",
        "--out",
        str(obs),
        "--scans-out",
        str(scans),
        "--targets",
        "36",
        "--seed",
        "3",
    ]
    assert main(args + ["--sigma-tilt-arcsec", "10", "--sigma-heading-arcsec", "30"]) == 0
    header = scans.read_text().splitlines()[0]
    assert "kappa_arcsec" in header and "sigma_kappa_arcsec" in header
    priors = tmp_path / "priors.csv"
    priors.write_text("ap,value,sigma,unit\nB7,180,5,arcsec\n")
    code = main(
        [
            "calibrate",
            str(obs),
            "--scans",
            str(scans),
            "--no-vce",
            "--ap-prior",
            "B6=180arcsec+-5arcsec",
            "--ap-priors",
            str(priors),
            "--json",
            str(out),
        ]
    )
    assert code == 0, capsys.readouterr()
    doc = json.loads(out.read_text())
    kinds = [(c["kind"], c["name"]) for c in doc["weighted_constraints"]]
    assert ("ap", "B6") in kinds and ("ap", "B7") in kinds and ("kappa", "S5") in kinds
    assert ("omega", "S5") in kinds  # the tilted scan's tilt reading
    assert doc["redundancy"]["total"]["sum"] == pytest.approx(doc["dof"], rel=1e-9)
    assert "weighted constraints (eq. 7)" in capsys.readouterr().out


def test_each_kind_of_constraint_is_its_own_variance_group():
    """Tilt readings, headings and AP priors each get a variance factor (issue 30 item 2). The
    headings' a priori sigma is stated 3x too large: their factor comes out near 1/9 (with
    r_g = 5 the estimate's 99.9 % bound is 0.46), the correctly stated tilt readings' near 1.
    At convergence the fitted weights make each estimated group's v^T P v / r_g = 1, computed
    here from the adjustment's own constraint residuals and redundancy numbers."""
    sim = tj.simulate(
        tj.Room(n_targets=60),
        aps="physical",
        seed=2,
        sigma_tilt=10 * ARCSEC,
        sigma_heading=20 * ARCSEC,
    )
    net = dataclasses.replace(sim.network, heading_sigma=3 * sim.network.heading_sigma)
    prior = {"C0": (sim.true_aps.get("C0", 0.0), 5 * ARCSEC)}
    model = tj.CalibrationModel(tj.Scanner(aps="physical"), ap_priors=prior)
    tested = tj.self_calibrate(net, model, tj.CalibrationOptions(snooping=tj.SnoopingOptions()))
    assert tested.ok, tested.message
    vc = {v.group: v for v in tested.variance_components}
    assert set(vc) == {"range", "hz", "el", "levelling", "heading", "ap_prior"}
    assert vc["heading"].n == len(net.scans) and vc["ap_prior"].n == 1
    assert vc["heading"].estimated and vc["heading"].factor < 0.46
    assert vc["levelling"].estimated and 0.2 < vc["levelling"].factor < 3.0
    # One prior has r < 1: held at its a priori sigma, and said why.
    assert not vc["ap_prior"].estimated and "redundancy" in vc["ap_prior"].note
    res = tested.calibration
    kinds = {"levelling": ("omega", "phi"), "heading": ("kappa",)}
    for group, names in kinds.items():
        rows = [c for c in res.weighted_constraints() if c["kind"] in names]
        sigma = vc[group].a_priori_sigma * np.sqrt(vc[group].factor)
        omega = sum((c["residual"] / sigma) ** 2 for c in rows)
        r_g = sum(c["redundancy"] for c in rows)
        assert r_g == pytest.approx(vc[group].redundancy, rel=1e-9)
        assert omega / r_g == pytest.approx(1.0, abs=0.05), group
    assert res.to_dict()["redundancy"]["total"]["sum"] == pytest.approx(res.dof, rel=1e-9)
