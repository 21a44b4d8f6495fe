"""What the sheets a detector misses hold for its texture check (JSON out).

A texture check that followed bends better (more local maps, the sheet's developable model) could
only confirm sheets whose keypoints match their texture. For every true sheet of a COCO set this
measures what the check has to work with: the image's keypoints in the sheet's true box, those
that pass the ratio test against its class's texture, and whether the box check's maps confirm
the sheet when given its true box (the best a proposal could do), with the IoU of the outline
they draw. Beside that: whether the detector draws the sheet at the threshold (the cascade as
built, the paper's matching at IoU 0.5), whether the texture search alone finds it, and the best
IoU of any box of its class the detector returns. The report counts these for the drawn and the
missed sheets apart.

    python bench/wild.py --sets-only --n-ood-hard 60       # renders var/bench/wild-ood-hard
    python bench/missed_sheets.py --model var/studies/quick-members-*/ensemble.pt \\
        --data var/bench/wild-ood-hard --out bench/results/missed_sheets.json
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.report import machine, write_report  # noqa: E402

# Fewer class matches than this in a true box: no map can confirm the sheet (the check's first
# map needs texture_check.MIN_INLIERS agreeing matches).
FEW_MATCHES = 6


def sheets(model: Path, data: Path, threshold: float, iou: float) -> list[dict]:
    """One row per true sheet of ``data`` (see the module's docstring)."""
    import torch
    from torchvision.ops import box_iou

    from workers.train.checkpoint import detect_object, load_detector
    from workers.train.data import load_coco_dataset, read_image_rgb
    from workers.train.texture_check import _inside

    detector = load_detector(model)
    check = detector.texture_check()
    if check is None:
        raise SystemExit(f"{model}: the detector has no texture check to measure")
    samples, classes = load_coco_dataset(data)
    unknown = sorted(set(classes) - set(detector.classes))
    if unknown:
        raise SystemExit(f"{data}: classes {unknown} are none of the detector's {detector.classes}")
    nothing = {
        "boxes": np.zeros((0, 4), np.float32),
        "scores": np.zeros(0, np.float32),
        "labels": np.zeros(0, np.int64),
    }
    rows = []
    for sample in samples:
        image = read_image_rgb(sample.image_path)
        height, width = image.shape[:2]
        matches = check.matches(image)
        every, points, labels, texture_points = matches
        (found,) = detect_object(detector, [image])
        searched = check.apply(image, nothing, matches=matches) if check.search else nothing
        truth = np.asarray(sample.boxes, np.float32).reshape(-1, 4)
        for box, name in zip(truth, (classes[label] for label in sample.labels)):
            label = detector.classes.index(name)
            inside = _inside(points, box)
            in_box = every[_inside(every, box)]
            outline, inliers, _, _ = check._fit(
                points[inside], labels[inside], texture_points[inside], label, box, width, height, in_box
            )

            def overlaps(detections, drawn_only: bool = False) -> np.ndarray:
                keep = detections["labels"] == label
                if drawn_only:
                    keep &= detections["scores"] >= threshold
                boxes = torch.as_tensor(np.asarray(detections["boxes"], np.float32)[keep]).reshape(-1, 4)
                return box_iou(boxes, torch.as_tensor(box)[None]).numpy().ravel()

            fitted_iou = overlaps({"boxes": outline[None], "labels": np.array([label])}) if outline is not None else []
            rows.append(
                {
                    "image": sample.image_path.name,
                    "class": name,
                    "side_px": round(float(np.sqrt((box[2] - box[0]) * (box[3] - box[1]))), 1),
                    "keypoints": len(in_box),
                    "class_matches": int((inside & (labels == label)).sum()),
                    "fits_given_true_box": outline is not None,
                    "fit_inliers": int(inliers),
                    "fit_outline_iou": round(float(fitted_iou[0]), 3) if len(fitted_iou) else None,
                    "drawn": bool((overlaps(found, drawn_only=True) >= iou).any()),
                    "found_by_search": bool((overlaps(searched) >= iou).any()),
                    "best_iou_of_its_class": round(float(overlaps(found).max(initial=0.0)), 3),
                }
            )
    return rows


def summary(rows: list[dict], iou: float) -> dict:
    """The drawn and the missed sheets, counted apart."""

    def median(values):
        return statistics.median(values) if values else None

    groups = {}
    for name, group in (("drawn", [r for r in rows if r["drawn"]]), ("missed", [r for r in rows if not r["drawn"]])):
        fitted = [r for r in group if r["fits_given_true_box"]]
        groups[name] = {
            "sheets": len(group),
            "median_side_px": median([r["side_px"] for r in group]),
            "median_keypoints": median([r["keypoints"] for r in group]),
            "median_class_matches": median([r["class_matches"] for r in group]),
            "under_few_matches": sum(r["class_matches"] < FEW_MATCHES for r in group),
            "fit_given_true_box": len(fitted),
            "fit_outline_at_iou": sum(r["fit_outline_iou"] >= iou for r in fitted),
            "found_by_search": sum(r["found_by_search"] for r in group),
            "a_box_of_its_class_at_iou": sum(r["best_iou_of_its_class"] >= iou for r in group),
        }
    return groups


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", type=Path, required=True, help="a checkpoint or ensemble with a texture check")
    parser.add_argument("--data", type=Path, default=ROOT / "var/bench/wild-ood-hard", help="a COCO folder of sheets")
    parser.add_argument("--threshold", type=float, default=0.8, help="the score a drawn box needs")
    parser.add_argument("--iou", type=float, default=0.5, help="the IoU a box needs to count as the sheet's")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args(argv)
    if not args.model.is_file():
        raise SystemExit(f"{args.model}: no such checkpoint")
    if not (args.data / "annotations.json").is_file():
        raise SystemExit(f"{args.data}: no annotations.json (render it with: python bench/wild.py --sets-only)")
    rows = sheets(args.model, args.data, args.threshold, args.iou)
    groups = summary(rows, args.iou)
    missed = groups["missed"]
    report = {
        "model": str(args.model),
        "data": str(args.data),
        "threshold": args.threshold,
        "iou": args.iou,
        "few_matches": FEW_MATCHES,
        "groups": groups,
        "headline": (
            f"{groups['drawn']['sheets']} of {len(rows)} true sheets drawn at {args.threshold}; of the "
            f"{missed['sheets']} missed, {missed['under_few_matches']} hold under {FEW_MATCHES} matches of their "
            f"texture, {missed['fit_given_true_box']} fit a map given their true box "
            f"({missed['fit_outline_at_iou']} of those outlines at IoU {args.iou})"
        ),
        "sheets": rows,
        "machine": machine(),
    }
    return write_report(report, args.out)


if __name__ == "__main__":
    main()
