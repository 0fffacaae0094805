"""Synthetic indoor panorama scenes with exact ground truth (issue 3).

    from simulate import generate_scene, PRESETS, EFFECTS
    res = generate_scene(Path("scenes/demo"), preset="demo", views=4, test_views=2,
                         height=256, seed=0, effects="all")
    res.manifest_path, res.timings

See docs/simulator.md for the conventions, presets and effects.
"""

from simulate.effects import EFFECTS
from simulate.generate import PRESETS, SimulationResult, generate_scene, parse_effects

__all__ = ["EFFECTS", "PRESETS", "SimulationResult", "generate_scene", "parse_effects"]
