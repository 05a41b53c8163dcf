"""Nothing eager around the engine (GUIDE, issue 37): a second adjustment of the same shape runs
its compiled programs and nothing else. Every JAX operation dispatched one at a time on the
host (an un-jitted ``vmap``, a ``jnp`` call on the result) runs a program of its own and costs
about 10 us; :mod:`dispatch` counts the programs executed, and these tests fail on any but the
engine's. Counts, not times: they hold on a loaded machine."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from dispatch import compiled_programs, executed_programs

import tlsjax as tj

#: The compiled programs of the engine: the adjustment with its quality (``run``), the score
#: tests' reduced system (``system``) and the held-out scans' corrections of the
#: cross-validation (``corrections``, one run per fold).
ENGINE = {"jit(run)", "jit(system)", "jit(corrections)"}


@pytest.fixture(scope="module")
def network():
    return tj.simulate(tj.Room(n_targets=24), seed=3, aps="A0 B6 B7 C0", tilted=True).network


def _eager(counts):
    return {name: n for name, n in counts.items() if name not in ENGINE}


def test_the_counter_sees_an_eager_operation_and_a_compiled_call():
    x = jnp.ones(3)
    f = jax.jit(lambda a: a * 2.0)
    f(x), jnp.sin(x), jax.vmap(jnp.cos)(x)  # compiled once outside the count
    with executed_programs() as counts:
        f(x)
        jnp.sin(x)
        jax.vmap(jnp.cos)(x)
    assert counts["jit(<lambda>)"] == 1
    assert counts["jit(sin)"] == 1 and counts["jit(cos)"] == 1
    assert sum(counts.values()) == 3
    with compiled_programs() as compiled:
        jax.jit(lambda a: a - 1.0)(x)  # a new program: compiled (or read from the cache)
        f(x)
    assert compiled == {"jit(<lambda>)": 1}, dict(compiled)


def test_a_second_calibration_of_a_network_transfers_nothing(network, monkeypatch):
    """The approximate values and the solver's settings go to the device once (kept with the
    memoised plan and the frozen options): a transfer of a few scalars costs about 0.4 ms, a
    tenth of a calibration of the Chow room."""
    first = tj.calibrate(network)
    transfers = []
    put = jax.device_put
    monkeypatch.setattr(jax, "device_put", lambda *a, **k: transfers.append(a) or put(*a, **k))
    again = tj.calibrate(network)
    assert transfers == []
    np.testing.assert_array_equal(again.ap_values, first.ap_values)
    # Other settings: their arrays go to the device, once.
    opts = tj.SolverOptions(tolerance=1e-5)
    tj.calibrate(network, options=opts), tj.calibrate(network, options=opts)
    assert len(transfers) == 1


def test_a_second_solve_runs_one_compiled_program(network):
    adj = tj.analyze(network)
    first = adj.solve()
    with executed_programs() as counts:
        again = adj.solve()
    assert counts == {"jit(run)": 1}, dict(counts)
    np.testing.assert_array_equal(again.ap_values, first.ap_values)
    # The public entry: a new plan and approximate values (numpy), the same compiled program.
    with executed_programs() as counts:
        res = tj.calibrate(network)
    assert counts == {"jit(run)": 1}, dict(counts)
    np.testing.assert_allclose(res.ap_values, first.ap_values, rtol=1e-10, atol=1e-16)


@pytest.mark.parametrize("snooping", [False, True])
def test_a_second_self_calibrate_dispatches_nothing_eagerly(network, snooping):
    options = tj.CalibrationOptions(snooping=tj.SnoopingOptions() if snooping else None)
    first = tj.self_calibrate(network, None, options)
    with compiled_programs() as compiled, executed_programs() as counts:
        again = tj.self_calibrate(network, None, options)
    assert _eager(counts) == {}, dict(counts)
    assert compiled == {}, dict(compiled)  # every fold reuses the compiled adjustment
    # It ran: one adjustment per step it took, as many as the first time, and the
    # cross-validation (on by default) two per fold.
    folds = [f for f in again.cross_validation.folds if f.ok]
    assert len(folds) == len(network.scans) and counts["jit(corrections)"] == len(folds)
    assert counts["jit(run)"] >= 2 + 2 * len(folds)
    np.testing.assert_allclose(again.calibration.ap_values, first.calibration.ap_values, rtol=1e-12)
