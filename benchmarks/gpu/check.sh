#!/usr/bin/env bash
# The device check of issue 58, on a lent GPU machine (the device tool), in its last call: install what
# benchmarks/gpu/prepare.sh carried (kept on the machine between calls), then `benchmarks/bench_gpu.py`: gsplat's
# build, the cuda-marked tests, the rasterizer, the DAG per preset and the step costs on the GPU, with a deadline that
# leaves time to copy the results back. Writes bench_gpu.json (a run to append to benchmarks/results/), the partial
# figures and the tests' log to $OUT. Any arguments go to bench_gpu.py (e.g. --presets smoke draft).
# Usage (device tool, run): bash benchmarks/gpu/check.sh [bench_gpu.py arguments]
set -uo pipefail
cd "$(git rev-parse --show-toplevel 2>/dev/null || pwd)"
OUT=${OUT:-/tmp/gpu_out}; mkdir -p "$OUT"
PY=${PY:-python3}
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader | tee "$OUT/gpu.txt"
if [ ! -f .gpu/site/.installed ]; then
  "$PY" -m pip install -q --no-index --no-deps --no-build-isolation --no-compile --no-cache-dir --upgrade --target .gpu/site \
    .gpu/call1/wheels/* && touch .gpu/site/.installed || { echo "wheels did not install"; exit 1; }
fi
mkdir -p .gpu/weights && cp .gpu/call1/weights/alexnet.ckpt .gpu/weights/
cat .gpu/call2/vgg16.ckpt.part1 .gpu/call3/vgg16.ckpt.part2 > .gpu/weights/vgg16.ckpt
if [ "$(sha256sum .gpu/weights/vgg16.ckpt | cut -d' ' -f1)" != "$(cat .gpu/call3/vgg16.ckpt.sha256)" ]; then
  echo "vgg16.ckpt: the two halves do not make the file (a call's folder missing?)"; rm .gpu/weights/vgg16.ckpt
fi
export PYTHONPATH="$PWD:$PWD/.gpu/site${PYTHONPATH:+:$PYTHONPATH}" LPIPS_WEIGHTS_DIR="$PWD/.gpu/weights"
export PYTHONUNBUFFERED=1 BENCH_COMMIT="$(cat .gpu/call3/commit 2>/dev/null || echo unknown)" TORCH_CUDA_ARCH_LIST=9.0
"$PY" -c "import torch, gsplat, hydra, av; print('torch', torch.__version__, 'cuda', torch.version.cuda, torch.cuda.get_device_name())"
"$PY" benchmarks/bench_gpu.py --results "$OUT" --outputs /tmp/gpu_check --deadline-s "${DEADLINE_S:-420}" "$@" \
  2>&1 | tee "$OUT/bench_gpu.log"
cp /tmp/gpu_check/bench_gpu.partial.json /tmp/gpu_check/bench_gpu_tests.log "$OUT/" 2>/dev/null
ls -la "$OUT"
