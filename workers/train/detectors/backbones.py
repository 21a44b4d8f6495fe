"""The R-CNN families' backbones: a feature pyramid on a classifier, its pretrained weights
(ImageNet from the local torch hub cache, never downloaded; COCO for the TensorFlow MobileNet),
which stages train, the input normalisation, the pyramid levels RoI pooling reads and the anchor
sizes per level.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING
from urllib.parse import urlparse

import numpy as np

from foldwise.weights import RCNN_BACKBONES
from workers.train.detectors import DetectorBuildError

if TYPE_CHECKING:
    from torch import nn

    from foldwise.config import DetectorConfig

# The backbone names each family accepts are in foldwise/weights.py: the config checks them
# before any work, without torch; the builders check again (a config built without validation).


class PretrainedWeightsMissing(FileNotFoundError):
    """``pretrained: imagenet`` but the ImageNet weights are not in the local torch hub cache."""


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
