"""360° Gaussian splatting (the "360-GS" renderer of pano-pipe).

    import splatting
    out = splatting.render(means, quats, scales, opacities, colors, viewmat,
                           splatting.EquirectCamera(512, 1024))

See docs/splatting.md for the math, the backends and the edge cases.
"""

from .cameras import CUBEMAP_FACE_NAMES, EquirectCamera, PinholeCamera, cubemap_faces
from .render import RenderOutput, render, render_cubemap
from .sh import eval_sh, num_sh_bases

__all__ = [
    "render",
    "render_cubemap",
    "RenderOutput",
    "EquirectCamera",
    "PinholeCamera",
    "cubemap_faces",
    "CUBEMAP_FACE_NAMES",
    "eval_sh",
    "num_sh_bases",
]
