"""RoIAlign over a feature pyramid whose backward pass is cheap on a CPU.

torchvision's CPU ``roi_align`` backward scatters each sample's gradient one channel at a time
on one thread: on ``configs/quick.yaml``'s Faster R-CNN it was a third of a training step on
2 cores (profiled: 16 ms per pyramid level per step of 8 images). Here each bin's bilinear
samples are a bag of feature rows (every channel of a pixel at once) with their corner weights,
pooled by ``embedding_bag``, whose backward adds whole rows by index: a step of that detector
took 0.70x the time. Values and gradients equal torchvision's ``roi_align(aligned=False)`` to
float rounding (tests/workers/train/test_roi_align.py).

Only training on a CPU with a fixed ``sampling_ratio`` takes this path; inference, ONNX
tracing (RoIAlign has an ONNX form) and CUDA keep torchvision's kernel.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor
from torchvision.ops import MultiScaleRoIAlign
from torchvision.ops.poolers import _convert_to_roi_format, _filter_input, _setup_scales


def _axis_samples(start: Tensor, length: Tensor, size: int, bins: int, per_bin: int):
    """Corner indices and weights along one axis, as torchvision's roi_align kernel reads them:
    per RoI, ``bins * per_bin`` sample positions, each with its low and high neighbour, their
    weights, and whether it lies on the map (a sample beyond a pixel outside contributes 0)."""
    steps = torch.arange(bins * per_bin, dtype=start.dtype, device=start.device)
    position = start[:, None] + (steps + 0.5) * (length[:, None] / (bins * per_bin))
    inside = (position >= -1.0) & (position <= size)
    position = position.clamp(min=0)
    low = position.floor().long()
    at_edge = low >= size - 1
    low = low.clamp(max=size - 1)
    high = torch.where(at_edge, low, low + 1)
    position = torch.where(at_edge, low.to(position.dtype), position)
    frac = position - low
    return low, high, 1.0 - frac, frac, inside


def pyramid_roi_align(
    features: list[Tensor],
    rois: Tensor,
    levels: Tensor,
    scales: list[float],
    output_size: tuple[int, int],
    sampling_ratio: int,
) -> Tensor:
    """torchvision's ``roi_align(aligned=False)`` of each RoI (``rois``: batch index, x1, y1,
    x2, y2) on its pyramid level (``levels``), as one gather over every level's pixels."""
    channels = features[0].shape[1]
    out_h, out_w = output_size
    rows = torch.cat([f.permute(0, 2, 3, 1).reshape(-1, channels) for f in features])
    scale = torch.tensor(scales, dtype=rois.dtype, device=rois.device)[levels]

    x1, y1, x2, y2 = (rois[:, 1:] * scale[:, None]).unbind(1)
    width = (x2 - x1).clamp(min=1.0)
    height = (y2 - y1).clamp(min=1.0)
    k = rois.shape[0]
    s = sampling_ratio
    indices = torch.zeros((k, out_h * out_w, 4 * s * s), dtype=torch.long, device=rois.device)
    weights = torch.zeros((k, out_h * out_w, 4 * s * s), dtype=rows.dtype, device=rois.device)
    offset = 0  # of the level's first pixel among the rows
    for level, feature in enumerate(features):  # the RoIs of one level share its map's size
        h, w = feature.shape[2], feature.shape[3]
        offset, level_offset = offset + feature.shape[0] * h * w, offset
        chosen = torch.where(levels == level)[0]
        if chosen.numel() == 0:
            continue
        ylo, yhi, wylo, wyhi, yin = _axis_samples(y1[chosen], height[chosen], h, out_h, s)
        xlo, xhi, wxlo, wxhi, xin = _axis_samples(x1[chosen], width[chosen], w, out_w, s)
        base = level_offset + rois[chosen, 0].long() * (h * w)

        def corner(yy: Tensor, xx: Tensor) -> Tensor:  # (n, out_h*s, out_w*s)
            return base[:, None, None] + yy[:, :, None] * w + xx[:, None, :]

        def product(wy: Tensor, wx: Tensor) -> Tensor:
            return wy[:, :, None] * wx[:, None, :]

        inside = (yin[:, :, None] & xin[:, None, :]).to(rows.dtype) / (s * s)
        index = torch.stack([corner(ylo, xlo), corner(ylo, xhi), corner(yhi, xlo), corner(yhi, xhi)], -1)
        weight = (
            torch.stack([product(wylo, wxlo), product(wylo, wxhi), product(wyhi, wxlo), product(wyhi, wxhi)], -1)
            * inside[..., None]
        )
        n = chosen.numel()
        # (n, out_h, s, out_w, s, 4) -> (n, out_h, out_w, s*s*4): a bin's samples and corners last.
        index = index.view(n, out_h, s, out_w, s, 4).permute(0, 1, 3, 2, 4, 5).reshape(n, out_h * out_w, -1)
        weight = weight.view(n, out_h, s, out_w, s, 4).permute(0, 1, 3, 2, 4, 5).reshape(n, out_h * out_w, -1)
        indices[chosen] = index
        weights[chosen] = weight
    # A bag of corners per bin: one fused weighted gather, whose backward adds rows by index.
    pooled = F.embedding_bag(
        indices.view(k * out_h * out_w, 4 * s * s),
        rows,
        per_sample_weights=weights.view(k * out_h * out_w, 4 * s * s),
        mode="sum",
    )
    return pooled.view(k, out_h, out_w, channels).permute(0, 3, 1, 2)


class PyramidRoIAlign(MultiScaleRoIAlign):
    """torchvision's ``MultiScaleRoIAlign`` (same levels, same values) whose training pass on a
    CPU runs ``pyramid_roi_align``; everywhere else it is torchvision's."""

    def forward(self, x: dict[str, Tensor], boxes: list[Tensor], image_shapes: list[tuple[int, int]]) -> Tensor:
        features = _filter_input(x, self.featmap_names)
        fast = (
            self.training
            and torch.is_grad_enabled()
            and self.sampling_ratio > 0
            and features[0].device.type == "cpu"
            and not torch.jit.is_tracing()
        )
        if not fast:
            return super().forward(x, boxes, image_shapes)
        if self.scales is None or self.map_levels is None:
            self.scales, self.map_levels = _setup_scales(
                features, image_shapes, self.canonical_scale, self.canonical_level
            )
        rois = _convert_to_roi_format(boxes)
        if len(features) == 1:
            levels = torch.zeros(rois.shape[0], dtype=torch.long, device=rois.device)
        else:
            levels = self.map_levels(boxes)
        return pyramid_roi_align(features, rois, levels, self.scales, self.output_size, self.sampling_ratio)
