"""Past one machine: two processes joined by ``jax.distributed`` each compute a share of the
realisations and every process gets all of them, bit for bit those of one process with the same
seed and per-device batch (two processes on this machine, one CPU device each).

The default test runs the one batch runner that Monte Carlo and the compatibility simulations
share (``run_batched``) on a small compiled function, so it costs three interpreter starts. The
same check on the public ``tj.monte_carlo`` compiles the whole chord adjustment in three
processes (about a minute of CPU): it runs with ``TLSJAX_TEST_DISTRIBUTED=1``.

Private import: ``_simulation._batch``, the runner itself and the chunk size it picks per
device kind (``auto_chunk``).
"""

import os
import socket
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

import tlsjax

_HEAD = """
import os, sys
os.environ["JAX_PLATFORMS"] = "cpu"
os.environ["XLA_FLAGS"] = os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=1"
import jax
jax.config.update("jax_enable_x64", True)
port, procs, me, out = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
if procs > 1:
    jax.distributed.initialize(
        f"localhost:{port}", num_processes=procs, process_id=me, initialization_timeout=120
    )
import numpy as np
"""

_TAIL = """
if procs > 1:
    jax.distributed.shutdown()
"""

# Seven realisations in slices of two: process 0 gets slices 0 and 2, process 1 slices 1 and 3
# (the last padded), so the gather has unequal shares to order.
BATCH = (
    _HEAD
    + textwrap.dedent(
        """
    import jax.numpy as jnp
    from tlsjax._simulation._batch import compile_batched, run_batched

    def one(k, key):
        x = jax.random.normal(jax.random.fold_in(key, k), (3,))
        return {"x": x, "s": jnp.sqrt(jnp.sum(x * x)), "k": k}

    key = jax.random.key_data(jax.random.key(4))
    b = compile_batched(one, (key,), 2)
    res, _ = run_batched(b, 7, (key,), desc="", progress=False)
    res2, _ = run_batched(b, 3, (key,), desc="", progress=False, indices=[6, 1, 5])
    np.savez(out, x=res["x"], s=res["s"], k=res["k"], x2=res2["x"], n=jax.process_count())
    """
    )
    + _TAIL
)

MONTE_CARLO = (
    _HEAD
    + textwrap.dedent(
        """
    jax.config.update("jax_compilation_cache_dir", os.environ["TLSJAX_TEST_CACHE"])
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
    import tlsjax as tj
    sim = tj.simulate(tj.Room(n_targets=12), seed=2, aps="A0 B6 B7 C0")
    model = tj.CalibrationModel(tj.Scanner(aps="A0 B6 B7 C0"))
    opts = tj.MonteCarloOptions(runs=7, chunk_size=2, seed=4, progress=False)
    mc = tj.monte_carlo(sim, model, opts)
    np.savez(out, aps=mc.ap_values, s0=mc.sigma0_sq, it=mc.iterations, res=mc.result,
             cov=mc.ap_covariance, n=jax.process_count())
    """
    )
    + _TAIL
)


def _free_port():
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _start(script, tmp_path, procs, tag, env):
    port = _free_port()
    outs = [tmp_path / f"{tag}{p}.npz" for p in range(procs)]
    jobs = [
        subprocess.Popen(
            [sys.executable, "-c", script, str(port), str(procs), str(p), str(outs[p])],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            env=env,
        )
        for p in range(procs)
    ]
    return jobs, outs


def _finish(groups, deadline_s):
    """Wait for every job; on a failure or past the deadline, kill the rest (a process whose
    peer died would otherwise wait in the runtime's own timeouts)."""
    end = time.monotonic() + deadline_s
    jobs = [j for g, _ in groups for j in g]
    try:
        for job in jobs:
            log, _ = job.communicate(timeout=max(end - time.monotonic(), 1))
            assert job.returncode == 0, log[-3000:]
    finally:
        for job in jobs:
            if job.poll() is None:
                job.kill()
                job.wait()
    return [[np.load(o) for o in outs] for _, outs in groups]


def _env(**extra):
    env = dict(os.environ, **extra)
    # The children import the tlsjax this test imported (a worktree may shadow an install).
    root = str(Path(tlsjax.__file__).resolve().parent.parent)
    env["PYTHONPATH"] = os.pathsep.join([root, env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    return env


def _assert_equal(one, both, keys):
    assert int(one["n"]) == 1 and all(int(r["n"]) == 2 for r in both)
    for r in both:  # every process holds every realisation, identical to one process's
        for key in keys:
            np.testing.assert_array_equal(r[key], one[key], err_msg=key)


def test_batches_over_two_processes_equal_one_bit_for_bit(tmp_path):
    env = _env()
    # The reference and the two-process run at once: three interpreters, small compiles.
    ref = _start(BATCH, tmp_path, 1, "one", env)
    two = _start(BATCH, tmp_path, 2, "two", env)
    (one,), both = _finish([ref, two], deadline_s=300)
    np.testing.assert_array_equal(one["k"], np.arange(7))
    np.testing.assert_array_equal(one["x2"], one["x"][[6, 1, 5]])
    _assert_equal(one, both, ("x", "s", "k", "x2"))


@pytest.mark.skipif(
    os.environ.get("TLSJAX_TEST_DISTRIBUTED") != "1",
    reason="compiles the Monte Carlo in three processes; set TLSJAX_TEST_DISTRIBUTED=1",
)
def test_monte_carlo_over_two_processes_equals_one_bit_for_bit(tmp_path):
    # One process first, filling a compilation cache that the two processes then read.
    env = _env(TLSJAX_TEST_CACHE=str(tmp_path / "cache"))
    ((one,),) = _finish([_start(MONTE_CARLO, tmp_path, 1, "one", env)], deadline_s=600)
    (both,) = _finish([_start(MONTE_CARLO, tmp_path, 2, "two", env)], deadline_s=600)
    assert np.all(one["res"] == 0)
    _assert_equal(one, both, ("aps", "s0", "it", "res", "cov"))


class _Device:
    def __init__(self, platform, limit):
        self.platform, self._limit = platform, limit

    def memory_stats(self):
        return {"bytes_limit": self._limit}


@pytest.mark.internal
def test_chunk_sized_by_cache_on_cpu_and_by_memory_on_an_accelerator(monkeypatch):
    """On a CPU a chunk's share stays near the cache-sized working set (measured optimum); on
    an accelerator it takes an eighth of the device's memory, capped, never above the runs."""
    import jax

    from tlsjax._simulation import _batch

    row = 225e3  # the Chow room's Jacobian rows per realisation, 4 APs [bytes]
    n = jax.local_device_count()
    cpu = _batch.auto_chunk(row, 1000)
    assert cpu == _batch.round_chunk(n * int(_batch.DEVICE_WORKING_SET // row))
    monkeypatch.setattr(jax, "local_devices", lambda: [_Device("gpu", 80e9)] * n)
    assert _batch.auto_chunk(row, 1000) == _batch.round_chunk(1000)
    assert _batch.auto_chunk(row, 10**6) == _batch.round_chunk(n * _batch.ACCELERATOR_MAX_ITEMS)
    small = 8 * 50 * row  # memory for 50 realisations' rows
    monkeypatch.setattr(jax, "local_devices", lambda: [_Device("gpu", small)] * n)
    assert _batch.auto_chunk(row, 1000) == _batch.round_chunk(n * 50)
