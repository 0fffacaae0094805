"""The GPU render bench's report (splatting/bench_gpu.py) without a GPU: its table from a result."""

from __future__ import annotations

from splatting.bench_gpu import to_markdown


def _row(tile=None, **kw):
    r = {"height": 512, "width": 1024, "gaussians": 300_000, "backend": "cuda", "forward_s": 0.00139,
         "forward_backward_s": 0.0037, "fps": 719.0, "peak_mem_forward_mb": 120.0, "peak_mem_forward_backward_mb": 300.0}
    if tile is not None:
        r["tile_size"] = tile
    return {**r, **kw}


def test_the_table_has_a_row_per_tile_size_and_reads_results_from_before_the_column():
    result = {"machine": {"gpu": "G", "torch": "t", "cuda": "c", "triton": "x"}, "repeats": 10, "cubemap": [],
              "render": [_row(8, forward_s=0.001, box_pairs=1_685_852, walked_pairs=1_400_000), _row(16), _row(),
                         {"height": 512, "width": 1024, "gaussians": 1_000_000, "backend": "torch", "skipped": "slow"}]}
    lines = [line for line in to_markdown(result).splitlines() if line.startswith("| 512×1024")]
    assert lines[0].startswith("| 512×1024 | 300,000 | cuda | 8 | 1,400,000 / 1,685,852 | 1.00 | 3.70 |")
    assert lines[1].startswith("| 512×1024 | 300,000 | cuda | 16 | – | 1.39 | 3.70 |")
    assert lines[2] == lines[1]  # no tile_size recorded: the renderer's default
    assert lines[3].count("|") == lines[0].count("|") and "slow" in lines[3]
