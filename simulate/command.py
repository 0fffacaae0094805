"""`pano-pipe simulate`: a typer-compatible command function (registered by the CLI)."""

from __future__ import annotations

from pathlib import Path

import typer

from simulate.effects import EFFECTS, OPT_IN_EFFECTS
from simulate.generate import PRESETS, SimulationResult, generate_scene

PHASE_ORDER = (
    "scene", "raycast", "furniture", "fixtures", "texture", "shading", "aa",
    "tripod", "exposure", "noise", "layout", "write",
)
PHASE_HELP = {
    "scene": "room, doorways, lights, cameras",
    "raycast": "ground-truth pass: one ray per pixel centre (shell)",
    "furniture": "placing boxes + ray-box tests (all passes)",
    "fixtures": "placing the lamps (their ray-box tests count under furniture)",
    "texture": "procedural albedo",
    "shading": "normals + Lambertian ceiling lights",
    "aa": "extra N x N sub-pixel rays (shell) + box filter",
    "tripod": "dark blob at the nadir (tripod / hand) + its mask",
    "exposure": "per-view gain + white balance",
    "noise": "sensor noise",
    "layout": "gt layout boundaries + HorizonNet corners",
    "write": "PNG / npy / JSON files",
    "other": "colour look-ups, clipping, bookkeeping",
}


def profile_table(result: SimulationResult, title: str | None = None):
    """A rich Table of the time each phase / effect took (seconds and share of the total)."""
    from rich.table import Table

    total = result.timings.get("total", sum(v for k, v in result.timings.items() if k != "total"))
    table = Table(title=title or f"simulate profile ({', '.join(result.effects) or 'no effects'})")
    table.add_column("phase / effect")
    table.add_column("seconds", justify="right")
    table.add_column("share", justify="right")
    keys = [k for k in PHASE_ORDER if k in result.timings] + sorted(
        k for k in result.timings if k not in PHASE_ORDER and k != "total"
    )
    for k in keys:
        v = result.timings[k]
        table.add_row(k, f"{v:.3f}", f"{100.0 * v / total:.1f}%" if total > 0 else "-")
    other = total - sum(result.timings[k] for k in keys)
    table.add_row("other", f"{other:.3f}", f"{100.0 * other / total:.1f}%" if total > 0 else "-")
    table.add_row("total", f"{total:.3f}", "100.0%", style="bold")
    return table


def simulate_command(
    out: Path = typer.Argument(..., help="Scene folder to write (replaced atomically if it exists)."),
    preset: str = typer.Option("cuboid", "--preset", help=f"Room preset: {', '.join(PRESETS)}."),
    views: int = typer.Option(4, "--views", help="Number of train panoramas."),
    test_views: int = typer.Option(2, "--test-views", help="Number of held-out test panoramas."),
    height: int = typer.Option(256, "--height", help="Image height in pixels (width = 2 x height)."),
    seed: int = typer.Option(0, "--seed", help="Random seed (the scene is deterministic for a seed)."),
    effects: str = typer.Option(
        "all", "--effects", help=f"Comma-separated effects from {', '.join(EFFECTS)}, or 'all' / 'none' "
        "('all' for the demo preset: texture, furniture, shading, aa; 'all' never includes the opt-in "
        f"{'; '.join(f'{k}: {v}' for k, v in OPT_IN_EFFECTS.items())}; name them).",
    ),
    aa_samples: int = typer.Option(2, "--aa-samples", help="Anti-aliasing: N x N samples per pixel."),
    with_layout: bool = typer.Option(
        False, "--with-layout", help="Also supply the gt layout as layout/ input (train views)."
    ),
    with_depth: bool = typer.Option(
        False, "--with-depth", help="Also supply the gt depth as depth/ input (train views)."
    ),
    walk: bool = typer.Option(
        False, "--walk", help="Train cameras along a walk through the rooms (a chain; presets with doorways)."
    ),
    tripod_height: float | None = typer.Option(
        None, "--tripod-height", help="Every camera at this height (m), as one tripod takes a capture."
    ),
    test_placement: str = typer.Option(
        "near", "--test-placement", help="Test cameras 'near' the train cameras (0.35-1 m, interpolation) or "
        "'away' from them (>= 1 m, anywhere in the free space: a walk-through of a sparse capture).",
    ),
    profile: bool = typer.Option(False, "--profile", help="Print the time each effect / phase took."),
) -> SimulationResult:
    """Write a synthetic indoor scene folder with exact ground truth (depth, layout, floor plan)."""
    from rich.markup import escape

    from runtime.console import console

    result = generate_scene(
        Path(out),
        preset=preset,
        views=views,
        test_views=test_views,
        height=height,
        seed=seed,
        effects=effects,
        aa_samples=aa_samples,
        with_layout=with_layout,
        with_depth=with_depth,
        walk=walk,
        tripod_height=tripod_height,
        test_placement=test_placement,
    )
    console.print(
        f"wrote {escape(str(result.manifest_path))} ({len(result.views)} views, {height}x{2 * height}, "
        f"effects: {', '.join(result.effects) or 'none'}) in {result.timings['total']:.2f} s"
    )
    if profile:
        console.print(profile_table(result))
    return result
