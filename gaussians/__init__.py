"""3D Gaussians for pano-pipe: the model, its initialisation, PLY I/O, losses and density control.

    from gaussians import Gaussians, save_ply, load_ply, render
"""

from gaussians.model import BUFFER_NAMES, PARAM_NAMES, SH_C0, Gaussians, render, rgb_to_sh, sh_to_rgb
from gaussians.ply import load_ply, save_ply

__all__ = [
    "Gaussians",
    "PARAM_NAMES",
    "BUFFER_NAMES",
    "SH_C0",
    "rgb_to_sh",
    "sh_to_rgb",
    "render",
    "save_ply",
    "load_ply",
]
