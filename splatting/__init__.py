"""360° Gaussian splatting (the "360-GS" renderer of pano-pipe).

    import splatting
    out = splatting.render(means, quats, scales, opacities, colors, viewmat,
                           splatting.EquirectCamera(512, 1024))

See docs/splatting.md for the math, the backends and the edge cases.
"""

from .cameras import (
    CUBEMAP_FACE_NAMES,
    PAPER_CROPS,
    EquirectCamera,
    PerspectiveRig,
    PinholeCamera,
    crop_rig,
    cubemap_faces,
    cubemap_rig,
)
from .render import DEFAULT_TILE, MAX_TILE, RenderOutput, render
from .stitch import render_cubemap, render_stitched, stitch, stitch_table
from .sh import eval_sh, num_sh_bases

__all__ = [
    "render",
    "render_cubemap",
    "render_stitched",
    "stitch",
    "stitch_table",
    "RenderOutput",
    "DEFAULT_TILE",
    "MAX_TILE",
    "EquirectCamera",
    "PinholeCamera",
    "cubemap_faces",
    "cubemap_rig",
    "crop_rig",
    "PerspectiveRig",
    "PAPER_CROPS",
    "CUBEMAP_FACE_NAMES",
    "eval_sh",
    "num_sh_bases",
]
