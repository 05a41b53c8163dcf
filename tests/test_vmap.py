"""Monte Carlo results do not depend on the chunk size or the number of devices (SPEC section 9)."""

import json
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

import tlsjax as tj
from tlsjax import APSet, CompatibilityOptions, MonteCarloOptions, compatibility_test, monte_carlo

ROOM = tj.Room(n_targets=24)
RUNS = 10

# The same computation run in a subprocess with two host devices (sharded batch axis).
SCRIPT = textwrap.dedent("""
    import json, sys
    import jax
    import numpy as np
    import tlsjax as tj
    from tlsjax import APSet, CompatibilityOptions, MonteCarloOptions, compatibility_test, monte_carlo
    assert len(jax.devices()) == 2, jax.devices()
    sim = tj.simulate(tj.Room(n_targets=24), seed=2)
    r = monte_carlo(sim, options=MonteCarloOptions(runs=%d, chunk_size=4, seed=9, progress=False))
    s = APSet(r.ap_names, r.ap_values[0], r.ap_covariance[0])
    t = APSet(r.ap_names, r.ap_values[1], r.ap_covariance[1])
    c = compatibility_test(s, t, tj.Room(n_targets=24), options=CompatibilityOptions(runs=%d, chunk_size=4, progress=False))
    json.dump({"devices": r.n_devices, "ap_values": r.ap_values.tolist(), "sigma0_sq": r.sigma0_sq.tolist(),
               "shares": c.shares.tolist(), "statistic": c.statistic, "G": c.null_matrix.tolist()}, sys.stdout)
""") % (RUNS, RUNS)


@pytest.fixture(scope="module")
def reference():
    sim = tj.simulate(ROOM, seed=2)
    return sim, monte_carlo(
        sim, options=MonteCarloOptions(runs=RUNS, chunk_size=RUNS, seed=9, progress=False)
    )


def test_chunk_size_invariance(reference):
    sim, ref = reference
    for chunk in (3, 4):
        r = monte_carlo(
            sim, options=MonteCarloOptions(runs=RUNS, chunk_size=chunk, seed=9, progress=False)
        )
        assert r.chunk_size == chunk
        np.testing.assert_allclose(r.ap_values, ref.ap_values, rtol=1e-12, atol=0)
        np.testing.assert_allclose(r.ap_covariance, ref.ap_covariance, rtol=1e-12, atol=0)
        np.testing.assert_allclose(r.sigma0_sq, ref.sigma0_sq, rtol=1e-12)
        np.testing.assert_array_equal(r.iterations, ref.iterations)
    # A different seed is a different experiment.
    other = monte_carlo(
        sim, options=MonteCarloOptions(runs=RUNS, chunk_size=RUNS, seed=10, progress=False)
    )
    assert not np.allclose(other.ap_values, ref.ap_values)
    # Realisation k is the same whether N is 4 or 10.
    few = monte_carlo(sim, options=MonteCarloOptions(runs=4, chunk_size=4, seed=9, progress=False))
    np.testing.assert_allclose(few.ap_values, ref.ap_values[:4], rtol=1e-12)


def test_compatibility_chunk_size_invariance(reference):
    _, ref = reference
    s = APSet(ref.ap_names, ref.ap_values[0], ref.ap_covariance[0])
    t = APSet(ref.ap_names, ref.ap_values[1], ref.ap_covariance[1])
    a = compatibility_test(
        s, t, ROOM, options=CompatibilityOptions(runs=RUNS, chunk_size=RUNS, progress=False)
    )
    b = compatibility_test(
        s, t, ROOM, options=CompatibilityOptions(runs=RUNS, chunk_size=4, progress=False)
    )
    np.testing.assert_array_equal(a.shares, b.shares)
    np.testing.assert_allclose(a.statistic, b.statistic, rtol=1e-12)
    np.testing.assert_allclose(a.null_matrix, b.null_matrix, rtol=1e-10, atol=1e-16)
    np.testing.assert_allclose(a.rms_mm, b.rms_mm, rtol=1e-12)
    assert a.p_value == b.p_value


def test_device_count_invariance(reference):
    _, ref = reference
    # The suite's XLA flags (its optimisation level, tests/conftest.py) and two host devices.
    flags = os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2"
    env = dict(os.environ, XLA_FLAGS=flags.strip(), JAX_PLATFORMS="cpu")
    proc = subprocess.run(
        [sys.executable, "-c", SCRIPT], capture_output=True, text=True, env=env, timeout=600
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    out = json.loads(proc.stdout)
    assert out["devices"] == 2
    np.testing.assert_allclose(np.array(out["ap_values"]), ref.ap_values, rtol=1e-12, atol=0)
    np.testing.assert_allclose(np.array(out["sigma0_sq"]), ref.sigma0_sq, rtol=1e-12)
    s = APSet(ref.ap_names, ref.ap_values[0], ref.ap_covariance[0])
    t = APSet(ref.ap_names, ref.ap_values[1], ref.ap_covariance[1])
    c = compatibility_test(
        s, t, ROOM, options=CompatibilityOptions(runs=RUNS, chunk_size=RUNS, progress=False)
    )
    # The 2-device run used APs from its own (equal to 1e-12) Monte Carlo: shares are counts.
    np.testing.assert_array_equal(np.array(out["shares"]), c.shares)
    np.testing.assert_allclose(out["statistic"], c.statistic, rtol=1e-12)
    np.testing.assert_allclose(np.array(out["G"]), c.null_matrix, rtol=1e-10, atol=1e-16)
