"""Test-time views of a detector and the merge of their detections.

``detect_at_views`` runs an R-CNN's eval forward at each size and quarter turn and maps the boxes
back (``view_runs``, ``turn_image``, ``unturn_boxes``; ``ensemble_detect``: several R-CNNs on one
trunk); ``merge_detections`` merges several runs (views, or the
members of an ensemble) into one image's detections, scored by the views' vote where the model
has one (``VOTE_FLOOR``).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from torch import nn


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
    (runs,) = view_runs([model], lambda batch: [detect(batch)], images, sizes, turns)
    heads = model.roi_heads
    vote = getattr(model, "view_vote", None)
    return [merge_detections(outputs, heads.nms_thresh, heads.detections_per_img, vote) for outputs in zip(*runs)]


def view_runs(
    models: Sequence[nn.Module],
    detect: Callable[[list], list[list[dict]]],
    images: list,
    sizes: Sequence[int],
    turns: Sequence[int],
) -> list[list[list[dict]]]:
    """Each of ``models``' detections on each view of the images (``detect_at_views``), unmerged:
    ``[model][view][image]``, the views turn by turn, each turn size by size, boxes in the images'
    own pixels. ``detect(batch)`` gives every model's one-size eval forward on a batch, a list per
    model (an ensemble's members share work there: ``ensemble_detect``); their transforms are
    set to each size in turn, and restored after.

    The turns that give images of one shape (0 and 2, 1 and 3) run as one batch: the batch is
    padded to its largest image, which such a pair leaves as it is, so each view's detections are
    the ones it gives alone, for half the forward calls (each call's fixed cost is large against
    small views' work on a CPU).
    """
    transforms = [model.transform for model in models]
    saved = [(transform.min_size, transform.max_size) for transform in transforms]
    turns, sizes = tuple(turns) or (0,), tuple(sizes) or (None,)
    found: dict[tuple[int, int, int | None], list[dict]] = {}
    count = len(images)
    try:
        for size in sizes:
            if size is not None:
                for transform in transforms:
                    transform.min_size, transform.max_size = (int(size),), int(size)
            for group in (tuple(t for t in turns if t % 2 == 0), tuple(t for t in turns if t % 2 == 1)):
                if not group:
                    continue
                batch = [turn_image(image, turn) if turn else image for turn in group for image in images]
                for index, outputs in enumerate(detect(batch)):
                    for place, turn in enumerate(group):
                        part = outputs[place * count : (place + 1) * count]
                        if turn:
                            part = [
                                {
                                    **output,
                                    "boxes": unturn_boxes(output["boxes"], turn, image.shape[-2], image.shape[-1]),
                                }
                                for output, image in zip(part, images)
                            ]
                        found[index, turn, size] = part
    finally:
        for transform, (min_size, max_size) in zip(transforms, saved):
            transform.min_size, transform.max_size = min_size, max_size
    return [[found[index, turn, size] for turn in turns for size in sizes] for index in range(len(models))]


def ensemble_detect(models: Sequence[nn.Module]) -> Callable[[list], list[list[dict]]]:
    """``view_runs``' ``detect`` for torchvision R-CNNs (an ensemble's members): each model's
    eval forward on a batch. Where the models' input transforms and backbone trunks are the same
    (``shares_trunk``: members trained on one frozen pretrained trunk), the batch is resized and
    the trunk run once, and each model runs its own feature pyramid, RPN and box head on those
    features: the same detections as each forward alone, for one trunk pass instead of one per model.
    """
    from collections import OrderedDict

    import torch
    from torchvision.models.detection.generalized_rcnn import GeneralizedRCNN

    if not shares_trunk(models):
        return lambda batch: [GeneralizedRCNN.forward(model, batch) for model in models]

    def detect(batch: list) -> list[list[dict]]:
        # GeneralizedRCNN.forward in eval, with the transform and the trunk done once.
        original_sizes = [(image.shape[-2], image.shape[-1]) for image in batch]
        resized, _ = models[0].transform(batch)
        trunk = models[0].backbone.body(resized.tensors)
        outputs = []
        for model in models:
            features = model.backbone.fpn(trunk)
            if isinstance(features, torch.Tensor):
                features = OrderedDict([("0", features)])
            proposals, _ = model.rpn(resized, features)
            detections, _ = model.roi_heads(features, proposals, resized.image_sizes)
            outputs.append(model.transform.postprocess(detections, resized.image_sizes, original_sizes))
        return outputs

    return detect


def shares_trunk(models: Sequence[nn.Module]) -> bool:
    """Whether torchvision R-CNNs (backbone ``body`` then ``fpn``) resize and normalise their
    input alike and have one backbone trunk: of one type, with equal parameters and buffers.
    One model: False (nothing to share)."""
    import torch

    if len(models) < 2:
        return False
    first = models[0]
    if not all(hasattr(model.backbone, "body") and hasattr(model.backbone, "fpn") for model in models):
        return False
    settings = ("image_mean", "image_std", "size_divisible", "fixed_size", "min_size", "max_size", "_skip_resize")
    state = first.backbone.body.state_dict()
    for model in models[1:]:
        if type(model.transform) is not type(first.transform) or type(model.backbone.body) is not type(
            first.backbone.body
        ):
            return False
        if any(getattr(model.transform, name, None) != getattr(first.transform, name, None) for name in settings):
            return False
        other = model.backbone.body.state_dict()
        if other.keys() != state.keys():
            return False
        if not all(
            other[key].shape == value.shape and other[key].dtype == value.dtype and torch.equal(other[key], value)
            for key, value in state.items()
        ):
            return False
    return True


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
