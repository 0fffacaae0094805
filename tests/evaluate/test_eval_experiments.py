"""Ablation / sweep bookkeeping: parameter mapping, Pareto fronts, tables, shared upstream copies."""

from __future__ import annotations

import json
import math
from typing import Literal

import pytest
from pydantic import BaseModel

from evaluation import experiments as E
from runfs.errors import PanoError


class _FakeTrainParams(BaseModel):
    init: Literal["auto", "random", "layout", "layout+depth"] = "auto"
    projection: Literal["360", "crops", "cubemap"] = "360"
    layout_reg: bool = True
    seed: int = 0
    iterations: int = 3000
    resolution: tuple[int, int] = (256, 512)
    max_gaussians: int | None = 200_000


def test_map_train_overrides():
    fields = _FakeTrainParams.model_fields
    out, missing = E.map_train_overrides({"init": "layout", "projection": "cubemap", "layout_reg": False,
                                          "seed": 3, "bogus": 1}, fields)
    assert out == {"init": "auto", "projection": "cubemap", "layout_reg": False, "seed": 3}
    assert missing == ["bogus"]
    assert E.resolution_value(64, fields["resolution"]) == [64, 128]

    class P2(BaseModel):
        height: int = 128
        init: Literal["random", "layout"] = "layout"

    assert E.resolution_value(64, P2.model_fields["height"]) == 64
    assert E.map_train_overrides({"init": "layout"}, P2.model_fields)[0] == {"init": "layout"}
    # every ablation step differs from the previous in exactly one setting; the baseline is the crops
    for baseline in ("crops", "cubemap"):
        variants = E.ablation_variants(baseline)
        assert variants[0][2]["projection"] == baseline
        for (_, _, a), (_, _, b) in zip(variants, variants[1:]):
            assert sum(a[k] != b[k] for k in a) == 1
    assert E.VARIANTS == E.ablation_variants("crops")
    with pytest.raises(PanoError, match="crops' or 'cubemap"):
        E.ablation_variants("fisheye")


def test_paper_config_fills_the_preset_but_explicit_settings_win():
    cfg = E.paper_config({"train": {"height": 64}, "evaluate": {"lpips": False}})
    assert cfg == {"train": {"height": 64, "preset": "paper"}, "evaluate": {"lpips": False, "resolution": "train"}}
    assert E.paper_config({"train": {"preset": "fast"}})["train"]["preset"] == "fast"


def test_pareto_mask():
    q = [10.0, 12.0, 11.0, 12.0, 9.0]
    c = [1.0, 5.0, 6.0, 4.0, 0.5]
    # 2 (11 dB at 6 s) is dominated by 3 (12 dB at 4 s); 1 by 3 (same dB, cheaper)
    assert E.pareto_mask(q, c) == [True, False, False, True, True]
    assert E.pareto_mask([1.0], [1.0]) == [True]


def test_parse_grid():
    assert E.parse_grid("300, 1000") == [300, 1000]
    assert E.parse_grid("5000,default", allow_none=True) == [5000, None]
    with pytest.raises(PanoError):
        E.parse_grid("abc")
    with pytest.raises(PanoError):
        E.parse_grid("-5")
    with pytest.raises(PanoError):
        E.parse_grid("")


def _row(label, psnrs):
    r = E.AblationRow(label, label, {})
    r.runs = [{"psnr": p, "ssim": 0.5, "ws_psnr": p - 1, "lpips": None, "train_seconds": 10.0,
               "num_gaussians": 100, "iterations": 500, "train_images": 32 if label in ("3D-GS*", "+ layout init") else 4}
              for p in psnrs]
    return r


def test_ablation_notes_table_and_chart(tmp_path):
    rows = [_row("3D-GS*", [13.0, 14.0]), _row("+ layout init", [16.0, 16.0]),
            _row("+ 360 splatting", [15.0, 16.6]), _row("+ layout reg", [15.9, 16.3])]
    assert rows[0].stat("psnr") == (13.5, pytest.approx(math.sqrt(0.5)))
    notes = E.ordering_notes(rows)
    # spread of a gain: √(0.71² + 0²) = 0.71 < 2.50
    assert notes[0] == "✓ + layout init improves on 3D-GS* by +2.50 dB, more than its spread 0.71 dB"
    assert notes[1].startswith("✗ + 360 splatting does NOT improve") and "spread 1.13 dB" in notes[1]
    # +0.30 dB against √(1.13² + 0.28²) = 1.17 dB
    assert notes[2].startswith("✓") and "within its spread 1.17 dB over 2 seeds" in notes[2]
    table = E.ablation_table(rows)
    assert "| 3D-GS* | 13.50 ± 0.71 |" in table and "| 13.64 |" in table
    assert "—" in table  # LPIPS missing shows a dash, not 0
    lines = table.splitlines()
    assert "| +2.50 (± 0.71) | yes | 500 | 32 | 10 | 100 |" in lines[3]
    assert "| +0.30 (± 1.17) | no | 500 | 4 | 10 | 100 |" in lines[5]
    E.plot_ablation(rows, tmp_path / "a.png")
    import cv2

    assert cv2.imread(str(tmp_path / "a.png")) is not None


def test_equal_budget_plan_and_projection_table():
    base = E.AblationRow("layout-init", "+ layout init", {"projection": "crops"})
    p360 = E.AblationRow("layout-reg", "+ layout reg", {"projection": "360"})
    base.runs = [{"psnr": p, "ssim": 0.70, "iterations": 100, "train_seconds": 10.0, "pixels_per_image": 64 * 64}
                 for p in (20.0, 20.2)]
    p360.runs = [{"psnr": p, "ssim": 0.75, "iterations": 100, "train_seconds": 30.0, "pixels_per_image": 64 * 128}
                 for p in (21.0, 21.2)]
    rows = [base, p360]
    cheap, iters, ratio = E.equal_budget_plan(rows, "time")
    assert cheap is base and iters == 300 and ratio == pytest.approx(3.0)
    cheap, iters, _ = E.equal_budget_plan(rows, "pixels")
    assert cheap is base and iters == 200
    assert E.equal_budget_plan(rows, "none") is None
    assert E.equal_budget_plan([base], "time") is None  # nothing to compare
    extra = E.AblationRow("layout-init-equal-time", "+ layout init (equal time)", base.settings)
    extra.runs = [dict(r, psnr=r["psnr"] + 0.5, iterations=300, train_seconds=30.0) for r in base.runs]
    table, notes = E.projection_table(rows, extra, "time")
    lines = table.splitlines()
    assert len(lines) == 4 and lines[2].startswith("| equal iterations | 20.10 / 0.700 | 21.10 / 0.750 | 100 / 100")
    assert "| equal time | 20.60 / 0.700 | 21.10 / 0.750 | 300 / 100 | 30 / 30 | +0.50" in lines[3]
    # +1.00 dB against a spread of √2·0.14 = 0.20: a clear win; +0.05 SSIM with no spread
    assert notes[0].startswith("✓ at equal iterations, 360 beats crops: +1.00 dB")
    assert notes[1].startswith("✓ at equal time, 360 beats crops: +0.50 dB")


def test_sweep_table_and_plot(tmp_path):
    pts = [E.SweepPoint(300, 64, None, psnr=15.0, train_seconds=10, fps=20, num_gaussians=1000),
           E.SweepPoint(1000, 128, 5000, psnr=18.0, train_seconds=60, fps=5, num_gaussians=5000)]
    for p, a in zip(pts, E.pareto_mask([p.psnr for p in pts], [p.train_seconds for p in pts])):
        p.pareto_time = a
    t = E.sweep_table(pts)
    assert "| 300 | 64 | default | 15.00 |" in t and "★" in t
    assert pts[1].label == "it1000-h128-cap5000"
    E.plot_sweep(pts, tmp_path / "s.png")
    assert (tmp_path / "s.png").stat().st_size > 1000


def test_prepare_variant_dir_copies_and_refreshes(tmp_path):
    base, var = tmp_path / "base", tmp_path / "var"
    for s, key in (("layout", "k1"), ("union", "k2")):
        (base / s).mkdir(parents=True)
        (base / s / "artifact.json").write_text(json.dumps({"meta": {"key": key}}))
        (base / s / "data.bin").write_text(s)
    E.prepare_variant_dir(base, var, ["layout", "union", "depth"])
    assert (var / "layout" / "data.bin").read_text() == "layout" and not (var / "depth").exists()
    (var / "union" / "data.bin").write_text("stale")
    (base / "union" / "artifact.json").write_text(json.dumps({"meta": {"key": "k3"}}))
    E.prepare_variant_dir(base, var, ["layout", "union"])
    assert (var / "union" / "data.bin").read_text() == "union"


# -- end to end: the grid really runs through the engine, sharing the upstream stages ----------------
TINY = {"sampling": {"density": 60.0}, "align": {"voxel_size": 0.15},
        "train": {"height": 16, "random_points": 300, "threads": 1, "log_every": 1, "checkpoint_every": 0},
        "evaluate": {"lpips": False}}


@pytest.fixture(scope="module")
def tiny_layout_scene(tmp_path_factory):
    import simulate
    from schemas.scene_loader import load_scene

    root = tmp_path_factory.mktemp("abl") / "rooms"
    simulate.generate_scene(root, preset="cuboid", views=2, test_views=1, height=16, seed=1, effects="none",
                            with_layout=True, with_depth=True)
    return load_scene(root)


def test_ablation_end_to_end(tiny_layout_scene, tmp_path):
    base = tmp_path / "run"
    res = E.run_ablation(tiny_layout_scene, base, TINY, seeds=1, iterations=2, log=lambda *a: None, equal="pixels")
    doc = json.loads(res["json"].read_text())
    assert [v["label"] for v in doc["variants"]] == ["3D-GS*", "+ layout init", "+ 360 splatting", "+ layout reg"]
    runs = [v["runs"][0] for v in doc["variants"]]
    assert [r["train"]["init"] for r in runs] == ["random", "layout+depth", "layout+depth", "layout+depth"]
    assert [r["train"]["projection"] for r in runs] == ["crops", "crops", "360", "360"]
    # the baseline's test panoramas are stitched from its crops; it trains on 8 crops per panorama
    assert [r["stitched"] for r in runs] == ["8 crops of 120°, 16 px"] * 2 + [None] * 2
    assert [r["train_images"] for r in runs] == [16, 16, 2, 2]
    assert [r["train"]["layout_reg"] for r in runs] == [False, False, False, True]
    assert all(r["train"]["iterations"] == 2 and r["psnr"] > 5 for r in runs)
    # equal pixels: a 16-px crop has half a 16x32 panorama's pixels, so the crops get 4 iterations
    eq = doc["equal_budget"]["row"]
    assert eq["key"] == "layout-init-equal-pixels" and eq["runs"][0]["train"]["iterations"] == 4
    assert eq["runs"][0]["train"]["projection"] == "crops" and "| equal pixels |" in doc["equal_budget"]["table"]
    assert len(res["notes"]) == 5 and not doc["warnings"]
    # upstream stages are shared: every variant holds the base run's artifacts, same keys
    for stage in ("layout", "union", "sampling", "align"):
        key = json.loads((base / stage / "artifact.json").read_text())["meta"]["key"]
        for v in ("3dgs-s0", "360-s0"):
            assert json.loads((base / "ablate" / v / stage / "artifact.json").read_text())["meta"]["key"] == key
    assert res["chart"].stat().st_size > 1000 and "| 3D-GS* |" in res["markdown"].read_text()
    # a second sweep-style run on the same base folder reuses everything upstream
    sw = E.run_sweep(tiny_layout_scene, base, TINY, iterations=[2], heights=[8, 16], caps=[None],
                     log=lambda *a: None)
    pts = sw["points"]
    assert [p.height for p in pts] == [8, 16] and all(p.psnr is not None and p.fps > 0 for p in pts)
    assert any(p.pareto_time for p in pts)
    ev = json.loads((base / "sweep" / pts[0].label / "evaluate" / "artifact.json").read_text())
    assert ev["data"]["resolution"] == [16, 32]  # every point evaluated at the largest training size
