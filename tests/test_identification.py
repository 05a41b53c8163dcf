"""Model identification (issue 41; SPEC section 7, "candidates the design can estimate, and
alternatives", "prediction"): score tests only of the terms the design can estimate, groups of
alternatives whose correlation after the model is checked against a dense projector, a one-step
estimate beyond the plausibility bounds flagged.

Small rooms (24 targets, six scans) so that each adjustment compiles once for the module.
Private import: the hand-written dense point model of ``tests/helpers.py`` (the oracle).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import dense_residuals

import tlsjax as tj

ARCSEC = np.pi / 180 / 3600
PHYSICAL = "A0 B6 B7 C0"
MODEL = tj.CalibrationModel(tj.Scanner(aps=PHYSICAL))
ROOM = tj.Room(n_targets=24)
#: A small room (1-4 m ranges), where a large range misfit is far from a change of scale.
SMALL = tj.Room(
    length=5, width=4, height=2.5, n_targets=24, stations=((1.5, 1.5, 1.2), (3.5, 2.5, 1.2))
)


@pytest.fixture(scope="module")
def c3_room():
    """The room with C3 (cos alpha, vertical circle eccentricity) in the data, the physical
    model without it; its score tests."""
    s = tj.simulate(ROOM, seed=0, aps=PHYSICAL + " C3")
    res = tj.calibrate(s.network, MODEL)
    return s, res, tj.score_tests(s.network, MODEL, res)


def test_a_range_scale_is_never_proposed_to_a_free_network():
    """A 20 mm range term and a 200 mm offset that the model lacks make the residuals large:
    at the observations A1's column then passes the engine's rank test (its distance from a
    change of scale is the residuals), at the adjusted observations it is exactly a change of
    scale. It is listed as not estimable with that reason, never significant; with two scale
    bars it is a candidate again. A0's one-step estimate (~200 mm) is flagged as implausible."""
    none = tj.CalibrationModel(tj.Scanner(aps="none"))
    true = {"A2": 0.02, "C3": 0.003, "A0": 0.2}
    s = tj.simulate(SMALL, seed=1, aps="A0 A2 C0 B7 C3", true_aps=true)
    tests = tj.score_tests(s.network, none, tj.calibrate(s.network, none))
    a1 = tests.test("A1")
    assert not a1.testable and not a1.significant and "scale" in a1.note
    assert "A1" not in [t.name for t in tests.significant] and tests.best().name != "A1"
    assert [t.name for t in tests.not_estimable] == ["A1"]
    assert "not estimable in this design" in tests.summary() and "A1" in tests.summary()
    doc = tests.to_dict()
    assert doc["not_estimable"][0]["name"] == "A1"
    a0 = tests.test("A0")
    assert a0.significant and a0.plausibility == "warning" and "A0" in a0.plausibility_note
    assert "[warning" in a0.summary()
    bars = tj.simulate(SMALL, seed=1, aps="A0 A2 C0 B7 C3", true_aps=true, scale_bars=2)
    tests = tj.score_tests(bars.network, none, tj.calibrate(bars.network, none))
    assert tests.test("A1").testable


def test_alternatives_are_grouped_by_their_correlation_after_the_model(c3_room):
    """The correlation of two candidates' whitened columns after the model, ``c_i^T Q_vv c_j``
    normalised, from a dense Jacobian of the hand-written model (``Q_vv = I - A A^+``): the
    group's correlation matches it; a pair beyond 0.9 is in one group."""
    s, res, tests = c3_room
    net = s.network
    assert tests.groups and all(len(g) > 1 for g in tests.groups)
    c3 = tests.test("C3")
    assert c3.significant and c3.alternatives  # C3 is in a group (with C5: cos 2 alpha)
    aps = PHYSICAL.split()
    x = np.concatenate([res.target_xyz.reshape(-1), res.eops.reshape(-1), res.ap_values])
    f = lambda x: dense_residuals(x, net, aps, len(net.targets), len(net.scans))
    A = np.asarray(jax.jacfwd(f)(jnp.asarray(x)))
    l = net.observations
    bases = {
        "C3": lambda a: np.cos(a),
        "C5": lambda a: np.cos(2 * a),
        "C1": lambda a: a,
        "C2": lambda a: np.sin(a),
        "C4": lambda a: np.sin(2 * a),
    }
    cols = {}
    for name, b in bases.items():
        c = np.zeros((len(l), 3))
        c[:, 2] = b(l[:, 2]) / net.sigmas[:, 2]
        cols[name] = np.concatenate([c.reshape(-1), np.zeros(A.shape[0] - c.size)])
    proj = lambda c: c - A @ np.linalg.lstsq(A, c, rcond=None)[0]
    r = {n: proj(c) for n, c in cols.items()}
    corr = lambda a, b: abs(r[a] @ r[b]) / np.sqrt((r[a] @ r[a]) * (r[b] @ r[b]))
    group = tests.group_of("C3")
    (other,) = [n for n in group if n != "C3"]
    assert np.isclose(c3.alternative_correlation, corr("C3", other), atol=1e-4)
    names = [n for n in bases if tests.test(n).testable]
    for a in names:
        for b in names:
            if a < b:
                assert corr(a, b) < 0.9 + 1e-4 or b in tests.group_of(a), (a, b, corr(a, b))
    # The summary shows the group with each one's T, and the JSON lists it.
    assert "alternatives" in tests.summary() and f"{other} T = " in tests.summary()
    assert list(group) in tests.to_dict()["alternatives"]
