"""`pano-pipe export-depth-model CHECKPOINT.pth OUT.onnx` (registered by pipeline/cli.py)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated

import typer


def export_depth_model_command(
    checkpoint: Annotated[
        Path,
        typer.Argument(
            help="Depth Anything V2 checkpoint as its authors publish it (depth_anything_v2_vits.pth)."
        ),
    ],
    out: Annotated[Path, typer.Argument(help="ONNX file to write.")],
    opset: Annotated[int, typer.Option("--opset", help="ONNX opset (>= 17).")] = 17,
) -> float:
    """Rebuild Depth Anything V2, load a checkpoint strictly, export to ONNX (dynamic size), check it
    against torch."""
    from depthnet.depth_anything import MAX_DIFF, export_onnx
    from runtime.console import console

    t0 = time.perf_counter()
    if checkpoint.is_file():  # a missing file is reported by export_onnx, as one line
        console.print(f"exporting {checkpoint} to {out} (load, trace, check against torch: under a minute on "
                      "a CPU)", soft_wrap=True)
    diff = export_onnx(checkpoint, out, opset=opset)
    console.print(
        f"wrote {out} (opset {opset}); onnxruntime vs torch max difference {diff:.2e} (< {MAX_DIFF:g}) "
        f"in {time.perf_counter() - t0:.1f} s. Use it with --set depth.model={out}",
        soft_wrap=True,
    )
    return diff  # for callers in Python; typer ignores it
