"""``evaluate_predictions``: the paper's detection score (PASCAL VOC mAP) and COCO's, side by side.

The paper's protocol (Sankar & Bartoli 2018, §5.1): IoU 0.5, detections below confidence 0.8
discarded, PASCAL VOC average precision per class, mean over classes. Per class:

1. pool the detections of every image and sort them by score, highest first, with a stable sort
   (tied scores keep input order: image order, then the order within an image);
2. match each detection to the ground-truth box of its image with the highest IoU, matched
   already or not (ties in IoU: the first box); IoU ≥ ``iou_threshold`` and that box not yet
   matched → true positive, already matched → false positive (a duplicate), else false positive;
3. AP = the area under the precision envelope (the running maximum of precision from the right),
   integrated at every recall step ("all-point" interpolation, VOC 2010 onwards).

mAP is the mean over the classes that have ground truth: a class without any ground-truth box
has no recall and is left out (its detections are false positives of nothing). With no ground
truth at all, mAP is undefined and reported as NaN (``None`` in JSON), never as 0 or 1.

Boxes are ``[x0, y0, x1, y1]`` in continuous pixel-edge coordinates, so a box's width is
``x1 - x0`` (no "+1" of the original VOC devkit). Zero-area boxes are valid and overlap nothing.

Because a detection's fate depends only on the higher-scored detections of its own image, the
matching is computed once: the thresholded score keeps a prefix of the sorted list, and a
breakdown group (condition, difficulty, ...) keeps the detections of its images in the same
order. ``.coco`` carries pycocotools' metrics on the same (unthresholded) inputs; they differ
from VOC AP50 by design (see ``coco_metrics``).
"""

from __future__ import annotations

import contextlib
import io
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

# Keys of pycocotools' 12 summary numbers, in ``COCOeval.stats`` order.
COCO_STAT_NAMES = ("AP", "AP50", "AP75", "APs", "APm", "APl", "AR1", "AR10", "AR100", "ARs", "ARm", "ARl")
# The key under which a breakdown pairs two group fields, e.g. "condition/difficulty": "fb/easy".
PAIR_SEPARATOR = "/"


@dataclass
class ClassResult:
    """The score of one class. ``ap`` is the paper's (thresholded) AP; NaN when no ground truth."""

    name: str
    ap: float
    ap_unthresholded: float
    num_ground_truth: int
    num_detections: int
    num_detections_kept: int  # score ≥ score_threshold
    true_positives: int  # among the kept detections
    false_positives: int  # among the kept detections
    recall: float  # of the kept detections; NaN when no ground truth
    precision: float  # of the kept detections; NaN when none kept


@dataclass
class GroupResult:
    """The score of the images of one breakdown group (e.g. condition "fb")."""

    map: float
    map_unthresholded: float
    num_images: int
    num_ground_truth: int
    per_class: dict[str, float]  # the paper's AP per class (NaN: no ground truth in this group)


@dataclass
class EvaluationResult:
    map: float  # the paper's protocol: detections below score_threshold dropped
    map_unthresholded: float  # usual VOC mAP over every detection
    per_class: dict[str, ClassResult]
    # breakdown[field][value], e.g. breakdown["condition"]["fb"], breakdown["difficulty"]["hard"],
    # breakdown["condition/difficulty"]["fb/hard"] (the pair exists when groups carry both fields).
    breakdown: dict[str, dict[str, GroupResult]]
    coco: dict[str, Any]  # pycocotools summary (COCO_STAT_NAMES) + per-class AP/AP50; {} if skipped
    score_threshold: float
    iou_threshold: float
    num_images: int
    num_ground_truth: int
    num_detections: int
    classes: list[str] = field(default_factory=list)

    def to_dict(self) -> dict[str, Any]:
        """A JSON-able dict; NaN (undefined: no ground truth) becomes None."""
        return json_safe(asdict(self))


def json_safe(value: Any) -> Any:
    """Dicts, lists and numbers made JSON-able: NaN and infinities become None, numpy scalars Python's."""
    if isinstance(value, dict):
        return {str(key): json_safe(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [json_safe(item) for item in value]
    if isinstance(value, (float, np.floating)):
        return None if not math.isfinite(float(value)) else float(value)
    if isinstance(value, np.integer):
        return int(value)
    return value


# --------------------------------------------------------------------------- input checking


@dataclass
class _Flat:
    """All images' boxes concatenated, with the image index of each row."""

    boxes: np.ndarray  # (n, 4) float64
    labels: np.ndarray  # (n,) int64
    image: np.ndarray  # (n,) int64
    scores: np.ndarray | None = None  # (n,) float64 for predictions


def _as_array(value: Any, what: str) -> np.ndarray:
    if hasattr(value, "detach"):  # a torch tensor: move to host without importing torch here
        value = value.detach().cpu().numpy()
    try:
        return np.asarray(value)
    except (TypeError, ValueError) as error:
        raise ValueError(f"{what}: not an array ({error})") from None


def _check_image(item: Any, index: int, kind: str, num_classes: int, with_scores: bool) -> tuple[np.ndarray, ...]:
    where = f"{kind}[{index}]"
    if not isinstance(item, Mapping):
        raise ValueError(f"{where}: expected a dict with boxes and labels, got {type(item).__name__}")
    for key in ("boxes", "labels") + (("scores",) if with_scores else ()):
        if key not in item:
            raise ValueError(f"{where}: missing {key!r}")
    boxes = _as_array(item["boxes"], f"{where}.boxes")
    labels = _as_array(item["labels"], f"{where}.labels")
    if boxes.size == 0:
        boxes = boxes.reshape(0, 4)
    if boxes.ndim != 2 or boxes.shape[1] != 4:
        raise ValueError(f"{where}.boxes: expected shape (n, 4), got {boxes.shape}")
    labels = labels.reshape(-1) if labels.ndim <= 1 else labels
    if labels.ndim != 1 or len(labels) != len(boxes):
        raise ValueError(f"{where}.labels: expected shape ({len(boxes)},), got {labels.shape}")
    if not (np.issubdtype(boxes.dtype, np.number) and not np.issubdtype(boxes.dtype, np.complexfloating)):
        raise ValueError(f"{where}.boxes: expected numbers, got dtype {boxes.dtype}")
    boxes = boxes.astype(np.float64)
    if not np.isfinite(boxes).all():
        raise ValueError(f"{where}.boxes: contains NaN or infinite coordinates")
    inverted = (boxes[:, 2] < boxes[:, 0]) | (boxes[:, 3] < boxes[:, 1])
    if inverted.any():
        row = int(np.flatnonzero(inverted)[0])
        raise ValueError(f"{where}.boxes[{row}]: x1 < x0 or y1 < y0 in {boxes[row].tolist()} (expected xyxy)")
    if len(labels) and not np.issubdtype(labels.dtype, np.integer):
        if not np.issubdtype(labels.dtype, np.floating) or not np.all(
            np.isfinite(labels) & (labels == np.round(labels))
        ):
            raise ValueError(f"{where}.labels: expected integer class indices, got {labels.dtype}")
    labels = labels.astype(np.int64)
    bad = (labels < 0) | (labels >= num_classes)
    if bad.any():
        raise ValueError(
            f"{where}.labels: class index {int(labels[bad][0])} outside 0..{num_classes - 1} (labels are 0-based)"
        )
    if not with_scores:
        return boxes, labels
    scores = _as_array(item["scores"], f"{where}.scores").reshape(-1)
    if len(scores) != len(boxes):
        raise ValueError(f"{where}.scores: expected {len(boxes)} scores, got {len(scores)}")
    if not np.issubdtype(scores.dtype, np.number):
        raise ValueError(f"{where}.scores: expected numbers, got dtype {scores.dtype}")
    scores = scores.astype(np.float64)
    if not np.isfinite(scores).all():
        raise ValueError(f"{where}.scores: contains NaN or infinite scores")
    return boxes, labels, scores


def _flatten(items: Sequence[Any], kind: str, num_classes: int, with_scores: bool) -> _Flat:
    parts = [_check_image(item, i, kind, num_classes, with_scores) for i, item in enumerate(items)]
    counts = np.array([len(part[0]) for part in parts], dtype=np.int64)
    image = np.repeat(np.arange(len(parts), dtype=np.int64), counts)
    if not parts or counts.sum() == 0:
        empty = _Flat(np.zeros((0, 4)), np.zeros(0, np.int64), image, np.zeros(0) if with_scores else None)
        return empty
    boxes = np.concatenate([part[0] for part in parts])
    labels = np.concatenate([part[1] for part in parts])
    scores = np.concatenate([part[2] for part in parts]) if with_scores else None
    return _Flat(boxes, labels, image, scores)


# --------------------------------------------------------------------------- VOC matching and AP


def pairwise_iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU of row-aligned box pairs ``a[i]``, ``b[i]`` (xyxy); 0 where the union is empty."""
    width = np.clip(np.minimum(a[:, 2], b[:, 2]) - np.maximum(a[:, 0], b[:, 0]), 0, None)
    height = np.clip(np.minimum(a[:, 3], b[:, 3]) - np.maximum(a[:, 1], b[:, 1]), 0, None)
    intersection = width * height
    area_a = (a[:, 2] - a[:, 0]) * (a[:, 3] - a[:, 1])
    area_b = (b[:, 2] - b[:, 0]) * (b[:, 3] - b[:, 1])
    union = area_a + area_b - intersection
    iou = np.zeros(len(a))
    np.divide(intersection, union, out=iou, where=union > 0)
    return iou


def _match(det: _Flat, gt: _Flat, order: np.ndarray, iou_threshold: float) -> np.ndarray:
    """True-positive flags of the detections taken in ``order`` (the VOC rule, all classes at once).

    Every detection is paired with each ground-truth box of the same (image, class); the pair of
    highest IoU (first box on ties) is its best match. Taken in score order, the first detection
    whose best match clears the threshold claims that box; later ones on the same box are duplicates.
    """
    num_classes = int(max(det.labels.max(initial=-1), gt.labels.max(initial=-1))) + 1
    is_tp = np.zeros(len(order), dtype=bool)
    if len(order) == 0 or len(gt.labels) == 0:
        return is_tp
    # Ground truth grouped by (image, class) key, original order kept inside a key.
    gt_key = gt.image * num_classes + gt.labels
    gt_sorted = np.argsort(gt_key, kind="stable")
    gt_key_sorted = gt_key[gt_sorted]
    det_key = det.image[order] * num_classes + det.labels[order]
    start = np.searchsorted(gt_key_sorted, det_key, side="left")
    count = np.searchsorted(gt_key_sorted, det_key, side="right") - start
    has_gt = count > 0
    if not has_gt.any():
        return is_tp
    # One row per (detection, candidate box), detections in score order, boxes in input order.
    pair_det = np.repeat(np.arange(len(order)), count)
    segment_start = np.cumsum(count) - count
    pair_offset = np.arange(len(pair_det)) - np.repeat(segment_start, count)
    pair_gt = gt_sorted[np.repeat(start, count) + pair_offset]
    iou = pairwise_iou(det.boxes[order][pair_det], gt.boxes[pair_gt])
    # Best box per detection: the maximum IoU of its segment, the first box reaching it.
    seg_starts = segment_start[has_gt]
    best_iou = np.maximum.reduceat(iou, seg_starts)
    reaches = iou == np.repeat(best_iou, count[has_gt])
    first_pair = np.flatnonzero(reaches)
    first_pair = first_pair[np.unique(pair_det[first_pair], return_index=True)[1]]
    best_gt = np.full(len(order), -1, dtype=np.int64)
    best_gt[pair_det[first_pair]] = pair_gt[first_pair]
    candidate = np.zeros(len(order), dtype=bool)
    candidate[np.flatnonzero(has_gt)] = best_iou >= iou_threshold
    candidate_index = np.flatnonzero(candidate)
    # The first candidate (in score order) per ground-truth box is the true positive.
    _, first = np.unique(best_gt[candidate_index], return_index=True)
    is_tp[candidate_index[first]] = True
    return is_tp


def average_precision(is_tp: np.ndarray, num_ground_truth: int) -> float:
    """All-point interpolated AP of detections already in score order; NaN without ground truth."""
    if num_ground_truth <= 0:
        return float("nan")
    if len(is_tp) == 0:
        return 0.0
    tp = np.cumsum(is_tp, dtype=np.float64)
    fp = np.cumsum(~is_tp, dtype=np.float64)
    recall = np.concatenate([[0.0], tp / num_ground_truth, [1.0]])
    precision = np.concatenate([[0.0], tp / (tp + fp), [0.0]])
    envelope = np.maximum.accumulate(precision[::-1])[::-1]
    steps = np.flatnonzero(recall[1:] != recall[:-1])
    return float(np.sum((recall[steps + 1] - recall[steps]) * envelope[steps + 1]))


def _nanmean(values: Sequence[float]) -> float:
    finite = [v for v in values if not math.isnan(v)]
    return float(np.mean(finite)) if finite else float("nan")


# --------------------------------------------------------------------------- public entry point


def evaluate_predictions(
    predictions: Sequence[Mapping[str, Any]],
    ground_truth: Sequence[Mapping[str, Any]],
    classes: Sequence[str],
    score_threshold: float = 0.8,
    iou_threshold: float = 0.5,
    groups: Sequence[Mapping[str, Any]] | None = None,
    coco: bool = True,
) -> EvaluationResult:
    """Score detections against ground truth, image by image (index i of each sequence = image i).

    ``predictions[i]``: ``boxes (n,4)`` xyxy pixels, ``scores (n,)``, ``labels (n,)`` 0-based.
    ``ground_truth[i]``: ``boxes (m,4)``, ``labels (m,)`` 0-based. ``groups[i]``: a dict of
    labels of image i (e.g. ``{"condition": "fb", "difficulty": "easy"}``) for ``.breakdown``;
    a field missing or None for an image leaves that image out of that field's breakdown.
    ``coco=False`` skips pycocotools (``.coco`` is then ``{}``), e.g. in tight training loops.
    """
    classes = [str(name) for name in classes]
    if not classes:
        raise ValueError("classes: at least one class name is needed")
    if len(set(classes)) != len(classes):
        raise ValueError(f"classes: duplicate names in {classes}")
    if not 0.0 <= float(score_threshold) <= 1.0 or math.isnan(float(score_threshold)):
        raise ValueError(f"score_threshold: expected a value in [0, 1], got {score_threshold}")
    if not 0.0 < float(iou_threshold) <= 1.0:
        raise ValueError(f"iou_threshold: expected a value in (0, 1], got {iou_threshold}")
    if len(predictions) != len(ground_truth):
        raise ValueError(
            f"predictions and ground_truth must cover the same images: {len(predictions)} vs {len(ground_truth)}"
        )
    if groups is not None and len(groups) != len(ground_truth):
        raise ValueError(f"groups: expected one entry per image ({len(ground_truth)}), got {len(groups)}")
    num_classes = len(classes)
    det = _flatten(predictions, "predictions", num_classes, with_scores=True)
    gt = _flatten(ground_truth, "ground_truth", num_classes, with_scores=False)
    assert det.scores is not None

    # Stable sort on the negated score: ties keep input order (image order, then within an image).
    order = np.argsort(-det.scores, kind="stable")
    is_tp = _match(det, gt, order, float(iou_threshold))
    sorted_labels = det.labels[order]
    sorted_image = det.image[order]
    kept = det.scores[order] >= score_threshold

    def score_subset(image_mask: np.ndarray | None) -> tuple[dict[str, float], dict[str, float], dict[int, Any]]:
        """AP per class (thresholded, unthresholded) over the images in ``image_mask`` (None: all)."""
        in_subset = np.ones(len(order), bool) if image_mask is None else image_mask[sorted_image]
        gt_in = np.ones(len(gt.labels), bool) if image_mask is None else image_mask[gt.image]
        ap, ap_all, details = {}, {}, {}
        for k, name in enumerate(classes):
            num_gt = int(np.count_nonzero(gt_in & (gt.labels == k)))
            rows = in_subset & (sorted_labels == k)
            tp_all = is_tp[rows]
            tp_kept = is_tp[rows & kept]
            ap[name] = average_precision(tp_kept, num_gt)
            ap_all[name] = average_precision(tp_all, num_gt)
            details[k] = (num_gt, len(tp_all), tp_kept)
        return ap, ap_all, details

    ap, ap_all, details = score_subset(None)
    per_class = {}
    for k, name in enumerate(classes):
        num_gt, num_det, tp_kept = details[k]
        true_positives = int(np.count_nonzero(tp_kept))
        per_class[name] = ClassResult(
            name=name,
            ap=ap[name],
            ap_unthresholded=ap_all[name],
            num_ground_truth=num_gt,
            num_detections=num_det,
            num_detections_kept=len(tp_kept),
            true_positives=true_positives,
            false_positives=len(tp_kept) - true_positives,
            recall=true_positives / num_gt if num_gt else float("nan"),
            precision=true_positives / len(tp_kept) if len(tp_kept) else float("nan"),
        )

    breakdown = _breakdown(groups, score_subset, gt, len(ground_truth)) if groups is not None else {}
    coco_result = (
        coco_metrics(predictions_flat=det, ground_truth_flat=gt, num_images=len(ground_truth), classes=classes)
        if coco
        else {}
    )
    return EvaluationResult(
        map=_nanmean(list(ap.values())),
        map_unthresholded=_nanmean(list(ap_all.values())),
        per_class=per_class,
        breakdown=breakdown,
        coco=coco_result,
        score_threshold=float(score_threshold),
        iou_threshold=float(iou_threshold),
        num_images=len(ground_truth),
        num_ground_truth=len(gt.labels),
        num_detections=len(det.labels),
        classes=classes,
    )


def _breakdown(groups, score_subset, gt: _Flat, num_images: int) -> dict[str, dict[str, GroupResult]]:
    for i, group in enumerate(groups):
        if not isinstance(group, Mapping):
            raise ValueError(f"groups[{i}]: expected a dict such as {{'condition': 'fb'}}, got {type(group).__name__}")
    fields: list[str] = []
    for group in groups:
        fields.extend(key for key in group if key not in fields)
    # The (condition, difficulty) pair is the paper's stage (c, δ): score it as one more field.
    labelled = [{key: value for key, value in group.items() if value is not None} for group in groups]
    pair = ("condition", "difficulty")
    if all(key in fields for key in pair):
        pair_field = PAIR_SEPARATOR.join(pair)
        for group in labelled:
            if all(key in group for key in pair):
                group[pair_field] = PAIR_SEPARATOR.join(str(group[key]) for key in pair)
        fields.append(pair_field)
    result: dict[str, dict[str, GroupResult]] = {}
    for key in fields:
        values = np.array([str(group[key]) if key in group else "" for group in labelled], dtype=object)
        present = np.array([key in group for group in labelled], dtype=bool)
        by_value: dict[str, GroupResult] = {}
        for value in sorted({v for v, p in zip(values, present) if p}):
            image_mask = present & (values == value)
            ap, ap_all, _ = score_subset(image_mask)
            by_value[value] = GroupResult(
                map=_nanmean(list(ap.values())),
                map_unthresholded=_nanmean(list(ap_all.values())),
                num_images=int(np.count_nonzero(image_mask)),
                num_ground_truth=int(np.count_nonzero(image_mask[gt.image])) if len(gt.image) else 0,
                per_class=ap,
            )
        result[key] = by_value
    return result


# --------------------------------------------------------------------------- COCO


def coco_metrics(*, predictions_flat: _Flat, ground_truth_flat: _Flat, num_images: int, classes: list[str]) -> dict:
    """pycocotools' bbox metrics on the same inputs (every detection, no score threshold).

    Where COCO's AP50 differs from VOC AP at IoU 0.5 (the paper's metric), by design:
    * matching: COCO gives a detection the best *unmatched* box with IoU ≥ 0.5, VOC its best box
      overall, a duplicate (false positive) if that box is taken;
    * interpolation: COCO samples the precision envelope at 101 recall points, VOC integrates it
      exactly (all-point);
    * COCO keeps only the 100 highest-scored detections per image (maxDets), VOC all of them.
    Both sort stably by score, both leave a class without ground truth out of the mean, both give
    AP 0 to a class with ground truth and no detection. Areas are box areas (w·h). Undefined
    values (pycocotools' -1: no ground truth) are NaN.
    """
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    categories = [{"id": k + 1, "name": name} for k, name in enumerate(classes)]
    images = [{"id": i + 1} for i in range(num_images)]

    def to_xywh(boxes: np.ndarray) -> np.ndarray:
        return np.column_stack([boxes[:, :2], boxes[:, 2:] - boxes[:, :2]])

    def annotations(flat: _Flat, with_scores: bool) -> list[dict]:
        xywh = to_xywh(flat.boxes)
        out = []
        for n in range(len(flat.labels)):
            record = {
                "id": n + 1,
                "image_id": int(flat.image[n]) + 1,
                "category_id": int(flat.labels[n]) + 1,
                "bbox": [float(v) for v in xywh[n]],
                "area": float(xywh[n, 2] * xywh[n, 3]),
                "iscrowd": 0,
            }
            if with_scores:
                assert flat.scores is not None
                record["score"] = float(flat.scores[n])
            out.append(record)
        return out

    def build(annotation_list: list[dict]) -> COCO:
        dataset = COCO()
        dataset.dataset = {"images": images, "categories": categories, "annotations": annotation_list}
        dataset.createIndex()
        return dataset

    # COCO.loadRes fails on an empty result list, so the detection set is built the same way as
    # the ground truth; pycocotools prints progress, which is not ours to show.
    with contextlib.redirect_stdout(io.StringIO()):
        coco_gt = build(annotations(ground_truth_flat, with_scores=False))
        coco_dt = build(annotations(predictions_flat, with_scores=True))
        evaluator = COCOeval(coco_gt, coco_dt, iouType="bbox")
        evaluator.evaluate()
        evaluator.accumulate()
        evaluator.summarize()
    stats = {name: (float(v) if v > -1 else float("nan")) for name, v in zip(COCO_STAT_NAMES, evaluator.stats)}
    # precision[T, R, K, A, M]: IoU thresholds, recall points, classes, area ranges, maxDets.
    precision = evaluator.eval["precision"]
    all_area, max_dets = 0, len(evaluator.params.maxDets) - 1
    iou_50 = int(np.argmin(np.abs(evaluator.params.iouThrs - 0.5)))
    per_class = {}
    for k, name in enumerate(classes):
        at_all = precision[:, :, k, all_area, max_dets]
        at_50 = precision[iou_50, :, k, all_area, max_dets]
        per_class[name] = {
            "AP": float(at_all[at_all > -1].mean()) if (at_all > -1).any() else float("nan"),
            "AP50": float(at_50[at_50 > -1].mean()) if (at_50 > -1).any() else float("nan"),
        }
    return {**stats, "per_class": per_class}


# --------------------------------------------------------------------------- a detector on a dataset


def detection_samples(
    image_ids: Sequence[int],
    predictions: Sequence[Mapping[str, np.ndarray]],
    groups: Sequence[Mapping[str, str]],
    images: int = 6,
    per_image: int = 5,
    min_score: float = 0.05,
) -> list[dict[str, Any]]:
    """A few test images' detections to show beside the scores (the dashboard): the first image
    of each (condition, difficulty) group, up to ``images``, each with its ``per_image`` best
    detections scoring at least ``min_score``; boxes rounded to 0.1 px."""
    chosen: dict[tuple[str, str], int] = {}
    for index, group in enumerate(groups):
        key = (group["condition"], group["difficulty"])
        if key not in chosen and len(chosen) < images:
            chosen[key] = index
    samples = []
    for (condition, difficulty), index in chosen.items():
        found = predictions[index]
        keep = np.flatnonzero(np.asarray(found["scores"]) >= min_score)[:per_image]
        samples.append(
            {
                "image_id": int(image_ids[index]),
                "condition": condition,
                "difficulty": difficulty,
                "boxes": [[round(float(v), 1) for v in found["boxes"][i]] for i in keep],
                "scores": [round(float(found["scores"][i]), 4) for i in keep],
                "labels": [int(found["labels"][i]) for i in keep],
            }
        )
    return samples


def detector_predictions(
    detector: Any,
    samples: Sequence[Any],
    classes: Sequence[str],
    *,
    batch_size: int = 16,
    on_batch: Callable[[int], None] | None = None,
    test_sizes: Sequence[int] | None = None,
    test_turns: Sequence[int] | None = None,
    texture_check: bool = True,
    with_evidence: bool = False,
) -> tuple[list[dict], list[dict], list[dict], list[str]]:
    """(predictions, ground truth, groups, the detector's class names) for ``evaluate_predictions``:
    ``detect_object`` on the samples' images, and their boxes with labels mapped to the detector's
    own class list by name (a dataset whose categories come in another order still scores right;
    a dataset class the detector does not know is an error). Groups are condition and difficulty.
    ``test_sizes`` and ``test_turns`` override the detector config's, ``texture_check=False`` leaves
    out the detector's texture check, ``with_evidence`` adds its evidence (see ``detect_object``).
    ``detector`` may be a list of detectors of one class list, scored as one (``detect_ensemble``)."""
    from workers.train.checkpoint import detect_ensemble

    detectors = list(detector) if isinstance(detector, (list, tuple)) else [detector]
    model_classes = [str(name) for name in detectors[0].meta.get("classes", classes)]
    unknown = [name for name in classes if name not in model_classes]
    if unknown:
        raise ValueError(
            f"the dataset has classes the detector was not trained on: {unknown} (detector classes: {model_classes})"
        )
    to_model = np.array([model_classes.index(name) for name in classes], dtype=np.int64)
    predictions = detect_ensemble(
        detectors,
        [sample.image_path for sample in samples],
        batch_size=batch_size,
        on_batch=on_batch,
        test_sizes=test_sizes,
        test_turns=test_turns,
        texture_check=texture_check,
        with_evidence=with_evidence,
    )
    ground_truth = [
        {"boxes": sample.boxes, "labels": to_model[np.asarray(sample.labels, dtype=np.int64)]} for sample in samples
    ]
    groups = [{"condition": sample.condition, "difficulty": sample.difficulty} for sample in samples]
    return predictions, ground_truth, groups, model_classes


def evaluate_detector(
    detector: Any,
    samples: Sequence[Any],
    classes: Sequence[str],
    *,
    score_threshold: float = 0.8,
    iou_threshold: float = 0.5,
    batch_size: int = 16,
    coco: bool = True,
    on_batch: Callable[[int], None] | None = None,
    **views: Any,
) -> EvaluationResult:
    """Run ``detect_object`` on the samples' images and score it against their boxes
    (``samples`` are ``workers.train.data.Sample``; ``views``: ``test_sizes``, ``test_turns``,
    ``texture_check`` overrides; see ``detector_predictions``)."""
    predictions, ground_truth, groups, model_classes = detector_predictions(
        detector, samples, classes, batch_size=batch_size, on_batch=on_batch, **views
    )
    return evaluate_predictions(
        predictions,
        ground_truth,
        model_classes,
        score_threshold=score_threshold,
        iou_threshold=iou_threshold,
        groups=groups,
        coco=coco,
    )


# --------------------------------------------------------------------------- at the threshold: precision, recall, confusion

# The "true class" of a false box that overlaps no object (at the IoU threshold).
NO_OBJECT = "no object"


@dataclass
class ImageErrors:
    """What went wrong on one image at the threshold (``index`` into the sequences scored)."""

    index: int
    true_positives: int
    false_positives: int  # kept boxes matching no object of their class
    false_negatives: int  # objects no kept box found

    @property
    def errors(self) -> int:
        return self.false_positives + self.false_negatives


@dataclass
class ThresholdResult:
    """Precision and recall of the detections kept at ``score_threshold`` (each kept box either
    finds an object of its class at IoU ≥ ``iou_threshold`` not found before it, or is false;
    the VOC matching of ``evaluate_predictions``), and what the false boxes were.

    ``confusion[given][true]``: false boxes given class ``given`` whose best-overlapping object
    (at IoU ≥ ``iou_threshold``) is of class ``true`` (``true == given``: a second box on an
    object already found), or ``NO_OBJECT`` when they overlap none that much. Counts of zero are
    left out. ``per_class[name]``: tp, fp, fn, precision, recall. Precision is NaN where nothing
    was kept, recall NaN where there is no object."""

    score_threshold: float
    iou_threshold: float
    classes: list[str]
    true_positives: int
    false_positives: int
    false_negatives: int
    precision: float
    recall: float
    per_class: dict[str, dict[str, float]]
    confusion: dict[str, dict[str, int]]
    per_image: list[ImageErrors]

    def worst_images(self, count: int) -> list[ImageErrors]:
        """The ``count`` images with most errors (false boxes plus objects missed), worst first;
        images without error are left out; ties keep image order."""
        wrong = [item for item in self.per_image if item.errors]
        return sorted(wrong, key=lambda item: -item.errors)[:count]

    def to_dict(self) -> dict[str, Any]:
        return json_safe({**asdict(self), "per_image": [asdict(item) for item in self.per_image]})


def _ratio(numerator: int, denominator: int) -> float:
    return numerator / denominator if denominator else float("nan")


def true_detections(prediction: Mapping[str, Any], truth: Mapping[str, Any], iou_threshold: float = 0.5) -> np.ndarray:
    """(n,) bool, in ``prediction``'s order: which of one image's detections are true under the
    VOC matching of ``evaluate_predictions`` (taken best score first, each claiming the object of
    its class it overlaps most at IoU ≥ ``iou_threshold``, if no better detection claimed it)."""
    num_classes = int(max(np.max(prediction["labels"], initial=-1), np.max(truth["labels"], initial=-1))) + 1
    det = _flatten([prediction], "prediction", max(num_classes, 1), with_scores=True)
    gt = _flatten([truth], "truth", max(num_classes, 1), with_scores=False)
    assert det.scores is not None
    order = np.argsort(-det.scores, kind="stable")
    flags = np.zeros(len(order), dtype=bool)
    flags[order] = _match(det, gt, order, float(iou_threshold))
    return flags


def precision_recall_at(
    predictions: Sequence[Mapping[str, Any]],
    ground_truth: Sequence[Mapping[str, Any]],
    classes: Sequence[str],
    score_threshold: float = 0.8,
    iou_threshold: float = 0.5,
) -> ThresholdResult:
    """Precision, recall and the confusion between classes of the detections at or above
    ``score_threshold``, image by image (the inputs of ``evaluate_predictions``: boxes xyxy,
    scores, 0-based labels). Totals are summed over classes (micro average)."""
    classes = [str(name) for name in classes]
    if not classes:
        raise ValueError("classes: at least one class name is needed")
    if not 0.0 <= float(score_threshold) <= 1.0:
        raise ValueError(f"score_threshold: expected a value in [0, 1], got {score_threshold}")
    if not 0.0 < float(iou_threshold) <= 1.0:
        raise ValueError(f"iou_threshold: expected a value in (0, 1], got {iou_threshold}")
    if len(predictions) != len(ground_truth):
        raise ValueError(
            f"predictions and ground_truth must cover the same images: {len(predictions)} vs {len(ground_truth)}"
        )
    det = _flatten(predictions, "predictions", len(classes), with_scores=True)
    gt = _flatten(ground_truth, "ground_truth", len(classes), with_scores=False)
    assert det.scores is not None
    kept = np.flatnonzero(det.scores >= score_threshold)
    order = kept[np.argsort(-det.scores[kept], kind="stable")]
    is_tp = _match(det, gt, order, float(iou_threshold))

    confusion: dict[str, dict[str, int]] = {}
    for row in order[~is_tp]:
        same_image = np.flatnonzero(gt.image == det.image[row])
        true = NO_OBJECT
        if len(same_image):
            overlaps = pairwise_iou(np.repeat(det.boxes[row : row + 1], len(same_image), axis=0), gt.boxes[same_image])
            best = int(np.argmax(overlaps))
            if overlaps[best] >= iou_threshold:
                true = classes[int(gt.labels[same_image[best]])]
        given = confusion.setdefault(classes[int(det.labels[row])], {})
        given[true] = given.get(true, 0) + 1

    num_images = len(ground_truth)
    tp_labels, fp_labels = det.labels[order[is_tp]], det.labels[order[~is_tp]]
    per_class = {}
    for k, name in enumerate(classes):
        tp, fp = int(np.count_nonzero(tp_labels == k)), int(np.count_nonzero(fp_labels == k))
        fn = int(np.count_nonzero(gt.labels == k)) - tp
        per_class[name] = {
            "tp": tp,
            "fp": fp,
            "fn": fn,
            "precision": _ratio(tp, tp + fp),
            "recall": _ratio(tp, tp + fn),
        }
    tp_per_image = np.bincount(det.image[order[is_tp]], minlength=num_images)
    fp_per_image = np.bincount(det.image[order[~is_tp]], minlength=num_images)
    gt_per_image = np.bincount(gt.image, minlength=num_images)
    per_image = [
        ImageErrors(i, int(tp_per_image[i]), int(fp_per_image[i]), int(gt_per_image[i] - tp_per_image[i]))
        for i in range(num_images)
    ]
    tp, fp = int(is_tp.sum()), int((~is_tp).sum())
    fn = len(gt.labels) - tp
    return ThresholdResult(
        score_threshold=float(score_threshold),
        iou_threshold=float(iou_threshold),
        classes=classes,
        true_positives=tp,
        false_positives=fp,
        false_negatives=fn,
        precision=_ratio(tp, tp + fp),
        recall=_ratio(tp, tp + fn),
        per_class=per_class,
        confusion=confusion,
        per_image=per_image,
    )
