#!/usr/bin/env bash
# `make gpu-check`: everything issue #12 measures on a GPU, in one go, outputs in docs/gpu_check/:
#   bench_kernels.*        pano-pipe bench kernels: registers, spills, SASS per pair (needs no GPU)
#   tests.txt              the suite's `cuda`-marked tests, here with the compiled Triton kernels
#                          (cuda backend vs cpp on the hard cases: images 1e-5, gradients 1e-4)
#   bench_render_gpu.*     pano-pipe bench render --device cuda
#   bench_train.*          pano-pipe bench train --device cuda (paper preset, demo scene, 512x1024)
#   profile_step.*         scripts/profile_train_step.py: a step's kernels and host time (with UPSTREAM)
#   tile8/bench_train.*    bench train once more with 8x8 tiles in training and evaluation
#   cap100k/bench_train.*  bench train with the model held at 100k Gaussians: evaluation FPS at 100k
#                          trained Gaussians, and 7,000 iterations of a 4-panorama room of a real
#                          room's size (issue 35's 85k)
# Needs torch with CUDA, triton, pytest and the project (installed, or on PYTHONPATH: docs/gpu.md).
# Switches: BENCH_KERNELS=0 skips the compile report (it needs no GPU: run it elsewhere);
# TILES (default 8,16): the tile sizes of bench render's cuda rows;
# T_TESTS, T_RENDER, T_PROFILE, T_TRAIN, T_MORE (seconds; 0 skips the part) bound each part, so that one lent call of fixed
# length returns every part's outputs (scripts/gpu_session.sh); XDIST=4 runs the tests on 4 workers;
# SCENE and UPSTREAM (a run folder of SCENE with the stages before train done, e.g. on a machine
# with open3d) make bench train and the profile train from there instead of preparing the demo.
# `scripts/gpu_check.sh prep` (here, where open3d is) prepares that: the demo scene simulated at
# 512x1024 with layout and depth in .gpuprep/demo512, its run until align in .gpuprep/upstream512,
# both packed into .gpucarry/prep.tgz for a GPU machine without open3d (docs/gpu.md). Prepare at
# the commit the GPU runs: the upstream stages' cache keys include their code.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PY:-.venv/bin/python}
[ -x "$PY" ] || PY=python3
if [ "${1:-}" = prep ]; then
    PYTHONPATH=$PWD "$PY" - <<'PREP'
from pathlib import Path

import simulate
from pipeline.bench_train import _run_in

root = Path(".gpuprep").resolve()
scene = root / "demo512"
if not scene.exists():
    simulate.generate_scene(scene, preset="demo", height=512, with_layout=True, with_depth=True)
config = {"train": {"preset": "paper", "device": "cuda", "height": 512}, "evaluate": {"device": "cuda"}}
_run_in(Path(".").resolve(), scene, root / "upstream512", config, "align")
PREP
    mkdir -p .gpucarry
    tar czf .gpucarry/prep.tgz .gpuprep
    du -h .gpucarry/prep.tgz
    exit 0
fi
# the installed entry point, else the module (the project on PYTHONPATH); an array, so that
# `timeout` can run it
PANO=("$(dirname "$PY")/pano-pipe")
[ -x "${PANO[0]}" ] || PANO=("$PY" -m pipeline.cli)
OUT=${OUT:-docs/gpu_check}
mkdir -p "$OUT"
"$PY" -c "import sys, torch; sys.exit(0 if torch.cuda.is_available() else 'gpu-check: torch sees no CUDA device')"
"$PY" -c "import torch; print(torch.cuda.get_device_name(), 'torch', torch.__version__)" | tee "$OUT/device.txt"
# how this Triton types a float argument (float32 in 3.8's binder; splatting/optional_triton.py)
"$PY" - <<'FLOATS' 2>&1 | tee "$OUT/triton_floats.txt" || true
import torch
import triton

from splatting import adam_triton
from splatting.kernel_report import bind

t = torch.zeros(4, dtype=torch.float64, device="cuda")
fn, _grid, args, options = adam_triton.adam_launch([(t, t, t, t, 1e-3)], 1, (0.9, 0.999), 1e-15, t)
spec = bind(fn, args, options, triton.compiler.make_backend(triton.runtime.driver.active.get_current_target()))[1]
print("triton", triton.__version__, "binds Adam's float arguments as", {s[0] for s, a in zip(spec, args) if isinstance(a, float)})
FLOATS
limit() {  # limit SECONDS CMD...: CMD, stopped after SECONDS when SECONDS is set; skipped when 0
    local t=$1; shift
    if [ "$t" = 0 ]; then echo "gpu-check: skipped (its time limit is 0): $*"; return 0; fi
    if [ -n "$t" ]; then timeout "$t" "$@"; else "$@"; fi
}
status=0
if [ "${BENCH_KERNELS:-1}" != 0 ]; then
    "${PANO[@]}" bench kernels --out "$OUT" 2>&1 | tee "$OUT/bench_kernels.log" || status=1
fi
# the tests first: a wrong kernel makes its timings meaningless
xdist=()
[ -n "${XDIST:-}" ] && xdist=(-n "$XDIST")
limit "${T_TESTS:-}" "$PY" -m pytest -q -p no:cacheprovider "${xdist[@]}" -rfE --durations=10 -m cuda \
    tests/splatting tests/gaussians tests/train 2>&1 | tee "$OUT/tests.txt" || status=1
limit "${T_RENDER:-}" "${PANO[@]}" bench render --device cuda --tile-sizes "${TILES:-8,16}" --out "$OUT" 2>&1 \
    | tee "$OUT/bench_render.log" || status=1
if [ -n "${UPSTREAM:-}" ]; then
    limit "${T_PROFILE:-}" "$PY" scripts/profile_train_step.py "$SCENE" "$UPSTREAM" --device cuda --out "$OUT" 2>&1 \
        | tee "$OUT/profile_step.log" || status=1
fi
prepared=()
[ -n "${UPSTREAM:-}" ] && prepared=("$SCENE" --upstream "$UPSTREAM")
# two runs: the first also compiles every kernel variant, the second finds them in Triton's disk cache
limit "${T_TRAIN:-}" "${PANO[@]}" bench train "${prepared[@]}" --device cuda --repeats 2 --out "$OUT" 2>&1 \
    | tee "$OUT/bench_train.log" || status=1
# the kernels are in the cache now: one run each
mkdir -p "$OUT/tile8" "$OUT/cap100k"
limit "${T_MORE:-}" "${PANO[@]}" bench train "${prepared[@]}" --device cuda --repeats 1 --out "$OUT/tile8" \
    --set train.tile_size=8 --set evaluate.tile_size=8 2>&1 | tee "$OUT/tile8/bench_train.log" || status=1
limit "${T_MORE:-}" "${PANO[@]}" bench train "${prepared[@]}" --device cuda --repeats 1 --out "$OUT/cap100k" \
    --set train.max_init_points=100000 --set train.max_gaussians=100000 2>&1 \
    | tee "$OUT/cap100k/bench_train.log" || status=1
echo "gpu-check: outputs in $OUT (status $status)"
exit $status
