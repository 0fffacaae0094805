"""HorizonNet (Sun et al., CVPR 2019) rebuilt in plain torch, without torchvision,
so that the authors' published checkpoints load into it and export to ONNX.

Module names and tensor shapes match the state dict HorizonNet's training
script saves (`{'state_dict': ..., 'kwargs': {'backbone', 'use_rnn'}}`):

- `feature_extractor.encoder.*`: a torchvision-layout ResNet (conv1, bn1,
  layer1..4; no fc/avgpool). HorizonNet replaces every Conv2d that pads
  horizontally by `Sequential(LR_PAD, Conv2d)`, so those weights are named
  `<conv>.1.weight` (e.g. `conv1.1.weight`, `layer1.0.conv2.1.weight`); the
  padding wraps around the panorama's left/right edges.
- `reduce_height_module.ghc_lst.{0..3}.layer.{0..3}.layers.{0.1,1}`: per encoder
  block, four height-halving conv (stride (2,1)) + BN + ReLU blocks
  ("GlobalHeightConv"), then upsampled along the width to 256 columns.
- `bi_rnn`: a 2-layer bidirectional LSTM (hidden 512) over the 256 columns,
  `linear`: 1024 -> 12 (3 outputs x 4 columns per step); without the RNN,
  `linear` is Linear-ReLU-Dropout-Linear (`linear.0`, `linear.3`).

Input [B,3,512,1024] RGB in [0,1] (normalised inside with ImageNet mean/std);
outputs bon [B,2,1024] (radians, downward) and cor [B,1,1024] (logits).
"""

from __future__ import annotations

import torch
import torch.nn as nn
import torch.nn.functional as F

#: torchvision ResNet depths: (block, blocks per layer).
RESNETS = {
    "resnet18": ("basic", (2, 2, 2, 2)),
    "resnet34": ("basic", (3, 4, 6, 3)),
    "resnet50": ("bottleneck", (3, 4, 6, 3)),
    "resnet101": ("bottleneck", (3, 4, 23, 3)),
    "resnet152": ("bottleneck", (3, 8, 36, 3)),
}

__all__ = ["HorizonNet", "RESNETS", "LRPad", "build_from_state_dict"]


class LRPad(nn.Module):
    """Pad the width circularly (the panorama wraps around); no parameters."""

    def __init__(self, padding: int):
        super().__init__()
        self.padding = padding

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        p = self.padding
        return torch.cat([x[..., -p:], x, x[..., :p]], dim=3)


def wrap_conv(in_c: int, out_c: int, k: int, stride=1, padding: int = 0, bias: bool = False) -> nn.Module:
    """A conv whose horizontal padding wraps, laid out as HorizonNet's wrap_lr_pad leaves it."""
    if padding == 0:
        return nn.Conv2d(in_c, out_c, k, stride=stride, padding=0, bias=bias)
    return nn.Sequential(
        LRPad(padding), nn.Conv2d(in_c, out_c, k, stride=stride, padding=(padding, 0), bias=bias)
    )


class BasicBlock(nn.Module):
    expansion = 1

    def __init__(self, in_c: int, planes: int, stride: int = 1, downsample: nn.Module | None = None):
        super().__init__()
        self.conv1 = wrap_conv(in_c, planes, 3, stride, 1)
        self.bn1 = nn.BatchNorm2d(planes)
        self.conv2 = wrap_conv(planes, planes, 3, 1, 1)
        self.bn2 = nn.BatchNorm2d(planes)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = downsample

    def forward(self, x):
        idt = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        return self.relu(out + idt)


class Bottleneck(nn.Module):
    expansion = 4

    def __init__(self, in_c: int, planes: int, stride: int = 1, downsample: nn.Module | None = None):
        super().__init__()
        # torchvision's "ResNet v1.5": the stride sits on the 3x3 conv.
        self.conv1 = nn.Conv2d(in_c, planes, 1, bias=False)
        self.bn1 = nn.BatchNorm2d(planes)
        self.conv2 = wrap_conv(planes, planes, 3, stride, 1)
        self.bn2 = nn.BatchNorm2d(planes)
        self.conv3 = nn.Conv2d(planes, planes * 4, 1, bias=False)
        self.bn3 = nn.BatchNorm2d(planes * 4)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = downsample

    def forward(self, x):
        idt = x if self.downsample is None else self.downsample(x)
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.relu(self.bn2(self.conv2(out)))
        out = self.bn3(self.conv3(out))
        return self.relu(out + idt)


class ResNetEncoder(nn.Module):
    """torchvision's ResNet trunk (no avgpool/fc); `width` scales the channels
    (64 = the real network; smaller only for fast tests)."""

    def __init__(self, backbone: str = "resnet50", width: int = 64):
        super().__init__()
        kind, layers = RESNETS[backbone]
        block = Bottleneck if kind == "bottleneck" else BasicBlock
        self.conv1 = wrap_conv(3, width, 7, 2, 3)
        self.bn1 = nn.BatchNorm2d(width)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(3, 2, 1)
        self.in_c = width
        self.layer1 = self._layer(block, width, layers[0], 1)
        self.layer2 = self._layer(block, width * 2, layers[1], 2)
        self.layer3 = self._layer(block, width * 4, layers[2], 2)
        self.layer4 = self._layer(block, width * 8, layers[3], 2)
        self.channels = [width * block.expansion * m for m in (1, 2, 4, 8)]

    def _layer(self, block, planes: int, n: int, stride: int) -> nn.Sequential:
        down = None
        if stride != 1 or self.in_c != planes * block.expansion:
            down = nn.Sequential(
                nn.Conv2d(self.in_c, planes * block.expansion, 1, stride=stride, bias=False),
                nn.BatchNorm2d(planes * block.expansion),
            )
        blocks = [block(self.in_c, planes, stride, down)]
        self.in_c = planes * block.expansion
        blocks += [block(self.in_c, planes) for _ in range(n - 1)]
        return nn.Sequential(*blocks)


class Resnet(nn.Module):
    """HorizonNet's wrapper: features of the four ResNet stages (1/4 .. 1/32)."""

    def __init__(self, backbone: str = "resnet50", width: int = 64):
        super().__init__()
        self.encoder = ResNetEncoder(backbone, width)

    def forward(self, x):
        e = self.encoder
        x = e.maxpool(e.relu(e.bn1(e.conv1(x))))
        f1 = e.layer1(x)
        f2 = e.layer2(f1)
        f3 = e.layer3(f2)
        f4 = e.layer4(f3)
        return [f1, f2, f3, f4]


class ConvCompressH(nn.Module):
    """Halve the feature height: conv 3x3 stride (2,1) + BN + ReLU."""

    def __init__(self, in_c: int, out_c: int, ks: int = 3):
        super().__init__()
        self.layers = nn.Sequential(
            wrap_conv(in_c, out_c, ks, stride=(2, 1), padding=ks // 2, bias=True),
            nn.BatchNorm2d(out_c),
            nn.ReLU(inplace=True),
        )

    def forward(self, x):
        return self.layers(x)


class GlobalHeightConv(nn.Module):
    def __init__(self, in_c: int, out_c: int):
        super().__init__()
        self.layer = nn.Sequential(
            ConvCompressH(in_c, in_c // 2),
            ConvCompressH(in_c // 2, in_c // 2),
            ConvCompressH(in_c // 2, in_c // 4),
            ConvCompressH(in_c // 4, out_c),
        )

    def forward(self, x, out_w: int):
        x = self.layer(x)
        factor = out_w // x.shape[3]
        # Upsample along the width with one wrapped column each side, then crop.
        x = torch.cat([x[..., -1:], x, x[..., :1]], 3)
        x = F.interpolate(x, size=(x.shape[2], out_w + 2 * factor), mode="bilinear", align_corners=False)
        return x[..., factor:-factor]


class GlobalHeightStage(nn.Module):
    def __init__(self, c1: int, c2: int, c3: int, c4: int, out_scale: int = 8):
        super().__init__()
        self.ghc_lst = nn.ModuleList([GlobalHeightConv(c, c // out_scale) for c in (c1, c2, c3, c4)])

    def forward(self, conv_list, out_w: int):
        bs = conv_list[0].shape[0]
        return torch.cat([f(x, out_w).reshape(bs, -1, out_w) for f, x in zip(self.ghc_lst, conv_list)], dim=1)


class HorizonNet(nn.Module):
    """HorizonNet for a fixed 512x1024 input. `width` != 64 only for tests."""

    out_scale = 8
    step_cols = 4
    rnn_hidden_size = 512

    def __init__(
        self, backbone: str = "resnet50", use_rnn: bool = True, width: int = 64, rnn_hidden: int = 512
    ):
        super().__init__()
        if backbone not in RESNETS:
            raise ValueError(f"unsupported backbone {backbone!r}; supported: {', '.join(RESNETS)}")
        self.backbone = backbone
        self.use_rnn = use_rnn
        self.rnn_hidden_size = rnn_hidden
        self.feature_extractor = Resnet(backbone, width)
        c1, c2, c3, c4 = self.feature_extractor.encoder.channels
        # Heights at 512x1024 are 128/64/32/16, each compressed 16x: 8/4/2/1 rows.
        c_last = (c1 * 8 + c2 * 4 + c3 * 2 + c4 * 1) // self.out_scale
        self.reduce_height_module = GlobalHeightStage(c1, c2, c3, c4, self.out_scale)
        n_out = 3 * self.step_cols
        if use_rnn:
            self.bi_rnn = nn.LSTM(
                c_last, rnn_hidden, num_layers=2, dropout=0.5, batch_first=False, bidirectional=True
            )
            self.drop_out = nn.Dropout(0.5)
            self.linear = nn.Linear(2 * rnn_hidden, n_out)
        else:
            self.linear = nn.Sequential(
                nn.Linear(c_last, rnn_hidden),
                nn.ReLU(inplace=True),
                nn.Dropout(0.5),
                nn.Linear(rnn_hidden, n_out),
            )
        # HorizonNet's output bias init: corners -1, ceiling -0.478 rad, floor +0.425 rad.
        last = self.linear if use_rnn else self.linear[-1]
        with torch.no_grad():
            last.bias[0:4].fill_(-1)
            last.bias[4:8].fill_(-0.478)
            last.bias[8:12].fill_(0.425)
        # Class attributes in HorizonNet, so not part of its state dict.
        self.register_buffer("x_mean", torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("x_std", torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1), persistent=False)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        if x.shape[2] != 512 or x.shape[3] != 1024:
            raise ValueError(f"HorizonNet takes 512x1024 input, got {tuple(x.shape[2:])}")
        x = (x[:, :3] - self.x_mean) / self.x_std
        feature = self.reduce_height_module(self.feature_extractor(x), x.shape[3] // self.step_cols)
        if self.use_rnn:
            feature = feature.permute(2, 0, 1)  # [w, b, c]
            output, _ = self.bi_rnn(feature)
            output = self.linear(self.drop_out(output))  # [w, b, 12]
            output = output.view(output.shape[0], output.shape[1], 3, self.step_cols).permute(1, 2, 0, 3)
        else:
            output = self.linear(feature.permute(0, 2, 1))  # [b, w, 12]
            output = output.view(output.shape[0], output.shape[1], 3, self.step_cols).permute(0, 2, 1, 3)
        output = output.contiguous().view(output.shape[0], 3, -1)  # [b, 3, 1024]
        return output[:, 1:], output[:, :1]  # bon, cor


def _infer_backbone(sd: dict) -> str:
    """ResNet depth from the state dict: block type and number of layer3 blocks."""
    bottleneck = any(k.startswith("feature_extractor.encoder.layer1.0.conv3") for k in sd)
    n3 = len({k.split(".")[3] for k in sd if k.startswith("feature_extractor.encoder.layer3.")})
    for name, (kind, layers) in RESNETS.items():
        if (kind == "bottleneck") == bottleneck and layers[2] == n3:
            return name
    raise ValueError(f"no supported ResNet has {n3} layer3 blocks of this kind")


def build_from_state_dict(sd: dict, kwargs: dict | None = None) -> HorizonNet:
    """A HorizonNet shaped like the checkpoint (backbone and use_rnn from its
    kwargs, else inferred; channel width and RNN size from the tensor shapes),
    with the weights loaded strictly."""
    kwargs = dict(kwargs or {})
    backbone = kwargs.get("backbone") or _infer_backbone(sd)
    if not str(backbone).startswith("resnet") or backbone not in RESNETS:
        raise ValueError(
            f"backbone {backbone!r} is not supported (ResNet backbones only: {', '.join(RESNETS)})"
        )
    use_rnn = kwargs.get("use_rnn", "bi_rnn.weight_ih_l0" in sd)
    w = sd.get("feature_extractor.encoder.bn1.weight")
    width = int(w.shape[0]) if w is not None else 64
    hidden = (
        int(sd["bi_rnn.weight_hh_l0"].shape[1])
        if "bi_rnn.weight_hh_l0" in sd
        else (int(sd["linear.0.weight"].shape[0]) if "linear.0.weight" in sd else 512)
    )
    net = HorizonNet(backbone, bool(use_rnn), width=width, rnn_hidden=hidden)
    net.load_state_dict(sd, strict=True)
    return net.eval()
