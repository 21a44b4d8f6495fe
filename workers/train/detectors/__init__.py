"""Detector families behind one constructor, ``build_detector``.

Every detector follows torchvision's detection interface:
``forward(images: list[Tensor[3, H, W] in 0..1], targets: list[dict(boxes xyxy, labels 1-based)] | None)``
returns a dict of named loss tensors in training mode and ``list[dict(boxes, scores, labels)]``
(labels 1-based, boxes in the input images' pixels) in eval mode.

Families: ``faster_rcnn`` (torchvision's Faster R-CNN), ``fast_rcnn`` (torchvision RoI heads fed
Edge Boxes proposals) and ``yolo`` (``workers.train.detectors.yolo``). The R-CNNs' feature
pyramids, their pretrained weights and anchors are in ``workers.train.detectors.backbones``; the
test-time views (sizes, quarter turns) and the merge that votes over them in
``workers.train.detectors.views``. Torch is imported lazily so that importing this package stays
cheap.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from torch import nn

    from foldwise.config import DetectorConfig

FAMILIES = ("faster_rcnn", "fast_rcnn", "yolo")


class DetectorBuildError(ValueError):
    """A detector configuration that cannot be built; the message names the bad key."""


def build_detector(
    config: DetectorConfig,
    num_classes: int,
    train_boxes: np.ndarray | None = None,
    *,
    train_image_sizes: np.ndarray | None = None,
    load_pretrained: bool = True,
) -> nn.Module:
    """A fresh detector for ``num_classes`` object classes (background excluded).

    ``train_boxes`` (n, 4) xyxy pixels of the training set only matter to the yolo family (its
    k-means anchors; ``train_image_sizes`` (n, 2) height, width of each box's image).
    ``load_pretrained=False`` builds the architecture ``config.pretrained`` implies without
    reading ImageNet weights (the caller loads a checkpoint's state next).
    """
    if num_classes < 1:
        raise DetectorBuildError(f"a detector needs at least one class, got num_classes={num_classes}")
    if config.family == "faster_rcnn":
        from workers.train.detectors.faster_rcnn import build_faster_rcnn

        return build_faster_rcnn(config, num_classes, load_pretrained=load_pretrained)
    if config.family == "fast_rcnn":
        from workers.train.detectors.fast_rcnn import build_fast_rcnn

        return build_fast_rcnn(config, num_classes, load_pretrained=load_pretrained)
    if config.family == "yolo":
        from workers.train.detectors.yolo import build_yolo

        if not load_pretrained:  # the yolo architecture does not depend on its initial weights
            config = config.model_copy(update={"pretrained": "none"})
        return build_yolo(config, num_classes, train_boxes, train_image_sizes=train_image_sizes)
    raise DetectorBuildError(f"detector.family {config.family!r} is unknown; known: {', '.join(FAMILIES)}")
