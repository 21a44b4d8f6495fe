"""Detection's speed against its accuracy: a model's views (input sizes, quarter turns) and
members cut down, side by side on one set, beside the keypoint recipe (JSON out).

Each row detects every image of ``--data`` (a COCO folder: ``bench/wild.py --sets-only`` renders
them) with the model's texture check, and reports seconds per image (network and check, images
read beforehand), the paper's mAP, and precision and recall at the threshold. Rows:

- ``as built``: the model's own views (``make run``'s ensemble: 5 sizes × 4 turns × 2 members);
- ``upright``: its sizes, no turns;
- ``one size``: 320 px (or ``--one-size``), no turns;
- ``one member``: the ensemble's first member at its own views;
- ``keypoints``: bench/keypoint_baseline.py.

    python bench/detect_speed.py --model var/studies/S/ensemble.pt --data var/bench/wild-ood-apart \\
        --out bench/results/detect_speed.json
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.report import machine, write_report  # noqa: E402
from bench.wild_scoring import _scores  # noqa: E402


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", type=Path, required=True)
    parser.add_argument("--data", type=Path, required=True, help="a COCO folder")
    parser.add_argument("--one-size", type=int, default=320)
    parser.add_argument("--threshold", type=float, default=0.8)
    parser.add_argument("--iou", type=float, default=0.5)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args(argv)

    from bench.keypoint_baseline import KeypointBaseline
    from workers.train.checkpoint import Detector, detect_object, load_detector
    from workers.train.data import load_coco_dataset, read_image_rgb

    detector = load_detector(args.model, device="cpu")
    samples, set_classes = load_coco_dataset(args.data)
    classes = detector.classes
    to_model = np.array([classes.index(name) for name in set_classes], np.int64)
    truth = [{"boxes": s.boxes, "labels": to_model[np.asarray(s.labels, np.int64)]} for s in samples]
    groups = [{"condition": s.condition, "difficulty": s.difficulty} for s in samples]
    images = [read_image_rgb(s.image_path) for s in samples]
    # The ensemble's first member as a detector of its own: its network, meta and the shared textures.
    members = getattr(detector.model, "members", None)
    first = None
    if members is not None:
        first = Detector(
            model=members[0],
            meta=detector.meta["members"][0],
            device=detector.device,
            textures=detector.textures,
            lookalikes=detector.lookalikes,
        )
    rows = [
        ("as built", detector, None, None),
        ("upright", detector, None, (0,)),
        ("one size", detector, (args.one_size,), (0,)),
    ]
    if first is not None:
        rows.append(("one member", first, None, None))
    detector.texture_check()  # built (or read from the cache) before any row is timed
    report: dict = {"model": str(args.model), "data": str(args.data), "images": len(samples), "rows": {}}
    for name, which, sizes, turns in rows:
        started = time.perf_counter()
        found = detect_object(which, images, test_sizes=sizes, test_turns=turns)
        seconds = time.perf_counter() - started
        report["rows"][name] = _scores(found, truth, classes, groups, args.threshold, args.iou, seconds)
        report["rows"][name]["views"] = {"sizes": sizes or "the model's", "turns": turns or "the model's"}
    baseline = KeypointBaseline(detector.textures, classes)
    started = time.perf_counter()
    found = [baseline.detect(image) for image in images]
    report["rows"]["keypoints"] = _scores(
        found, truth, classes, groups, args.threshold, args.iou, time.perf_counter() - started
    )
    frame = f"{images[0].shape[1]}x{images[0].shape[0]}" if images else "-"
    report["headline"] = f"{args.data.name} ({len(samples)} images, {frame}): " + "; ".join(
        f"{name} {row['seconds_per_image']:.2f} s/image, mAP {row['map']:.3f}" for name, row in report["rows"].items()
    )
    report["machine"] = machine()
    return write_report(report, args.out)


if __name__ == "__main__":
    main()
