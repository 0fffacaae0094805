#!/usr/bin/env bash
# `make setup`'s torch: the pinned version, built for what this machine has.
#   TORCH_BUILD=auto (default): the CUDA build when nvidia-smi lists a GPU, else the CPU build
#   TORCH_BUILD=cpu | cuda:     force one
# The CPU build comes from the default index (on our CI machines the local CPU wheel, so no
# resolver pulls CUDA wheels); the CUDA build from TORCH_CUDA_INDEX, with the triton it pins.
# The CPU build gets the `interpreter` extra (the triton CI checks the GPU kernels with).
# Prints one line saying which build it installed; writes it to .venv/.torch-build.
set -euo pipefail
PIP=${PIP:-.venv/bin/pip}
PY=${PY:-.venv/bin/python}
TORCH=${TORCH:-torch==2.13.0}
BUILD=${TORCH_BUILD:-auto}
INDEX=${TORCH_CUDA_INDEX:-https://download.pytorch.org/whl/cu128}
case "$BUILD" in
  auto) if command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L 2>/dev/null | grep -q '^GPU'; then
          BUILD=cuda; why="nvidia-smi lists a GPU"; else BUILD=cpu; why="no NVIDIA GPU seen"; fi ;;
  cpu|cuda) why="TORCH_BUILD=$BUILD" ;;
  *) echo "error: TORCH_BUILD must be auto, cpu or cuda (got '$BUILD')" >&2; exit 2 ;;
esac
if [ "$BUILD" = cuda ]; then
  "$PIP" install -q "$TORCH" --index-url "$INDEX" --extra-index-url https://pypi.org/simple
else
  "$PIP" install -q "$TORCH"
fi
got=$("$PY" -c "import torch; print(torch.__version__, 'CUDA ' + torch.version.cuda if torch.version.cuda else 'CPU')")
echo "torch: installed $got build ($why; make setup TORCH_BUILD=cpu|cuda forces one, after make clean-venv)"
if [ "$BUILD" = cuda ] && [ -z "$("$PY" -c 'import torch; print(torch.version.cuda or "")')" ]; then
  echo "error: asked for the CUDA build but got a CPU one from $INDEX (set TORCH_CUDA_INDEX)" >&2; exit 2
fi
echo "$BUILD" > "$(dirname "$PY")/../.torch-build"
