"""Time Depth Anything V2 Small per cube face and per view (docs/depth.md, "Speed").

    PYTHONPATH=. .venv/bin/python scripts/bench_depth_anything.py [--threads 2] [--sizes 518,392,266]

Random weights (the cost of the trained network is the same), exported with
depthnet.depth_anything.export_module, run through depthnet's cube-face path
on a random 512x1024 panorama; onnxruntime with CUDA when it has it, else CPU.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from depthnet.cubemap import run_cubemap
from depthnet.depth_anything import DepthAnythingV2, export_module
from depthnet.runner import OnnxDepthModel


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--sizes", default="518,392,266", help="cube face sides (multiples of 14)")
    args = ap.parse_args()
    torch.manual_seed(0)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "da2_small.onnx"
        export_module(DepthAnythingV2(), path)
        rgb = np.random.default_rng(0).random((512, 1024, 3), dtype=np.float32)
        for size in map(int, args.sizes.split(",")):
            model = OnnxDepthModel(path, threads=args.threads, overrides={"face_size": size})
            face = rgb[:size, :size]
            model.predict(face, (size, size))  # warm-up
            t = time.perf_counter()
            model.predict(face, (size, size))
            per_face = time.perf_counter() - t
            t = time.perf_counter()
            run_cubemap(model, rgb, (512, 1024))
            per_view = time.perf_counter() - t
            provider = model.session.get_providers()[0]
            print(f"face {size}: {per_face:.2f} s per face, {per_view:.1f} s per view "
                  f"(6 faces + stitching to 512x1024), {provider}, {args.threads} threads", flush=True)


if __name__ == "__main__":
    main()
