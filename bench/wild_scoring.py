"""Scoring a detector on a COCO folder as bench/wild.py reports it.

``score``: a checkpoint (or several, as one ensemble) at the paper's protocol and unthresholded,
class-agnostic, per class and per scene kind, with precision and recall at the threshold
(``_scores`` builds that report from any detector's predictions); ``score_keypoint_baseline``:
the keypoint recipe (bench/keypoint_baseline.py) scored the same way, side by side with foldwise.
"""

from __future__ import annotations

import time
from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np


def class_agnostic(predictions: list[dict], ground_truth: list[dict]) -> tuple[list[dict], list[dict]]:
    """The same detections and boxes with every class merged into one ("the object"): a box of
    any class at a target counts, and boxes of several classes at one place are suppressed to
    the best (IoU 0.5) so that they are not counted as false positives of each other. Scored
    beside the class-aware mAP, it splits "does not find the sheet" from "names it wrong"."""
    import torch
    from torchvision.ops import nms

    merged = []
    for prediction in predictions:
        boxes, scores = torch.as_tensor(prediction["boxes"]), torch.as_tensor(prediction["scores"])
        keep = nms(boxes, scores, 0.5).numpy() if len(boxes) else np.zeros(0, np.int64)
        merged.append(
            {
                "boxes": prediction["boxes"][keep],
                "scores": prediction["scores"][keep],
                "labels": np.zeros(len(keep), np.int64),
            }
        )
    truth = [{"boxes": item["boxes"], "labels": np.zeros(len(item["labels"]), np.int64)} for item in ground_truth]
    return merged, truth


def _at_threshold(predictions, truth, classes, score_threshold: float, iou_threshold: float) -> dict:
    """What a user who draws every box scoring at least ``score_threshold`` sees
    (``precision_recall_at``, the mAP's matching): precision, recall, and the counts."""
    from workers.train.evaluation import precision_recall_at

    result = precision_recall_at(predictions, truth, classes, score_threshold, iou_threshold)
    drawn = result.true_positives + result.false_positives
    targets = result.true_positives + result.false_negatives
    report = {
        "precision": result.precision if drawn else None,
        "recall": result.recall if targets else None,
        "drawn": drawn,
        "true": result.true_positives,
        "targets": targets,
    }
    if predictions and all("confirmed" in found for found in predictions):
        # Of those, the boxes the texture confirmed (the rest stand on the network's word alone):
        # where the false ones come from.
        confirmed = [
            {key: found[key][found["confirmed"]] for key in ("boxes", "scores", "labels")} for found in predictions
        ]
        alone = precision_recall_at(confirmed, truth, classes, score_threshold, iou_threshold)
        report["confirmed"] = {"drawn": alone.true_positives + alone.false_positives, "true": alone.true_positives}
    return report


def _scores(
    predictions,
    truth,
    model_classes,
    groups,
    score_threshold: float,
    iou_threshold: float,
    seconds: float,
    parts: Mapping[str, Sequence[int]] | None = None,
) -> dict:
    """One detector's report on one set: the paper's mAP (and unthresholded), class-agnostic mAP,
    per class and per scene kind, what a user drawing boxes at the threshold sees, and time.
    ``parts``: named lists of image indices, each also scored alone (its mAP and what is drawn at
    the threshold), e.g. the half of a set a setting was chosen on and the half held out."""
    from workers.train.evaluation import evaluate_predictions

    protocol = {"score_threshold": score_threshold, "iou_threshold": iou_threshold, "coco": False}
    payload = evaluate_predictions(predictions, truth, model_classes, groups=groups, **protocol).to_dict()
    agnostic = evaluate_predictions(*class_agnostic(predictions, truth), ["object"], **protocol).to_dict()
    by_kind = {
        name: {
            "map": group.get("map"),
            "map_unthresholded": group.get("map_unthresholded"),
            "images": group.get("num_images"),
        }
        for name, group in payload.get("breakdown", {}).get("difficulty", {}).items()
    }
    scored_parts = {}
    for name, indices in (parts or {}).items():
        part_predictions, part_truth = [predictions[i] for i in indices], [truth[i] for i in indices]
        part = evaluate_predictions(part_predictions, part_truth, model_classes, **protocol).to_dict()
        scored_parts[name] = {
            "images": len(indices),
            "map": part["map"],
            "at_threshold": _at_threshold(part_predictions, part_truth, model_classes, score_threshold, iou_threshold),
        }
    return {
        **({"parts": scored_parts} if parts else {}),
        "images": len(truth),
        "map": payload["map"],
        "map_unthresholded": payload["map_unthresholded"],
        "at_threshold": _at_threshold(predictions, truth, model_classes, score_threshold, iou_threshold),
        "class_agnostic": {"map": agnostic["map"], "map_unthresholded": agnostic["map_unthresholded"]},
        "per_class": {name: entry.get("ap") for name, entry in payload["per_class"].items()},
        "by_kind": by_kind,
        "seconds": seconds,
        "seconds_per_image": seconds / max(len(truth), 1),
    }


def score_keypoint_baseline(
    textures: dict, data: Path, score_threshold: float, iou_threshold: float, parts=None
) -> dict:
    """The keypoint recipe (bench/keypoint_baseline.py) on a COCO folder, scored as ``score`` scores
    foldwise (``parts``: as ``_scores`` takes them)."""
    from bench.keypoint_baseline import KeypointBaseline
    from workers.train.data import load_coco_dataset, read_image_rgb

    samples, classes = load_coco_dataset(data)
    baseline = KeypointBaseline(textures, classes)
    started = time.perf_counter()
    predictions = [baseline.detect(read_image_rgb(sample.image_path)) for sample in samples]
    seconds = time.perf_counter() - started
    truth = [{"boxes": sample.boxes, "labels": np.asarray(sample.labels, np.int64)} for sample in samples]
    groups = [{"condition": sample.condition, "difficulty": sample.difficulty} for sample in samples]
    return _scores(predictions, truth, classes, groups, score_threshold, iou_threshold, seconds, parts)


def score(
    checkpoint, data: Path, score_threshold: float, iou_threshold: float, test_sizes=None, test_turns=None
) -> dict:
    """The detector's scores on a COCO folder. ``checkpoint``: one path, or a list of paths whose
    detectors are scored as one (``workers.train.checkpoint.detect_ensemble``)."""
    from workers.train.checkpoint import load_detector
    from workers.train.data import load_coco_dataset
    from workers.train.evaluation import detector_predictions

    samples, classes = load_coco_dataset(data)
    checkpoints = [checkpoint] if isinstance(checkpoint, (str, Path)) else list(checkpoint)
    detectors = [load_detector(path, device="cpu") for path in checkpoints]
    started = time.perf_counter()
    predictions, truth, groups, model_classes = detector_predictions(
        detectors, samples, classes, test_sizes=test_sizes, test_turns=test_turns
    )
    return _scores(
        predictions, truth, model_classes, groups, score_threshold, iou_threshold, time.perf_counter() - started
    )
