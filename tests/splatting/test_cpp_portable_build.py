"""The compiled kernel built for a machine without AVX-512 (`PANO_PIPE_MARCH=x86-64-v3`:
AVX2 and FMA, one tile row per vector instead of two) renders and differentiates as this
machine's native build does.

The native build on CI machines (and ours) has AVX-512, so without this test the one-row
code path, which laptops and AMD machines run, would never execute in CI.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from splatting import raster_cpp

ROOT = Path(__file__).resolve().parents[2]

# Renders a small room (wide splats spanning two 8-column windows, odd row counts, the
# ±180° seam and both poles are all in it) and saves the image and every gradient.
_CASE = """
import sys, torch
from splatting import EquirectCamera, render
from splatting.bench import indoor_scene
means, quats, scales, opac, rgb = indoor_scene(3000, seed=3)
args = [t.clone().requires_grad_(True) for t in (means, quats, scales, opac, rgb)]
vm = torch.eye(4, requires_grad=True)
out = render(*args, vm, EquirectCamera(48, 96), backend="cpp")
assert out.backend == "cpp", out.backend
g = torch.Generator().manual_seed(0)
loss = (out.image * torch.rand(out.image.shape, generator=g)).sum() + 0.1 * out.depth.sum() + out.alpha.sum()
loss.backward()
torch.save({"image": out.image.detach(), "depth": out.depth.detach(), "alpha": out.alpha.detach(),
            "grads": [t.grad for t in args] + [vm.grad]}, sys.argv[1])
"""


def _run(tmp_path: Path, name: str, env: dict) -> dict:
    out = tmp_path / f"{name}.pt"
    subprocess.run([sys.executable, "-c", _CASE, str(out)], cwd=ROOT, env=env, check=True, timeout=900)
    return torch.load(out)


@pytest.mark.skipif(not raster_cpp.available(), reason="no C++ toolchain: the cpp backend is not built")
def test_a_build_without_avx512_gives_the_native_builds_image_and_gradients(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(ROOT), "OMP_NUM_THREADS": "1"}
    native = _run(tmp_path, "native", env)
    portable = _run(tmp_path, "v3", {**env, "PANO_PIPE_MARCH": "x86-64-v3"})
    for key in ("image", "depth", "alpha"):  # the same operations lane by lane
        assert torch.equal(native[key], portable[key]), key
    for a, b in zip(native["grads"], portable["grads"]):  # only the order of the sums differs
        assert float(a.abs().max()) > 0
        assert float((a - b).abs().max()) <= 1e-5 * float(a.abs().max())
