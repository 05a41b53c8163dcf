"""Geometry, observation model, AP registry, datum and small linear algebra (SPEC sections 1-3, 6).

Every number is checked against an independent source: matrices written out by hand from the
SPEC, central finite differences, closed-form values and identities.

Private imports: the geometry, the AP corrections, the datum and the small linear algebra are
private building blocks, each tested against an independent source.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import tlsjax as tj
from tlsjax import PRESETS, Scanner, register_ap, registered_aps, resolve_aps
from tlsjax._linalg import rank_revealing_cholesky, spd_inverse
from tlsjax._model._aps import GROUPS, ap_corrections, get_ap
from tlsjax._model._datum import move_eop, move_points, null_space_columns
from tlsjax._model._geometry import (
    angles_from_matrix,
    cartesian_from_spherical,
    is_face2,
    rigid_fit,
    rotation_matrix,
    rotation_matrix_column_z,
    spherical_from_cartesian,
    wrap_angle,
)
from tlsjax._model._points import point_geometry, point_misclosure, simulate_point_observations

pytestmark = pytest.mark.internal

DEG = np.pi / 180
ARCSEC = DEG / 3600
FULL_APS = resolve_aps("chow2013") + ("A5", "A6", "A7", "A8", "B11", "B12", "C9", "C10")


# --------------------------------------------------------------------------------------------
# Rotations (SPEC section 1)
# --------------------------------------------------------------------------------------------


def _R1(w):
    return np.array([[1, 0, 0], [0, np.cos(w), np.sin(w)], [0, -np.sin(w), np.cos(w)]])


def _R2(p):
    return np.array([[np.cos(p), 0, -np.sin(p)], [0, 1, 0], [np.sin(p), 0, np.cos(p)]])


def _R3(k):
    return np.array([[np.cos(k), np.sin(k), 0], [-np.sin(k), np.cos(k), 0], [0, 0, 1]])


def _random_angles(rng, n):
    return np.stack(
        [
            rng.uniform(-80, 80, n) * DEG,
            rng.uniform(-80, 80, n) * DEG,
            rng.uniform(-179, 179, n) * DEG,
        ],
        axis=1,
    )


def test_rotation_matrix_is_R3_R2_R1():
    rng = np.random.default_rng(0)
    for w, p, k in _random_angles(rng, 10):
        R_ref = _R3(k) @ _R2(p) @ _R1(w)
        R_jax = np.asarray(rotation_matrix(w, p, k))
        R_np = rotation_matrix(w, p, k, xp=np)
        np.testing.assert_allclose(R_jax, R_ref, atol=1e-15)
        np.testing.assert_allclose(R_np, R_ref, atol=1e-15)
        np.testing.assert_allclose(R_jax @ R_jax.T, np.eye(3), atol=1e-14)
        assert np.isclose(np.linalg.det(R_jax), 1.0, atol=1e-14)
        # The compensator's column written out alone: R e3 of the matrices written out by hand,
        # and bitwise that of the whole matrix (the same products, summed in the same order).
        np.testing.assert_allclose(rotation_matrix_column_z(w, p, k, np), R_ref[:, 2], atol=1e-15)
        assert np.array_equal(rotation_matrix_column_z(w, p, k, np), R_np[:, 2])
        assert np.array_equal(np.asarray(rotation_matrix_column_z(w, p, k)), R_jax[:, 2])


def test_rotation_matrix_hand_values():
    # Each elementary rotation at 90 deg, from the SPEC matrices by hand.
    np.testing.assert_allclose(
        np.asarray(rotation_matrix(0.0, 0.0, np.pi / 2)),
        [[0, 1, 0], [-1, 0, 0], [0, 0, 1]],
        atol=1e-15,
    )
    np.testing.assert_allclose(
        np.asarray(rotation_matrix(np.pi / 2, 0.0, 0.0)),
        [[1, 0, 0], [0, 0, 1], [0, -1, 0]],
        atol=1e-15,
    )
    np.testing.assert_allclose(
        np.asarray(rotation_matrix(0.0, np.pi / 2, 0.0)),
        [[0, 0, -1], [0, 1, 0], [1, 0, 0]],
        atol=1e-15,
    )


def test_angles_from_matrix_round_trip():
    rng = np.random.default_rng(1)
    for ang in _random_angles(rng, 50):
        R = _R3(ang[2]) @ _R2(ang[1]) @ _R1(ang[0])
        np.testing.assert_allclose(angles_from_matrix(R), ang, atol=1e-12)


# --------------------------------------------------------------------------------------------
# Spherical observations, faces, wrapping
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("xp", [np, jnp])
def test_spherical_hand_values(xp):
    pts = np.array(
        [
            [0.0, 1.0, 1.0],
            [1.0, 0.0, 0.0],
            [-2.0, 0.0, 0.0],
            [0.0, -3.0, 0.0],
            [1.0, 1.0, -np.sqrt(2.0)],
        ]
    )
    expected = np.array(
        [
            [np.sqrt(2.0), 90 * DEG, 45 * DEG],
            [1.0, 0.0, 0.0],
            [2.0, np.pi, 0.0],
            [3.0, 270 * DEG, 0.0],
            [2.0, 45 * DEG, -45 * DEG],
        ]
    )
    got = np.asarray(spherical_from_cartesian(xp.asarray(pts), xp=xp))
    np.testing.assert_allclose(got, expected, atol=1e-15)
    # Panoramic face 2 of (0, -1, 1): hybrid (270 deg, 45 deg) -> (90 deg, 135 deg).
    got2 = np.asarray(
        spherical_from_cartesian(xp.asarray([0.0, -1.0, 1.0]), xp.asarray(True), xp=xp)
    )
    np.testing.assert_allclose(got2, [np.sqrt(2.0), 90 * DEG, 135 * DEG], atol=1e-15)


def test_spherical_cartesian_round_trip_both_faces():
    rng = np.random.default_rng(2)
    x = rng.normal(size=(200, 3)) * rng.uniform(0.5, 20, size=(200, 1))
    l = np.asarray(spherical_from_cartesian(jnp.asarray(x)))
    assert np.all((l[:, 1] >= 0) & (l[:, 1] < 2 * np.pi))
    assert np.all(np.abs(l[:, 2]) <= np.pi / 2)
    np.testing.assert_allclose(np.linalg.norm(x, axis=1), l[:, 0], rtol=1e-15)
    np.testing.assert_allclose(np.asarray(cartesian_from_spherical(jnp.asarray(l))), x, atol=1e-13)
    np.testing.assert_allclose(cartesian_from_spherical(l, xp=np), x, atol=1e-13)

    # Panoramic: directions with hybrid theta >= pi are observed in face 2.
    face2 = l[:, 1] >= np.pi
    assert face2.any() and (~face2).any()
    lp = np.asarray(spherical_from_cartesian(jnp.asarray(x), jnp.asarray(face2)))
    np.testing.assert_allclose(lp[face2, 1], l[face2, 1] - np.pi, atol=1e-15)
    np.testing.assert_allclose(lp[face2, 2], np.pi - l[face2, 2], atol=1e-15)
    np.testing.assert_allclose(lp[~face2], l[~face2], atol=0)
    # SPEC ranges of a panoramic scanner: theta in [0, pi), alpha in [-pi/2, 3pi/2).
    assert np.all((lp[:, 1] >= 0) & (lp[:, 1] < np.pi))
    assert np.all((lp[:, 2] >= -np.pi / 2) & (lp[:, 2] < 1.5 * np.pi))
    np.testing.assert_array_equal(
        np.asarray(is_face2(jnp.asarray(lp[:, 2]))), face2 & (np.abs(l[:, 2]) < np.pi / 2)
    )
    np.testing.assert_allclose(np.asarray(cartesian_from_spherical(jnp.asarray(lp))), x, atol=1e-13)


def test_wrap_angle():
    cases = {
        0.0: 0.0,
        np.pi: np.pi,
        -np.pi: np.pi,
        3 * np.pi: np.pi,
        -3 * np.pi: np.pi,
        2 * np.pi: 0.0,
        2 * np.pi - 1e-3: -1e-3,
        2 * np.pi + 1e-3: 1e-3,
        -2 * np.pi + 1e-3: 1e-3,
        np.pi + 1e-9: -np.pi + 1e-9,
        -np.pi + 1e-9: -np.pi + 1e-9,
        1.0: 1.0,
        -1.0: -1.0,
    }
    a = np.array(list(cases))
    got = np.asarray(wrap_angle(jnp.asarray(a)))
    np.testing.assert_allclose(got, np.array(list(cases.values())), atol=1e-12)
    rng = np.random.default_rng(3)
    a = rng.uniform(-50, 50, 10000)
    w = np.asarray(wrap_angle(jnp.asarray(a)))
    assert np.all((w > -np.pi) & (w <= np.pi))
    turns = (a - w) / (2 * np.pi)
    np.testing.assert_allclose(turns, np.round(turns), atol=1e-12)


# --------------------------------------------------------------------------------------------
# Jacobian blocks of the point model vs central finite differences
# --------------------------------------------------------------------------------------------


def _central_fd(f, x, step):
    x = np.asarray(x, dtype=float)
    cols = []
    for k in range(x.size):
        h = step * max(1.0, abs(x[k]))
        xp, xm = x.copy(), x.copy()
        xp[k] += h
        xm[k] -= h
        cols.append((np.asarray(f(xp)) - np.asarray(f(xm))) / (2 * h))
    return np.stack(cols, axis=-1)


def _coefficients(rng, names):
    c = []
    for n in names:
        u = get_ap(n).unit
        c.append(rng.normal() * (0.01 if u == "m" else (200 * ARCSEC if u == "rad" else 5e-4)))
    return np.array(c)


@pytest.mark.parametrize("architecture", ["hybrid", "panoramic"])
def test_point_misclosure_jacobian_matches_finite_differences(architecture):
    rng = np.random.default_rng(4)
    scanner = Scanner(architecture=architecture, aps=FULL_APS, unit_length=1.1, unit_length_2=0.55)
    names = scanner.aps
    sl = ((0, len(names)),)
    f = jax.jit(lambda X, eop, c, l: point_misclosure(X, eop, c, l, (scanner,), (names,), sl, 0))
    jac = jax.jit(
        jax.jacfwd(
            lambda X, eop, c, l: point_misclosure(X, eop, c, l, (scanner,), (names,), sl, 0),
            argnums=(0, 1, 2),
        )
    )
    seen_face2 = False
    for trial in range(8):
        eop = np.concatenate(
            [rng.uniform(-2, 2, 3), rng.uniform(-0.5, 0.5, 2), rng.uniform(-3, 3, 1)]
        )
        R = rotation_matrix(*eop[3:], xp=np)
        # A scanner-space direction away from the wrap lines and the poles; every other trial
        # behind the scanner (hybrid theta >= pi: face 2 of a panoramic scanner).
        th = rng.uniform(200, 340) * DEG if trial % 2 else rng.uniform(20, 160) * DEG
        al = rng.uniform(-60, 60) * DEG
        rho = rng.uniform(2, 15)
        x = rho * np.array([np.cos(al) * np.cos(th), np.cos(al) * np.sin(th), np.sin(al)])
        X = R.T @ x + eop[:3]
        face2 = architecture == "panoramic" and th >= np.pi
        seen_face2 |= face2
        l_geo = np.asarray(
            spherical_from_cartesian(
                jnp.asarray(x), jnp.asarray(face2) if architecture == "panoramic" else None
            )
        )
        l_obs = l_geo + np.array([1e-3, 50 * ARCSEC, -50 * ARCSEC])
        c = _coefficients(rng, names)
        JX, Je, Jc = (np.asarray(J) for J in jac(X, eop, c, l_obs))
        FX = _central_fd(lambda v: f(v, eop, c, l_obs), X, 1e-6)
        Fe = _central_fd(lambda v: f(X, v, c, l_obs), eop, 1e-6)
        Fc = _central_fd(lambda v: f(X, eop, v, l_obs), c, 1e-6)
        # Central differences with step h carry a rounding error of about eps |f| / h, f the
        # observations (ranges to 15 m): a floor of some 1e-8 under the truncation error.
        floor = 8 * np.finfo(np.float64).eps * np.abs(l_obs).max() / 1e-6
        for J, F in ((JX, FX), (Je, Fe), (Jc, Fc)):
            np.testing.assert_allclose(J, F, rtol=1e-6, atol=floor)
        # The AP block is exactly the basis of each term (linear in the coefficients).
        assert np.abs(Jc).max() > 0.1
        # Misclosure is small here (l_obs near F + Delta), i.e. nothing wrapped by 2 pi.
        assert np.all(np.abs(np.asarray(f(X, eop, c, l_obs))) < 0.1)
    assert seen_face2 == (architecture == "panoramic")


def test_point_misclosure_selects_instrument_block():
    """Two instruments: the block of the other instrument has zero derivative."""
    s1 = Scanner(aps="A0 B6 C0")
    s2 = Scanner(aps="A0 B7")
    X = np.array([3.0, 4.0, 1.0])
    eop = np.array([0.1, -0.2, 0.3, 0.01, -0.02, 0.5])
    l = np.asarray(spherical_from_cartesian(point_geometry(jnp.asarray(X), jnp.asarray(eop))))
    c = np.array([1e-3, 2e-4, 3e-4, 4e-3, 5e-4])
    jac = jax.jit(
        jax.jacfwd(
            lambda c, inst: point_misclosure(
                X, eop, c, l, (s1, s2), (s1.aps, s2.aps), ((0, 3), (3, 5)), inst
            )
        )
    )
    for inst, other in ((0, slice(3, 5)), (1, slice(0, 3))):
        J = np.asarray(jac(c, inst))
        assert np.all(J[:, other] == 0)
        assert np.abs(J).sum() > 0
    # Instrument 1 with A0 = 4 mm: the range misclosure is exactly that, B7 = 5e-4 rad * tan(alpha).
    f = np.asarray(point_misclosure(X, eop, c, l, (s1, s2), (s1.aps, s2.aps), ((0, 3), (3, 5)), 1))
    np.testing.assert_allclose(f, [4e-3, 5e-4 * np.tan(l[2]), 0.0], atol=1e-15)


# --------------------------------------------------------------------------------------------
# AP registry (SPEC section 3)
# --------------------------------------------------------------------------------------------

SPEC_GROUPS = {
    **{f"A{i}": "range" for i in range(9)},
    **{f"B{i}": "hz" for i in range(1, 13)},
    **{f"C{i}": "el" for i in range(11)},
}


def _spec_basis(name, r, t, a, arch, U, U2):
    """The basis functions of SPEC section 3, written out independently (numpy)."""
    table = {
        "A0": np.ones_like(r),
        "A1": r,
        "A2": np.sin(a),
        "A3": np.sin(4 * np.pi * r / U),
        "A4": np.cos(4 * np.pi * r / U),
        "A5": np.sin(4 * np.pi * r / U2),
        "A6": np.cos(4 * np.pi * r / U2),
        "A7": np.sin(4 * t),
        "A8": np.cos(4 * t),
        "B1": t,
        "B2": np.sin(t),
        "B3": np.cos(t),
        "B4": np.sin(2 * t),
        "B5": np.cos(2 * t),
        "B6": 1 / np.cos(a) - (1.0 if arch == "hybrid" else 0.0),
        "B7": np.tan(a),
        "B8": 1 / r,
        "B9": np.sin(a),
        "B10": np.cos(a),
        "B11": np.sin(3 * a),
        "B12": np.sin(4 * a),
        "C0": np.ones_like(r),
        "C1": a,
        "C2": np.sin(a),
        "C3": np.cos(a),
        "C4": np.sin(2 * a),
        "C5": np.cos(2 * a),
        "C6": 1 / r,
        "C7": np.sin(t),
        "C8": np.cos(t),
        "C9": np.sin(3 * t),
        "C10": np.cos(3 * t),
    }
    return table[name]


def test_registry_has_every_spec_term_with_its_group():
    names = set(registered_aps())
    assert set(SPEC_GROUPS) <= names
    for name, group in SPEC_GROUPS.items():
        assert get_ap(name).group == group, name
    assert get_ap("A1").unit == "1" and get_ap("A0").unit == "m" and get_ap("B6").unit == "rad"
    assert get_ap("B8").unit == "m" and get_ap("C6").unit == "m" and get_ap("C1").unit == "1"


@pytest.mark.parametrize("architecture", ["hybrid", "panoramic"])
def test_ap_corrections_single_terms(architecture):
    rng = np.random.default_rng(5)
    scanner = Scanner(architecture=architecture, aps=(), unit_length=1.3, unit_length_2=0.7)
    n = 64
    r = rng.uniform(1, 20, n)
    t = rng.uniform(0, np.pi if architecture == "panoramic" else 2 * np.pi, n)
    if architecture == "panoramic":
        a = (
            np.where(rng.uniform(size=n) < 0.5, rng.uniform(-80, 80, n), rng.uniform(100, 260, n))
            * DEG
        )
    else:
        a = rng.uniform(-80, 80, n) * DEG
    l = np.stack([r, t, a], axis=1)
    for name, group in SPEC_GROUPS.items():
        c = 0.37
        got = np.asarray(ap_corrections(jnp.asarray([c]), (name,), jnp.asarray(l), scanner))
        assert got.shape == (n, 3)
        g = GROUPS.index(group)
        expected = np.zeros((n, 3))
        expected[:, g] = c * _spec_basis(name, r, t, a, architecture, 1.3, 0.7)
        # atol: the cyclic terms' argument 4 pi rho / U (up to ~200 rad) carries ~1e-14 rounding.
        np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-13, err_msg=name)
    # The corrections of several terms add up.
    names = ("A0", "A3", "B6", "B8", "C0", "C9")
    coeffs = np.array([1e-3, 2e-3, 3e-4, 4e-3, 5e-4, 6e-4])
    got = np.asarray(ap_corrections(jnp.asarray(coeffs), names, jnp.asarray(l), scanner))
    expected = np.zeros((n, 3))
    for name, c in zip(names, coeffs):
        expected[:, GROUPS.index(SPEC_GROUPS[name])] += c * _spec_basis(
            name, r, t, a, architecture, 1.3, 0.7
        )
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-15)


def test_presets_and_parsing():
    chow = PRESETS["chow2013"]
    assert len(chow) == 24
    assert set(chow) == {f"A{i}" for i in range(5)} | {f"B{i}" for i in range(1, 11)} | {
        f"C{i}" for i in range(9)
    }
    assert resolve_aps("chow2013") == chow
    assert resolve_aps("A0, B6 C0") == ("A0", "B6", "C0")
    assert resolve_aps(["C0", "A0"]) == ("C0", "A0")
    assert resolve_aps("physical, A1") == ("A0", "B6", "B7", "C0", "A1")
    assert resolve_aps("A2,physical") == ("A2", "A0", "B6", "B7", "C0")
    assert resolve_aps(None) == () and resolve_aps("none") == ()
    with pytest.raises(ValueError, match="A0"):
        resolve_aps("A0 B6, physical")
    with pytest.raises(ValueError, match="C0"):
        resolve_aps(["C0", "C0"])
    with pytest.raises(ValueError, match="Q9"):
        resolve_aps("A0 Q9")
    assert Scanner(aps="physical").aps == ("A0", "B6", "B7", "C0")


# --------------------------------------------------------------------------------------------
# Simulated observations are consistent with the model
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("architecture", ["hybrid", "panoramic"])
def test_simulated_observations_close_the_model(architecture):
    rng = np.random.default_rng(6)
    aps = "A0 A1 A3 A4 B1 B6 B7 B8 C0 C1 C6 C9"
    scanner = Scanner(architecture=architecture, aps=aps, unit_length=0.9)
    names = scanner.aps
    # The papers' true values (SPEC section 8): 10 mm range terms, 3' angular terms, B8/C6 10 mm.
    c = jnp.asarray(
        [
            tj._simulation._room.default_true_value(n) * s
            for n, s in zip(names, rng.choice([-1.0, 1.0], len(names)))
        ]
    )
    sl = ((0, len(names)),)
    eop = np.array([1.0, 2.0, 1.5, 0.05, -0.03, 0.7])
    u = rng.normal(size=(40, 3))
    X = np.asarray(eop[:3]) + u / np.linalg.norm(u, axis=1, keepdims=True) * rng.uniform(
        1.5, 20, (40, 1)
    )
    x = np.asarray(jax.vmap(lambda p: point_geometry(p, jnp.asarray(eop)))(jnp.asarray(X)))
    hyb = spherical_from_cartesian(x, xp=np)
    face2 = hyb[:, 1] >= np.pi if architecture == "panoramic" else np.zeros(len(X), bool)
    sim = jax.vmap(
        lambda Xi, f2: simulate_point_observations(
            Xi,
            jnp.asarray(eop),
            c,
            (scanner,),
            (names,),
            sl,
            0,
            jnp.zeros(3),
            f2 if architecture == "panoramic" else None,
        )
    )
    l = sim(jnp.asarray(X), jnp.asarray(face2))
    mis = np.asarray(
        jax.vmap(
            lambda Xi, li: point_misclosure(
                Xi, jnp.asarray(eop), c, li, (scanner,), (names,), sl, 0
            )
        )(jnp.asarray(X), l)
    )
    assert np.abs(mis).max() < 1e-12
    # The APs really moved the observations away from the geometry (cyclic range terms included).
    l_geo = spherical_from_cartesian(x, face2 if architecture == "panoramic" else None, xp=np)
    d = np.asarray(l) - l_geo
    assert np.abs(d[:, 0]).max() > 1e-3 and np.abs(d[:, 1:]).max() > 10 * ARCSEC
    # Independent check of the range equation: rho_obs = |x| + sum range terms at l_obs.
    lo = np.asarray(l)
    cc = np.asarray(c)
    expected_range = np.linalg.norm(x, axis=1) + sum(
        cc[k] * _spec_basis(n, lo[:, 0], lo[:, 1], lo[:, 2], architecture, 0.9, 0.6)
        for k, n in enumerate(names)
        if SPEC_GROUPS[n] == "range"
    )
    np.testing.assert_allclose(lo[:, 0], expected_range, atol=1e-12)


# --------------------------------------------------------------------------------------------
# Datum (SPEC section 6)
# --------------------------------------------------------------------------------------------

# Jitted once per action: eager vmap(jacfwd) dispatches many tiny kernels and is slow.
_null_space = jax.jit(null_space_columns, static_argnums=(0, 2))


def _skew(v):
    return np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])


def test_null_space_columns_of_points():
    rng = np.random.default_rng(7)
    X = rng.normal(size=(5, 3)) * 4
    G = np.asarray(_null_space(move_points, jnp.asarray(X), tuple(range(6))))
    assert G.shape == (5, 3, 6)
    for i in range(5):
        np.testing.assert_allclose(G[i], np.hstack([np.eye(3), -_skew(X[i])]), atol=1e-15)
    # Column selection (levelled datum: tx, ty, tz, rz).
    G4 = np.asarray(_null_space(move_points, jnp.asarray(X), (0, 1, 2, 5)))
    np.testing.assert_allclose(G4, G[..., [0, 1, 2, 5]], atol=0)
    # A scale bar (two points stacked) gets both points' rows.
    P = X[:2].reshape(1, 6)
    Gb = np.asarray(_null_space(move_points, jnp.asarray(P), tuple(range(6))))
    np.testing.assert_allclose(Gb[0], np.vstack([G[0], G[1]]), atol=1e-15)


def test_move_eop_columns_keep_scanner_coordinates():
    rng = np.random.default_rng(8)
    eops = np.concatenate(
        [rng.normal(size=(4, 3)) * 3, rng.uniform(-0.6, 0.6, (4, 2)), rng.uniform(-3, 3, (4, 1))],
        axis=1,
    )
    He = np.asarray(_null_space(move_eop, jnp.asarray(eops), tuple(range(6))))  # (4, 6, 6)
    X = rng.normal(size=(6, 3)) * 5
    Hx = np.asarray(_null_space(move_points, jnp.asarray(X), tuple(range(6))))  # (6, 3, 6)

    @jax.jit
    def changes(eps):
        """|x(X + eps dX, eop + eps deop) - x(X, eop)| for every scan, motion column and point,
        and the same with the pose left alone (shape (2, scans, 6, points))."""

        def one(eop, He_j, X_i, Hx_i, col, move_pose):
            base = point_geometry(X_i, eop)
            moved = point_geometry(X_i + eps * Hx_i[:, col], eop + move_pose * eps * He_j[:, col])
            return jnp.linalg.norm(moved - base)

        f = jax.vmap(one, in_axes=(None, None, 0, 0, None, None))  # points
        f = jax.vmap(f, in_axes=(None, None, None, None, 0, None))  # columns
        f = jax.vmap(f, in_axes=(0, 0, None, None, None, None))  # scans
        cols = jnp.arange(6)
        return jnp.stack([f(eops, He, X, Hx, cols, 1.0), f(eops, He, X, Hx, cols, 0.0)])

    (d1, alone), (d2, _) = np.asarray(changes(1e-4)), np.asarray(changes(2e-4))
    scale = 1 + np.linalg.norm(X, axis=1).max() + np.linalg.norm(eops[:, :3], axis=1).max()
    # Second order: at most ~|x| eps^2, and it scales like eps^2 (or sits at rounding level).
    assert d1.max() < 100 * 1e-8 * scale
    assert np.all(d2 < 5 * d1 + 1e-12)
    assert d2.max() > 2 * d1.max()
    # Moving the point alone changes x at first order: the check can fail.
    assert alone.min() > 1e-6


# --------------------------------------------------------------------------------------------
# Small linear algebra and the approximate values
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("p", [3, 4, 6])
def test_spd_inverse_matches_numpy(p):
    rng = np.random.default_rng(10 + p)
    M = rng.normal(size=(7, p, p))
    A = M @ np.swapaxes(M, -1, -2) + 0.1 * np.eye(p)
    got = np.asarray(spd_inverse(jnp.asarray(A)))
    np.testing.assert_allclose(
        got, np.linalg.inv(A), rtol=1e-9, atol=1e-9 * np.abs(np.linalg.inv(A)).max()
    )
    np.testing.assert_allclose(got @ A, np.broadcast_to(np.eye(p), A.shape), atol=1e-9)


def test_rank_revealing_cholesky_flags_dependent_column():
    rng = np.random.default_rng(11)
    B = rng.normal(size=(30, 6))
    B[:, 3] = 0.6 * B[:, 0] - 1.7 * B[:, 2]  # exactly dependent on earlier columns
    B /= np.linalg.norm(B, axis=0)
    A = B.T @ B  # unit diagonal, rank 5
    L, dep, piv = rank_revealing_cholesky(jnp.asarray(A), jnp.zeros(6, dtype=bool), 1e-8)
    L, dep, piv = np.asarray(L), np.asarray(dep), np.asarray(piv)
    np.testing.assert_array_equal(dep, [False, False, False, True, False, False])
    assert abs(piv[3]) < 1e-12 and np.all(piv[~dep] > 1e-3)
    ind = ~dep
    np.testing.assert_allclose((L @ L.T)[np.ix_(ind, ind)], A[np.ix_(ind, ind)], atol=1e-13)
    np.testing.assert_array_equal(np.triu(L, 1), 0)
    # The Cholesky factor of the independent block is the textbook one.
    np.testing.assert_allclose(
        L[np.ix_(ind, ind)], np.linalg.cholesky(A[np.ix_(ind, ind)]), atol=1e-13
    )
    # A fixed parameter is treated like a dependent one.
    _, dep_f, _ = rank_revealing_cholesky(
        jnp.asarray(A), jnp.asarray([False, True, False, False, False, False]), 1e-8
    )
    np.testing.assert_array_equal(np.asarray(dep_f), [False, True, False, True, False, False])


def test_rigid_fit_recovers_rotation_and_translation():
    rng = np.random.default_rng(12)
    for ang in _random_angles(rng, 5):
        R = _R3(ang[2]) @ _R2(ang[1]) @ _R1(ang[0])
        t = rng.normal(size=3) * 10
        src = rng.normal(size=(9, 3)) * 5
        dst = src @ R.T + t
        R_est, t_est = rigid_fit(src, dst)
        np.testing.assert_allclose(R_est, R, atol=1e-12)
        np.testing.assert_allclose(t_est, t, atol=1e-11)
    # A reflection is never returned: mirrored data still gives a proper rotation.
    R_est, _ = rigid_fit(src, src * np.array([1.0, 1.0, -1.0]))
    assert np.isclose(np.linalg.det(R_est), 1.0)


# --------------------------------------------------------------------------------------------
# A user-registered term behaves exactly like a built-in one
# --------------------------------------------------------------------------------------------


def test_user_term_equals_builtin_in_calibration():
    term = register_ap(
        "Zuser1",
        "el",
        lambda r, t, a, s: jnp.ones_like(a),
        "rad",
        "user copy of C0",
        overwrite=True,
    )
    assert term.group == "el" and "Zuser1" in registered_aps()
    assert resolve_aps("A0 Zuser1") == ("A0", "Zuser1")
    sim = tj.simulate(tj.Room(n_targets=24), seed=3, aps="A0 B6 B7 C0", tilted=True)
    res_c0 = tj.calibrate(sim.network, tj.CalibrationModel(tj.Scanner(aps="A0 B6 B7 C0")))
    res_u = tj.calibrate(sim.network, tj.CalibrationModel(tj.Scanner(aps="A0 B6 B7 Zuser1")))
    assert res_c0.ok and res_u.ok, (res_c0.message, res_u.message)
    assert res_u.ap_names == ("A0", "B6", "B7", "Zuser1") and res_u.ap_units[3] == "rad"
    assert np.all(np.isfinite(res_c0.ap_values)) and np.all(np.isfinite(res_c0.ap_sigmas))
    np.testing.assert_allclose(res_u.ap_values, res_c0.ap_values, rtol=1e-10)
    np.testing.assert_allclose(res_u.ap_sigmas, res_c0.ap_sigmas, rtol=1e-10)
    assert np.isclose(res_u.sigma0, res_c0.sigma0, rtol=1e-10)
    np.testing.assert_allclose(res_u.eops, res_c0.eops, rtol=1e-10, atol=1e-12)
    # And the estimate is the simulated truth (180") within a few sigma.
    i = res_u.ap_names.index("Zuser1")
    assert abs(res_u.ap_values[i] - sim.true_aps["C0"]) < 5 * res_u.ap_sigmas[i]


@pytest.mark.parametrize("r", [5, 40, 59])
def test_forward_substitution_and_cholesky_inverse_match_numpy(r):
    from tlsjax._linalg import cholesky_inverse, forward_substitution

    A = np.random.default_rng(r).normal(size=(r, r))
    A = A @ A.T + r * np.eye(r)
    L = np.linalg.cholesky(A)
    B = np.random.default_rng(1).normal(size=(r, 7))
    np.testing.assert_allclose(
        np.asarray(forward_substitution(jnp.asarray(L), jnp.asarray(B))),
        np.linalg.solve(L, B),
        rtol=1e-10,
        atol=1e-12,
    )
    np.testing.assert_allclose(
        np.asarray(cholesky_inverse(jnp.asarray(L))), np.linalg.inv(A), rtol=1e-9, atol=1e-12
    )
