"""ImageNet weights in the local torch hub cache, checked before any work (never downloaded).

``detector.pretrained: imagenet`` makes the detector start from torchvision's ImageNet
classifier. foldwise never downloads: the file must already be in the torch hub cache, and a
run that lacks it must say so before it renders a single image, not at its first training
step. This module knows the files without importing torch (the CLI checks a config in
milliseconds); a test pins the table to torchvision's own weight enums.

It also knows which backbone names each detector family builds on, so that a config naming
one it cannot build is refused at once (foldwise.config), not at the first training step.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

# torchvision classifier -> (weights enum entry, file name of its ImageNet weights).
IMAGENET_WEIGHTS = {
    "mobilenet_v3_large": ("MobileNet_V3_Large_Weights.IMAGENET1K_V1", "mobilenet_v3_large-8738ca79.pth"),
    "mobilenet_v3_small": ("MobileNet_V3_Small_Weights.IMAGENET1K_V1", "mobilenet_v3_small-047dcff4.pth"),
    "resnet18": ("ResNet18_Weights.IMAGENET1K_V1", "resnet18-f37072fd.pth"),
    "resnet34": ("ResNet34_Weights.IMAGENET1K_V1", "resnet34-b627a593.pth"),
    "resnet50": ("ResNet50_Weights.IMAGENET1K_V1", "resnet50-0676ba61.pth"),
    "resnet101": ("ResNet101_Weights.IMAGENET1K_V1", "resnet101-63fe2227.pth"),
}


# Backbone names accepted by the two R-CNN families, mapped to the torchvision classifier
# they start from. The "_320" variant differs in torchvision only by its input size, which
# here comes from ``config.input_size``, so it shares the mobilenet backbone.
RCNN_BACKBONES = {
    "mobilenet_v3_large_fpn": "mobilenet_v3_large",
    "mobilenet_v3_large_320_fpn": "mobilenet_v3_large",
    "resnet50_fpn_v2": "resnet50",
    # TensorFlow-slim's MobileNetV3-Large x0.75 (workers/train/detectors/mobilenet_v3_tf.py):
    # the backbone whose COCO weights ship with foldwise (``pretrained: coco``).
    "mobilenet_v3_large_075_fpn": "mobilenet_v3_large_075",
}
# R-CNN backbones whose COCO weights ship with foldwise (``pretrained: coco``); the others start
# from torchvision's ImageNet classifiers (``pretrained: imagenet``, from the torch hub cache).
COCO_BACKBONES = ("mobilenet_v3_large_075_fpn",)
# yolo builds on any classifier of IMAGENET_WEIGHTS; detection-style names
# ("mobilenet_v3_large_fpn", "mobilenet_v3_large_320_fpn", "resnet50_fpn_v2") name the same one.
YOLO_BACKBONE_NAME = re.compile(r"^(?P<base>[a-z0-9_]+?)(?:_320)?(?:_fpn)?(?:_v[12])?$")


def backbone_problem(family: str, backbone: str) -> str | None:
    """Why the ``family`` detector cannot be built on ``backbone`` (None when it can)."""
    if family == "yolo":
        match = YOLO_BACKBONE_NAME.match(backbone.strip().lower())
        if match and match.group("base") in IMAGENET_WEIGHTS:
            return None
        return (
            f"detector.backbone {backbone!r} is not supported by the yolo detector; known: "
            f"{', '.join(sorted(IMAGENET_WEIGHTS))} (optionally with a detection suffix such as _fpn, _320_fpn or _fpn_v2)"
        )
    if backbone in RCNN_BACKBONES:
        return None
    return (
        f"detector.backbone {backbone!r} is not supported by the {family} detector; known: {', '.join(RCNN_BACKBONES)}"
    )


def pretrained_problem(family: str, backbone: str, pretrained: str) -> str | None:
    """Why ``backbone`` cannot start from ``pretrained`` weights (None when it can)."""
    if pretrained == "none":
        return None
    if family == "yolo":
        if pretrained == "imagenet":
            return None
        return f"detector.pretrained {pretrained!r}: the yolo detector starts from ImageNet weights or none"
    source = "coco" if backbone in COCO_BACKBONES else "imagenet"
    if pretrained == source:
        return None
    return f"detector.pretrained {pretrained!r}: backbone {backbone!r} has {source!r} (or 'none')"


def torch_hub_dir() -> Path:
    """``torch.hub.get_dir()`` without importing torch: $TORCH_HOME/hub, else $XDG_CACHE_HOME/torch/hub."""
    if os.environ.get("TORCH_HOME"):
        return Path(os.environ["TORCH_HOME"]).expanduser() / "hub"
    cache = os.environ.get("XDG_CACHE_HOME") or str(Path("~/.cache").expanduser())
    return Path(cache).expanduser() / "torch" / "hub"


def classifier_of(backbone: str) -> str | None:
    """The torchvision classifier a detector backbone starts from (the longest known prefix)."""
    matches = [name for name in IMAGENET_WEIGHTS if backbone.strip().lower().startswith(name)]
    return max(matches, key=len) if matches else None


def missing_imagenet_weights(backbone: str) -> str | None:
    """Why ``pretrained: imagenet`` cannot start on this machine, or None when the file is in place."""
    classifier = classifier_of(backbone)
    if classifier is None:
        return None  # an unknown backbone is the detector builder's error to report
    enum_entry, filename = IMAGENET_WEIGHTS[classifier]
    path = torch_hub_dir() / "checkpoints" / filename
    if path.is_file():
        return None
    fetch = f"import torchvision; torchvision.models.get_weight('{enum_entry}').get_state_dict(progress=True)"
    return (
        f"detector.pretrained: 'imagenet' needs {path} (the ImageNet weights of {classifier}, for backbone "
        f"{backbone!r}) and it is not there; foldwise never downloads. On a machine with a network run "
        f'python -c "{fetch}" and copy the file to that path (or set TORCH_HOME), or set detector.pretrained: none'
    )
