#!/bin/bash
# The device checks of issue 36 in one run on a GPU machine (the device tool's `run`), from the
# repository's root; everything comes back under $OUT:
#   $OUT/gpu_tests.log   the tests that take the `device` fixture, on CUDA (and the CPU)
#   $OUT/bench_gpu.json  experiments/bench_gpu.py's figures, $OUT/bench_gpu.log its table
# The machine has torch, numpy, scipy, pillow, pytest, hypothesis, tqdm, matplotlib, pyyaml,
# tifffile, imageio; carry the rest as wheels in .whl (listed in .git/info/exclude), made here with
#   python3 -m pip download --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
#     --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 \
#     -d .whl kornia kornia_rs openexr pyserial
# and run it as:  run(command="bash experiments/gpu_check.sh", carry=[".whl"], timeout_s=590)
# BENCH_GPU_BUDGET (seconds, default 400) bounds the benchmark, which writes its JSON after each part.
set -o pipefail
export PYTHONUNBUFFERED=1 PYTHONPATH="$PWD${PYTHONPATH:+:$PYTHONPATH}"
OUT=${OUT:-/tmp/gpu-check}
mkdir -p "$OUT"
if [ -d .whl ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl \
    || exit 1
  export PYTHONPATH="$PYTHONPATH:/tmp/site"
fi
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv 2>&1 | tee "$OUT/gpu.txt"
python3 -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available())" | tee -a "$OUT/gpu.txt"
timeout 150 python3 -m pytest -q -p no:cacheprovider -o addopts="" -k "cuda or device" \
  tests/test_device.py tests/test_host_sync.py tests/test_lm.py tests/test_fri.py tests/test_fri_kernel.py \
  tests/test_synth.py tests/test_sphere.py tests/test_calibrate.py 2>&1 | tee "$OUT/gpu_tests.log"
BENCH_GPU_BUDGET=${BENCH_GPU_BUDGET:-400} python3 experiments/bench_gpu.py --output "$OUT" 2>&1 | tee "$OUT/bench_gpu.log"
