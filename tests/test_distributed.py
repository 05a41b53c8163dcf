"""Monte Carlo past one machine: two processes joined by ``jax.distributed`` each compute a share
of the realisations and every process gets all of them, bit for bit those of one process with
the same seed and per-device batch (two processes on this machine, one CPU device each)."""

import socket
import subprocess
import sys
import textwrap

import numpy as np

SCRIPT = textwrap.dedent(
    """
    import os, sys
    os.environ["JAX_PLATFORMS"] = "cpu"
    os.environ["XLA_FLAGS"] = "--xla_force_host_platform_device_count=1"
    import jax
    port, procs, me, out = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
    if procs > 1:
        jax.distributed.initialize(f"localhost:{port}", num_processes=procs, process_id=me)
    import numpy as np
    import tlsjax as tj
    sim = tj.simulate(tj.Room(n_targets=12), seed=2, aps="A0 B6 B7 C0")
    model = tj.CalibrationModel(tj.Scanner(aps="A0 B6 B7 C0"))
    opts = tj.MonteCarloOptions(runs=7, chunk_size=2, seed=4, progress=False)
    mc = tj.monte_carlo(sim, model, opts)
    np.savez(out, aps=mc.ap_values, s0=mc.sigma0_sq, it=mc.iterations, res=mc.result,
             cov=mc.ap_covariance, n=jax.process_count())
    if procs > 1:
        jax.distributed.shutdown()
    """
)


def _free_port():
    with socket.socket() as s:
        s.bind(("localhost", 0))
        return s.getsockname()[1]


def _run(tmp_path, procs, tag):
    port = _free_port()
    outs = [tmp_path / f"{tag}{p}.npz" for p in range(procs)]
    jobs = [
        subprocess.Popen(
            [sys.executable, "-c", SCRIPT, str(port), str(procs), str(p), str(outs[p])],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        for p in range(procs)
    ]
    for job in jobs:
        log, _ = job.communicate(timeout=600)
        assert job.returncode == 0, log[-3000:]
    return [np.load(o) for o in outs]


def test_two_processes_equal_one_bit_for_bit(tmp_path):
    (one,) = _run(tmp_path, 1, "one")
    both = _run(tmp_path, 2, "two")
    assert int(one["n"]) == 1 and all(int(r["n"]) == 2 for r in both)
    assert np.all(one["res"] == 0)
    for r in both:  # every process holds every realisation, identical to one process's
        for key in ("aps", "s0", "it", "res", "cov"):
            np.testing.assert_array_equal(r[key], one[key], err_msg=key)
