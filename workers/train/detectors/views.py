"""Test-time views of a detector and the merge of their detections.

``detect_at_views`` runs an R-CNN's eval forward at each size and quarter turn and maps the boxes
back (``turn_image``, ``unturn_boxes``); ``merge_detections`` merges several runs (views, or the
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
