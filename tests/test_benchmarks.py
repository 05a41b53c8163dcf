"""The Ceres comparison benchmark runs end to end on a few realisations and writes its JSON.

The benchmark reaches into the engine's private functions (the compiled draws of Monte Carlo,
the adjustment program); a change of one of them once broke it for a whole working session
without any test failing. This runs it in a new process, as a user would, with the load gate
open, the command-line timings off and the Ceres peer left out (building it takes a minute where
Ceres is installed): no time is asserted, only that it completes, writes strict JSON, and that
its tlsjax Monte Carlo converged on every realisation.
"""

import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_bench_ceres_runs_and_writes_its_results(tmp_path):
    out = tmp_path / "ceres.json"
    argv = [sys.executable, str(ROOT / "benchmarks" / "bench_ceres.py"), "--cases", "physical"]
    argv += ["--rounds", "1", "--repeats", "1", "--scipy-repeats", "1", "--runs", "8"]
    argv += ["--no-cli", "--no-peer", "--max-load", "1e9", "--wait", "0", "--devices", "1"]
    argv += ["--out", str(out)]
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    run = subprocess.run(argv, cwd=ROOT, env=env, capture_output=True, text=True)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    result = json.loads(out.read_text(), parse_constant=_refuse)
    case = result["cases"]["physical"]
    assert case["montecarlo"]["runs"] == 8
    assert case["montecarlo"]["tlsjax_successful"] == 8
    single = case["single"]["times_s"]
    assert {"run", "solve", "calibrate"} <= set(single)
    assert result["ceres"] == {"skipped": "--no-peer"}


def _refuse(constant):
    raise AssertionError(f"the benchmark wrote {constant}: not strict JSON")
