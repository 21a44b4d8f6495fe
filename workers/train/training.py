"""``train_detector(S_tr, ω_in, t)``: t SGD iterations on rendered samples, ω written to disk.

A short loop in the spirit of torchvision's ``references/detection``: SGD with momentum, a
linear warm-up, then a constant or cosine learning rate; batches drawn with replacement from
S_tr (iterations ≫ images); images read once per call. Seeded: the same seed, samples,
ω_in and config give the same weights on the CPU.

A non-finite loss or gradient never reaches the weights: the step is skipped and recorded
({step, reason, loss terms, lr}), the learning rate halves for the rest of the call, and after
``config.max_nonfinite_steps`` such steps ``TrainingDiverged`` stops the run.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor, nn

from foldwise.config import DetectorConfig
from workers.train.augment import augmented, build_augmentation
from workers.train.checkpoint import (
    NoRoomError,
    check_compatible,
    load_state,
    payload_textures,
    read_checkpoint,
    resolve_device,
    save_checkpoint,
    torch_threads,
)
from workers.train.data import Sample, read_image_rgb, validate_box

# Warm-up starts at this fraction of the learning rate (torchvision's references use 0.001).
WARMUP_START_FACTOR = 0.001
# final_loss averages the last few finite step losses (one step alone is noisy).
FINAL_LOSS_WINDOW = 10


class TrainingDiverged(RuntimeError):
    """Too many non-finite losses or gradients in one train_detector call."""


@dataclass
class TrainStats:
    iterations: int
    seconds: float
    images_seen: int
    final_loss: float
    nonfinite_steps: list[dict]
    device: str
    losses: list[float] = field(default_factory=list)  # per step, nan where the step was skipped

    def to_dict(self) -> dict[str, Any]:
        """JSON-able (non-finite numbers become None, which JSON and SQL JSON columns accept)."""

        def clean(value: Any) -> Any:
            if isinstance(value, float) and not math.isfinite(value):
                return None
            if isinstance(value, dict):
                return {key: clean(item) for key, item in value.items()}
            if isinstance(value, list):
                return [clean(item) for item in value]
            return value

        return clean(asdict(self))


def sample_batches(n_images: int, iterations: int, batch_size: int, seed: int) -> np.ndarray:
    """(iterations, batch_size) image indices, drawn uniformly with replacement, seeded."""
    rng = np.random.default_rng(np.random.SeedSequence([seed, 0x5EED]))
    return rng.integers(0, n_images, size=(iterations, batch_size))


def learning_rate_at(step: int, iterations: int, config: DetectorConfig) -> float:
    """Learning rate of ``step`` (0-based) of a call with ``iterations`` steps."""
    base = config.learning_rate
    warmup = min(config.warmup_iterations, max(iterations - 1, 0))
    if step < warmup:
        fraction = step / warmup
        return base * (WARMUP_START_FACTOR + (1 - WARMUP_START_FACTOR) * fraction)
    if config.lr_schedule == "constant":
        return base
    span = max(iterations - warmup - 1, 1)
    progress = min((step - warmup) / span, 1.0)
    floor = config.min_lr_fraction
    return base * (floor + (1 - floor) * 0.5 * (1 + math.cos(math.pi * progress)))


def image_tensor(image: np.ndarray, device: torch.device) -> Tensor:
    """(H, W, 3) uint8 RGB to a (3, H, W) float tensor in 0..1."""
    return torch.from_numpy(image).to(device).permute(2, 0, 1).float().div_(255)


def sample_target(sample: Sample, device: torch.device) -> dict[str, Tensor]:
    """torchvision target of a sample: boxes xyxy float32, labels 1-based (0 is background)."""
    return {
        "boxes": torch.as_tensor(sample.boxes, dtype=torch.float32, device=device).reshape(-1, 4),
        "labels": torch.as_tensor(sample.labels, dtype=torch.int64, device=device) + 1,
    }


def compute_losses(model: nn.Module, images: list[Tensor], targets: list[dict[str, Tensor]]) -> dict[str, Tensor]:
    """The model's named loss terms on one batch (model in training mode)."""
    return model(images, targets)


def _validate(samples: Sequence[Sample], iterations: int, classes: Sequence[str], config: DetectorConfig) -> None:
    if iterations < 0:
        raise ValueError(f"iterations must be >= 0, got {iterations}")
    if not classes:
        raise ValueError("classes is empty: a detector needs at least one class")
    if len(set(classes)) != len(classes):
        raise ValueError(f"classes has duplicates: {list(classes)}")
    if iterations > 0 and not samples:
        raise ValueError("no training samples: S_tr is empty")
    for sample in samples:
        if len(sample.labels) and (sample.labels.min() < 0 or sample.labels.max() >= len(classes)):
            raise ValueError(
                f"{sample.image_path}: labels {sample.labels.tolist()} outside 0..{len(classes) - 1} ({len(classes)} classes)"
            )
        if len(sample.boxes):
            widths = sample.boxes[:, 2:] - sample.boxes[:, :2]
            if not np.all(np.isfinite(sample.boxes)) or np.any(widths <= 0):
                raise ValueError(f"{sample.image_path}: degenerate or non-finite box in {sample.boxes.tolist()}")


def _initial_model(
    samples: Sequence[Sample],
    images: list[np.ndarray],
    init: str | Path | None,
    config: DetectorConfig,
    classes: Sequence[str],
    seed: int,
) -> tuple[nn.Module, int, str | None, dict[str, np.ndarray] | None, dict[str, np.ndarray] | None]:
    """(model, iterations already trained, parent path, ω_in's textures, ω_in's lookalikes) for a
    fresh or warm start."""
    from workers.train.detectors import build_detector

    boxes = [sample.boxes for sample in samples]
    sizes = [np.tile(image.shape[:2], (len(sample.boxes), 1)) for sample, image in zip(samples, images)]
    train_boxes = np.concatenate(boxes).reshape(-1, 4) if boxes else np.zeros((0, 4), np.float32)
    train_sizes = np.concatenate(sizes).reshape(-1, 2) if sizes else np.zeros((0, 2), np.int64)
    if len(train_boxes) == 0:
        train_boxes, train_sizes = None, None

    torch.manual_seed(seed)
    if init is None:
        model = build_detector(config, len(classes), train_boxes, train_image_sizes=train_sizes)
        return model, 0, None, None, None
    payload = read_checkpoint(init)
    meta = payload["meta"]
    check_compatible(meta, config, classes, init)
    # ω_in's state replaces the initial weights (no ImageNet file needed).
    model = build_detector(config, len(classes), train_boxes, train_image_sizes=train_sizes, load_pretrained=False)
    load_state(model, payload["state_dict"], init)
    return (
        model,
        int(meta.get("iterations", 0)),
        str(init),
        payload_textures(payload),
        payload_textures(payload, "lookalikes"),
    )


def train_detector(
    samples: list[Sample],
    init: str | Path | None,
    iterations: int,
    config: DetectorConfig,
    classes: list[str],
    out: str | Path,
    seed: int = 0,
    on_step: Callable[[int], None] | None = None,
    textures: Mapping[str, np.ndarray] | None = None,
    on_no_room: Callable[[NoRoomError], None] | None = None,
    lookalikes: Mapping[str, np.ndarray] | None = None,
) -> TrainStats:
    """Train ``iterations`` steps from ω_in (``init``; None: fresh weights per
    ``config.pretrained``) on ``samples`` and write the checkpoint ω to ``out``.

    ``init`` may equal ``out`` (ω_in is read before ω is written). ``on_step(steps_done)`` is
    called after every step (progress display). With ``config.texture_check`` the checkpoint
    carries the classes' ``textures`` and the ``lookalikes`` (each None: ω_in's, where it has them)
    its texture check must not confirm (``assets.lookalikes``). When the volume has no
    room for ω (:class:`NoRoomError`; the file at ``out`` is then as it was), ``on_no_room(error)``
    is called: it returns to have the write tried again (having waited for room), or raises to
    give up; without it the error is raised, and the trained weights are lost.
    """
    _validate(samples, iterations, classes, config)
    with torch_threads(config.num_threads):
        return _train(
            samples, init, iterations, config, list(classes), Path(out), seed, on_step, textures, on_no_room, lookalikes
        )


def _train(
    samples: list[Sample],
    init: str | Path | None,
    iterations: int,
    config: DetectorConfig,
    classes: list[str],
    out: Path,
    seed: int,
    on_step: Callable[[int], None] | None = None,
    textures: Mapping[str, np.ndarray] | None = None,
    on_no_room: Callable[[NoRoomError], None] | None = None,
    lookalikes: Mapping[str, np.ndarray] | None = None,
) -> TrainStats:
    started = time.perf_counter()
    device = resolve_device(config.device)
    images = [read_image_rgb(sample.image_path) for sample in samples]  # once per call
    for sample, image in zip(samples, images):
        for box in sample.boxes:
            validate_box(box, image.shape[1], image.shape[0], str(sample.image_path))
    model, prior_iterations, parent, init_textures, init_lookalikes = _initial_model(
        samples, images, init, config, classes, seed
    )
    if config.texture_check:
        # What the parent's check knew is inherited where the caller gives nothing new.
        textures = init_textures if textures is None else textures
        lookalikes = init_lookalikes if lookalikes is None else lookalikes
        missing = [name for name in classes if not textures or name not in textures]
        if missing:
            raise ValueError(
                f"detector.texture_check needs each class's texture; none for {missing}: give them "
                "(the experiment's asset catalog), start from a checkpoint that carries them, or turn the check off"
            )
    model.to(device).train()

    cache = getattr(model, "proposal_cache", None)
    if cache is not None:
        # Fast R-CNN: proposals once per image, from (or into) the file beside it.
        for sample, image in zip(samples, images):
            cache.proposals(image, sample.image_path)

    parameters = [p for p in model.parameters() if p.requires_grad]
    optimizer = torch.optim.SGD(
        parameters, lr=config.learning_rate, momentum=config.momentum, weight_decay=config.weight_decay
    )
    targets = [sample_target(sample, device) for sample in samples]
    transform = build_augmentation(config.augmentation, (config.input_size, config.input_size))
    batches = sample_batches(len(samples), iterations, config.batch_size, seed) if iterations else np.zeros((0, 0), int)

    # The sampling inside the model (RPN and RoI minibatches) draws from torch's generator:
    # reseed it here so step 0 depends only on (seed, batch, weights), not on how ω was built.
    torch.manual_seed(seed)
    if device.type == "cuda":
        torch.cuda.manual_seed_all(seed)

    losses: list[float] = []
    nonfinite: list[dict] = []
    lr_scale = 1.0
    clip = config.grad_clip_norm if config.grad_clip_norm > 0 else float("inf")
    for step in range(iterations):
        if on_step is not None and step:
            on_step(step)
        lr = learning_rate_at(step, iterations, config) * lr_scale
        for group in optimizer.param_groups:
            group["lr"] = lr
        batch = batches[step]
        buffers_before = [buffer.detach().clone() for buffer in model.buffers()]
        if transform is None:
            batch_images, batch_targets = [image_tensor(images[i], device) for i in batch], [targets[i] for i in batch]
        else:
            pairs = [augmented(transform, images[i], samples[i].boxes, samples[i].labels, device) for i in batch]
            batch_images, batch_targets = [p[0] for p in pairs], [p[1] for p in pairs]
        loss_terms = compute_losses(model, batch_images, batch_targets)
        loss = sum(loss_terms.values())
        reason = None
        if not torch.isfinite(loss):
            reason = "non-finite loss"
        else:
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            grad_norm = torch.nn.utils.clip_grad_norm_(parameters, clip)
            if not torch.isfinite(grad_norm):
                reason = "non-finite gradient"
        if reason is not None:
            optimizer.zero_grad(set_to_none=True)
            # A non-finite forward pass may also have polluted BatchNorm running statistics.
            with torch.no_grad():
                for buffer, saved in zip(model.buffers(), buffers_before):
                    buffer.copy_(saved)
            nonfinite.append(
                {
                    "step": step,
                    "reason": reason,
                    "loss_terms": {k: float(v.detach()) for k, v in loss_terms.items()},
                    "lr": lr,
                }
            )
            losses.append(float("nan"))
            lr_scale *= 0.5
            if len(nonfinite) > config.max_nonfinite_steps:
                raise TrainingDiverged(
                    f"training diverged: {len(nonfinite)} non-finite steps in {step + 1} iterations "
                    f"(detector.max_nonfinite_steps = {config.max_nonfinite_steps}); last at step {step}: "
                    f"{reason}, loss terms {nonfinite[-1]['loss_terms']}, learning rate {lr:.3g}. "
                    f"Lower detector.learning_rate (now {config.learning_rate:g}) or check the training images."
                )
            continue
        optimizer.step()
        losses.append(float(loss.detach()))

    if on_step is not None and iterations:
        on_step(iterations)
    finite = [value for value in losses if math.isfinite(value)]
    final_loss = float(np.mean(finite[-FINAL_LOSS_WINDOW:])) if finite else float("nan")
    meta = {
        "family": config.family,
        "backbone": config.backbone,
        "classes": classes,
        "input_size": config.input_size,
        "iterations": prior_iterations + iterations,
        "config": config.model_dump(mode="json"),
        "parent": parent,
        "seed": seed,
        "train_images": len(samples),
        "torch": str(torch.__version__),
    }
    if config.calibration == "shipped":  # recorded, so the checkpoint keeps its meaning if the shipped file changes
        from workers.train.calibration import shipped_calibration

        meta["calibration"] = shipped_calibration().to_dict()
    model.eval()
    kept = {name: np.asarray(textures[name]) for name in classes} if config.texture_check and textures else None
    while True:
        try:
            save_checkpoint(model, meta, out, textures=kept, lookalikes=lookalikes if kept else None)
            break
        except NoRoomError as error:
            if on_no_room is None:
                raise
            on_no_room(error)  # waits for room, or raises to give up
    return TrainStats(
        iterations=iterations,
        seconds=time.perf_counter() - started,
        images_seen=iterations * config.batch_size,
        final_loss=final_loss,
        nonfinite_steps=nonfinite,
        device=str(device),
        losses=losses,
    )
