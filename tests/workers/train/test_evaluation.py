"""evaluate_predictions: the VOC rule against a plain reference, and every difference from COCO's AP50."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from workers.train.evaluation import average_precision, evaluate_predictions

CLASSES = ["astronaut", "coffee", "chelsea"]


# --------------------------------------------------------------------------- plain references


def plain_iou(a, b) -> float:
    width = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    height = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    intersection = width * height
    union = (a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - intersection
    return intersection / union if union > 0 else 0.0


def reference_ap(predictions, ground_truth, k, score_threshold=0.0, iou_threshold=0.5, rule="voc", points="all"):
    """AP of class k written as loops, straight from the protocol text.

    rule "voc": each detection takes its best box (matched or not); taken → duplicate (FP).
    rule "coco": each detection takes the best box still unmatched with IoU ≥ threshold (on equal
    IoU pycocotools keeps the later box), detections sorted per image, at most 100 per image.
    points "all": exact area under the precision envelope; "101": COCO's 101 recall samples.
    """
    detections = []
    for i, image in enumerate(predictions):
        per_image = [
            (float(s), i, list(map(float, b)))
            for b, s, label in zip(image["boxes"], image["scores"], image["labels"])
            if int(label) == k and float(s) >= score_threshold
        ]
        if rule == "coco":
            per_image = sorted(per_image, key=lambda d: -d[0])[:100]
        detections.extend(per_image)
    detections = sorted(detections, key=lambda d: -d[0])  # Python's sort is stable
    boxes = {
        i: [list(map(float, b)) for b, lab in zip(g["boxes"], g["labels"]) if int(lab) == k]
        for i, g in enumerate(ground_truth)
    }
    num_gt = sum(len(v) for v in boxes.values())
    if num_gt == 0:
        return float("nan")
    matched = {i: [False] * len(v) for i, v in boxes.items()}
    flags = []
    for _, i, box in detections:
        if rule == "voc":
            best, best_j = -1.0, -1
            for j, gt_box in enumerate(boxes[i]):
                overlap = plain_iou(box, gt_box)
                if overlap > best:
                    best, best_j = overlap, j
            if best_j >= 0 and best >= iou_threshold and not matched[i][best_j]:
                matched[i][best_j] = True
                flags.append(True)
            else:
                flags.append(False)
        else:
            best, best_j = min(iou_threshold, 1 - 1e-10), -1
            for j, gt_box in enumerate(boxes[i]):
                overlap = plain_iou(box, gt_box)
                if matched[i][j] or overlap < best:
                    continue
                best, best_j = overlap, j
            if best_j >= 0:
                matched[i][best_j] = True
            flags.append(best_j >= 0)
    recall, precision, tp = [], [], 0
    for n, flag in enumerate(flags, start=1):
        tp += flag
        recall.append(tp / num_gt)
        precision.append(tp / n)
    if points == "all":
        mrec, mpre = [0.0] + recall + [1.0], [0.0] + precision + [0.0]
        for n in range(len(mpre) - 2, -1, -1):
            mpre[n] = max(mpre[n], mpre[n + 1])
        return sum((mrec[n + 1] - mrec[n]) * mpre[n + 1] for n in range(len(mrec) - 1) if mrec[n + 1] != mrec[n])
    envelope = precision[:]
    for n in range(len(envelope) - 2, -1, -1):
        envelope[n] = max(envelope[n], envelope[n + 1])
    total = 0.0
    for r in np.linspace(0.0, 1.0, 101):
        reached = [n for n, value in enumerate(recall) if value >= r]
        total += envelope[reached[0]] if reached else 0.0
    return total / 101


def random_case(seed: int, num_classes: int = 3):
    """Images with 0-3 objects, detections near them (duplicates, wrong classes) and strays;
    scores on a 0.1 grid so that ties are common."""
    rng = np.random.default_rng(seed)
    predictions, ground_truth = [], []
    for _ in range(int(rng.integers(0, 9))):
        n = int(rng.integers(0, 4))
        xy = rng.uniform(0, 80, (n, 2))
        gt_boxes = np.column_stack([xy, xy + rng.uniform(4, 40, (n, 2))])
        gt_labels = rng.integers(0, num_classes, n)
        boxes, labels = [], []
        for box, label in zip(gt_boxes, gt_labels):
            for _ in range(int(rng.integers(0, 4))):  # 0: a miss, 2-3: duplicates
                size = box[2:] - box[:2]
                boxes.append(box + rng.normal(0, 0.2, 4) * np.concatenate([size, size]))
                labels.append(label if rng.random() < 0.85 else int(rng.integers(0, num_classes)))
        for _ in range(int(rng.integers(0, 3))):  # strays
            xy0 = rng.uniform(0, 80, 2)
            boxes.append(np.concatenate([xy0, xy0 + rng.uniform(4, 40, 2)]))
            labels.append(int(rng.integers(0, num_classes)))
        boxes = np.array(boxes, dtype=np.float64).reshape(-1, 4)
        boxes[:, 2:] = np.maximum(boxes[:, 2:], boxes[:, :2])  # jitter may invert a box
        predictions.append(
            {"boxes": boxes, "labels": np.array(labels, np.int64), "scores": np.round(rng.uniform(0, 1, len(boxes)), 1)}
        )
        ground_truth.append({"boxes": gt_boxes, "labels": gt_labels})
    return predictions, ground_truth


def same(a: float, b: float, tol: float = 1e-9) -> bool:
    return (math.isnan(a) and math.isnan(b)) or abs(a - b) <= tol


# --------------------------------------------------------------------------- randomized agreement


@pytest.mark.parametrize("seed", range(150))
def test_voc_ap_matches_plain_reference(seed):
    predictions, ground_truth = random_case(seed)
    rng = np.random.default_rng(10_000 + seed)
    score_threshold = float(rng.choice([0.0, 0.5, 0.8]))
    iou_threshold = float(rng.choice([0.3, 0.5, 0.7]))
    result = evaluate_predictions(
        predictions, ground_truth, CLASSES, score_threshold=score_threshold, iou_threshold=iou_threshold, coco=False
    )
    expected, expected_all = [], []
    for k, name in enumerate(CLASSES):
        ap = reference_ap(predictions, ground_truth, k, score_threshold, iou_threshold)
        ap_all = reference_ap(predictions, ground_truth, k, 0.0, iou_threshold)
        assert same(result.per_class[name].ap, ap), (name, result.per_class[name].ap, ap)
        assert same(result.per_class[name].ap_unthresholded, ap_all)
        expected += [ap] if not math.isnan(ap) else []
        expected_all += [ap_all] if not math.isnan(ap_all) else []
    assert same(result.map, float(np.mean(expected)) if expected else math.nan)
    assert same(result.map_unthresholded, float(np.mean(expected_all)) if expected_all else math.nan)


@pytest.mark.parametrize("seed", range(40))
def test_coco_ap50_is_the_reference_under_cocos_rule_and_101_points(seed):
    """Swapping exactly the documented differences (best-unmatched matching, 101-point sampling,
    100 detections per image) into the plain reference reproduces pycocotools' AP50: no other
    difference hides between the two metrics."""
    predictions, ground_truth = random_case(seed)
    result = evaluate_predictions(predictions, ground_truth, CLASSES, score_threshold=0.0)
    for k, name in enumerate(CLASSES):
        coco_like = reference_ap(predictions, ground_truth, k, rule="coco", points="101")
        assert same(result.coco["per_class"][name]["AP50"], coco_like, tol=1e-6), name


def test_many_images_vectorised_path_matches_reference():
    """One large pooled case (hundreds of images, many ties) through the vectorised matcher."""
    predictions, ground_truth = [], []
    for seed in range(60):
        p, g = random_case(500 + seed)
        predictions += p
        ground_truth += g
    result = evaluate_predictions(predictions, ground_truth, CLASSES, score_threshold=0.3, coco=False)
    for k, name in enumerate(CLASSES):
        assert same(result.per_class[name].ap, reference_ap(predictions, ground_truth, k, 0.3))


# --------------------------------------------------------------------------- hand-made cases vs COCO


def box(x0, y0, x1, y1):
    return [float(x0), float(y0), float(x1), float(y1)]


def gt(*boxes, labels=None):
    return {"boxes": np.array(boxes, float).reshape(-1, 4), "labels": np.array(labels or [0] * len(boxes), np.int64)}


def det(*items):
    """items: (box, score) or (box, score, label)."""
    return {
        "boxes": np.array([item[0] for item in items], float).reshape(-1, 4),
        "scores": np.array([item[1] for item in items], float),
        "labels": np.array([item[2] if len(item) > 2 else 0 for item in items], np.int64),
    }


def evaluate(predictions, ground_truth, classes=("a",), **kwargs):
    kwargs.setdefault("score_threshold", 0.0)
    return evaluate_predictions(predictions, ground_truth, list(classes), **kwargs)


def test_duplicate_detection_is_a_false_positive_in_both():
    """Two boxes A, B; detections: A (0.9), a duplicate of A (0.8), B (0.7).
    VOC: TP, FP, TP → precision 1, 1/2, 2/3 at recall 1/2, 1/2, 1 → AP = ½·1 + ½·⅔ = 5/6.
    COCO also rejects the duplicate (A is taken, B does not overlap it) but samples the envelope
    at 101 recall points: 51 points at precision 1 (recall 0..0.50) and 50 at ⅔ → 84.33/101."""
    result = evaluate(
        [det((box(0, 0, 10, 10), 0.9), (box(0, 0, 10, 10), 0.8), (box(20, 20, 30, 30), 0.7))],
        [gt(box(0, 0, 10, 10), box(20, 20, 30, 30))],
    )
    assert result.map == pytest.approx(5 / 6)
    assert result.per_class["a"].false_positives == 1
    assert result.coco["AP50"] == pytest.approx((51 + 50 * 2 / 3) / 101)


def test_partial_recall_101_points_vs_all_points():
    """Three boxes, one found at the top score. All-point AP = recall · precision = ⅓.
    COCO counts the recall points 0, 0.01, ..., 0.33 (34 of 101) at precision 1: 34/101 ≈ 0.3366."""
    result = evaluate(
        [det((box(0, 0, 10, 10), 0.9))],
        [gt(box(0, 0, 10, 10), box(20, 20, 30, 30), box(40, 40, 50, 50))],
    )
    assert result.map == pytest.approx(1 / 3)
    assert result.coco["AP50"] == pytest.approx(34 / 101)


def test_full_recall_at_constant_precision_agrees():
    """A false positive then a true positive: precision ½ at recall 1 everywhere on the envelope,
    so both interpolations give exactly ½ (interpolation only matters where the envelope steps)."""
    result = evaluate(
        [det((box(50, 50, 60, 60), 0.9), (box(0, 0, 10, 10), 0.8))],
        [gt(box(0, 0, 10, 10))],
    )
    assert result.map == pytest.approx(0.5)
    assert result.coco["AP50"] == pytest.approx(0.5)


def test_second_box_taken_by_coco_not_by_voc():
    """Boxes A = [0,0,10,10] and B = [0,0,10,8] overlap (IoU 0.8). Detection 1 (0.9) is A itself;
    detection 2 (0.8) is [0,0,10,9]: IoU 0.9 with A, 0.889 with B.
    VOC: detection 2's best box is A, already matched → duplicate, FP; B is never found:
    TP, FP → AP = ½ (recall ½ at precision 1). COCO: A is taken, so detection 2 takes the best
    unmatched box B (IoU ≥ 0.5) → TP, TP → AP50 = 1."""
    result = evaluate(
        [det((box(0, 0, 10, 10), 0.9), (box(0, 0, 10, 9), 0.8))],
        [gt(box(0, 0, 10, 10), box(0, 0, 10, 8))],
    )
    assert result.map == pytest.approx(0.5)
    assert result.per_class["a"].true_positives == 1
    assert result.coco["AP50"] == pytest.approx(1.0)


def test_tied_scores_keep_input_order_in_both():
    """A TP in image 0 and an FP in image 1, both scored 0.9 (one box, in image 0).
    Both metrics sort stably, so input order decides: TP first → AP 1; the same detections with
    images swapped put the FP first → precision ½ at recall 1 → AP ½. COCO agrees in both orders
    (image ids follow input order, its sorts are mergesorts)."""
    tp, fp = det((box(0, 0, 10, 10), 0.9)), det((box(50, 50, 60, 60), 0.9))
    first = evaluate([tp, fp], [gt(box(0, 0, 10, 10)), gt()])
    assert first.map == pytest.approx(1.0)
    assert first.coco["AP50"] == pytest.approx(1.0)
    second = evaluate([fp, tp], [gt(), gt(box(0, 0, 10, 10))])
    assert second.map == pytest.approx(0.5)
    assert second.coco["AP50"] == pytest.approx(0.5)


def test_tied_scores_within_one_image_match_in_input_order():
    """Two detections of the same box with the same score: the first listed is the TP, the second a
    duplicate. A later, lower-scored detection of a second box completes recall. Listing the
    duplicate first changes nothing here (both have the same IoU, one is TP, one FP, then the
    second box at 2/3 precision): AP = ½ + ½·⅔ in both orders, and COCO gives its 101-point value."""
    a, b = box(0, 0, 10, 10), box(20, 20, 30, 30)
    result = evaluate([det((a, 0.9), (box(0, 0, 10, 9), 0.9), (b, 0.5))], [gt(a, b)])
    assert result.map == pytest.approx(5 / 6)
    assert result.coco["AP50"] == pytest.approx((51 + 50 * 2 / 3) / 101)


def test_class_without_ground_truth_is_left_out_of_the_mean_in_both():
    """Class "b" has detections but no box anywhere. Its AP is undefined (no recall), NaN, and the
    mean runs over "a" only: mAP = AP(a) = 1. pycocotools also skips it (its precision stays -1),
    so COCO's AP50 is "a"'s: 1. Its detections are not false positives of "a"."""
    result = evaluate(
        [det((box(0, 0, 10, 10), 0.9, 0), (box(0, 0, 10, 10), 0.95, 1))],
        [gt(box(0, 0, 10, 10))],
        classes=("a", "b"),
    )
    assert math.isnan(result.per_class["b"].ap)
    assert result.per_class["b"].num_detections == 1
    assert result.map == pytest.approx(1.0)
    assert result.coco["AP50"] == pytest.approx(1.0)
    assert math.isnan(result.coco["per_class"]["b"]["AP50"])
    assert result.to_dict()["per_class"]["b"]["ap"] is None


def test_no_detections_at_all_scores_zero_in_both():
    """Ground truth and no detection anywhere: recall 0, AP 0 for every class with boxes (not
    undefined). pycocotools' loadRes would crash on an empty result list; our in-memory conversion
    yields its well-defined 0."""
    result = evaluate([det(), det()], [gt(box(0, 0, 10, 10)), gt(box(5, 5, 20, 20), labels=[1])], classes=("a", "b"))
    assert result.map == 0.0 and result.map_unthresholded == 0.0
    assert result.per_class["a"].ap == 0.0 and result.per_class["b"].ap == 0.0
    assert result.coco["AP50"] == 0.0


def test_empty_images_change_nothing_and_their_detections_are_false_positives():
    """Images without boxes or detections do not count; a detection in an image without boxes is
    an FP in both metrics (here scored below the TP, so the envelope stays 1 up to recall 1)."""
    base = evaluate([det((box(0, 0, 10, 10), 0.9))], [gt(box(0, 0, 10, 10))])
    padded = evaluate(
        [det(), det((box(0, 0, 10, 10), 0.9)), det(), det((box(1, 1, 5, 5), 0.3))],
        [gt(), gt(box(0, 0, 10, 10)), gt(), gt()],
    )
    assert base.map == padded.map == 1.0
    assert padded.per_class["a"].false_positives == 1
    assert padded.coco["AP50"] == pytest.approx(1.0)


def test_no_ground_truth_at_all_is_undefined_not_zero():
    """With no box in any image, no class has recall: mAP is NaN (None in JSON), with or without
    detections, and pycocotools' -1 ("undefined") is reported as NaN too. A test set without
    ground truth is a bug upstream; a score of 0 or 1 would hide it."""
    for predictions in ([det(), det()], [det((box(0, 0, 10, 10), 0.9)), det()]):
        result = evaluate(predictions, [gt(), gt()], classes=("a", "b"), groups=[{"condition": "fb"}] * 2)
        assert math.isnan(result.map) and math.isnan(result.map_unthresholded)
        assert math.isnan(result.coco["AP50"])
        payload = result.to_dict()
        assert payload["map"] is None and payload["coco"]["AP"] is None
        assert payload["breakdown"]["condition"]["fb"]["map"] is None
        json.dumps(payload, allow_nan=False)
    empty = evaluate([], [], classes=("a",))
    assert math.isnan(empty.map) and empty.num_images == 0


def test_coco_keeps_only_100_detections_per_image():
    """150 stray detections scored above the only true positive in one image: VOC ranks the TP
    151st → AP = 1/151. COCO keeps the 100 best per image, drops the TP → AP50 = 0."""
    strays = [(box(200 + i, 200, 205 + i, 205), 0.9) for i in range(150)]
    result = evaluate([det(*strays, (box(0, 0, 10, 10), 0.5))], [gt(box(0, 0, 10, 10))])
    assert result.map == pytest.approx(1 / 151)
    assert result.coco["AP50"] == 0.0


def test_zero_area_boxes_overlap_nothing():
    """A zero-area box has IoU 0 with everything (0/0 is not a match): the detection on the
    degenerate box is an FP, the real one a TP, and the degenerate box is never found.
    pycocotools' IoU is 0/0 = NaN there, which never matches either; the two differ only by the
    101-point sampling (51 points at precision ½)."""
    degenerate = box(5, 5, 5, 12)
    result = evaluate(
        [det((degenerate, 0.9), (box(0, 0, 10, 10), 0.8))],
        [gt(degenerate, box(0, 0, 10, 10))],
    )
    # FP, TP: precision 0, ½ at recall 0, ½ → envelope ½ on (0, ½] → AP = ¼.
    assert result.map == pytest.approx(0.25)
    assert result.coco["AP50"] == pytest.approx(51 * 0.5 / 101)


def test_iou_exactly_at_threshold_is_a_match():
    """IoU ≥ threshold matches (the contract; VOC's devkit used >): [0,0,10,5] vs [0,0,10,10] is
    exactly 0.5 and is a TP in both."""
    result = evaluate([det((box(0, 0, 10, 5), 0.9))], [gt(box(0, 0, 10, 10))])
    assert result.map == 1.0
    assert result.coco["AP50"] == pytest.approx(1.0)


def test_wrong_class_is_a_miss_and_a_false_positive():
    result = evaluate([det((box(0, 0, 10, 10), 0.9, 1))], [gt(box(0, 0, 10, 10))], classes=("a", "b"))
    assert result.per_class["a"].ap == 0.0
    assert math.isnan(result.per_class["b"].ap)
    assert result.map == 0.0


# --------------------------------------------------------------------------- the paper's threshold


def test_threshold_drops_low_confidence_true_positives():
    """Two boxes, both found, one at 0.9 and one at 0.5: unthresholded AP 1; the paper's 0.8 cut
    drops the second → recall ½ → AP ½. A score exactly at the threshold is kept."""
    predictions = [det((box(0, 0, 10, 10), 0.9)), det((box(0, 0, 10, 10), 0.5))]
    ground_truth = [gt(box(0, 0, 10, 10)), gt(box(0, 0, 10, 10))]
    result = evaluate_predictions(predictions, ground_truth, ["a"])
    assert result.score_threshold == 0.8
    assert result.map == pytest.approx(0.5)
    assert result.map_unthresholded == pytest.approx(1.0)
    assert result.per_class["a"].num_detections == 2
    assert result.per_class["a"].num_detections_kept == 1
    assert result.per_class["a"].recall == pytest.approx(0.5)
    at_threshold = [det((box(0, 0, 10, 10), 0.9)), det((box(0, 0, 10, 10), 0.8))]
    assert evaluate_predictions(at_threshold, ground_truth, ["a"]).map == pytest.approx(1.0)


def test_threshold_also_drops_false_positives():
    """A low-scored FP ranked above nothing useful: dropping it cannot lower AP; an FP at 0.85
    ranked above the TP still counts under the paper's cut."""
    predictions = [det((box(50, 50, 60, 60), 0.85), (box(0, 0, 10, 10), 0.82), (box(30, 30, 40, 40), 0.1))]
    result = evaluate_predictions(predictions, [gt(box(0, 0, 10, 10))], ["a"])
    assert result.map == pytest.approx(0.5)
    assert result.per_class["a"].false_positives == 1


# --------------------------------------------------------------------------- breakdown


def test_breakdown_groups_equal_evaluating_each_subset():
    predictions, ground_truth = [], []
    for seed in range(6):
        p, g = random_case(900 + seed)
        predictions += p
        ground_truth += g
    rng = np.random.default_rng(3)
    conditions = rng.choice(["fb", "mb", "po"], len(ground_truth))
    difficulties = rng.choice(["easy", "hard"], len(ground_truth))
    groups = [{"condition": c, "difficulty": d} for c, d in zip(conditions, difficulties)]
    groups[0] = {"condition": "canonical", "difficulty": None}  # no difficulty: left out of that field
    result = evaluate_predictions(predictions, ground_truth, CLASSES, score_threshold=0.5, groups=groups, coco=False)
    assert set(result.breakdown) == {"condition", "difficulty", "condition/difficulty"}
    assert "canonical" in result.breakdown["condition"]
    assert "canonical/None" not in result.breakdown["condition/difficulty"]

    def subset_map(keep):
        idx = [i for i in range(len(groups)) if keep(groups[i])]
        sub = evaluate_predictions(
            [predictions[i] for i in idx], [ground_truth[i] for i in idx], CLASSES, score_threshold=0.5, coco=False
        )
        return sub, len(idx)

    for field in ("condition", "difficulty"):
        for value, group_result in result.breakdown[field].items():
            expected, count = subset_map(lambda g: g.get(field) == value)
            assert group_result.num_images == count
            assert same(group_result.map, expected.map)
            assert same(group_result.map_unthresholded, expected.map_unthresholded)
            assert group_result.num_ground_truth == expected.num_ground_truth
    for pair, group_result in result.breakdown["condition/difficulty"].items():
        c, d = pair.split("/")
        expected, count = subset_map(lambda g: g["condition"] == c and g["difficulty"] == d)
        assert group_result.num_images == count
        assert same(group_result.map, expected.map)
        for name in CLASSES:
            assert same(group_result.per_class[name], expected.per_class[name].ap)


def test_breakdown_hand_made():
    """fb images are all found, po images all missed: fb 1, po 0, overall ½ (one class)."""
    found, missed = det((box(0, 0, 10, 10), 0.9)), det()
    truth = gt(box(0, 0, 10, 10))
    result = evaluate(
        [found, missed, found, missed],
        [truth] * 4,
        groups=[
            {"condition": "fb", "difficulty": "easy"},
            {"condition": "po", "difficulty": "easy"},
            {"condition": "fb", "difficulty": "hard"},
            {"condition": "po", "difficulty": "hard"},
        ],
    )
    assert result.map == pytest.approx(0.5)
    assert result.breakdown["condition"]["fb"].map == 1.0
    assert result.breakdown["condition"]["po"].map == 0.0
    assert result.breakdown["difficulty"]["easy"].map == pytest.approx(0.5)
    assert result.breakdown["condition/difficulty"]["po/hard"].map == 0.0
    assert result.breakdown["condition/difficulty"]["fb/easy"].num_images == 1


# --------------------------------------------------------------------------- inputs


def test_accepts_lists_and_torch_tensors():
    torch = pytest.importorskip("torch")
    as_lists = evaluate(
        [{"boxes": [[0, 0, 10, 10]], "scores": [0.9], "labels": [0]}], [{"boxes": [[0, 0, 10, 10]], "labels": [0]}]
    )
    as_tensors = evaluate(
        [{"boxes": torch.tensor([[0.0, 0, 10, 10]]), "scores": torch.tensor([0.9]), "labels": torch.tensor([0])}],
        [{"boxes": torch.tensor([[0.0, 0, 10, 10]]), "labels": torch.tensor([0])}],
    )
    assert as_lists.map == as_tensors.map == 1.0
    empty = evaluate([{"boxes": [], "scores": [], "labels": []}], [{"boxes": np.zeros((0, 4)), "labels": []}])
    assert math.isnan(empty.map)


@pytest.mark.parametrize(
    "prediction, truth, message",
    [
        (
            {"boxes": [[0, 0, 10, 10]], "scores": [float("nan")], "labels": [0]},
            None,
            r"predictions\[0\]\.scores: contains NaN",
        ),
        (
            {"boxes": [[0, 0, float("nan"), 10]], "scores": [0.9], "labels": [0]},
            None,
            r"predictions\[0\]\.boxes: contains NaN",
        ),
        ({"boxes": [[0, 0, float("inf"), 10]], "scores": [0.9], "labels": [0]}, None, r"NaN or infinite"),
        ({"boxes": [[10, 0, 0, 10]], "scores": [0.9], "labels": [0]}, None, r"boxes\[0\]: x1 < x0"),
        ({"boxes": [[0, 0, 10, 10]], "scores": [0.9], "labels": [3]}, None, r"class index 3 outside 0\.\.0"),
        ({"boxes": [[0, 0, 10, 10]], "scores": [0.9, 0.8], "labels": [0]}, None, r"expected 1 scores, got 2"),
        ({"boxes": [[0, 0, 10]], "scores": [0.9], "labels": [0]}, None, r"expected shape \(n, 4\)"),
        ({"boxes": [[0, 0, 10, 10]], "labels": [0]}, None, r"missing 'scores'"),
        (None, {"boxes": [[0, 0, 10, 10]], "labels": [-1]}, r"ground_truth\[0\]\.labels: class index -1"),
        (None, {"boxes": [[0, 0, 10, 10]], "labels": [0.5]}, r"expected integer class indices"),
        (None, {"boxes": [[0, float("nan"), 10, 10]], "labels": [0]}, r"ground_truth\[0\]\.boxes: contains NaN"),
    ],
)
def test_rejects_bad_input_with_a_clear_error(prediction, truth, message):
    prediction = prediction or {"boxes": [[0, 0, 10, 10]], "scores": [0.9], "labels": [0]}
    truth = truth or {"boxes": [[0, 0, 10, 10]], "labels": [0]}
    with pytest.raises(ValueError, match=message):
        evaluate([prediction], [truth])


def test_rejects_mismatched_lengths_and_bad_arguments():
    one_det, one_gt = det((box(0, 0, 1, 1), 0.5)), gt(box(0, 0, 1, 1))
    with pytest.raises(ValueError, match="same images: 1 vs 2"):
        evaluate([one_det], [one_gt, one_gt])
    with pytest.raises(ValueError, match=r"groups: expected one entry per image \(1\), got 2"):
        evaluate([one_det], [one_gt], groups=[{}, {}])
    with pytest.raises(ValueError, match="score_threshold"):
        evaluate([one_det], [one_gt], score_threshold=1.5)
    with pytest.raises(ValueError, match="iou_threshold"):
        evaluate([one_det], [one_gt], iou_threshold=0.0)
    with pytest.raises(ValueError, match="at least one class"):
        evaluate([one_det], [one_gt], classes=())
    with pytest.raises(ValueError, match="duplicate"):
        evaluate([one_det], [one_gt], classes=("a", "a"))
    with pytest.raises(ValueError, match=r"groups\[0\]"):
        evaluate([one_det], [one_gt], groups=["fb"])


def test_average_precision_edges():
    assert math.isnan(average_precision(np.zeros(0, bool), 0))
    assert average_precision(np.zeros(0, bool), 3) == 0.0
    assert average_precision(np.array([True, True]), 2) == 1.0
    assert average_precision(np.array([False, False]), 2) == 0.0


# --------------------------------------------------------------------------- a detector on samples


def test_evaluate_detector_maps_labels_by_class_name(monkeypatch, tmp_path):
    """The dataset lists classes in another order than the detector: ground truth is renamed to
    the detector's indices, so a perfect detector scores 1, and an unknown class is an error."""
    import sys
    import types

    from workers.train.data import Sample
    from workers.train.evaluation import evaluate_detector

    detector_classes = ["a", "b"]
    outputs = {  # the detector's answers per image, in its own class indices
        "0.png": {
            "boxes": np.array([[0, 0, 10, 10]], np.float32),
            "scores": np.array([0.9], np.float32),
            "labels": np.array([0]),
        },
        "1.png": {
            "boxes": np.array([[5, 5, 20, 20]], np.float32),
            "scores": np.array([0.95], np.float32),
            "labels": np.array([1]),
        },
    }
    fake = types.ModuleType("workers.train.checkpoint")
    fake.detect_ensemble = lambda detectors, images, on_batch=None, **options: [outputs[Path(p).name] for p in images]
    monkeypatch.setitem(sys.modules, "workers.train.checkpoint", fake)
    detector = types.SimpleNamespace(meta={"classes": detector_classes})
    dataset_classes = ["b", "a"]  # category order of the dataset differs
    samples = [
        Sample(tmp_path / "0.png", [[0, 0, 10, 10]], [1], condition="fb", difficulty="easy"),
        Sample(tmp_path / "1.png", [[5, 5, 20, 20]], [0], condition="po", difficulty="hard"),
    ]
    result = evaluate_detector(detector, samples, dataset_classes)
    assert result.classes == detector_classes
    assert result.map == 1.0
    assert result.breakdown["condition/difficulty"]["po/hard"].map == 1.0
    with pytest.raises(ValueError, match=r"not trained on: \['c'\]"):
        evaluate_detector(detector, samples, ["b", "a", "c"])


# --------------------------------------------------------------------------- at the threshold

from workers.train.evaluation import NO_OBJECT, precision_recall_at  # noqa: E402


def _dets(boxes, scores, labels):
    return {
        "boxes": np.asarray(boxes, float).reshape(-1, 4),
        "scores": np.asarray(scores, float),
        "labels": np.asarray(labels, int),
    }


def _truth(boxes, labels):
    return {"boxes": np.asarray(boxes, float).reshape(-1, 4), "labels": np.asarray(labels, int)}


def test_precision_and_recall_count_only_the_boxes_kept_at_the_threshold():
    predictions = [
        _dets([[0, 0, 10, 10], [20, 20, 30, 30], [40, 40, 50, 50]], [0.95, 0.7, 0.9], [0, 1, 1]),
        _dets([], [], []),
    ]
    truth = [_truth([[0, 0, 10, 10], [20, 20, 30, 30]], [0, 1]), _truth([[5, 5, 9, 9]], [1])]
    result = precision_recall_at(predictions, truth, ["a", "b"], score_threshold=0.8, iou_threshold=0.5)
    # kept: a on its object (TP), b on nothing (FP); b at 0.7 dropped, so its object is missed
    assert (result.true_positives, result.false_positives, result.false_negatives) == (1, 1, 2)
    assert result.precision == pytest.approx(0.5) and result.recall == pytest.approx(1 / 3)
    assert result.per_class["a"] == {"tp": 1, "fp": 0, "fn": 0, "precision": 1.0, "recall": 1.0}
    assert result.per_class["b"]["fn"] == 2 and result.per_class["b"]["precision"] == 0.0
    assert result.confusion == {"b": {NO_OBJECT: 1}}
    lower = precision_recall_at(predictions, truth, ["a", "b"], score_threshold=0.5)
    assert (lower.true_positives, lower.false_positives, lower.false_negatives) == (2, 1, 1)


def test_the_confusion_names_the_class_a_false_box_was_given_and_the_true_one():
    predictions = [
        _dets(
            [[0, 0, 10, 10], [0, 0, 10, 11], [20, 20, 30, 30], [60, 60, 70, 70]], [0.99, 0.9, 0.95, 0.85], [0, 0, 0, 1]
        )
    ]
    truth = [_truth([[0, 0, 10, 10], [20, 20, 30, 30]], [0, 1])]
    result = precision_recall_at(predictions, truth, ["a", "b"])
    # a second "a" on the found a; an "a" on the b; a "b" on nothing; the b itself missed
    assert result.confusion == {"a": {"a": 1, "b": 1}, "b": {NO_OBJECT: 1}}
    assert (result.true_positives, result.false_positives, result.false_negatives) == (1, 3, 1)
    assert result.per_class["b"]["recall"] == 0.0


def test_worst_images_rank_by_errors_and_undefined_ratios_are_nan():
    predictions = [
        _dets([], [], []),
        _dets([[0, 0, 5, 5], [9, 9, 12, 12]], [0.9, 0.9], [0, 0]),
        _dets([[0, 0, 5, 5]], [0.9], [0]),
    ]
    truth = [_truth([[0, 0, 5, 5]], [0]), _truth([], []), _truth([[0, 0, 5, 5]], [0])]
    result = precision_recall_at(predictions, truth, ["a"])
    assert [(item.index, item.errors) for item in result.worst_images(5)] == [(1, 2), (0, 1)]
    assert result.worst_images(1)[0].false_positives == 2
    nothing = precision_recall_at([_dets([], [], [])], [_truth([], [])], ["a"])
    assert math.isnan(nothing.precision) and math.isnan(nothing.recall)
    assert nothing.to_dict()["precision"] is None
    with pytest.raises(ValueError, match="same images"):
        precision_recall_at([], [_truth([], [])], ["a"])


def test_true_detections_flags_each_box_in_its_own_order_by_the_maps_matching():
    """The mAP's matching, per detection: the better-scored of two boxes on one object is true,
    the other a duplicate; a box of another class, or too loose, is false; the flags come back
    in the prediction's order, not the score order."""
    from workers.train.evaluation import true_detections

    truth = {"boxes": np.array([[0, 0, 10, 10], [20, 20, 30, 30]], np.float32), "labels": np.array([0, 1])}
    prediction = {
        "boxes": np.array([[0, 0, 10, 9], [0, 0, 10, 10], [20, 20, 30, 30], [20, 20, 40, 40]], np.float32),
        "scores": np.array([0.6, 0.9, 0.8, 0.95], np.float32),
        "labels": np.array([0, 0, 0, 1]),
    }
    assert true_detections(prediction, truth, 0.5).tolist() == [False, True, False, False]
    empty = {"boxes": np.zeros((0, 4), np.float32), "scores": np.zeros(0, np.float32), "labels": np.zeros(0, np.int64)}
    assert true_detections(empty, truth).tolist() == []
    assert (
        true_detections(prediction, {"boxes": np.zeros((0, 4)), "labels": np.zeros(0, np.int64)}).tolist()
        == [False] * 4
    )
