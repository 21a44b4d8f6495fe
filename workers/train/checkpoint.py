"""Self-describing detector checkpoints ω, and ``detect_object`` (inference; ``detect_ensemble``
for several checkpoints detecting as one).

A checkpoint is one ``torch.save`` file holding plain data only (loadable with
``weights_only=True``)::

    {"format": "foldwise-detector", "format_version": 1,
     "meta": {"family", "backbone", "classes", "input_size", "iterations" (cumulative),
              "config" (the DetectorConfig), "buffers" (e.g. yolo anchors, as lists), ...},
     "state_dict": {...}}

``load_detector(path)`` rebuilds the model from ``meta`` alone. Writes are atomic (a temp file
in the same folder, then rename), so a crash never leaves a half-written ω behind.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from foldwise.config import DetectorConfig

CHECKPOINT_FORMAT = "foldwise-detector"
CHECKPOINT_VERSION = 1
# DetectorConfig fields that change the network's shape or meaning: a warm start must agree.
ARCHITECTURE_FIELDS = ("family", "backbone")
RCNN_FAMILIES = ("faster_rcnn", "fast_rcnn")


class CheckpointError(ValueError):
    """A checkpoint that cannot be read, or that does not fit the requested detector."""


@dataclass
class Detector:
    """A trained detector ω: the model (eval mode) and its self-description."""

    model: nn.Module
    meta: dict[str, Any]
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))

    @property
    def classes(self) -> list[str]:
        return list(self.meta["classes"])

    @property
    def config(self) -> DetectorConfig:
        return DetectorConfig.model_validate(self.meta["config"])


def _named_buffers(model: nn.Module) -> dict[str, list]:
    """Buffers that are not BatchNorm running statistics (e.g. anchors), as JSON-able lists."""
    skip = ("running_mean", "running_var", "num_batches_tracked")
    return {
        name: buffer.detach().cpu().tolist()
        for name, buffer in model.named_buffers()
        if not name.endswith(skip) and buffer.numel() <= 4096
    }


def save_checkpoint(model: nn.Module, meta: dict[str, Any], path: str | Path) -> Path:
    """Write ``model`` and ``meta`` to ``path`` atomically; returns the path."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = dict(meta)
    meta.setdefault("buffers", _named_buffers(model))
    payload = {
        "format": CHECKPOINT_FORMAT,
        "format_version": CHECKPOINT_VERSION,
        "meta": meta,
        "state_dict": {name: tensor.detach().cpu() for name, tensor in model.state_dict().items()},
    }
    descriptor, temporary = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(descriptor, "wb") as handle:
            torch.save(payload, handle)
            handle.flush()
            os.fsync(handle.fileno())
        os.chmod(temporary, 0o644)  # mkstemp makes it private; other roles read checkpoints
        os.replace(temporary, path)
    except BaseException:
        if os.path.exists(temporary):
            os.unlink(temporary)
        raise
    return path


def read_checkpoint(path: str | Path) -> dict[str, Any]:
    """The raw checkpoint payload, checked for format and version."""
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"checkpoint {path} does not exist")
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # noqa: BLE001 (torch raises many types for a corrupt or foreign file)
        raise CheckpointError(f"checkpoint {path} cannot be read: {type(error).__name__}: {error}") from None
    if not isinstance(payload, dict) or payload.get("format") != CHECKPOINT_FORMAT:
        raise CheckpointError(f"{path} is not a foldwise detector checkpoint")
    version = payload.get("format_version")
    if version != CHECKPOINT_VERSION:
        raise CheckpointError(
            f"checkpoint {path} has format version {version}; this foldwise reads version {CHECKPOINT_VERSION}"
        )
    return payload


def check_compatible(meta: dict[str, Any], config: DetectorConfig, classes: Sequence[str], path: str | Path) -> None:
    """Raise CheckpointError when ω_in cannot initialise a detector of ``config`` for ``classes``."""
    problems = []
    for key in ARCHITECTURE_FIELDS:
        if meta.get(key) != getattr(config, key):
            problems.append(f"{key}: checkpoint has {meta.get(key)!r}, config asks for {getattr(config, key)!r}")
    built_with = meta.get("config", {}).get("pretrained")
    if config.family in RCNN_FAMILIES and built_with != config.pretrained:
        # ImageNet-initialised R-CNN backbones freeze BatchNorm; random ones train it: other layers.
        problems.append(f"pretrained: checkpoint was built with {built_with!r}, config asks for {config.pretrained!r}")
    if list(meta.get("classes", [])) != list(classes):
        problems.append(f"classes: checkpoint has {list(meta.get('classes', []))}, training set has {list(classes)}")
    if problems:
        raise CheckpointError(f"cannot warm-start from {path}: " + "; ".join(problems))


@contextmanager
def torch_threads(count: int) -> Iterator[None]:
    """Run with ``count`` torch intra-op threads (0: leave torch's choice), then restore.

    On a shared, oversubscribed CPU, more threads than free cores makes torch several times
    slower (its OpenMP workers spin), so the config's thread count matters in inference too.
    """
    previous = torch.get_num_threads()
    if count > 0:
        torch.set_num_threads(count)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def resolve_device(device: str | torch.device | None) -> torch.device:
    """``auto``/None: CUDA when available, else CPU; ``cuda`` without a GPU is an error."""
    if device is None or str(device) == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    device = torch.device(device)
    if device.type == "cuda" and not torch.cuda.is_available():
        raise RuntimeError("detector.device is 'cuda' but torch sees no CUDA device")
    return device


def model_from_meta(meta: dict[str, Any], config: DetectorConfig | None = None) -> nn.Module:
    """An untrained model with the architecture described by ``meta`` (or ``config``)."""
    from workers.train.detectors import build_detector

    config = config or DetectorConfig.model_validate(meta["config"])
    # The state dict brings the weights: no ImageNet file needed.
    return build_detector(config, len(meta["classes"]), load_pretrained=False)


def load_state(model: nn.Module, state_dict: dict[str, torch.Tensor], path: str | Path) -> None:
    try:
        model.load_state_dict(state_dict)
    except RuntimeError as error:
        raise CheckpointError(f"checkpoint {path} does not fit the detector it describes: {error}") from None


def load_detector(path: str | Path, device: str | torch.device | None = None) -> Detector:
    """Rebuild the detector stored at ``path`` from its metadata alone, in eval mode."""
    payload = read_checkpoint(path)
    meta = payload["meta"]
    model = model_from_meta(meta)
    load_state(model, payload["state_dict"], path)
    target = resolve_device(device)
    model.to(target).eval()
    return Detector(model=model, meta=meta, device=target)


def _image_array(image: np.ndarray | str | Path, index: int) -> tuple[np.ndarray, Path | None]:
    from workers.train.data import as_rgb_uint8, read_image_rgb

    if isinstance(image, (str, Path)):
        return read_image_rgb(image), Path(image)
    return as_rgb_uint8(image, where=f"images[{index}]"), None


@contextmanager
def _test_views(model: nn.Module, sizes: Sequence[int] | None, turns: Sequence[int] | None) -> Iterator[None]:
    """The model detects at ``sizes`` and ``turns`` inside the block (None: as built), as before after it."""
    overrides = {name: tuple(value) for name, value in (("test_sizes", sizes), ("test_turns", turns)) if value is not None}
    saved = {name: getattr(model, name) for name in overrides}
    try:
        for name, value in overrides.items():
            setattr(model, name, value)
        yield
    finally:
        for name, value in saved.items():
            setattr(model, name, value)


def detect_object(
    detector: Detector,
    images: Sequence[np.ndarray | str | Path],
    batch_size: int = 8,
    on_batch: Callable[[int], None] | None = None,
    test_sizes: Sequence[int] | None = None,
    test_turns: Sequence[int] | None = None,
) -> list[dict[str, np.ndarray]]:
    """Detections per image: ``boxes`` (n, 4) float32 xyxy in that image's pixels, ``scores``
    (n,) float32, ``labels`` (n,) int64 0-based class indices, best score first.

    Images are RGB uint8 arrays or paths (read with OpenCV); any size (the model resizes to
    its input size and maps boxes back). Runs with the detector config's ``num_threads``.
    ``on_batch(images_done)`` is called after every batch (progress display). ``test_sizes``
    overrides the detector config's input sizes to detect at (R-CNN families; ``()``: its
    input size alone), ``test_turns`` its quarter turns (``()``: the images as they are).
    """
    if batch_size < 1:
        raise ValueError(f"batch_size must be at least 1, got {batch_size}")
    if test_sizes is not None and detector.meta["family"] not in RCNN_FAMILIES:
        raise ValueError(f"test_sizes: only the R-CNN families detect at several sizes, not {detector.meta['family']}")
    if test_turns is not None and detector.meta["family"] not in RCNN_FAMILIES:
        raise ValueError(f"test_turns: only the R-CNN families detect on turned views, not {detector.meta['family']}")
    model = detector.model
    model.eval()
    results: list[dict[str, np.ndarray]] = []
    threads = int(detector.meta.get("config", {}).get("num_threads", 0))
    with torch.no_grad(), torch_threads(threads), _test_views(model, test_sizes, test_turns):
        for start in range(0, len(images), batch_size):
            arrays = [_image_array(image, start + i) for i, image in enumerate(images[start : start + batch_size])]
            cache = getattr(model, "proposal_cache", None)
            if cache is not None:
                # Fast R-CNN: fill the proposal cache from files beside the images when present.
                for array, path in arrays:
                    cache.proposals(array, path)
            tensors = [
                torch.from_numpy(array).to(detector.device).permute(2, 0, 1).float().div_(255) for array, _ in arrays
            ]
            for output in model(tensors):
                results.append(
                    {
                        "boxes": output["boxes"].detach().cpu().numpy().astype(np.float32).reshape(-1, 4),
                        "scores": output["scores"].detach().cpu().numpy().astype(np.float32),
                        "labels": output["labels"].detach().cpu().numpy().astype(np.int64) - 1,
                    }
                )
            if on_batch is not None:
                on_batch(len(results))
    return results


def detect_ensemble(
    detectors: Sequence[Detector],
    images: Sequence[np.ndarray | str | Path],
    on_batch: Callable[[int], None] | None = None,
    **options: Any,
) -> list[dict[str, np.ndarray]]:
    """Several detectors of one class list detecting as one (an ensemble, e.g. the final models of
    two runs with other seeds): each runs ``detect_object`` (with ``options``: batch_size,
    test_sizes, test_turns) at its views, and their detections
    merge per image as a detector's views do (per-class NMS at the first detector's IoU, its
    detection cap). One detector is ``detect_object`` itself. Two runs of ``quick.yaml`` (seeds 0
    and 1) merged scored 0.01-0.06 more on each out-of-domain set than either alone (bench/README.md,
    "... and seed ensembles")."""
    from workers.train.detectors import merge_detections

    if not detectors:
        raise ValueError("an ensemble needs at least one detector")
    first = detectors[0]
    for index, detector in enumerate(detectors[1:], start=2):
        if detector.classes != first.classes:
            raise ValueError(
                f"detector {index} has the classes {detector.classes}, detector 1 {first.classes}: "
                "an ensemble needs one class list, in one order"
            )

    def progress(member: int):  # images done across the members, 0..len(images) once
        if on_batch is None:
            return None
        return lambda done: on_batch((member * len(images) + done) // len(detectors))

    runs = [
        detect_object(detector, images, on_batch=progress(member), **options) for member, detector in enumerate(detectors)
    ]
    if len(runs) == 1:
        return runs[0]
    heads = getattr(first.model, "roi_heads", None)  # yolo has none: torchvision's NMS IoU, the config's cap
    iou, limit = (heads.nms_thresh, heads.detections_per_img) if heads is not None else (0.5, first.config.detections_per_image)
    return [merge_detections(outputs, iou, limit) for outputs in zip(*runs)]
