"""Property-based tests over randomised network designs (issue 12, item 5).

Each drawn network either converges with every AP within 4.5 sigma of its truth and sigma0
consistent with the noise drawn (``noise_scale / sigma_scale``; with VCE, each variance factor),
or returns a result code that names what makes it undeterminable (a target network from one
station: A0). Never "did not converge" on a well-posed design, never a NaN. The designs
(tests/networks.py): rooms of random size; targets on the faces; the faces as planes plus boards
of any orientation 0.3-2 m from the stations, or infinite planes crossing the room; one to three
stations; levelled scans or scans tilted by up to 90 deg towards any azimuth; hybrid or
panoramic; partial visibility (field of view, range, occlusion); noise from 1/40 to 40 times the
a priori sigmas, a priori sigmas scaled by 1e-6 or 1e6; VCE and snooping on and off for targets.

The draws are derandomised (tests/conftest.py) and sizes come from a small set, so that most
draws reuse compiled code. The explicit examples are the failures of the issue: planes crossing
the room near the stations, two scans from one station, noise-free data and sigmas scaled by
1e-6, 1e-9 and 1e6.
"""

import dataclasses

import numpy as np
from helpers import _R
from hypothesis import assume, example, given, settings
from networks import (
    APS,
    DEG,
    N_TARGETS,
    POINTS_PER_PLANE,
    SIX_SCANS,
    ST1,
    ST2,
    Case,
    cases,
    check,
    examples,
    partial_case,
    plane_case,
    point_case,
    run,
)

import tlsjax as tj

#: Two stations, one levelled and one rolled scan each (the shapes of the drawn designs).
FOUR_SCANS = (
    (*ST1, 0.0, 0.0, 0.0),
    (*ST1, -45 * DEG, 0.0, 60 * DEG),
    (*ST2, 0.0, 0.0, 20 * DEG),
    (*ST2, 45 * DEG, 0.0, 80 * DEG),
)
POINT_ROOM = tj.NetworkDesign(
    room=(14.0, 11.0, 3.0),
    scans=FOUR_SCANS,
    n_targets=N_TARGETS,
    common_targets=True,
    aps=APS,
    elevation_limits=(-89.0 * DEG, 89.0 * DEG),
    max_incidence=85.0 * DEG,
)
PLANE_ROOM = tj.NetworkDesign(
    room=(14.0, 11.0, 3.0),
    scans=FOUR_SCANS,
    faces_as_planes=True,
    planes=(
        tj.Board.tilted((5.5, 4.5, 1.5), 2.0, 2.0, azimuth=200 * DEG, tilt=20 * DEG),
        tj.Board.tilted((8.5, 7.5, 1.2), 2.0, 2.0, azimuth=-60 * DEG, tilt=-35 * DEG),
    ),
    points_per_plane=POINTS_PER_PLANE,
    aps=APS,
    elevation_limits=(-89.0 * DEG, 89.0 * DEG),
    max_incidence=88.0 * DEG,
)
#: The issue's room: six faces and three oblique planes crossing it 0.35-2 m from the
#: stations, six scans (two rolled by -45 and +45 deg), 30 points per plane and scan.
OBLIQUE_ROOM = tj.NetworkDesign(
    room=(14.0, 11.0, 3.0),
    scans=SIX_SCANS,
    faces_as_planes=True,
    planes=(
        tj.RoomPlane((1, 1, 1), (5.0, 4.5, 2.1)),
        tj.RoomPlane((-1, 2, 3), (9.5, 7.0, 2.6)),
        tj.RoomPlane((2, -1, 1.5), (7.0, 5.5, 1.5)),
    ),
    points_per_plane=30,
)
#: Two levelled scans from one station: the free targets absorb A0 (and every AP whose effect
#: is the same in both scans).
ONE_STATION = dataclasses.replace(
    POINT_ROOM, scans=((*ST1, 0.0, 0.0, 0.0), (*ST1, 0.0, 0.0, 60 * DEG))
)


def _scaled(design, noise, sigma):
    return dataclasses.replace(design, noise_scale=noise, sigma_scale=sigma)


def _holds(case: Case):
    try:
        sim = tj.simulate_design(case.design, seed=case.seed)
    except ValueError:
        assume(False)  # the design is not a network (e.g. a scan sees too few targets)
    sim, res, tested = run(case, sim)
    check(case, sim, res, tested)


@settings(max_examples=examples(6))
@given(case=cases(point_case))
@example(case=Case(_scaled(POINT_ROOM, 0.0, 1.0)))
@example(case=Case(_scaled(POINT_ROOM, 1.0, 1e-6)))
@example(case=Case(_scaled(POINT_ROOM, 1.0, 1e-9)))
@example(case=Case(_scaled(POINT_ROOM, 1.0, 1e6)))
@example(case=Case(_scaled(POINT_ROOM, 0.0, 1.0), testing=True))
@example(case=Case(_scaled(POINT_ROOM, 1.0, 1e-6), testing=True))
@example(case=Case(ONE_STATION, single_station=True))
def test_point_networks(case):
    _holds(case)


@settings(max_examples=examples(4))
@given(case=cases(plane_case))
@example(case=Case(OBLIQUE_ROOM, kind="planes"))
@example(case=Case(_scaled(PLANE_ROOM, 0.0, 1.0), kind="planes"))
@example(case=Case(_scaled(PLANE_ROOM, 1.0, 1e-6), kind="planes"))
@example(case=Case(_scaled(PLANE_ROOM, 1.0, 1e-9), kind="planes"))
@example(case=Case(_scaled(PLANE_ROOM, 1.0, 1e6), kind="planes"))
def test_plane_networks(case):
    _holds(case)


#: Two planes crossing a room seen from two stations, no targets: with the suite's compile flags
#: the last undamped step of its Gauss-Helmert adjustment was rejected by the cost's rounding
#: from an estimate whose state had not settled, and the loop ran damped to its iteration limit
#: (tlsjax._adjustment._solver: such a candidate, converged and settled, is taken).
_ROUNDING_TIE = Case(
    tj.NetworkDesign(
        room=(9.8, 13.920520593761573, 3.02851045407511),
        scans=(
            (
                1.3,
                1.1572325551289797,
                1.0207803816272314,
                0.8904703622932736,
                0.535528926519926,
                1.4348394828340185,
            ),
            (
                7.096507571019032,
                1.2853461244695825,
                0.8836106281788734,
                -1.4600696177241632,
                -0.4301382057623237,
                0.866294932138945,
            ),
            (
                1.3,
                1.1572325551289797,
                1.0207803816272314,
                0.8065342516103962,
                0.37564530332871643,
                -1.1606516860270815,
            ),
            (
                7.096507571019032,
                1.2853461244695825,
                0.8836106281788734,
                0.09752733310321489,
                -0.2620866280207868,
                0.0128639876771619,
            ),
        ),
        n_targets=0,
        faces_as_planes=True,
        planes=(
            tj.RoomPlane((0.0, 0.0, 1.0), (1.3, 1.1572325551289797, 2.8963205695243137)),
            tj.RoomPlane((0.0, 0.0, -1.0), (1.3, 1.1572325551289797, 0.12778856829462448)),
        ),
        points_per_plane=POINTS_PER_PLANE,
        architecture="hybrid",
        aps=APS,
        levelling=False,
        elevation_limits=(-1.041410838193476, 0.6981317007977318),
        max_range=17.29123446565624,
        noise_scale=0.17644442623118545,
    ),
    seed=57447,
    kind="crossing planes",
)


@settings(max_examples=examples(2))
@given(case=cases(partial_case))
@example(case=_ROUNDING_TIE)
def test_partial_visibility(case):
    _holds(case)


def test_the_checks_can_fail():
    """The outcome check rejects a wrong AP, a sigma0 off the noise and an unnamed defect: the
    converged result of the regression room with its truth moved by 10 sigma, with the noise
    model claimed 2x, and as a one-station design."""
    case = Case(POINT_ROOM)
    sim, res, _ = run(case)
    assert res.result == 0, res.message
    check(case, sim, res)
    i = res.ap_names.index("B7")
    moved = dict(sim.true_aps, B7=sim.true_aps["B7"] + 10 * res.ap_sigmas[i])
    for bad_case, bad_sim in (
        (case, dataclasses.replace(sim, true_aps=moved)),
        (Case(_scaled(POINT_ROOM, 2.0, 1.0)), sim),
        (Case(POINT_ROOM, single_station=True), sim),
    ):
        try:
            check(bad_case, bad_sim, res)
        except AssertionError:
            continue
        raise AssertionError(f"check passed a wrong outcome: {bad_case}")
    assert np.isfinite(res.sigma0)


def test_simulated_design_satisfies_the_models():
    """Noise-free observations of a design, checked with the models written out by hand
    (hybrid, A0 B6 B7 C0; Chow et al. 2013, eqs. 1-3): ``l - Delta(l) = F(X, EOP)`` for targets
    and ``n . (R^T x(l - Delta) + S) = d`` for plane points; the field of view, the range
    limit, the sigma scale and the levelled scans are those of the design."""
    design = dataclasses.replace(
        OBLIQUE_ROOM,
        scans=FOUR_SCANS,
        n_targets=30,
        points_per_plane=10,
        elevation_limits=(-30 * DEG, 60 * DEG),
        max_range=9.0,
        noise_scale=0.0,
        sigma_scale=1e-3,
    )
    sim = tj.simulate_design(design, seed=3)
    net = sim.network
    a = sim.true_aps
    R = np.stack([_R(*e[3:]) for e in sim.true_eops])

    def corrected(l):
        rho, th, al = l[:, 0], l[:, 1], l[:, 2]
        return np.stack(
            [
                rho - a["A0"],
                th - a["B6"] * (1 / np.cos(al) - 1) - a["B7"] * np.tan(al),
                al - a["C0"],
            ],
            axis=1,
        )

    X = sim.true_targets[net.target_index]
    x = np.einsum("nij,nj->ni", R[net.scan_index], X - sim.true_eops[net.scan_index, :3])
    F = np.stack(
        [
            np.linalg.norm(x, axis=1),
            np.mod(np.arctan2(x[:, 1], x[:, 0]), 2 * np.pi),
            np.arctan2(x[:, 2], np.hypot(x[:, 0], x[:, 1])),
        ],
        axis=1,
    )
    np.testing.assert_allclose(corrected(net.observations), F, rtol=0, atol=1e-10)
    assert np.all(F[:, 0] <= 9.0) and np.all(np.abs(F[:, 2] - 15 * DEG) <= 45 * DEG + 1e-9)

    lp = corrected(net.plane_observations)
    xp = lp[:, :1] * np.stack(
        [
            np.cos(lp[:, 2]) * np.cos(lp[:, 1]),
            np.cos(lp[:, 2]) * np.sin(lp[:, 1]),
            np.sin(lp[:, 2]),
        ],
        axis=1,
    )
    Xp = (
        np.einsum("nji,nj->ni", R[net.plane_scan_index], xp)
        + sim.true_eops[net.plane_scan_index, :3]
    )
    P = sim.true_planes[net.plane_index]
    np.testing.assert_allclose(np.einsum("ni,ni->n", P[:, :3], Xp), P[:, 3], rtol=0, atol=1e-9)
    assert len(net.plane_observations) <= 10 * len(net.scans) * len(net.planes)
    # The a priori sigmas are sigma_scale x nominal; levelling only on the untilted scans.
    np.testing.assert_allclose(net.sigmas[:, 1:], 1e-3 * design.sigma_angle, rtol=1e-12)
    assert np.all(net.sigmas[:, 0] >= 1e-3 * design.sigma_range * (1 - 1e-12))
    untilted = np.all(sim.true_eops[:, 3:5] == 0, axis=1)
    np.testing.assert_array_equal(net.is_levelled, untilted)
    np.testing.assert_allclose(net.levelling_sigma[untilted], 1e-3 * design.sigma_levelling)
    assert sim.expected_sigma0 == 0.0
