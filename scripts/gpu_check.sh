#!/usr/bin/env bash
# `make gpu-check`: everything issue #12 measures on a GPU, in one go, outputs in docs/gpu_check/:
#   bench_kernels.*        pano-pipe bench kernels: registers, spills, SASS per pair (needs no GPU)
#   tests.txt              the suite's `cuda`-marked tests, here with the compiled Triton kernels
#                          (cuda backend vs cpp on the hard cases: images 1e-5, gradients 1e-4)
#   bench_render_gpu.*     pano-pipe bench render --device cuda
#   bench_train.*          pano-pipe bench train --device cuda (paper preset, demo scene, 512x1024)
# Needs torch with CUDA, triton, pytest and the project installed (docs/gpu.md).
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-.venv/bin/python}
[ -x "$PY" ] || PY=python3
PANO=${PANO:-$(dirname "$PY")/pano-pipe}
[ -x "$PANO" ] || PANO=pano-pipe
OUT=${OUT:-docs/gpu_check}
mkdir -p "$OUT"
"$PY" -c "import sys, torch; sys.exit(0 if torch.cuda.is_available() else 'gpu-check: torch sees no CUDA device')"
"$PY" -c "import torch; print(torch.cuda.get_device_name(), 'torch', torch.__version__)" | tee "$OUT/device.txt"
status=0
"$PANO" bench kernels --out "$OUT" 2>&1 | tee "$OUT/bench_kernels.log" || status=1
# the tests first: a wrong kernel makes its timings meaningless
"$PY" -m pytest -q -p no:cacheprovider -m cuda tests/splatting tests/train 2>&1 | tee "$OUT/tests.txt" || status=1
"$PANO" bench render --device cuda --out "$OUT" 2>&1 | tee "$OUT/bench_render.log" || status=1
"$PANO" bench train --device cuda --out "$OUT" 2>&1 | tee "$OUT/bench_train.log" || status=1
echo "gpu-check: outputs in $OUT (status $status)"
exit $status
