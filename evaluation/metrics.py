"""Image and depth metrics for rendered panoramas.

Images are float RGB in [0, 1], [H, W, 3] (numpy or torch). Every function
returns a Python float so results drop straight into pydantic models.

- PSNR: 10·log10(1 / MSE) over all pixels and channels.
- SSIM: Gaussian window 11×11, σ = 1.5, C1 = 0.01², C2 = 0.03², zero padding
  ("same" size), averaged over pixels and channels: exactly the SSIM of the
  3DGS code base, so numbers compare with papers that use it.
- WS-PSNR: PSNR with every row weighted by cos(latitude) of its centre
  (Sun et al. 2017), because an equirectangular image over-samples the poles.
- LPIPS (v0.1, AlexNet or VGG16 backbone, written here in torch): the
  published weights from their standard places (torch hub cache, the lpips
  wheel); `load_lpips` returns the model or raises LpipsUnavailable with the
  missing file, its URL and where to put it, so callers report
  "unavailable: <reason>", never 0.
- Depth: AbsRel and RMSE over pixels whose ground truth is finite and > 0.
"""

from __future__ import annotations

import contextlib
import importlib.util
import io
import math
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

__all__ = [
    "psnr",
    "ssim",
    "ws_psnr",
    "latitude_weights",
    "error_map",
    "depth_metrics",
    "gaussian_window",
    "LPIPS",
    "LpipsUnavailable",
    "load_lpips",
    "find_lpips_weights",
    "LPIPS_ENV",
    "OFFLINE_ENV",
    "hub_backbone_path",
    "lpips_package_heads",
]

# Clamp for perfect reconstructions: PSNR of identical images is reported as
# 10·log10(1/1e-10) = 100 dB instead of inf, which JSON cannot hold.
_MIN_MSE = 1e-10


def _np(x) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=np.float64)


def _check_pair(a: np.ndarray, b: np.ndarray) -> None:
    if a.shape != b.shape:
        raise ValueError(f"image shapes differ: {a.shape} vs {b.shape}")
    if a.ndim not in (2, 3):
        raise ValueError(f"expected [H,W] or [H,W,C], got shape {a.shape}")


def _valid(err: np.ndarray, mask) -> np.ndarray:
    """The per-pixel errors of the valid pixels (`mask` [H,W] bool; None = all)."""
    return err if mask is None else err[np.asarray(mask, dtype=bool)]


def psnr(pred, gt, max_val: float = 1.0, mask=None) -> float:
    """PSNR in dB over the valid pixels of `mask` ([H,W] bool, None = all)."""
    a, b = _np(pred), _np(gt)
    _check_pair(a, b)
    mse = float(np.mean(_valid((a - b) ** 2, mask)))
    return 10.0 * math.log10(max_val**2 / max(mse, _MIN_MSE))


def latitude_weights(height: int) -> np.ndarray:
    """[H] cos(latitude) of each row centre of an equirectangular image."""
    theta = (0.5 - (np.arange(height) + 0.5) / height) * np.pi
    return np.cos(theta)


def ws_psnr(pred, gt, max_val: float = 1.0, mask=None) -> float:
    """Weighted-to-spherically-uniform PSNR for equirectangular images (over `mask`'s valid pixels)."""
    a, b = _np(pred), _np(gt)
    _check_pair(a, b)
    err = (a - b) ** 2
    if err.ndim == 3:
        err = err.mean(axis=2)
    w = np.broadcast_to(latitude_weights(a.shape[0])[:, None], err.shape)
    if mask is not None:
        w = w * np.asarray(mask, dtype=bool)
    wmse = float((err * w).sum() / max(w.sum(), 1e-300))
    return 10.0 * math.log10(max_val**2 / max(wmse, _MIN_MSE))


def gaussian_window(size: int = 11, sigma: float = 1.5) -> np.ndarray:
    """Normalised 1D Gaussian of `size` taps."""
    x = np.arange(size, dtype=np.float64) - (size - 1) / 2.0
    g = np.exp(-(x**2) / (2.0 * sigma**2))
    return g / g.sum()


def ssim(pred, gt, window: int = 11, sigma: float = 1.5, max_val: float = 1.0, mask=None) -> float:
    """Mean SSIM, 3DGS style (Gaussian window, zero padding, same-size maps). With `mask`: masked
    pixels zeroed in both images (their content has no effect), the map averaged over valid ones."""
    a, b = _np(pred), _np(gt)
    _check_pair(a, b)
    if mask is not None:
        keep = np.asarray(mask, dtype=bool)
        a, b = a * (keep[..., None] if a.ndim == 3 else keep), b * (keep[..., None] if b.ndim == 3 else keep)
    if a.ndim == 2:
        a, b = a[..., None], b[..., None]
    x = torch.from_numpy(a).permute(2, 0, 1)[None]  # [1,C,H,W] float64
    y = torch.from_numpy(b).permute(2, 0, 1)[None]
    c = x.shape[1]
    g = torch.from_numpy(gaussian_window(window, sigma))
    k = (g[:, None] * g[None, :]).expand(c, 1, window, window).contiguous()
    pad = window // 2

    def blur(t):
        return F.conv2d(t, k, padding=pad, groups=c)

    mu_x, mu_y = blur(x), blur(y)
    sxx = blur(x * x) - mu_x**2
    syy = blur(y * y) - mu_y**2
    sxy = blur(x * y) - mu_x * mu_y
    c1, c2 = (0.01 * max_val) ** 2, (0.03 * max_val) ** 2
    m = ((2 * mu_x * mu_y + c1) * (2 * sxy + c2)) / ((mu_x**2 + mu_y**2 + c1) * (sxx + syy + c2))
    if mask is not None:
        return float(_valid(m.mean(dim=1)[0].numpy(), mask).mean())
    return float(m.mean())


def colour_fit(pred, gt, mask=None) -> np.ndarray:
    """`pred` after the per-channel least-squares gain and bias that best match it to `gt` (over
    `mask`'s valid pixels), clipped to [0, 1]: metrics on it measure the reconstruction with the
    panorama's exposure and white balance factored out."""
    a, b = _np(pred), _np(gt)
    _check_pair(a, b)
    keep = np.ones(a.shape[:2], bool) if mask is None else np.asarray(mask, dtype=bool)
    out = np.empty_like(a)
    for c in range(a.shape[2] if a.ndim == 3 else 1):
        x = a[..., c] if a.ndim == 3 else a
        y = b[..., c] if b.ndim == 3 else b
        xs, ys = x[keep], y[keep]
        var = float(np.var(xs)) if xs.size else 0.0
        gain = float(np.mean((xs - xs.mean()) * (ys - ys.mean())) / var) if var > 1e-12 else 1.0
        bias = float(ys.mean() - gain * xs.mean()) if xs.size else 0.0
        fitted = np.clip(gain * x + bias, 0.0, 1.0)
        if a.ndim == 3:
            out[..., c] = fitted
        else:
            out = fitted
    return out


def error_map(pred, gt) -> np.ndarray:
    """[H,W] mean absolute error over channels, in [0, 1]."""
    a, b = _np(pred), _np(gt)
    _check_pair(a, b)
    e = np.abs(a - b)
    return e.mean(axis=2) if e.ndim == 3 else e


def depth_metrics(pred, gt, mask=None) -> dict[str, float | int]:
    """AbsRel = mean |d − d*| / d*, RMSE = sqrt(mean (d − d*)²) over valid ground truth.

    Valid: ground truth finite and > 0 (and `mask` where given). Returns NaN
    metrics with count 0 when nothing is valid.
    """
    d, g = _np(pred), _np(gt)
    if d.shape != g.shape:
        raise ValueError(f"depth shapes differ: {d.shape} vs {g.shape}")
    valid = np.isfinite(g) & (g > 0) & np.isfinite(d)
    if mask is not None:
        valid &= _np(mask).astype(bool)
    n = int(valid.sum())
    if n == 0:
        return {"abs_rel": float("nan"), "rmse": float("nan"), "count": 0}
    diff = d[valid] - g[valid]
    return {
        "abs_rel": float(np.mean(np.abs(diff) / g[valid])),
        "rmse": float(np.sqrt(np.mean(diff**2))),
        "count": n,
    }


def view_metrics(render: np.ndarray, gt: np.ndarray, lpips_model=None, mask: np.ndarray | None = None,
                 flat: np.ndarray | None = None) -> dict[str, float | None]:
    """PSNR / SSIM / WS-PSNR (and LPIPS with a model) of one rendered panorama, over the valid
    pixels of `mask` ([H,W] bool; None = all). LPIPS sees both images with masked pixels zeroed.
    With `flat` (an RGB colour), also the PSNR and SSIM of an image of that one colour: the floor."""
    keep = None if mask is None else mask[..., None]
    fitted = colour_fit(render, gt, mask)  # exposure and white balance factored out
    return {
        "psnr": psnr(render, gt, mask=mask),
        "ssim": ssim(render, gt, mask=mask),
        "ws_psnr": ws_psnr(render, gt, mask=mask),
        "lpips": (lpips_model.distance(render if keep is None else render * keep, gt if keep is None else gt * keep)
                  if lpips_model is not None else None),
        "psnr_colorfit": psnr(fitted, gt, mask=mask),
        "ssim_colorfit": ssim(fitted, gt, mask=mask),
        **flat_metrics(flat, gt, mask),
    }


def flat_metrics(flat: np.ndarray | None, gt: np.ndarray, mask: np.ndarray | None = None) -> dict[str, float | None]:
    """`flat_psnr` and `flat_ssim`: the PSNR and SSIM of an image of the one colour `flat` against `gt`
    over `mask` (both None without a colour)."""
    if flat is None:
        return {"flat_psnr": None, "flat_ssim": None}
    image = np.broadcast_to(np.asarray(flat, gt.dtype), gt.shape)
    return {"flat_psnr": psnr(image, gt, mask=mask), "flat_ssim": ssim(image, gt, mask=mask)}



# -- LPIPS ----------------------------------------------------------------------
LPIPS_ENV = "PANO_PIPE_LPIPS_WEIGHTS"
OFFLINE_ENV = "PANO_PIPE_OFFLINE"  # set: never download weights (tests, air-gapped machines)
# Where the published files come from: torchvision's model zoo and the lpips repository
# (its wheel, lpips 0.1.4, ships the same heads under lpips/weights/v0.1/).
TORCHVISION_URL = "https://download.pytorch.org/models/"
LPIPS_HEADS_URL = "https://github.com/richzhang/PerceptualSimilarity/raw/master/lpips/weights/v0.1/"
LPIPS_PACKAGE_VERSION = "0.1.4"

# File names as published: torchvision's ImageNet backbones and the lpips
# package's v0.1 linear heads (github.com/richzhang/PerceptualSimilarity).
_BACKBONE_FILES = {"alex": "alexnet-owt-7be5be79.pth", "vgg": "vgg16-397923af.pth"}
_LIN_FILES = {"alex": "alex.pth", "vgg": "vgg.pth"}
_CHANNELS = {"alex": (64, 192, 384, 256, 256), "vgg": (64, 128, 256, 512, 512)}


class LpipsUnavailable(RuntimeError):
    """LPIPS cannot be computed; str(e) is the reason shown to users."""


def _alexnet_features() -> torch.nn.Sequential:
    # torchvision's alexnet().features, same indices so its state dict loads.
    return torch.nn.Sequential(
        torch.nn.Conv2d(3, 64, 11, 4, 2), torch.nn.ReLU(), torch.nn.MaxPool2d(3, 2),
        torch.nn.Conv2d(64, 192, 5, padding=2), torch.nn.ReLU(), torch.nn.MaxPool2d(3, 2),
        torch.nn.Conv2d(192, 384, 3, padding=1), torch.nn.ReLU(),
        torch.nn.Conv2d(384, 256, 3, padding=1), torch.nn.ReLU(),
        torch.nn.Conv2d(256, 256, 3, padding=1), torch.nn.ReLU(), torch.nn.MaxPool2d(3, 2),
    )  # fmt: skip


def _vgg16_features() -> torch.nn.Sequential:
    layers: list[torch.nn.Module] = []
    cin = 3
    for v in (64, 64, "M", 128, 128, "M", 256, 256, 256, "M", 512, 512, 512, "M", 512, 512, 512, "M"):
        if v == "M":
            layers.append(torch.nn.MaxPool2d(2, 2))
        else:
            layers += [torch.nn.Conv2d(cin, v, 3, padding=1), torch.nn.ReLU()]
            cin = v
    return torch.nn.Sequential(*layers)


# Where LPIPS taps the backbone (after these ReLUs), as in lpips.pretrained_networks.
_SLICES = {"alex": (2, 5, 8, 10, 12), "vgg": (4, 9, 16, 23, 30)}


class LPIPS(torch.nn.Module):
    """LPIPS v0.1: unit-normalised backbone features, squared differences, learned 1×1 weights."""

    def __init__(self, net: str = "alex"):
        super().__init__()
        if net not in _SLICES:
            raise ValueError(f"LPIPS backbone must be 'alex' or 'vgg', not {net!r}")
        self.net_name = net
        self.features = _alexnet_features() if net == "alex" else _vgg16_features()
        self.lins = torch.nn.ModuleList(torch.nn.Conv2d(c, 1, 1, bias=False) for c in _CHANNELS[net])
        self.register_buffer("shift", torch.tensor([-0.030, -0.088, -0.188]).view(1, 3, 1, 1))
        self.register_buffer("scale", torch.tensor([0.458, 0.448, 0.450]).view(1, 3, 1, 1))
        self.requires_grad_(False)
        self.eval()

    def load_weights(self, backbone: dict, lin: dict) -> None:
        feats = {k.removeprefix("features."): v for k, v in backbone.items() if k.startswith("features.")}
        self.features.load_state_dict(feats)
        lins = {}
        for i in range(5):
            key = f"lin{i}.model.1.weight"
            if key not in lin:
                raise KeyError(f"missing {key}")
            lins[f"{i}.weight"] = lin[key]
        self.lins.load_state_dict(lins)

    def _taps(self, x: torch.Tensor) -> list[torch.Tensor]:
        out, start = [], 0
        for end in _SLICES[self.net_name]:
            for layer in self.features[start:end]:
                x = layer(x)
            out.append(x)
            start = end
        return out

    @torch.no_grad()
    def forward(self, pred: torch.Tensor, gt: torch.Tensor) -> torch.Tensor:
        """pred, gt: [B,3,H,W] in [0,1]; returns [B] distances."""
        a = ((pred * 2 - 1) - self.shift) / self.scale
        b = ((gt * 2 - 1) - self.shift) / self.scale
        total = torch.zeros(pred.shape[0], dtype=pred.dtype)
        for fa, fb, lin in zip(self._taps(a), self._taps(b), self.lins):
            fa = fa / (fa.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            fb = fb / (fb.pow(2).sum(1, keepdim=True).sqrt() + 1e-10)
            total = total + lin((fa - fb) ** 2).mean(dim=(1, 2, 3))
        return total

    def distance(self, pred, gt) -> float:
        """LPIPS of two [H,W,3] images in [0,1]."""
        a = torch.as_tensor(_np(pred), dtype=torch.float32).permute(2, 0, 1)[None]
        b = torch.as_tensor(_np(gt), dtype=torch.float32).permute(2, 0, 1)[None]
        return float(self(a, b)[0])


@dataclass
class LpipsFiles:
    backbone: Path
    lin: Path


def hub_backbone_path(net: str = "alex") -> Path:
    """Where torch hub keeps torchvision's backbone (honours $TORCH_HOME)."""
    return Path(torch.hub.get_dir()) / "checkpoints" / _BACKBONE_FILES[net]


def lpips_package_heads(net: str = "alex") -> Path | None:
    """The linear heads inside the installed `lpips` wheel (lpips/weights/v0.1/<net>.pth), or None.

    The package is located, not imported: its __init__ imports torchvision, which the CPU
    torch pinned here cannot load."""
    spec = importlib.util.find_spec("lpips")
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(next(iter(spec.submodule_search_locations))) / "weights" / "v0.1" / _LIN_FILES[net]


def _user_location(what: str, p: Path, net: str) -> LpipsFiles:
    """A folder or merged .pth the user named: it is the answer, found or not."""
    if p.is_file():
        return LpipsFiles(p, p)
    if not p.is_dir():
        raise LpipsUnavailable(f"no {net} LPIPS weights: {p} ({what}) does not exist")
    bb, lin = p / _BACKBONE_FILES[net], p / _LIN_FILES[net]
    if not bb.is_file() and hub_backbone_path(net).is_file():
        bb = hub_backbone_path(net)
    missing = [f.name for f in (bb, lin) if not f.is_file()]
    if missing:
        raise LpipsUnavailable(f"no {net} LPIPS weights: {p} ({what}) lacks {' and '.join(missing)}")
    return LpipsFiles(bb, lin)


def find_lpips_weights(net: str = "alex", explicit: str | Path | None = None, download: bool = True) -> LpipsFiles:
    """Locate the backbone and linear-head weights, or raise LpipsUnavailable naming what is missing.

    A location the user names (`explicit`, then $PANO_PIPE_LPIPS_WEIGHTS: a folder with the two
    published files, or one .pth holding both state dicts) is the only place looked. Otherwise the
    standard places: torchvision's backbone in the torch hub cache, downloaded there on first use
    with torch.hub.load_state_dict_from_url (unless `download` is False or $PANO_PIPE_OFFLINE is
    set), and the linear heads shipped in the `lpips` wheel.
    """
    if net not in _LIN_FILES:
        raise LpipsUnavailable(f"unknown LPIPS backbone {net!r} (use 'alex' or 'vgg')")
    if explicit:
        return _user_location("parameter lpips_weights", Path(explicit).expanduser(), net)
    if os.environ.get(LPIPS_ENV):
        return _user_location(f"${LPIPS_ENV}", Path(os.environ[LPIPS_ENV]).expanduser(), net)

    heads = lpips_package_heads(net)
    if heads is None or not heads.is_file():
        where = "the lpips package is not installed" if heads is None else f"{heads} is missing"
        raise LpipsUnavailable(
            f"no {net} LPIPS linear heads: {where}; install the wheel that carries them with "
            f"`pip install --no-deps lpips=={LPIPS_PACKAGE_VERSION}` (--no-deps keeps torchvision out), "
            f"or put {LPIPS_HEADS_URL}{_LIN_FILES[net]} and {TORCHVISION_URL}{_BACKBONE_FILES[net]} "
            f"in a folder named by ${LPIPS_ENV}")
    backbone = hub_backbone_path(net)
    if not backbone.is_file():
        _download_backbone(net, backbone, download)
    return LpipsFiles(backbone, heads)


#: Downloads of a backbone that failed in this process: (url, destination) -> the reason. A batch or
#: an ablation evaluates many times; offline, each would try again and say so again.
_FAILED_DOWNLOADS: dict[tuple[str, str], str] = {}


def _download_backbone(net: str, dest: Path, allowed: bool) -> None:
    url = TORCHVISION_URL + _BACKBONE_FILES[net]
    if not allowed or os.environ.get(OFFLINE_ENV):
        why = "downloads are off" + (f" (${OFFLINE_ENV} is set)" if os.environ.get(OFFLINE_ENV) else "")
        raise LpipsUnavailable(f"{dest} is missing and {why}: download {url} and put it there")
    key = (url, str(dest))
    if key in _FAILED_DOWNLOADS:  # tried once in this process already: not again
        raise LpipsUnavailable(_FAILED_DOWNLOADS[key])
    try:
        # Checks the published SHA-256 prefix in the file name; writes nothing on failure. torch hub
        # announces the download (on stdout or stderr, by version): dropped, as a failure is said once,
        # in the reason, and stderr is kept for the one error line.
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
            torch.hub.load_state_dict_from_url(url, map_location="cpu", weights_only=True, progress=False,
                                               check_hash=True)
    except Exception as e:  # offline, proxy, disk full, bad hash: the user needs the same three facts
        from urllib.parse import urlsplit

        from models.network import describe_failure

        reason = (f"{dest} is missing and downloading {url} failed "
                  f"({describe_failure(e, urlsplit(url).hostname or url)}); download it by hand and put it there")
        _FAILED_DOWNLOADS[key] = reason
        raise LpipsUnavailable(reason) from None
    if not dest.is_file():  # a hub dir changed under us
        raise LpipsUnavailable(f"downloaded {url} but {dest} is not there")


def _load_state(path: Path) -> dict:
    from runfs.checkpoints import load_weights
    from runfs.errors import PanoError

    try:
        state = load_weights(path)
    except PanoError as e:  # truncated download, not a checkpoint, pickled code: say which file
        raise LpipsUnavailable(f"could not load LPIPS weights from {path}: {e.problem}") from None
    if not isinstance(state, dict):
        raise LpipsUnavailable(f"could not load LPIPS weights from {path}: not a state dict")
    return state


def load_lpips(net: str = "alex", weights: str | Path | None = None, download: bool = True) -> LPIPS:
    """An LPIPS model with weights loaded, or LpipsUnavailable(reason)."""
    files = find_lpips_weights(net, weights, download)
    model = LPIPS(net)
    backbone = _load_state(files.backbone)
    lin = backbone if files.lin == files.backbone else _load_state(files.lin)
    try:
        model.load_weights(backbone, lin)
    except (KeyError, RuntimeError) as e:  # keys or shapes of another network
        where = files.backbone if files.lin == files.backbone else f"{files.backbone} / {files.lin}"
        raise LpipsUnavailable(f"LPIPS weights in {where} do not fit the {net} network: {e}") from None
    return model
