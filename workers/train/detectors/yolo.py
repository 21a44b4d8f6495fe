"""A YOLOv2-style single-shot grid detector (Redmon & Farhadi 2016, "YOLO9000") on a torchvision backbone.

The paper compares Fast R-CNN, Faster R-CNN and YOLO9000; this is the third, rebuilt on
torchvision parts so it trains from random initialisation on a CPU:

* **Input.** Every image is letterboxed into ``input_size × input_size`` (aspect kept, scaled
  to fit, placed at the top-left corner, grey padding) and ImageNet-normalised. The scale is
  stored per axis, so boxes map back to the original pixels exactly (``x = x_in / sx``).
* **Backbone.** A torchvision feature extractor (MobileNetV3 features or a ResNet up to
  ``layer4``, random initialisation unless ``pretrained``) cut at strides 8, 16 and 32; like
  YOLOv2's passthrough layer the stride-32 map is upsampled and joined to the stride-16
  one, so the head predicts on a stride-16 grid (8 × 8 cells at 128 px) by default
  (``grid_stride=32``: the classic single map; ``grid_stride=8``: one more join, for small
  objects, ~20% slower). BatchNorm momentum is 0.1 everywhere (MobileNetV3 ships 0.01,
  which leaves eval statistics stale after a short increment); weights are channels-last.
* **Anchors.** k-means of the training boxes' (w, h), normalised by the letterbox input size,
  with YOLOv2's distance ``1 − IoU`` of centred boxes (:func:`kmeans_anchors`); kept as the
  persistent buffer ``anchors`` so they travel in the state dict.
* **Head.** Per cell and anchor: ``(tx, ty, tw, th, objectness, class logits)``, decoded as
  ``cx = (j − m + (1 + 2m)·σ(tx)) · stride``, ``w = anchor_w · exp(tw)`` (exp input clamped
  to ±4 in value only, so an overshooting logit still gets a gradient back).
* **Targets.** YOLOv2's: the cell holding the box centre and the anchor of best centred IoU
  (:func:`assign_targets`). By default also, as in YOLOv4/v5, the neighbouring cell nearest
  the centre along each axis (``cell_margin`` m = 0.5 lets a cell reach half a cell beyond
  its border) and every anchor of centred IoU ≥ 0.5. The reason is the paper's protocol,
  which drops detections scored below 0.8: a canonical object is centred, i.e. on the
  corner of four cells of an even grid, and k-means of near-identical boxes gives
  near-identical anchors, so a single responsible slot flips with sub-pixel changes and
  its objectness settles near 0.5. ``cell_margin=0, anchor_match_iou=1`` is plain YOLOv2.
* **Losses.** Box: YOLOv2's loss on the t's (binary KL of σ(t) to the target offset,
  smooth-L1 on the log-size, small boxes weighted up to 2×): its gradients do not grow
  with the box, unlike an IoU loss through ``exp``, which diverged here at lr 0.01.
  Objectness: BCE on logits (object weight 5, no-object weight 1, as darknet's region
  layer), where predictions that are not responsible but overlap a ground truth above
  ``ignore_iou`` (0.6) are left out of the no-object term; classes: cross-entropy. Each
  box weighs 1 however many predictions answer for it; terms are summed per image and
  averaged over the batch, so an image without objects pays only its no-object term.
* **Output.** torchvision's detection interface: a dict of losses in training mode; in eval
  mode per image ``{"boxes": (n, 4) xyxy original pixels, "scores", "labels" (1-based)}``
  with ``score = σ(objectness) · softmax(class)``, a low score threshold, class-aware NMS
  (``torchvision.ops.batched_nms``) and a cap on detections per image.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any
from urllib.parse import urlparse

import numpy as np
import torch
import torch.nn.functional as F
import torchvision
from torch import Tensor, nn
from torchvision.ops import batched_nms, box_iou

from foldwise.weights import IMAGENET_WEIGHTS, YOLO_BACKBONE_NAME

__all__ = [
    "DEFAULT_NUM_ANCHORS",
    "YOLOv2Detector",
    "assign_targets",
    "build_yolo",
    "centred_iou",
    "decode_boxes",
    "default_anchors",
    "encode_targets",
    "kmeans_anchors",
    "letterbox",
]

DEFAULT_NUM_ANCHORS = 5

# YOLOv2's VOC anchors (in 13-cell grid units), divided by 13: the fallback when there are no
# training boxes to cluster (and the placeholder a checkpoint's anchors overwrite).
_YOLOV2_VOC_ANCHORS = (
    np.array([[1.3221, 1.73145], [3.19275, 4.00944], [5.05587, 8.09892], [9.47112, 4.84053], [11.2364, 10.0071]]) / 13.0
)

# Smallest anchor or box side kept by k-means, as a fraction of the input size: a 1-px box at
# 2048 px is still above it, and it keeps log(w / anchor) finite for degenerate boxes.
_MIN_RELATIVE_SIDE = 1e-4

# exp(tw) is clamped here: a box at most e^4 ≈ 55 times its anchor, and never inf.
_MAX_LOG_SCALE = 4.0

_IMAGENET_MEAN = (0.485, 0.456, 0.406)
_IMAGENET_STD = (0.229, 0.224, 0.225)
_PAD_VALUE = 0.5
_BATCHNORM_MOMENTUM = 0.1

# Backbone base name -> (torchvision builder, ImageNet weights enum entry): the classifiers
# foldwise knows the ImageNet files of (foldwise/weights.py).
_BACKBONES: dict[str, tuple[str, str]] = {
    name: (name, enum_entry) for name, (enum_entry, _file) in IMAGENET_WEIGHTS.items()
}
# Detection-style names ("mobilenet_v3_large_fpn", "mobilenet_v3_large_320_fpn",
# "resnet50_fpn_v2") name the same feature extractor; the passthrough join plays the FPN's role.
_BACKBONE_NAME = YOLO_BACKBONE_NAME


# --------------------------------------------------------------------------------------------
# Anchors
# --------------------------------------------------------------------------------------------


def centred_iou(wh_a: np.ndarray, wh_b: np.ndarray) -> np.ndarray:
    """IoU of boxes sharing one centre, from their (w, h): ``(n, 2), (k, 2) -> (n, k)``."""
    wh_a = np.asarray(wh_a, dtype=np.float64)
    wh_b = np.asarray(wh_b, dtype=np.float64)
    inter = np.minimum(wh_a[:, None, 0], wh_b[None, :, 0]) * np.minimum(wh_a[:, None, 1], wh_b[None, :, 1])
    union = (wh_a[:, 0] * wh_a[:, 1])[:, None] + (wh_b[:, 0] * wh_b[:, 1])[None, :] - inter
    return inter / np.maximum(union, 1e-12)


def default_anchors(k: int = DEFAULT_NUM_ANCHORS) -> np.ndarray:
    """A sensible anchor set without training boxes: (k, 2) (w, h) fractions of the input size.

    Five anchors are YOLOv2's VOC set; other counts spread square, tall and wide shapes over
    sizes from 8% to 80% of the input, smallest first.
    """
    if k < 1:
        raise ValueError(f"number of anchors must be at least 1, got {k}")
    if k == len(_YOLOV2_VOC_ANCHORS):
        anchors = _YOLOV2_VOC_ANCHORS.copy()
    else:
        sides = np.geomspace(0.08, 0.8, k)
        aspects = np.array([1.0, 0.5, 2.0])[np.arange(k) % 3]  # h / w
        anchors = np.stack([sides / np.sqrt(aspects), sides * np.sqrt(aspects)], axis=1)
        anchors = np.clip(anchors, _MIN_RELATIVE_SIDE, 1.0)
    return _sort_by_area(anchors)


def _sort_by_area(anchors: np.ndarray) -> np.ndarray:
    order = np.lexsort((anchors[:, 0], anchors[:, 0] * anchors[:, 1]))
    return anchors[order]


def _kmeans_pp_init(wh: np.ndarray, k: int, rng: np.random.Generator) -> np.ndarray:
    centres = [wh[rng.integers(len(wh))]]
    for _ in range(1, k):
        distance = 1.0 - centred_iou(wh, np.array(centres)).max(axis=1)
        weights = distance**2
        total = weights.sum()
        if total <= 0:  # every point sits on a centre already
            break
        centres.append(wh[rng.choice(len(wh), p=weights / total)])
    return np.array(centres)


def _lloyd(wh: np.ndarray, centres: np.ndarray, max_iter: int) -> tuple[np.ndarray, float]:
    k = len(centres)
    assignment = None
    for _ in range(max_iter):
        iou = centred_iou(wh, centres)
        new_assignment = iou.argmax(axis=1)
        if assignment is not None and np.array_equal(new_assignment, assignment):
            break
        assignment = new_assignment
        for j in range(k):
            members = wh[assignment == j]
            if len(members):
                centres[j] = members.mean(axis=0)
            else:  # an empty cluster takes the point worst served by the others
                worst = int(iou.max(axis=1).argmin())
                centres[j] = wh[worst]
    mean_iou = float(centred_iou(wh, centres).max(axis=1).mean())
    return centres, mean_iou


def kmeans_anchors(
    wh: np.ndarray,
    k: int = DEFAULT_NUM_ANCHORS,
    *,
    seed: int = 0,
    n_init: int = 3,
    max_iter: int = 100,
    max_points: int = 20000,
) -> np.ndarray:
    """YOLOv2 anchors: k-means of box shapes with distance ``1 − IoU`` of centred boxes.

    ``wh`` holds (w, h) as fractions of the input size. Deterministic for a given seed
    (k-means++ seeding, ``n_init`` restarts, the best mean IoU kept). Non-finite or
    non-positive shapes are dropped and sides clipped to ``[1e-4, 1]``; with no usable shape
    the :func:`default_anchors` come back, and with fewer distinct shapes than ``k`` those
    shapes are completed by the default anchors least like them. Returns (k, 2) float64
    sorted by area.
    """
    if k < 1:
        raise ValueError(f"number of anchors must be at least 1, got {k}")
    wh = np.asarray(wh, dtype=np.float64).reshape(-1, 2)
    usable = np.isfinite(wh).all(axis=1) & (wh > 0).all(axis=1)
    wh = np.clip(wh[usable], _MIN_RELATIVE_SIDE, 1.0)
    if len(wh) == 0:
        return default_anchors(k)
    rng = np.random.default_rng(seed)
    if len(wh) > max_points:
        wh = wh[np.sort(rng.choice(len(wh), size=max_points, replace=False))]
    distinct = np.unique(wh, axis=0)
    if len(distinct) <= k:
        return _complete_with_defaults(distinct, k)
    best_centres, best_iou = None, -1.0
    for _ in range(max(1, n_init)):
        centres = _kmeans_pp_init(wh, k, rng)
        if len(centres) < k:  # degenerate spread: fewer than k separable shapes
            return _complete_with_defaults(np.unique(centres, axis=0), k)
        centres, mean_iou = _lloyd(wh, centres.copy(), max_iter)
        if mean_iou > best_iou:
            best_centres, best_iou = centres, mean_iou
    return _sort_by_area(best_centres)


def _complete_with_defaults(anchors: np.ndarray, k: int) -> np.ndarray:
    """Fill up to k anchors with the default shapes least like those present (greedy)."""
    anchors = [a for a in anchors]
    pool = list(default_anchors(max(k, DEFAULT_NUM_ANCHORS))) + list(default_anchors(2 * k + 1))
    while len(anchors) < k:
        present = np.array(anchors)
        candidates = np.array(pool)
        closeness = centred_iou(candidates, present).max(axis=1)
        pick = int(closeness.argmin())
        anchors.append(pool.pop(pick))
    return _sort_by_area(np.array(anchors))


# --------------------------------------------------------------------------------------------
# Geometry: letterbox, encoding and decoding
# --------------------------------------------------------------------------------------------


def letterbox(image: Tensor, input_size: int, canvas_size: int | None = None) -> tuple[Tensor, tuple[float, float]]:
    """Resize ``image (3, H, W)`` to fit ``input_size`` (aspect kept) at the canvas's top-left.

    Returns the canvas ``(3, C, C)`` (``C = canvas_size or input_size``, padding grey) and the
    per-axis scale ``(sx, sy)`` = resized / original size, so that ``x_in = x * sx`` exactly.
    """
    canvas_size = canvas_size or input_size
    # Plain ints also under ONNX export, whose tracer hands out sizes as tensors (the export
    # is then for this image size: workers/train/export.py).
    height, width = int(image.shape[-2]), int(image.shape[-1])
    scale = input_size / max(height, width)
    new_w = max(1, min(input_size, round(width * scale)))
    new_h = max(1, min(input_size, round(height * scale)))
    if (new_h, new_w) != (height, width):
        resized = F.interpolate(
            image[None], size=(new_h, new_w), mode="bilinear", align_corners=False, antialias=new_h < height
        )[0]
    else:
        resized = image
    canvas = image.new_full((3, canvas_size, canvas_size), _PAD_VALUE)
    canvas[:, :new_h, :new_w] = resized.clamp(0.0, 1.0)
    return canvas, (new_w / width, new_h / height)


def _offset_range(cell_margin: float) -> tuple[float, float]:
    """The centre offset σ(t) maps to: ``[−margin, 1 + margin]`` of a cell."""
    return -cell_margin, 1.0 + 2.0 * cell_margin


def _straight_through_clamp(t: Tensor, bound: float) -> Tensor:
    """``t`` clamped to ±bound in value, identity in gradient.

    A plain clamp has zero gradient outside the bound: a size logit that overshoots once
    (large early steps) would stay stuck at a huge box for good.
    """
    return t + (t.clamp(-bound, bound) - t).detach()


def decode_boxes(raw: Tensor, anchors: Tensor, stride: float, cell_margin: float = 0.0) -> Tensor:
    """Box predictions ``raw (..., gh, gw, A, 4)`` of ``(tx, ty, tw, th)`` to xyxy in input pixels.

    ``anchors (A, 2)`` are in input pixels; cell (row i, column j) spans
    ``[j·stride, (j+1)·stride) × [i·stride, (i+1)·stride)``. The centre is
    ``(j − m + (1 + 2m)·σ(tx))·stride`` with ``m = cell_margin`` (YOLOv2: m = 0; a margin of
    0.5 lets a cell also predict objects centred up to half a cell beyond its border), the size
    ``anchor · exp(t)`` with ``t`` clamped to ±4.
    """
    low, span = _offset_range(cell_margin)
    grid_h, grid_w = raw.shape[-4], raw.shape[-3]
    rows = torch.arange(grid_h, device=raw.device, dtype=raw.dtype).view(grid_h, 1, 1)
    cols = torch.arange(grid_w, device=raw.device, dtype=raw.dtype).view(1, grid_w, 1)
    cx = (cols + low + span * torch.sigmoid(raw[..., 0])) * stride
    cy = (rows + low + span * torch.sigmoid(raw[..., 1])) * stride
    w = anchors[:, 0] * torch.exp(_straight_through_clamp(raw[..., 2], _MAX_LOG_SCALE))
    h = anchors[:, 1] * torch.exp(_straight_through_clamp(raw[..., 3], _MAX_LOG_SCALE))
    return torch.stack([cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2], dim=-1)


def _box_anchor_iou(boxes: Tensor, anchors: Tensor) -> Tensor:
    w = (boxes[:, 2] - boxes[:, 0]).clamp(min=1e-6)
    h = (boxes[:, 3] - boxes[:, 1]).clamp(min=1e-6)
    inter = torch.minimum(w[:, None], anchors[None, :, 0]) * torch.minimum(h[:, None], anchors[None, :, 1])
    union = (w * h)[:, None] + (anchors[:, 0] * anchors[:, 1])[None, :] - inter
    return inter / union


def assign_targets(
    boxes: Tensor,
    anchors: Tensor,
    stride: float,
    grid_size: tuple[int, int],
    *,
    cell_margin: float = 0.0,
    anchor_match_iou: float = 1.0,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The predictions responsible for each box: ``(box_index, rows, cols, anchor_index)``.

    YOLOv2 (``cell_margin=0``, ``anchor_match_iou=1``): the cell holding the box centre
    (clamped into the grid) and the anchor of best centred IoU, one prediction per box.
    With ``cell_margin=0.5`` the two neighbouring cells nearest the centre (one across each
    axis) also answer for it, and ``anchor_match_iou < 1`` adds every anchor whose centred
    IoU with the box reaches it (YOLOv4/v5's assignment). Why: a centred object sits on a
    cell border of an even grid, and near-identical k-means anchors tie; a single
    responsible slot then flips on sub-pixel changes and objectness can never be confident.
    When boxes compete for one slot, the centre cell's claim beats a neighbour's, then the
    better anchor IoU, then the later box.
    """
    grid_h, grid_w = grid_size
    if boxes.numel() == 0:
        empty = torch.zeros(0, dtype=torch.long, device=boxes.device)
        return empty, empty, empty, empty
    cx = (boxes[:, 0] + boxes[:, 2]) / 2 / stride
    cy = (boxes[:, 1] + boxes[:, 3]) / 2 / stride
    col = cx.floor().clamp(0, grid_w - 1).long()
    row = cy.floor().clamp(0, grid_h - 1).long()
    iou = _box_anchor_iou(boxes, anchors)
    best = iou.argmax(dim=1)
    matched = iou >= anchor_match_iou
    matched[torch.arange(len(boxes), device=boxes.device), best] = True

    n = len(boxes)
    cell_candidates = [(torch.arange(n, device=boxes.device), row, col, torch.ones(n, device=boxes.device))]
    if cell_margin > 0:
        step_x = torch.where(cx - col < 0.5, -1, 1)
        step_y = torch.where(cy - row < 0.5, -1, 1)
        for d_row, d_col in ((0, step_x), (step_y, 0)):
            r, c = row + d_row, col + d_col
            # Only neighbours that can reach the centre (within the margin) and lie in the grid.
            reach_x = ((cx - c) >= -cell_margin) & ((cx - c) <= 1 + cell_margin)
            reach_y = ((cy - r) >= -cell_margin) & ((cy - r) <= 1 + cell_margin)
            inside = (r >= 0) & (r < grid_h) & (c >= 0) & (c < grid_w) & reach_x & reach_y
            index = torch.nonzero(inside, as_tuple=True)[0]
            cell_candidates.append((index, r[index], c[index], torch.zeros(len(index), device=boxes.device)))

    box_index, rows, cols, anchor_index, priority = [], [], [], [], []
    for index, r, c, is_centre in cell_candidates:
        pair_box, pair_anchor = torch.nonzero(matched[index], as_tuple=True)
        source = index[pair_box]
        box_index.append(source)
        rows.append(r[pair_box])
        cols.append(c[pair_box])
        anchor_index.append(pair_anchor)
        priority.append(2.0 * is_centre[pair_box] + iou[source, pair_anchor])
    box_index, rows, cols, anchor_index, priority = (
        torch.cat(x) for x in (box_index, rows, cols, anchor_index, priority)
    )
    # Resolve competing claims: order by (priority, box order), keep the last per slot.
    order = torch.argsort(box_index, stable=True)
    order = order[torch.argsort(priority[order], stable=True)]
    box_index, rows, cols, anchor_index = box_index[order], rows[order], cols[order], anchor_index[order]
    slot = (rows * grid_w + cols) * anchors.shape[0] + anchor_index
    keep = _last_occurrence(slot)
    keep = keep[torch.argsort(box_index[keep], stable=True)]  # grouped by box, for readers
    return box_index[keep], rows[keep], cols[keep], anchor_index[keep]


def encode_targets(
    boxes: Tensor,
    rows: Tensor,
    cols: Tensor,
    anchor_index: Tensor,
    anchors: Tensor,
    stride: float,
    cell_margin: float = 0.0,
) -> Tensor:
    """``(tx, ty, tw, th)`` that :func:`decode_boxes` turns back into ``boxes (n, 4)``.

    ``boxes`` xyxy in input pixels, each predicted from cell (``rows``, ``cols``) and anchor
    ``anchor_index`` (e.g. from :func:`assign_targets`). Offsets are kept a hair inside the
    sigmoid's open range so the logits stay finite.
    """
    low, span = _offset_range(cell_margin)
    cx = (boxes[:, 0] + boxes[:, 2]) / 2 / stride
    cy = (boxes[:, 1] + boxes[:, 3]) / 2 / stride
    w = (boxes[:, 2] - boxes[:, 0]).clamp(min=1e-6)
    h = (boxes[:, 3] - boxes[:, 1]).clamp(min=1e-6)
    eps = 1e-6
    sig_x = ((cx - cols - low) / span).clamp(eps, 1 - eps)
    sig_y = ((cy - rows - low) / span).clamp(eps, 1 - eps)
    return torch.stack(
        [
            torch.logit(sig_x),
            torch.logit(sig_y),
            torch.log(w / anchors[anchor_index, 0]),
            torch.log(h / anchors[anchor_index, 1]),
        ],
        dim=1,
    )


# --------------------------------------------------------------------------------------------
# Backbone
# --------------------------------------------------------------------------------------------


def _resolve_backbone(name: str) -> tuple[str, str]:
    match = _BACKBONE_NAME.match(name.strip().lower())
    base = match.group("base") if match else None
    if base not in _BACKBONES:
        known = ", ".join(sorted(_BACKBONES))
        raise ValueError(
            f"detector.backbone {name!r} is not supported by the yolo detector; known: {known} "
            "(optionally with a detection suffix such as _fpn, _320_fpn or _fpn_v2)"
        )
    return _BACKBONES[base]


def _load_imagenet_weights(model: nn.Module, weights_name: str, backbone: str) -> None:
    """Load torchvision's ImageNet weights from the local torch hub cache; never download."""
    weights = torchvision.models.get_weight(weights_name)
    filename = Path(urlparse(weights.url).path).name
    path = Path(torch.hub.get_dir()) / "checkpoints" / filename
    if not path.is_file():
        raise FileNotFoundError(
            f"detector.pretrained is 'imagenet' but the ImageNet weights of backbone {backbone!r} are not in "
            f"the local torch hub cache: {path} is missing. foldwise never downloads weights; copy the file "
            f"there (it is {weights.url}) or set detector.pretrained to 'none'."
        )
    state = torch.load(path, map_location="cpu", weights_only=True)
    model.load_state_dict(state)


class _Backbone(nn.Module):
    """A torchvision classifier cut into stages ending at strides 8, 16 and 32."""

    def __init__(self, name: str, pretrained: bool) -> None:
        super().__init__()
        builder, weights_name = _resolve_backbone(name)
        model = torchvision.models.get_model(builder, weights=None)
        if pretrained:
            _load_imagenet_weights(model, weights_name, name)
        if builder.startswith("mobilenet"):
            blocks = list(model.features)
            end8, end16 = self._last_block_of_stride(blocks, 8), self._last_block_of_stride(blocks, 16)
            self.to_stride8 = nn.Sequential(*blocks[: end8 + 1])
            self.to_stride16 = nn.Sequential(*blocks[end8 + 1 : end16 + 1])
            self.to_stride32 = nn.Sequential(*blocks[end16 + 1 :])
        else:
            self.to_stride8 = nn.Sequential(
                model.conv1, model.bn1, model.relu, model.maxpool, model.layer1, model.layer2
            )
            self.to_stride16 = model.layer3
            self.to_stride32 = model.layer4
        for module in self.modules():
            if isinstance(module, nn.BatchNorm2d):
                # MobileNetV3 ships with momentum 0.01, tuned for ImageNet-long runs; an increment of
                # a few hundred steps would leave eval-mode statistics near their initial values.
                module.momentum = _BATCHNORM_MOMENTUM
        # Probe in eval mode: a train-mode pass would fold the probe into BatchNorm statistics.
        self.eval()
        with torch.no_grad():
            features = self(torch.zeros(1, 3, 64, 64))
        self.train()
        if [f.shape[-1] for f in features] != [8, 4, 2]:
            raise RuntimeError(f"backbone {name!r}: unexpected strides {[64 // f.shape[-1] for f in features]}")
        self.channels = [f.shape[1] for f in features]

    @staticmethod
    def _last_block_of_stride(blocks: list[nn.Module], stride: int) -> int:
        x = torch.zeros(1, 3, 64, 64)
        last = -1
        with torch.no_grad():
            for index, block in enumerate(blocks):
                block.eval()
                x = block(x)
                block.train()
                if x.shape[-1] == 64 // stride:
                    last = index
        if last < 0:
            raise RuntimeError(f"backbone has no stride-{stride} stage")
        return last

    def forward(self, x: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        c8 = self.to_stride8(x)
        c16 = self.to_stride16(c8)
        return c8, c16, self.to_stride32(c16)


def _conv_bn(in_channels: int, out_channels: int, kernel: int) -> nn.Sequential:
    return nn.Sequential(
        nn.Conv2d(in_channels, out_channels, kernel, padding=kernel // 2, bias=False),
        nn.BatchNorm2d(out_channels),
        nn.LeakyReLU(0.1, inplace=True),
    )


# --------------------------------------------------------------------------------------------
# The detector
# --------------------------------------------------------------------------------------------


class YOLOv2Detector(nn.Module):
    """YOLOv2-style detector with torchvision's detection interface (see the module docstring)."""

    def __init__(
        self,
        backbone: str,
        num_classes: int,
        anchors: np.ndarray,
        input_size: int,
        *,
        pretrained: bool = False,
        grid_stride: int = 16,
        head_width: int = 128,
        ignore_iou: float = 0.6,
        cell_margin: float = 0.5,
        anchor_match_iou: float = 0.5,
        box_weight: float = 1.0,
        objectness_weight: float = 5.0,
        noobject_weight: float = 1.0,
        class_weight: float = 1.0,
        score_threshold: float = 0.01,
        nms_iou: float = 0.45,
        detections_per_image: int = 100,
        channels_last: bool = True,
    ) -> None:
        super().__init__()
        if num_classes < 1:
            raise ValueError(f"num_classes must be at least 1, got {num_classes}")
        if grid_stride not in (8, 16, 32):
            raise ValueError(f"grid_stride must be 8, 16 or 32, got {grid_stride}")
        anchors = np.asarray(anchors, dtype=np.float64)
        if anchors.ndim != 2 or anchors.shape[1] != 2 or len(anchors) < 1 or not (anchors > 0).all():
            raise ValueError(f"anchors must be a (k, 2) array of positive (w, h), got shape {anchors.shape}")
        self.num_classes = num_classes
        self.num_anchors = len(anchors)
        self.input_size = input_size
        # The letterboxed image sits in a canvas padded to a multiple of 32, so grid cells are
        # exactly `grid_stride` pixels whatever the input size.
        self.canvas_size = int(math.ceil(input_size / 32) * 32)
        self.grid_stride = grid_stride
        self.ignore_iou = ignore_iou
        self.cell_margin = cell_margin
        self.anchor_match_iou = anchor_match_iou
        self.box_weight = box_weight
        self.objectness_weight = objectness_weight
        self.noobject_weight = noobject_weight
        self.class_weight = class_weight
        self.score_threshold = score_threshold
        self.nms_iou = nms_iou
        self.detections_per_image = detections_per_image

        # (w, h) as fractions of the input size; a persistent buffer so checkpoints carry them.
        self.register_buffer("anchors", torch.as_tensor(anchors, dtype=torch.float32))
        self.register_buffer("pixel_mean", torch.tensor(_IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("pixel_std", torch.tensor(_IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

        self.backbone = _Backbone(backbone, pretrained)
        c8, c16, c32 = self.backbone.channels
        self.reduce32 = _conv_bn(c32, head_width, 1)
        # YOLOv2's passthrough, top-down: finer features joined with upsampled coarser context
        # down to the grid's stride.
        self.reduce16 = _conv_bn(c16, head_width // 2, 1) if grid_stride <= 16 else None
        self.merge16 = _conv_bn(head_width + head_width // 2, head_width, 3) if grid_stride == 8 else None
        self.reduce8 = _conv_bn(c8, head_width // 2, 1) if grid_stride == 8 else None
        head_in = head_width if grid_stride == 32 else head_width + head_width // 2
        self.head = nn.Sequential(_conv_bn(head_in, head_width, 3), _conv_bn(head_width, head_width, 3))
        self.predict = nn.Conv2d(head_width, self.num_anchors * (5 + num_classes), 1)
        self._init_prediction_layer()
        # NHWC: oneDNN's CPU convolutions (depthwise ones above all) run 15–35% faster here.
        self.channels_last = channels_last
        if channels_last:
            self.to(memory_format=torch.channels_last)

    def _init_prediction_layer(self) -> None:
        nn.init.normal_(self.predict.weight, std=0.01)
        bias = self.predict.bias.detach().view(self.num_anchors, 5 + self.num_classes)
        bias.zero_()
        # Objectness starts at a 1% prior, so the many empty cells do not swamp the first steps.
        bias[:, 4] = math.log(0.01 / 0.99)

    # ---- input --------------------------------------------------------------------------

    def _check_inputs(self, images: list[Tensor], targets: list[dict[str, Tensor]] | None) -> None:
        if not isinstance(images, (list, tuple)) or len(images) == 0:
            raise ValueError("images must be a non-empty list of (3, H, W) tensors")
        for index, image in enumerate(images):
            if not isinstance(image, Tensor) or image.ndim != 3 or image.shape[0] != 3:
                shape = tuple(image.shape) if isinstance(image, Tensor) else type(image).__name__
                raise ValueError(f"images[{index}] must be a (3, H, W) tensor, got {shape}")
            if not image.is_floating_point():
                raise ValueError(f"images[{index}] must be float in [0, 1], got dtype {image.dtype}")
        if targets is None:
            return
        if len(targets) != len(images):
            raise ValueError(f"got {len(images)} images but {len(targets)} targets")
        for index, target in enumerate(targets):
            boxes, labels = target.get("boxes"), target.get("labels")
            if boxes is None or labels is None:
                raise ValueError(f"targets[{index}] needs 'boxes' and 'labels'")
            if boxes.ndim != 2 or boxes.shape[1] != 4:
                raise ValueError(f"targets[{index}]['boxes'] must be (n, 4) xyxy, got {tuple(boxes.shape)}")
            if labels.shape != (boxes.shape[0],):
                raise ValueError(f"targets[{index}]: {boxes.shape[0]} boxes but labels of shape {tuple(labels.shape)}")
            if not torch.isfinite(boxes).all():
                raise ValueError(f"targets[{index}]['boxes'] has non-finite values")
            degenerate = (boxes[:, 2] <= boxes[:, 0]) | (boxes[:, 3] <= boxes[:, 1])
            if degenerate.any():
                bad = boxes[degenerate][0].tolist()
                raise ValueError(f"targets[{index}]: boxes need positive width and height, got {bad}")
            if labels.numel() and (labels.min() < 1 or labels.max() > self.num_classes):
                raise ValueError(
                    f"targets[{index}]['labels'] must be in 1..{self.num_classes} (0 is background), "
                    f"got {labels.tolist()}"
                )

    def _prepare(self, images: list[Tensor]) -> tuple[Tensor, list[tuple[float, float]]]:
        canvases, scales = [], []
        for image in images:
            canvas, scale = letterbox(image, self.input_size, self.canvas_size)
            canvases.append(canvas)
            scales.append(scale)
        batch = (torch.stack(canvases) - self.pixel_mean) / self.pixel_std
        if self.channels_last:
            batch = batch.contiguous(memory_format=torch.channels_last)
        return batch, scales

    # ---- network ------------------------------------------------------------------------

    def _raw_predictions(self, batch: Tensor) -> Tensor:
        """(B, gh, gw, A, 5 + C) raw head outputs."""
        c8, c16, c32 = self.backbone(batch)
        features = self.reduce32(c32)
        if self.reduce16 is not None:
            features = F.interpolate(features, size=c16.shape[-2:], mode="nearest")
            features = torch.cat([self.reduce16(c16), features], dim=1)
        if self.reduce8 is not None:
            features = F.interpolate(self.merge16(features), size=c8.shape[-2:], mode="nearest")
            features = torch.cat([self.reduce8(c8), features], dim=1)
        out = self.predict(self.head(features))
        b, _, gh, gw = out.shape
        return out.reshape(b, self.num_anchors, 5 + self.num_classes, gh, gw).permute(0, 3, 4, 1, 2)

    def forward(
        self, images: list[Tensor], targets: list[dict[str, Tensor]] | None = None
    ) -> dict[str, Tensor] | list[dict[str, Tensor]]:
        if self.training and targets is None:
            raise ValueError("in training mode the yolo detector needs targets")
        self._check_inputs(images, targets)
        batch, scales = self._prepare(images)
        raw = self._raw_predictions(batch)
        anchors_px = self.anchors * self.input_size
        if self.training:
            return self._losses(raw, anchors_px, targets, scales)
        sizes = [(image.shape[-2], image.shape[-1]) for image in images]
        return self._postprocess(raw, anchors_px, scales, sizes)

    # ---- training -----------------------------------------------------------------------

    def _box_loss(
        self, raw_boxes: Tensor, boxes: Tensor, rows: Tensor, cols: Tensor, anchor_index: Tensor, anchors_px: Tensor
    ) -> Tensor:
        """YOLOv2's coordinate loss on the t's, per prediction: (n,).

        Centre offsets: binary KL divergence between σ(t) and the target offset (the gradient
        is σ(t) − target, as in logistic regression, and the loss is 0 at the target). Sizes:
        smooth-L1 on ``t − log(size / anchor)``, target clamped to the decodable range.
        Unlike an IoU loss through ``exp``, neither gradient grows with the box, so a step
        that overshoots cannot run away. Small boxes weigh up to 2× (YOLOv2's ``2 − w·h``).
        """
        target = encode_targets(boxes, rows, cols, anchor_index, anchors_px, self.grid_stride, self.cell_margin)
        offset_target = torch.sigmoid(target[:, :2])
        offset_loss = F.binary_cross_entropy_with_logits(raw_boxes[:, :2], offset_target, reduction="none")
        entropy = F.binary_cross_entropy(offset_target, offset_target, reduction="none")
        size_target = target[:, 2:].clamp(-_MAX_LOG_SCALE, _MAX_LOG_SCALE)
        size_loss = F.smooth_l1_loss(raw_boxes[:, 2:], size_target, reduction="none", beta=1.0)
        relative_area = (boxes[:, 2] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 1]) / self.input_size**2
        return (2.0 - relative_area.clamp(0, 1)) * ((offset_loss - entropy).sum(dim=1) + size_loss.sum(dim=1))

    def _losses(
        self, raw: Tensor, anchors_px: Tensor, targets: list[dict[str, Tensor]], scales: list[tuple[float, float]]
    ) -> dict[str, Tensor]:
        raw = raw.float()
        batch_size, grid_h, grid_w = raw.shape[:3]
        pred_boxes = decode_boxes(raw[..., :4], anchors_px, self.grid_stride, self.cell_margin)  # (B, gh, gw, A, 4)
        objectness = raw[..., 4]
        noobj_mask = torch.ones_like(objectness, dtype=torch.bool)

        box_terms, class_terms, positive_logits, positive_weights = [], [], [], []
        for index, (target, (sx, sy)) in enumerate(zip(targets, scales)):
            boxes = target["boxes"].to(raw.device, torch.float32)
            if boxes.numel() == 0:
                continue
            boxes = boxes * boxes.new_tensor([sx, sy, sx, sy])
            labels = target["labels"].to(raw.device, torch.int64) - 1
            with torch.no_grad():
                # Not responsible but already a good box: neither pushed up nor down.
                overlap = box_iou(pred_boxes[index].detach().reshape(-1, 4), boxes).amax(dim=1)
                noobj_mask[index] &= (overlap <= self.ignore_iou).view(grid_h, grid_w, -1)
            box_index, rows, cols, anchor_index = assign_targets(
                boxes,
                anchors_px,
                self.grid_stride,
                (grid_h, grid_w),
                cell_margin=self.cell_margin,
                anchor_match_iou=self.anchor_match_iou,
            )
            noobj_mask[index, rows, cols, anchor_index] = False
            # Each box weighs 1 however many predictions answer for it.
            weight = 1.0 / torch.bincount(box_index, minlength=len(boxes)).float()[box_index]
            matched_boxes = boxes[box_index]
            box_terms.append(
                weight
                * self._box_loss(
                    raw[index, rows, cols, anchor_index, :4], matched_boxes, rows, cols, anchor_index, anchors_px
                )
            )
            class_logits = raw[index, rows, cols, anchor_index, 5:]
            class_terms.append(weight * F.cross_entropy(class_logits, labels[box_index], reduction="none"))
            positive_logits.append(objectness[index, rows, cols, anchor_index])
            positive_weights.append(weight)

        negatives = objectness[noobj_mask]
        objectness_loss = self.noobject_weight * F.binary_cross_entropy_with_logits(
            negatives, torch.zeros_like(negatives), reduction="sum"
        )
        box_loss = raw.new_zeros(())
        class_loss = raw.new_zeros(())
        if positive_logits:
            positives = torch.cat(positive_logits)
            objectness_loss = objectness_loss + self.objectness_weight * F.binary_cross_entropy_with_logits(
                positives, torch.ones_like(positives), weight=torch.cat(positive_weights), reduction="sum"
            )
            box_loss = torch.cat(box_terms).sum()
            class_loss = torch.cat(class_terms).sum()
        return {
            "loss_box": self.box_weight * box_loss / batch_size,
            "loss_objectness": objectness_loss / batch_size,
            "loss_classifier": self.class_weight * class_loss / batch_size,
        }

    # ---- inference ----------------------------------------------------------------------

    @torch.no_grad()
    def _postprocess(
        self,
        raw: Tensor,
        anchors_px: Tensor,
        scales: list[tuple[float, float]],
        sizes: list[tuple[int, int]],
    ) -> list[dict[str, Tensor]]:
        raw = raw.float()
        boxes_all = decode_boxes(raw[..., :4], anchors_px, self.grid_stride, self.cell_margin).flatten(
            1, 3
        )  # (B, N, 4)
        scores_all = torch.sigmoid(raw[..., 4:5]) * torch.softmax(raw[..., 5:], dim=-1)
        scores_all = scores_all.flatten(1, 3)  # (B, N, C)
        results = []
        for index, ((sx, sy), (height, width)) in enumerate(zip(scales, sizes)):
            boxes = boxes_all[index] / boxes_all.new_tensor([sx, sy, sx, sy])
            boxes[:, 0::2] = boxes[:, 0::2].clamp(0, width)
            boxes[:, 1::2] = boxes[:, 1::2].clamp(0, height)
            box_index, class_index = torch.nonzero(scores_all[index] > self.score_threshold, as_tuple=True)
            boxes = boxes[box_index]
            scores = scores_all[index, box_index, class_index]
            valid = (boxes[:, 2] > boxes[:, 0]) & (boxes[:, 3] > boxes[:, 1])
            boxes, scores, class_index = boxes[valid], scores[valid], class_index[valid]
            keep = batched_nms(boxes, scores, class_index, self.nms_iou)[: self.detections_per_image]
            results.append({"boxes": boxes[keep], "scores": scores[keep], "labels": class_index[keep] + 1})
        return results


def _last_occurrence(values: Tensor) -> Tensor:
    """Positions (ascending) of the last occurrence of each distinct value."""
    n = values.numel()
    if n <= 1:
        return torch.arange(n, device=values.device)
    later_equal = (values[:, None] == values[None, :]).triu(diagonal=1).any(dim=1)
    return torch.nonzero(~later_equal, as_tuple=True)[0]


def build_yolo(
    config: Any,
    num_classes: int,
    train_boxes: np.ndarray | None,
    *,
    train_image_sizes: np.ndarray | None = None,
    num_anchors: int | None = None,
    seed: int = 0,
    **options: Any,
) -> YOLOv2Detector:
    """A YOLOv2-style detector for ``config`` (a :class:`foldwise.config.DetectorConfig`).

    ``train_boxes`` (n, 4) xyxy in the training images' pixels give the k-means anchors;
    ``train_image_sizes`` (n, 2) ``(height, width)`` of each box's image normalise them the way
    the letterbox will (by the longer side); without it the images are taken to be
    ``config.input_size`` square. ``train_boxes=None`` (rebuilding from a checkpoint, whose
    state dict then brings the anchors) uses :func:`default_anchors` as the placeholder.
    The anchor count comes from ``num_anchors``, else ``config.num_anchors`` where the config
    has one, else 5. ``options`` go to :class:`YOLOv2Detector` (grid_stride, head_width, loss
    weights, score_threshold, nms_iou, detections_per_image); the score threshold and the
    detection cap default to the config's ``box_score_threshold`` and ``detections_per_image``.
    """
    k = num_anchors if num_anchors is not None else getattr(config, "num_anchors", DEFAULT_NUM_ANCHORS)
    input_size = int(config.input_size)
    if train_boxes is None:
        anchors = default_anchors(k)
    else:
        boxes = np.asarray(train_boxes, dtype=np.float64)
        if boxes.size == 0:
            boxes = boxes.reshape(0, 4)
        if boxes.ndim != 2 or boxes.shape[1] != 4:
            raise ValueError(f"train_boxes must be (n, 4) xyxy pixels, got shape {boxes.shape}")
        wh = boxes[:, 2:4] - boxes[:, 0:2]
        if train_image_sizes is not None:
            sizes = np.asarray(train_image_sizes, dtype=np.float64).reshape(-1, 2)
            if len(sizes) != len(boxes):
                raise ValueError(f"train_image_sizes has {len(sizes)} rows for {len(boxes)} train_boxes")
            if not (sizes > 0).all():
                raise ValueError("train_image_sizes must be positive (height, width) pairs")
            longer_side = sizes.max(axis=1, keepdims=True)
        else:
            longer_side = float(input_size)
        anchors = kmeans_anchors(wh / longer_side, k, seed=seed)
    # Inference settings shared with the other families, where the config has them.
    for option, key in (("score_threshold", "box_score_threshold"), ("detections_per_image", "detections_per_image")):
        if option not in options and hasattr(config, key):
            options[option] = getattr(config, key)
    return YOLOv2Detector(
        backbone=config.backbone,
        num_classes=num_classes,
        anchors=anchors,
        input_size=input_size,
        pretrained=config.pretrained == "imagenet",
        **options,
    )
