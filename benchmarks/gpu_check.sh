#!/usr/bin/env bash
# The GPU check of issue 37 (item 5), run on a lent accelerator machine whose image has JAX with
# CUDA: the same code, unchanged and uninstalled (PYTHONPATH), runs the 1,000-run Monte Carlo
# benchmark on the GPU, then on the same machine's CPUs (the baseline from the same machine), then
# the fast test subset on the GPU. Results go to $OUT (default /tmp/gpu_check).
#
#   OUT=/tmp/gpu_check bash benchmarks/gpu_check.sh
set -u
OUT=${OUT:-/tmp/gpu_check}
mkdir -p "$OUT"
export PYTHONPATH=$PWD PYTHONUNBUFFERED=1
py=${PYTHON:-python3}
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv | tee "$OUT/nvidia_smi.txt"
$py -c "import jax; print('jax', jax.__version__, jax.devices())"
mc="$py benchmarks/bench_montecarlo.py --runs 1000"
# 1. GPU: the default chunk (sized from the device's memory), then 250 per call for comparison.
timeout 180 $mc --cases physical,chow2013-noscale --scipy-runs 3 --out "$OUT/montecarlo_gpu.json"
timeout 75 $mc --cases physical --chunk-size 250 --scipy-runs 1 --out "$OUT/montecarlo_gpu_chunk250.json"
# 2. The same machine's CPUs, one JAX device per core.
JAX_PLATFORMS=cpu timeout 100 $mc --cases physical --scipy-runs 1 --out "$OUT/montecarlo_cpu.json"
# 3. The fast test subset on the GPU (progress in the log: a timeout still leaves it).
timeout "${TEST_SECONDS:-120}" $py -m pytest -m fast -p no:cacheprovider -v -rf tests 2>&1 |
    tee "$OUT/tests_gpu.log" | grep -E "FAILED|ERROR|passed|failed" | tail -40
exit 0
