"""Depth Anything V2 (Yang et al., 2024) in torch: a DINOv2 ViT encoder and a DPT head.

Written here from the published architecture so that the official checkpoints
(`depth_anything_v2_vits.pth`, a bare state dict) load with `strict=True`:
module and parameter names follow the official state-dict keys
(`pretrained.*` the encoder, `depth_head.*` the head).

    model = load_checkpoint("depth_anything_v2_vits.pth")      # ViT-S/14, 24.8 M parameters
    disparity = model(normalize(rgb))                          # [B,H,W], H and W multiples of 14
    export_onnx("depth_anything_v2_vits.pth", "da2_small.onnx")

Input: RGB in [0,1], ImageNet mean/std normalised, NCHW, sides multiples of
14 (the official `infer_image` resizes to 518 on the short side). Output:
relative inverse depth (affine-invariant disparity) at the input resolution,
clamped at 0 by the final ReLU. The exported ONNX has dynamic batch, height
and width: the position-embedding interpolation is written as two bicubic
weight matrices built from the input size (identical to torch's bicubic with
the official scale factor), not as a resize whose scale the tracer would
freeze. See docs/depth.md.
"""

from __future__ import annotations

import warnings
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from depthnet.runner import write_metadata
from runfs.checkpoints import load_weights
from runfs.errors import PanoError

PATCH = 14
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
MAX_DIFF = 1e-4  # onnxruntime vs torch on the export check, as `onnx_vs_torch` measures it
# What the depth stage reads from an exported model's metadata (depthnet.runner.DepthContract fields).
CONTRACT = {
    "output": "disparity",
    "normalization": "imagenet",
    "multiple_of": PATCH,
    "projection": "cubemap",
}


@dataclass(frozen=True)
class Config:
    """One Depth Anything V2 size. Only `small` has a licence that lets us offer it (Apache-2.0)."""

    name: str = "vits"
    embed_dim: int = 384
    depth: int = 12
    num_heads: int = 6
    features: int = 64
    out_channels: tuple[int, int, int, int] = (48, 96, 192, 384)
    layers: tuple[int, int, int, int] = (2, 5, 8, 11)  # the blocks whose outputs the DPT head reads
    pretrain_size: int = 518  # DINOv2's position embeddings cover 37 x 37 patches


SMALL = Config()
BASE = Config("vitb", 768, 12, 12, 128, (96, 192, 384, 768), (2, 5, 8, 11))
LARGE = Config("vitl", 1024, 24, 16, 256, (256, 512, 1024, 1024), (4, 11, 17, 23))
CONFIGS = {c.name: c for c in (SMALL, BASE, LARGE)}


# ----------------------------------------------------------------------------- DINOv2 encoder


class PatchEmbed(nn.Module):
    def __init__(self, dim: int):
        super().__init__()
        self.proj = nn.Conv2d(3, dim, kernel_size=PATCH, stride=PATCH)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.proj(x).flatten(2).transpose(1, 2)  # [B, rows*cols, C], row-major patches


class Attention(nn.Module):
    def __init__(self, dim: int, num_heads: int):
        super().__init__()
        self.num_heads = num_heads
        self.scale = (dim // num_heads) ** -0.5
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b, n, c = x.shape
        qkv = self.qkv(x).reshape(b, n, 3, self.num_heads, c // self.num_heads).permute(2, 0, 3, 1, 4)
        q, k, v = qkv[0] * self.scale, qkv[1], qkv[2]
        attn = (q @ k.transpose(-2, -1)).softmax(dim=-1)
        return self.proj((attn @ v).transpose(1, 2).reshape(b, n, c))


class Mlp(nn.Module):
    def __init__(self, dim: int, hidden: int):
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.act = nn.GELU()
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(self.act(self.fc1(x)))


class LayerScale(nn.Module):
    def __init__(self, dim: int, init: float = 1.0):
        super().__init__()
        self.gamma = nn.Parameter(torch.full((dim,), init))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.gamma


class Block(nn.Module):
    """Pre-norm transformer block with LayerScale on both residual branches."""

    def __init__(self, dim: int, num_heads: int):
        super().__init__()
        self.norm1 = nn.LayerNorm(dim, eps=1e-6)
        self.attn = Attention(dim, num_heads)
        self.ls1 = LayerScale(dim)
        self.norm2 = nn.LayerNorm(dim, eps=1e-6)
        self.mlp = Mlp(dim, 4 * dim)
        self.ls2 = LayerScale(dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        x = x + self.ls1(self.attn(self.norm1(x)))
        return x + self.ls2(self.mlp(self.norm2(x)))


def _cubic_weights(t: torch.Tensor, a: float = -0.75) -> list[torch.Tensor]:
    """Keys' cubic convolution weights of the taps at offsets -1, 0, 1, 2 (torch's bicubic, A = -0.75)."""

    def near(x):  # |x| <= 1
        return ((a + 2) * x - (a + 3)) * x * x + 1

    def far(x):  # 1 < |x| < 2
        return ((a * x - 5 * a) * x + 8 * a) * x - 4 * a

    return [far(t + 1), near(t), near(1 - t), far(2 - t)]


def bicubic_matrix(n_out, n_in: int, offset: float, like: torch.Tensor) -> torch.Tensor:
    """[n_out, n_in] weights of torch's bicubic resize (align_corners=False) with scale factor
    (n_out + offset) / n_in, as DINOv2 interpolates its position embeddings.

    Torch maps output index i to source (i + 0.5) / factor - 0.5 and clamps the
    taps at the border. Built from tensor ops, so `n_out` may be a traced size
    and the ONNX export keeps it dynamic.
    """
    dst = torch.arange(n_out, dtype=like.dtype, device=like.device)
    n = dst.new_ones(dst.shape).sum()  # n_out as a (traced) float
    src = (dst + 0.5) * (n_in / (n + offset)) - 0.5
    i0 = torch.floor(src)
    weights = _cubic_weights(src - i0)
    cols = torch.arange(n_in, dtype=like.dtype, device=like.device)
    m = torch.zeros_like(dst)[:, None] * cols[None]  # zeros [n_out, n_in], traceable
    for k, w in enumerate(weights):
        tap = (i0 + (k - 1)).clamp(0, n_in - 1)
        m = m + w[:, None] * (tap[:, None] == cols[None]).to(like.dtype)
    return m


class DinoVisionTransformer(nn.Module):
    """DINOv2 ViT/14 (no register tokens) as Depth Anything V2 uses it."""

    def __init__(self, cfg: Config):
        super().__init__()
        dim = cfg.embed_dim
        self.grid = cfg.pretrain_size // PATCH
        self.patch_embed = PatchEmbed(dim)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, dim))
        self.pos_embed = nn.Parameter(torch.zeros(1, self.grid * self.grid + 1, dim))
        self.mask_token = nn.Parameter(torch.zeros(1, dim))  # unused at inference; part of the checkpoint
        self.blocks = nn.ModuleList(Block(dim, cfg.num_heads) for _ in range(cfg.depth))
        self.norm = nn.LayerNorm(dim, eps=1e-6)
        nn.init.trunc_normal_(self.pos_embed, std=0.02)
        nn.init.normal_(self.cls_token, std=1e-6)
        for m in self.modules():
            if isinstance(m, nn.Linear):
                nn.init.trunc_normal_(m.weight, std=0.02)
                nn.init.zeros_(m.bias)

    def position_embedding(self, height: int, width: int) -> torch.Tensor:
        """[1, 1 + rows*cols, C] for an image of height x width pixels.

        DINOv2 resizes its 37 x 37 grid bicubically with scale factor
        (cells + 0.1) / 37 (the 0.1 avoids a floating-point off-by-one), and
        uses the grid unchanged for a square input of exactly 37 x 37 patches.
        """
        pos = self.pos_embed
        cls_pos, grid = pos[:, :1], pos[0, 1:].reshape(self.grid, self.grid, -1)
        rows, cols = height // PATCH, width // PATCH
        my = bicubic_matrix(rows, self.grid, 0.1, pos)
        mx = bicubic_matrix(cols, self.grid, 0.1, pos)
        # The official code returns the stored grid when the image is square with as many patches
        # as the grid. A 0/1 flag computed from the (possibly traced) sizes blends towards the
        # identity, so no Python branch freezes one case into the exported graph.
        grid_idx = torch.arange(self.grid, device=pos.device)
        eye_y = (torch.arange(rows, device=pos.device)[:, None] == grid_idx).to(pos.dtype)
        eye_x = (torch.arange(cols, device=pos.device)[:, None] == grid_idx).to(pos.dtype)
        n_rows = my.new_ones(my.shape[:1]).sum()
        square = my.new_ones(()) * height == width
        native = ((n_rows == self.grid) & square).to(pos.dtype)
        my = my + native * (eye_y - my)
        mx = mx + native * (eye_x - mx)
        patch_pos = torch.einsum("ia,abc,jb->ijc", my, grid, mx).reshape(1, -1, grid.shape[-1])
        return torch.cat([cls_pos, patch_pos], dim=1)

    def tokens(self, x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[-2:]
        t = self.patch_embed(x)
        t = torch.cat([self.cls_token.expand(t.shape[0], -1, -1), t], dim=1)
        return t + self.position_embedding(h, w)

    def intermediate_layers(self, x: torch.Tensor, layers) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """(patch tokens [B,N,C], class token [B,C]) after the final norm, for each block in `layers`."""
        t = self.tokens(x)
        out = []
        for i, blk in enumerate(self.blocks):
            t = blk(t)
            if i in layers:
                n = self.norm(t)
                out.append((n[:, 1:], n[:, 0]))
        return out


# ----------------------------------------------------------------------------- DPT head


class ResidualConvUnit(nn.Module):
    def __init__(self, features: int):
        super().__init__()
        self.conv1 = nn.Conv2d(features, features, 3, padding=1)
        self.conv2 = nn.Conv2d(features, features, 3, padding=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x + self.conv2(F.relu(self.conv1(F.relu(x))))


class FeatureFusionBlock(nn.Module):
    """Adds the skip features (after a residual unit), refines, upsamples (align_corners), projects."""

    def __init__(self, features: int):
        super().__init__()
        self.out_conv = nn.Conv2d(features, features, 1)
        self.resConfUnit1 = ResidualConvUnit(features)  # noqa: N815 (checkpoint key names)
        self.resConfUnit2 = ResidualConvUnit(features)  # noqa: N815

    def forward(self, x: torch.Tensor, skip: torch.Tensor | None = None, size=None) -> torch.Tensor:
        if skip is not None:
            x = x + self.resConfUnit1(skip)
        x = self.resConfUnit2(x)
        if size is None:
            x = F.interpolate(x, scale_factor=2.0, mode="bilinear", align_corners=True)
        else:
            x = F.interpolate(x, size=size, mode="bilinear", align_corners=True)
        return self.out_conv(x)


class DPTHead(nn.Module):
    def __init__(self, in_dim: int, features: int, out_channels):
        super().__init__()
        c1, c2, c3, c4 = out_channels
        self.projects = nn.ModuleList(nn.Conv2d(in_dim, c, 1) for c in out_channels)
        self.resize_layers = nn.ModuleList(
            [
                nn.ConvTranspose2d(c1, c1, kernel_size=4, stride=4),  # 1/14 -> 4/14
                nn.ConvTranspose2d(c2, c2, kernel_size=2, stride=2),  # 1/14 -> 2/14
                nn.Identity(),
                nn.Conv2d(c4, c4, kernel_size=3, stride=2, padding=1),  # 1/14 -> 1/28
            ]
        )
        scratch = nn.Module()
        for k, c in enumerate(out_channels, start=1):
            setattr(scratch, f"layer{k}_rn", nn.Conv2d(c, features, 3, padding=1, bias=False))
        for k in range(1, 5):
            setattr(scratch, f"refinenet{k}", FeatureFusionBlock(features))
        scratch.output_conv1 = nn.Conv2d(features, features // 2, 3, padding=1)
        scratch.output_conv2 = nn.Sequential(
            nn.Conv2d(features // 2, 32, 3, padding=1),
            nn.ReLU(),
            nn.Conv2d(32, 1, 1),
            nn.ReLU(),
            nn.Identity(),
        )
        self.scratch = scratch

    def forward(self, feats, rows, cols, out_hw) -> torch.Tensor:
        s = self.scratch
        maps = []
        for i, (tokens, _cls) in enumerate(feats):
            x = tokens.permute(0, 2, 1).reshape(tokens.shape[0], tokens.shape[-1], rows, cols)
            maps.append(self.resize_layers[i](self.projects[i](x)))
        l1, l2, l3, l4 = (getattr(s, f"layer{k}_rn")(m) for k, m in enumerate(maps, start=1))
        p4 = s.refinenet4(l4, size=l3.shape[2:])
        p3 = s.refinenet3(p4, l3, size=l2.shape[2:])
        p2 = s.refinenet2(p3, l2, size=l1.shape[2:])
        p1 = s.refinenet1(p2, l1)
        out = F.interpolate(s.output_conv1(p1), size=out_hw, mode="bilinear", align_corners=True)
        return s.output_conv2(out)


class DepthAnythingV2(nn.Module):
    """x [B,3,H,W] ImageNet-normalised, H and W multiples of 14 -> relative disparity [B,H,W] (>= 0)."""

    def __init__(self, cfg: Config = SMALL):
        super().__init__()
        self.cfg = cfg
        self.pretrained = DinoVisionTransformer(cfg)
        self.depth_head = DPTHead(cfg.embed_dim, cfg.features, cfg.out_channels)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        h, w = x.shape[-2:]
        rows, cols = h // PATCH, w // PATCH
        feats = self.pretrained.intermediate_layers(x, self.cfg.layers)
        # The official head upsamples to (rows*14, cols*14): the input size for valid inputs.
        depth = self.depth_head(feats, rows, cols, (h, w))
        return F.relu(depth).squeeze(1)


def normalize(rgb: torch.Tensor) -> torch.Tensor:
    """[B,3,H,W] RGB in [0,1] -> the network's input (ImageNet mean/std)."""
    mean = torch.tensor(IMAGENET_MEAN, dtype=rgb.dtype, device=rgb.device).view(1, 3, 1, 1)
    std = torch.tensor(IMAGENET_STD, dtype=rgb.dtype, device=rgb.device).view(1, 3, 1, 1)
    return (rgb - mean) / std


# ----------------------------------------------------------------------------- checkpoints and ONNX


def _config_from_state_dict(sd: dict) -> Config:
    dim_key = "pretrained.patch_embed.proj.weight"
    if dim_key not in sd:
        raise ValueError("no pretrained.patch_embed.proj.weight: not a Depth Anything V2 state dict")
    dim = sd[dim_key].shape[0]
    for cfg in CONFIGS.values():
        if cfg.embed_dim == dim:
            return cfg
    raise ValueError(f"encoder width {dim} is not ViT-S/B/L (384/768/1024)")


def load_checkpoint(path: str | Path) -> DepthAnythingV2:
    """An official Depth Anything V2 checkpoint (a bare state dict, as the authors publish it),
    loaded strictly; a {'state_dict': ...} or {'model': ...} wrapper and 'module.' prefixes too."""
    path = Path(path)
    if not path.is_file():
        raise PanoError(path, "checkpoint file does not exist")
    sd = load_weights(path)
    if isinstance(sd, dict):
        for wrapper in ("state_dict", "model"):
            if isinstance(sd.get(wrapper), dict):
                sd = sd[wrapper]
    if not isinstance(sd, dict) or not sd or not all(isinstance(v, torch.Tensor) for v in sd.values()):
        raise PanoError(path, "expected a state dict of tensors (depth_anything_v2_vits.pth)")
    sd = {k.removeprefix("module."): v for k, v in sd.items()}
    try:
        model = DepthAnythingV2(_config_from_state_dict(sd))
        model.load_state_dict(sd, strict=True)
    except (RuntimeError, ValueError) as e:
        msg = " ".join(str(e).split())
        raise PanoError(path, f"does not load into Depth Anything V2: {msg[:300]}") from None
    return model.eval()


class _Exported(nn.Module):
    """What the ONNX file computes: normalised image -> disparity [B,1,H,W] (the runner's layout)."""

    def __init__(self, model: DepthAnythingV2):
        super().__init__()
        self.model = model

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.model(x)[:, None]


def export_module(
    model: DepthAnythingV2,
    out: str | Path,
    check_size: tuple[int, int] = (98, 140),
    opset: int = 17,
    seed: int = 0,
    face_size: int = 518,
) -> float:
    """Export `model` to ONNX (dynamic batch, height and width) with the depth contract in its
    metadata. Checked on random inputs of `check_size` and of a second size (a size frozen into
    the graph would fail there): returns the difference `onnx_vs_torch` measures, which must be
    at most MAX_DIFF."""
    if opset < 17:
        raise PanoError("--opset", f"opset {opset} is too old: use 17 or newer")
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    module = _Exported(model.eval()).eval()
    g = torch.Generator().manual_seed(seed)
    h, w = check_size
    if h % PATCH or w % PATCH:
        raise ValueError(f"check size {h}x{w} is not a multiple of {PATCH}")
    x = normalize(torch.rand(1, 3, h, w, generator=g))
    tmp = out.with_name(out.name + ".partial")
    try:
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the tracer's notes on traced sizes: meant to be dynamic
            torch.onnx.export(
                module,
                (x,),
                str(tmp),
                dynamo=False,
                opset_version=opset,
                input_names=["image"],
                output_names=["disparity"],
                dynamic_axes={"image": {0: "batch", 2: "height", 3: "width"},
                              "disparity": {0: "batch", 2: "height", 3: "width"}},
                do_constant_folding=True,
            )
        write_metadata(
            tmp,
            {**CONTRACT, "face_size": face_size},
            {"architecture": f"Depth Anything V2 ({model.cfg.name})", "depth_model": "affine inverse depth",
             "config": asdict(model.cfg)},
        )
        session = _session(tmp)
        diff = max(
            onnx_vs_torch(module, session, normalize(torch.rand(1, 3, *size, generator=g)))
            for size in (check_size, (check_size[0] + PATCH, check_size[1] + 2 * PATCH))
        )
        del session
        if not diff <= MAX_DIFF:
            raise PanoError(out, f"onnxruntime and torch disagree by {diff:.3g} (limit {MAX_DIFF:g})")
        tmp.replace(out)
    finally:
        tmp.unlink(missing_ok=True)  # a failed or interrupted export leaves nothing behind
    return diff


def _session(onnx_path: str | Path):
    from models.onnxrt import inference_session, onnxruntime

    opts = onnxruntime().SessionOptions()
    opts.log_severity_level = 4
    return inference_session(onnx_path, opts, ["CPUExecutionProvider"])


def onnx_vs_torch(module: nn.Module, onnx_model, x: torch.Tensor) -> float:
    """max |onnxruntime - torch| / max(1, max |torch|) of `module` and its export (a path or an
    onnxruntime session) on `x`: the absolute difference for outputs up to 1 (random weights), the
    relative one for a trained model's disparities (tens)."""
    sess = onnx_model if hasattr(onnx_model, "run") else _session(onnx_model)
    with torch.no_grad():
        ref = module(x).numpy()
    (got,) = sess.run(None, {sess.get_inputs()[0].name: x.numpy()})
    if got.shape != ref.shape:
        return float("inf")
    return float(abs(got - ref).max()) / max(1.0, float(abs(ref).max()))


def export_onnx(ckpt_path: str | Path, onnx_path: str | Path, opset: int = 17) -> float:
    """Official checkpoint (.pth) -> checked ONNX; returns the max onnxruntime-torch difference.
    The exporter `pano-pipe models` and `depth.model: X.pth` call."""
    if opset < 17:
        raise PanoError("--opset", f"opset {opset} is too old: use 17 or newer")
    with torch.no_grad():
        return export_module(load_checkpoint(ckpt_path), onnx_path, opset=opset)
