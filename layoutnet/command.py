"""`pano-pipe export-layout-model CHECKPOINT.pth OUT.onnx` (registered by pipeline/cli.py)."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Annotated

import typer


def export_layout_model_command(
    checkpoint: Annotated[
        Path, typer.Argument(help="HorizonNet checkpoint (.pth) as its authors publish them.")
    ],
    out: Annotated[Path, typer.Argument(help="ONNX file to write.")],
    opset: Annotated[int, typer.Option("--opset", help="ONNX opset (>= 17).")] = 17,
) -> float:
    """Rebuild HorizonNet, load a checkpoint, export to ONNX (512x1024, batch 1), check it against torch."""
    from layoutnet.export import MAX_DIFF, export_checkpoint
    from runtime.console import console

    t0 = time.perf_counter()
    diff = export_checkpoint(checkpoint, out, opset=opset)
    console.print(
        f"wrote {out} (opset {opset}); onnxruntime vs torch max difference {diff:.2e} (< {MAX_DIFF:g}) "
        f"in {time.perf_counter() - t0:.1f} s. Use it with --set layout.model={out}"
    )
    return diff  # for callers in Python; typer ignores it
