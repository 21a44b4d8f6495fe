"""Detector families behind one constructor, ``build_detector``.

Every detector follows torchvision's detection interface:
``forward(images: list[Tensor[3, H, W] in 0..1], targets: list[dict(boxes xyxy, labels 1-based)] | None)``
returns a dict of named loss tensors in training mode and ``list[dict(boxes, scores, labels)]``
(labels 1-based, boxes in the input images' pixels) in eval mode.

Families: ``faster_rcnn`` (torchvision's Faster R-CNN), ``fast_rcnn`` (torchvision RoI heads fed
Edge Boxes proposals) and ``yolo`` (``workers.train.detectors.yolo``). Torch is imported lazily
so that importing this package stays cheap.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING
from urllib.parse import urlparse

import numpy as np

from foldwise.weights import RCNN_BACKBONES

if TYPE_CHECKING:
    from torch import nn

    from foldwise.config import DetectorConfig

FAMILIES = ("faster_rcnn", "fast_rcnn", "yolo")

# The backbone names each family accepts are in foldwise/weights.py: the config checks them
# before any work, without torch; the builders check again (a config built without validation).


class PretrainedWeightsMissing(FileNotFoundError):
    """``pretrained: imagenet`` but the ImageNet weights are not in the local torch hub cache."""


class DetectorBuildError(ValueError):
    """A detector configuration that cannot be built; the message names the bad key."""


def imagenet_weights_path(classifier: str) -> tuple[Path, str]:
    """Where torchvision keeps the ImageNet weights of ``classifier`` offline, and their URL."""
    import torch
    import torchvision

    weights = torchvision.models.get_model_weights(classifier).IMAGENET1K_V1
    filename = Path(urlparse(weights.url).path).name
    return Path(torch.hub.get_dir()) / "checkpoints" / filename, weights.url


def load_imagenet_state(classifier: str, backbone_name: str) -> dict:
    """ImageNet weights of ``classifier`` from the local torch hub cache; never downloads."""
    import torch

    path, url = imagenet_weights_path(classifier)
    if not path.is_file():
        raise PretrainedWeightsMissing(
            f"detector.pretrained is 'imagenet' but the ImageNet weights for backbone {backbone_name!r} "
            f"are not in the local torch hub cache: expected {path}. foldwise never downloads weights: "
            f"copy {path.name} (published at {url}) there, or set detector.pretrained to 'none'."
        )
    return torch.load(path, map_location="cpu", weights_only=True)


def build_backbone(config: DetectorConfig, load_pretrained: bool = True) -> nn.Module:
    """A feature pyramid (``config.fpn_channels`` channels) on a torchvision classifier.

    Random initialisation trains every layer with ordinary BatchNorm; ImageNet weights freeze
    the first stages (and, for mobilenet, BatchNorm statistics: small batches) as torchvision's
    detection models do. ``load_pretrained=False`` keeps that architecture (frozen BatchNorm)
    without reading the ImageNet file: for a model whose weights come from a checkpoint.
    """
    import torchvision
    from torch import nn
    from torchvision.models.detection.backbone_utils import BackboneWithFPN
    from torchvision.ops import FrozenBatchNorm2d
    from torchvision.ops.feature_pyramid_network import LastLevelMaxPool

    classifier_name = RCNN_BACKBONES.get(config.backbone)
    if classifier_name is None:
        raise DetectorBuildError(
            f"detector.backbone {config.backbone!r} is not supported by the {config.family} detector; "
            f"known: {', '.join(RCNN_BACKBONES)}"
        )
    if classifier_name == "mobilenet_v3_large_075":
        return _mobilenet_v3_large_075_fpn(config, load_pretrained)
    pretrained = config.pretrained == "imagenet"
    state = load_imagenet_state(classifier_name, config.backbone) if pretrained and load_pretrained else None

    if classifier_name == "mobilenet_v3_large":
        classifier = torchvision.models.mobilenet_v3_large(
            weights=None, norm_layer=FrozenBatchNorm2d if pretrained else nn.BatchNorm2d
        )
        if state is not None:
            classifier.load_state_dict(state)
        body = classifier.features
        stages = freeze_early_stages(body, trainable_stages(config))
        # Strides 8, 16 and 32: torchvision's own variant reads stride 32 only, too coarse for
        # 10-pixel objects in 128-pixel images.
        returned = [stages[2], stages[3], stages[-1]]
        return_layers = {str(index): str(level) for level, index in enumerate(returned)}
        in_channels = [body[index].out_channels for index in returned]
    else:
        # resnet50_fpn_v2: BatchNorm throughout, like torchvision's fasterrcnn_resnet50_fpn_v2.
        body = torchvision.models.resnet50(weights=None)
        if state is not None:
            body.load_state_dict(state)
        trainable = ["layer4", "layer3", "layer2", "layer1", "conv1", "bn1"][: trainable_stages(config)]
        if "conv1" in trainable:
            trainable.append("bn1")
        for name, parameter in body.named_parameters():
            if not name.startswith(tuple(trainable)):
                parameter.requires_grad_(False)
        return_layers = {f"layer{k}": str(k - 1) for k in (1, 2, 3, 4)}
        in_channels = [256, 512, 1024, 2048]

    return BackboneWithFPN(
        body,
        return_layers,
        in_channels,
        config.fpn_channels,
        extra_blocks=LastLevelMaxPool(),
        norm_layer=nn.BatchNorm2d if classifier_name == "resnet50" else None,
    )


def trainable_stages(config: DetectorConfig) -> int:
    """How many backbone stages train, counted from the last: the config's
    ``trainable_backbone_stages``, else 3 for pretrained weights (torchvision's default for
    fine-tuning) and every stage from random ones. Stages: the stem, each block that halves the
    resolution, and the last 1x1 convolution (mobilenets, 6 in all); layer4..layer1 and the stem
    (resnet, 5)."""
    if config.trainable_backbone_stages is not None:
        return config.trainable_backbone_stages
    return 3 if config.pretrained != "none" else 6


def freeze_early_stages(body: nn.Sequential, trainable: int) -> list[int]:
    """Freeze a mobilenet body but for its last ``trainable`` stages; returns where each stage
    starts (the stem, each strided block, the last 1x1 conv: as torchvision's extractor)."""
    stages = [0] + [i for i, block in enumerate(body) if getattr(block, "_is_cn", False)] + [len(body) - 1]
    first_trained = len(body) if trainable == 0 else stages[max(len(stages) - trainable, 0)]
    for block in body[:first_trained]:
        for parameter in block.parameters():
            parameter.requires_grad_(False)
    return stages


def _mobilenet_v3_large_075_fpn(config: DetectorConfig, load_pretrained: bool) -> nn.Module:
    """The feature pyramid on TensorFlow-slim's MobileNetV3-Large x0.75 (strides 8, 16, 32).

    With ``pretrained: coco`` the early stages keep the COCO weights (``trainable_stages``) and
    the rest fine-tunes; BatchNorm is folded into those weights, so it stays frozen throughout.
    """
    from torch import nn
    from torchvision.models.detection.backbone_utils import BackboneWithFPN
    from torchvision.ops.feature_pyramid_network import LastLevelMaxPool

    from workers.train.detectors.mobilenet_v3_tf import (
        FEATURE_CHILDREN,
        FOLDED_BATCHNORM,
        load_coco_weights,
        mobilenet_v3_large_075_body,
    )

    pretrained = config.pretrained == "coco"
    body = mobilenet_v3_large_075_body(FOLDED_BATCHNORM if pretrained else nn.BatchNorm2d)
    if pretrained and load_pretrained:
        load_coco_weights(body)
    freeze_early_stages(body, trainable_stages(config))
    return BackboneWithFPN(
        body,
        {str(child): str(level) for level, child in enumerate(FEATURE_CHILDREN)},
        [body[child].out_channels for child in FEATURE_CHILDREN],
        config.fpn_channels,
        extra_blocks=LastLevelMaxPool(),
        # The body's features are unnormalised (std ~13 at stride 8 on 0..255 input): without
        # BatchNorm the fresh pyramid and RPN diverged at the first steps.
        norm_layer=nn.BatchNorm2d,
    )


def input_normalization(config: DetectorConfig) -> tuple[list[float], list[float]]:
    """The (mean, std) the detector's transform applies to 0..1 images: ImageNet's statistics
    for torchvision's classifiers, 0..255 for the TensorFlow MobileNet (trained on raw pixels)."""
    if RCNN_BACKBONES.get(config.backbone) == "mobilenet_v3_large_075":
        from workers.train.detectors.mobilenet_v3_tf import PIXEL_SCALE

        return [0.0, 0.0, 0.0], [1.0 / PIXEL_SCALE] * 3
    return [0.485, 0.456, 0.406], [0.229, 0.224, 0.225]


def feature_map_names(backbone: nn.Module) -> list[str]:
    """The FPN levels RoI pooling reads (every level but the extra max-pooled one)."""
    import torch

    was_training = backbone.training
    backbone.eval()
    with torch.no_grad():
        names = [name for name in backbone(torch.zeros(1, 3, 64, 64)) if name != "pool"]
    backbone.train(was_training)
    return names


def anchor_sizes(config: DetectorConfig, levels: int, per_level: int = 2) -> tuple[tuple[float, ...], ...]:
    """Anchor sizes in input pixels, log-spaced over ``config.anchor_size_range`` × input size.

    Fine levels get the small sizes: e.g. 128 px input, 4 levels: (10, 15), (21, 30), (43, 62), (89, 128).
    """
    low, high = config.anchor_size_range
    sizes = np.geomspace(low * config.input_size, high * config.input_size, levels * per_level)
    return tuple(tuple(float(round(s, 2)) for s in sizes[i * per_level : (i + 1) * per_level]) for i in range(levels))


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


def detect_at_views(
    model: nn.Module, detect: Callable[[list], list[dict]], images: list, sizes: Sequence[int], turns: Sequence[int]
) -> list[dict]:
    """An R-CNN's detections (``detect(images)``: its one-size eval forward on a batch) on each
    view of the images: resized to each of ``sizes`` (``config.test_sizes``; empty: the model's
    own size) and turned by each of ``turns`` quarter turns (``config.test_turns``; empty: as
    they are), merged per image by per-class NMS at the model's own NMS IoU and detection cap,
    scored by the views' vote where the model has one (``model.view_vote``: ``merge_detections``).

    Each size keeps the model's square rule (the longer side at ``size``); every run's boxes are
    mapped back to the images' own pixels (resize and turn undone), so they merge as they are.
    The size is restored after, also when a run fails.
    """
    transform, heads = model.transform, model.roi_heads
    saved = transform.min_size, transform.max_size
    runs = []
    try:
        for turn in turns or (0,):
            turned = [turn_image(image, turn) for image in images] if turn else images
            for size in sizes or (None,):
                if size is not None:
                    transform.min_size, transform.max_size = (int(size),), int(size)
                outputs = detect(turned)
                if turn:
                    outputs = [
                        {**output, "boxes": unturn_boxes(output["boxes"], turn, image.shape[-2], image.shape[-1])}
                        for output, image in zip(outputs, images)
                    ]
                runs.append(outputs)
    finally:
        transform.min_size, transform.max_size = saved
    vote = getattr(model, "view_vote", None)
    return [merge_detections(outputs, heads.nms_thresh, heads.detections_per_img, vote) for outputs in zip(*runs)]


# A run votes for a box only with a score of at least this (the same 0.3 the texture check starts
# from): weak boxes that many views give clutter would otherwise add up over the paper's cut.
VOTE_FLOOR = 0.3


def merge_detections(outputs: Sequence[dict], iou_threshold: float, limit: int, vote: float | None = None) -> dict:
    """One image's detections from several runs (views, or several detectors) as one: per-class
    NMS at ``iou_threshold`` over all their boxes, the best ``limit`` kept, best first. Each
    run is a dict of ``boxes`` (n, 4) xyxy, ``scores`` (n,), ``labels`` (n,), tensors or arrays
    (the result is of the first run's kind).

    ``vote`` None: a kept box keeps its own score (the best of the boxes it suppresses). A
    fraction ``vote`` in (0, 1]: the runs vote (``detector.view_vote``): a kept box scores
    ``1 - prod over runs (1 - vote * s_r)``, ``s_r`` the best score of that run's boxes it
    suppressed, where it is at least ``VOTE_FLOOR`` (the run abstains otherwise), so a box most
    runs find outranks one a single run is sure of. A box no run scores at the floor, and one
    run alone, keep their scores. The same boxes are kept either way; only scores and order
    differ. Written in tensor operations only, as ONNX export traces it.
    """
    import torch
    from torchvision.ops import batched_nms, box_iou

    arrays = not isinstance(outputs[0]["boxes"], torch.Tensor)
    boxes = torch.cat([torch.as_tensor(output["boxes"]).reshape(-1, 4) for output in outputs])
    scores = torch.cat([torch.as_tensor(output["scores"]) for output in outputs])
    labels = torch.cat([torch.as_tensor(output["labels"]) for output in outputs])
    keep = batched_nms(boxes, scores, labels, iou_threshold)
    if vote is None or len(outputs) < 2:
        keep = keep[:limit]
        merged = {"boxes": boxes[keep], "scores": scores[keep], "labels": labels[keep]}
    else:
        runs = torch.cat(
            [torch.full_like(torch.as_tensor(output["scores"]), index) for index, output in enumerate(outputs)]
        )
        # Each box belongs to the first kept box (best first) of its class it overlaps: the one
        # that suppressed it in the greedy NMS above (a kept box belongs to itself).
        overlaps = (box_iou(boxes[keep], boxes) > iou_threshold) & (labels[keep][:, None] == labels[None, :])
        owner = overlaps & (overlaps.to(torch.int32).cumsum(0) == 1)
        voting = torch.where(scores >= VOTE_FLOOR, scores, torch.zeros_like(scores))[None, :]  # abstaining: 0
        missed = torch.ones_like(keep, dtype=scores.dtype)
        for index in range(len(outputs)):
            best = _row_max(torch.where(owner & (runs == index)[None, :], voting, torch.zeros_like(voting)))
            missed = missed * (1 - vote * best)
        # A box no run scored at the floor keeps its own (low) score.
        voted = torch.where(missed < 1, 1 - missed, scores[keep])
        order = voted.sort(descending=True).indices[:limit]
        keep = keep[order]
        merged = {"boxes": boxes[keep], "scores": voted[order], "labels": labels[keep]}
    return {key: value.numpy() for key, value in merged.items()} if arrays else merged


def _row_max(values):
    """Each row's maximum of a (k, n) tensor, 0 for rows of an empty one (n = 0)."""
    import torch

    return torch.nn.functional.pad(values, (0, 1)).amax(1)


def turn_image(image, turn: int):
    """A (C, H, W) image turned by ``turn`` quarter turns counter-clockwise: ``torch.rot90(image,
    turn, dims=(1, 2))`` written as a transpose and flips, which ONNX has (rot90 it has not)."""
    if turn == 1:
        return image.transpose(1, 2).flip(1)
    if turn == 2:
        return image.flip((1, 2))
    if turn == 3:
        return image.transpose(1, 2).flip(2)
    return image


def unturn_boxes(boxes, turn: int, height, width):
    """xyxy boxes found on an image turned by ``turn`` quarter turns counter-clockwise
    (``turn_image``), in the pixels of the image as it was
    (``height`` x ``width``): exact, a turned box is a box."""
    import torch

    x1, y1, x2, y2 = boxes.unbind(-1)
    if turn == 1:
        return torch.stack([width - y2, x1, width - y1, x2], -1)
    if turn == 2:
        return torch.stack([width - x2, height - y2, width - x1, height - y1], -1)
    if turn == 3:
        return torch.stack([y1, height - x2, y2, height - x1], -1)
    return boxes
