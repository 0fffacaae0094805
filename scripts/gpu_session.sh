#!/usr/bin/env bash
# One lent GPU call for everything `make gpu-check` measures: each part bounded in time
# (scripts/gpu_check.sh's T_* switches), so that a call of fixed length returns all of them, and
# the outputs packed into one file, $OUT/gpu_check.tgz (a call returns at most 8 files). On the
# GPU machine, carrying .gpucarry (prepared here first: docs/gpu.md "A GPU session, prepared"):
#     bash scripts/gpu_session.sh          (the device tool's run: timeout_s 595, carry [".gpucarry"])
# then here: tar xzf <files_at>/gpu_check.tgz -C /tmp && cp -r /tmp/gpu_check/* docs/gpu_check/
# The default limits add up to 550 s (the step's profile, measured on 2026-11-28, skipped: T_PROFILE=0),
# so that one call of the 600 s a command may run returns every part. The H200's runs of 2026-11-28:
# 290 and 365 s in all, the tests 107 s on 4 workers, the two paper runs 98 and 55 s.
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:?set OUT (the device tool sets it)}
python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site \
    .gpucarry/*.whl || exit 1
export PYTHONPATH=/tmp/site:$PWD PYTHONUNBUFFERED=1
tar xzf .gpucarry/prep.tgz
G=/tmp/gpu_check
mkdir -p "$G"
trap 'tar czf "$OUT/gpu_check.tgz" -C /tmp gpu_check' EXIT
nvidia-smi > "$G/nvidia_smi.txt" 2>&1
BENCH_KERNELS=0 PY=python3 SCENE=$PWD/.gpuprep/demo512 UPSTREAM=$PWD/.gpuprep/upstream512 OUT=$G XDIST=4 \
    T_TESTS=${T_TESTS:-140} T_RENDER=${T_RENDER:-80} T_PROFILE=${T_PROFILE:-0} T_TRAIN=${T_TRAIN:-180} \
    T_MORE=${T_MORE:-75} \
    bash scripts/gpu_check.sh
