"""`pano-pipe bench train`'s comparison: medians per checkout, the ratio, the step parts, and a
bad --against refused before anything runs."""

from __future__ import annotations

from pathlib import Path

import pytest

from pipeline.bench_train import _markdown, _median, bench_train
from runfs.errors import PanoError


def _run(its, seconds, psnr, parts):
    return {"train_seconds": seconds, "iterations": its, "iterations_per_s": its / seconds, "num_gaussians": 1000,
            "backend": "cpp", "step_seconds": parts, "heldout_psnr": psnr, "render_fps": 3.0, "run_wall_s": 9.0}


def test_medians_ratio_and_parts_table(tmp_path):
    this = [_run(100, s, p, {"render": s / 4, "backward": s / 2}) for s, p in ((10.0, 30.0), (12.0, 30.2), (50.0, 29.0))]
    other = [_run(100, s, p, None) for s, p in ((20.0, 30.1), (26.0, 30.0), (22.0, 30.3))]
    m_this, m_other = _median(this), _median(other)
    assert m_this["iterations_per_s"] == pytest.approx(100 / 12.0)
    assert m_other["iterations_per_s"] == pytest.approx(100 / 22.0)
    assert m_this["step_seconds"] == {"render": 3.0, "backward": 6.0}
    assert m_other["step_seconds"] is None  # an older checkout reports no parts
    result = {**m_this, "other": m_other, "speedup": m_this["iterations_per_s"] / m_other["iterations_per_s"],
              "psnr_delta_db": m_this["heldout_psnr"] - m_other["heldout_psnr"], "gpu": None, "device": "cpu",
              "preset": "paper", "height": 512, "iterations": 100, "repeats": 3,
              "checkouts": {"this": "/a", "other": "/b"}}
    md = _markdown(result, tmp_path / "demo", tmp_path / "b")
    assert "**1.83x**" in md and "-0.10 dB" in md
    assert "| this | 3.00 | 6.00 |" in md and "--against" in md


def test_against_must_be_a_checkout(tmp_path):
    with pytest.raises(PanoError, match="not a pano-pipe checkout"):
        bench_train(None, "cpu", "paper", 16, tmp_path / "b.md", tmp_path / "b.json", iterations=1, against=tmp_path)
    assert not (tmp_path / "b.json").exists()


def test_set_overrides_reach_this_checkout_only(tmp_path, monkeypatch):
    """`--set` (e.g. an older checkout's defaults) changes this checkout's config, not the other's,
    and the printed command repeats it."""
    import pipeline.bench_train as bt

    other = tmp_path / "older"
    (other / "pipeline").mkdir(parents=True)
    (other / "pipeline" / "engine.py").write_text("")
    seen = []

    def fake_run_in(checkout, scene, run_dir, config, until):
        seen.append((checkout, until, config))
        run_dir.mkdir(parents=True, exist_ok=True)
        return {"wall": 1.0, "train": {"train_seconds": 2.0, "iterations": 4, "num_gaussians": 10},
                "evaluate": {"mean": {"psnr": 30.0}}}

    monkeypatch.setattr(bt, "_run_in", fake_run_in)
    res = bench_train(tmp_path / "scene", "cpu", "paper", 16, tmp_path / "b.md", tmp_path / "b.json", iterations=4,
                      against=other, this_overrides={"train": {"lr_scale": 1.0}}, log=lambda *_: None)
    this_cfgs = [c for co, _, c in seen if co != other.resolve()]
    other_cfgs = [c for co, _, c in seen if co == other.resolve()]
    assert this_cfgs and other_cfgs
    assert all(c["train"]["lr_scale"] == 1.0 and c["train"]["iterations"] == 4 for c in this_cfgs)
    assert all("lr_scale" not in c["train"] and c["train"]["iterations"] == 4 for c in other_cfgs)
    assert res["this_overrides"] == {"train": {"lr_scale": 1.0}}
    assert "--set train.lr_scale=1.0" in (tmp_path / "b.md").read_text()


def test_windows_split_the_run_by_its_log():
    """It/s through the run from the train log: a run at 50 it/s for its first 300 iterations
    (compiles, say) and 100 it/s after shows the slow spans alone, with the Gaussians at each
    span's end."""
    from pipeline.bench_train import _windows

    log, t = [[1, 0.01, 1000]], 0.01
    for it in range(10, 701, 10):
        t += 0.2 if it <= 300 else 0.1  # 10 iterations
        log.append([it, round(t, 6), 1000 + it])
    w = _windows(log, 700)
    assert [x["to"] for x in w] == [100, 200, 300, 400, 500, 600, 700]
    assert w[0]["from"] == 1 and w[-1]["gaussians"] == 1700
    assert all(x["iterations_per_s"] == pytest.approx(100.0) for x in w[3:])
    assert all(x["iterations_per_s"] < 80 for x in w[:3])
    assert _windows(log[:1], 700) == [] and _windows(log, 3) == []
    md = _markdown({**_median([{**_run(700, 5.0, 30.0, None), "windows": w, "kernel_variants": {"adam_triton._adam": 3}}]),
                    "gpu": None, "device": "cpu", "preset": "paper", "height": 512, "iterations": 700, "repeats": 1,
                    "checkouts": {"this": "/a"}}, Path("/tmp/demo"), None)
    assert "| 300–400 | 100.0 | 1,400 |" in md and "`adam_triton._adam` 3" in md
    runs = [_run(700, 10.0, 30.0, None), _run(700, 5.0, 30.0, None)]  # cold, then warm
    md = _markdown({**_median(runs), "runs": {"this": runs}, "gpu": "GPU", "device": "cuda", "preset": "paper",
                    "height": 512, "iterations": 700, "repeats": 2, "checkouts": {"this": "/a"}}, Path("/tmp/demo"), None)
    assert "Runs of this in order: 70.0, 140.0 it/s" in md
