"""The Gaussian model: plain tensors in the parametrisation of the original 3DGS.

Trainable tensors live in raw (unconstrained) form, exactly what the standard
PLY stores: log scales, logit opacities, un-normalised (w, x, y, z)
quaternions, SH coefficients without the +0.5 offset (the renderer adds it).
Three bookkeeping tensors ride along for the layout regulariser:
`is_layout` (initialised from the layout cloud), `normals` (the plane normal,
into the room) and `u0` (the initial position the regulariser measures from).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from splatting.render import DEFAULT_EPS2D

__all__ = ["Gaussians", "PARAM_NAMES", "BUFFER_NAMES", "SH_C0", "rgb_to_sh", "sh_to_rgb", "render", "render_stitched"]

SH_C0 = 0.28209479177387814

#: The optimised tensors, in the order the optimiser and checkpoints use.
PARAM_NAMES = ("means", "quats", "log_scales", "opacity_logits", "sh_dc", "sh_rest")
#: Per-Gaussian bookkeeping that densification carries along but nothing optimises.
BUFFER_NAMES = ("is_layout", "normals", "u0")


def rgb_to_sh(rgb: torch.Tensor) -> torch.Tensor:
    """Degree-0 SH coefficient whose colour (with the renderer's +0.5) is `rgb`."""
    return (rgb - 0.5) / SH_C0


def sh_to_rgb(sh_dc: torch.Tensor) -> torch.Tensor:
    return sh_dc * SH_C0 + 0.5


@dataclass
class Gaussians:
    """N Gaussians. Shapes: means [N,3], quats [N,4] (w,x,y,z), log_scales [N,3],
    opacity_logits [N], sh_dc [N,1,3], sh_rest [N,K-1,3] (K = (degree+1)²),
    is_layout [N] bool, normals [N,3], u0 [N,3]."""

    means: torch.Tensor
    quats: torch.Tensor
    log_scales: torch.Tensor
    opacity_logits: torch.Tensor
    sh_dc: torch.Tensor
    sh_rest: torch.Tensor
    is_layout: torch.Tensor
    normals: torch.Tensor
    u0: torch.Tensor
    #: The renderer's screen-space dilation (squared pixels) the model was fitted with; every render
    #: of it uses this one, as the same Gaussians drawn with another dilation lose their fit
    #: (docs/training.md, "The sampling grid and the dilation"). Stored in the PLY as a comment.
    eps2d: float = DEFAULT_EPS2D

    def __post_init__(self):
        n = self.means.shape[0]
        expect = {
            "means": (n, 3), "quats": (n, 4), "log_scales": (n, 3), "opacity_logits": (n,),
            "is_layout": (n,), "normals": (n, 3), "u0": (n, 3),
        }
        for name, shape in expect.items():
            got = tuple(getattr(self, name).shape)
            if got != shape:
                raise ValueError(f"Gaussians.{name}: expected shape {list(shape)}, got {list(got)}")
        if tuple(self.sh_dc.shape) != (n, 1, 3):
            raise ValueError(f"Gaussians.sh_dc: expected shape [{n}, 1, 3], got {list(self.sh_dc.shape)}")
        if self.sh_rest.ndim != 3 or self.sh_rest.shape[0] != n or self.sh_rest.shape[2] != 3:
            raise ValueError(f"Gaussians.sh_rest: expected shape [{n}, K-1, 3], got {list(self.sh_rest.shape)}")
        k = self.sh_rest.shape[1] + 1
        if int(round(math.sqrt(k))) ** 2 != k or k > 16:
            raise ValueError(f"Gaussians.sh_rest: {k} SH bases per channel is not (degree+1)² for degree 0..3")
        if self.is_layout.dtype != torch.bool:
            raise ValueError("Gaussians.is_layout must be a bool tensor")

    # -- shape -------------------------------------------------------------
    def __len__(self) -> int:
        return int(self.means.shape[0])

    @property
    def num(self) -> int:
        return len(self)

    @property
    def sh_degree(self) -> int:
        """The largest SH degree the coefficients hold (0..3)."""
        return int(round(math.sqrt(self.sh_rest.shape[1] + 1))) - 1

    # -- derived quantities -----------------------------------------------
    @property
    def scales(self) -> torch.Tensor:
        return torch.exp(self.log_scales)

    @property
    def opacities(self) -> torch.Tensor:
        return torch.sigmoid(self.opacity_logits)

    @property
    def sh(self) -> torch.Tensor:
        """[N, K, 3] all SH coefficients."""
        return torch.cat([self.sh_dc, self.sh_rest], dim=1)

    # -- construction / conversion ---------------------------------------
    @classmethod
    def create(
        cls,
        means,
        colors=None,
        log_scales=None,
        quats=None,
        opacity_logits=None,
        sh_degree: int = 3,
        is_layout=None,
        normals=None,
        u0=None,
        dtype=torch.float32,
    ) -> Gaussians:
        """Convenience constructor with sensible defaults (grey, 1 cm, identity rotation, opacity 0.1)."""
        means = torch.as_tensor(means, dtype=dtype).reshape(-1, 3)
        n = means.shape[0]
        colors = torch.full((n, 3), 0.5, dtype=dtype) if colors is None else torch.as_tensor(colors, dtype=dtype)
        k = (sh_degree + 1) ** 2
        quats_t = torch.tensor([1.0, 0, 0, 0], dtype=dtype).repeat(n, 1) if quats is None else quats
        return cls(
            means=means,
            quats=torch.as_tensor(quats_t, dtype=dtype),
            log_scales=(torch.full((n, 3), math.log(0.01), dtype=dtype) if log_scales is None
                        else torch.as_tensor(log_scales, dtype=dtype)),
            opacity_logits=(torch.full((n,), math.log(0.1 / 0.9), dtype=dtype) if opacity_logits is None
                            else torch.as_tensor(opacity_logits, dtype=dtype)),
            sh_dc=rgb_to_sh(colors.reshape(n, 1, 3)),
            sh_rest=torch.zeros((n, k - 1, 3), dtype=dtype),
            is_layout=(torch.zeros(n, dtype=torch.bool) if is_layout is None
                       else torch.as_tensor(is_layout, dtype=torch.bool)),
            normals=torch.zeros((n, 3), dtype=dtype) if normals is None else torch.as_tensor(normals, dtype=dtype),
            u0=means.clone() if u0 is None else torch.as_tensor(u0, dtype=dtype),
        )

    def tensors(self) -> dict[str, torch.Tensor]:
        return {k: getattr(self, k) for k in PARAM_NAMES + BUFFER_NAMES}

    def params(self) -> dict[str, torch.Tensor]:
        return {k: getattr(self, k) for k in PARAM_NAMES}

    def detach(self) -> Gaussians:
        """A copy cut from autograd (new leaf tensors, same values)."""
        return Gaussians(**{k: v.detach().clone() for k, v in self.tensors().items()}, eps2d=self.eps2d)

    def to(self, device=None, dtype=None) -> Gaussians:
        out = {}
        for k, v in self.tensors().items():
            out[k] = v.to(device=device) if v.dtype == torch.bool else v.to(device=device, dtype=dtype)
        return Gaussians(**out, eps2d=self.eps2d)

    def requires_grad_(self, flag: bool = True) -> Gaussians:
        for k in PARAM_NAMES:
            getattr(self, k).requires_grad_(flag)
        return self

    def index(self, idx) -> Gaussians:
        """The subset `idx` (bool mask or index tensor), detached."""
        return Gaussians(**{k: v.detach()[idx].clone() for k, v in self.tensors().items()}, eps2d=self.eps2d)

    @staticmethod
    def cat(parts: list[Gaussians]) -> Gaussians:
        return Gaussians(**{k: torch.cat([getattr(p, k).detach() for p in parts], 0)
                            for k in PARAM_NAMES + BUFFER_NAMES}, eps2d=parts[0].eps2d)

    def with_sh_degree(self, degree: int) -> Gaussians:
        """A copy holding `degree` SH bands (extra bands dropped, missing ones zero)."""
        k = (degree + 1) ** 2 - 1
        rest = self.sh_rest.detach()
        if rest.shape[1] >= k:
            rest = rest[:, :k].clone()
        else:
            rest = torch.cat([rest, rest.new_zeros(len(self), k - rest.shape[1], 3)], 1)
        g = self.detach()
        g.sh_rest = rest
        return g


def _splat_args(g: Gaussians, viewmat, background, sh_degree: int | None):
    """The splatting arguments of `g`: (means, quats, scales, opacities, colors, viewmat), the SH
    degree and the background, as tensors of the model's dtype and device."""
    degree = g.sh_degree if sh_degree is None else int(sh_degree)
    if not 0 <= degree <= g.sh_degree:
        raise ValueError(f"sh_degree {degree} outside 0..{g.sh_degree} (the bands this model holds)")
    k = (degree + 1) ** 2
    # only the bands in use enter the graph, so the others get no gradient (and no optimiser work)
    colors = g.sh_dc if k == 1 else torch.cat([g.sh_dc, g.sh_rest[:, : k - 1]], dim=1)
    viewmat = torch.as_tensor(viewmat, dtype=g.means.dtype, device=g.means.device)
    if background is not None:
        background = torch.as_tensor(background, dtype=g.means.dtype, device=g.means.device)
    args = (g.means, g.quats, torch.exp(g.log_scales), torch.sigmoid(g.opacity_logits), colors, viewmat)
    return args, degree, background


def render(
    g: Gaussians,
    viewmat: torch.Tensor,
    camera,
    backend: str | None = None,
    background=None,
    sh_degree: int | None = None,
    **kwargs,
):
    """Render `g` with the splatting package. `viewmat` is world-to-camera [4,4];
    `camera` a splatting.EquirectCamera or PinholeCamera; `sh_degree` (default:
    all bands the model holds) selects how many SH bands are evaluated.
    Returns splatting's output (.image [H,W,3], .alpha, .depth, .means2d, .radii, ...)."""
    import splatting

    args, degree, background = _splat_args(g, viewmat, background, sh_degree)
    kwargs.setdefault("eps2d", g.eps2d)
    return splatting.render(*args, camera, sh_degree=degree, background=background, backend=backend, **kwargs)


def render_stitched(
    g: Gaussians,
    viewmat: torch.Tensor,
    height: int,
    width: int,
    rig,
    backend: str | None = None,
    background=None,
    sh_degree: int | None = None,
    **kwargs,
):
    """An equirectangular `height` × `width` image of `g` stitched from the crops of `rig` (a
    splatting.PerspectiveRig): the perspective baseline's panorama (splatting.render_stitched)."""
    import splatting

    args, degree, background = _splat_args(g, viewmat, background, sh_degree)
    kwargs.setdefault("eps2d", g.eps2d)
    return splatting.render_stitched(*args, height, width, rig, sh_degree=degree, background=background,
                                     backend=backend, **kwargs)
