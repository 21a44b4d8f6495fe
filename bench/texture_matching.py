"""The texture check's matching side by side: brute force against FLANN's KD-trees, and the
image's sharpening before SIFT at other amounts (JSON out).

The check (workers/train/texture_check.py) matches each image's SIFT keypoints to the textures'
(56,329 of them for the five default textures and their tilted views). Brute force compares each
with every one; FLANN's randomized KD-trees (the check's default) look a few hundred up. Per COCO
set: the network detects once (its detections without the check), then each matcher checks the
same detections, timed, and both are scored under the paper's protocol, with the share of images
whose checked detections are the same. Each ``--sharpen AMOUNT`` adds the FLANN check with the
image's unsharp mask at that amount instead of the built ``SHARPEN_AMOUNT`` (0: none), on the
same detections.

Sets default to the four of ``bench/wild.py`` for configs/quick.yaml (render them first with
``python bench/wild.py --sets-only``):

    python bench/texture_matching.py --model var/studies/quick-members-0/ensemble.pt \\
        --out bench/results/texture_matching.json [--sharpen 0 --sharpen 1.5]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.report import machine, write_report  # noqa: E402  (light: the standard library)

DEFAULT_SETS = ("wild-in-domain-quick", "wild-ood", "wild-ood-b", "wild-ood-apart")
MATCHERS = {"brute_force": True, "flann": False}  # name: TextureCheck(exact=...)


def same_detections(first: dict, second: dict, tolerance_px: float = 0.5) -> bool:
    """Whether two checked outputs of one image hold the same boxes (within ``tolerance_px``),
    classes and confirmations, in the same order."""
    if len(first["boxes"]) != len(second["boxes"]):
        return False
    return bool(
        np.array_equal(first["labels"], second["labels"])
        and np.array_equal(first["confirmed"], second["confirmed"])
        and np.allclose(first["boxes"], second["boxes"], atol=tolerance_px)
    )


def compare_on_set(
    detector, data: Path, every: int, score_threshold: float, iou_threshold: float, sharpen: tuple[float, ...] = ()
) -> dict:
    """Both matchers on one COCO folder (every ``every``-th image), checking the same network
    detections; then FLANN with the image sharpened at each amount of ``sharpen``."""
    from workers.train.data import load_coco_dataset, read_image_rgb
    from workers.train.evaluation import detector_predictions, evaluate_predictions
    from workers.train.texture_check import SHARPEN_AMOUNT, TextureCheck

    samples, classes = load_coco_dataset(data)
    samples = samples[::every]
    started = time.perf_counter()
    network, truth, _groups, model_classes = detector_predictions(detector, samples, classes, texture_check=False)
    result: dict = {"dir": str(data), "images": len(samples), "network_seconds": time.perf_counter() - started}
    checked: dict[str, list[dict]] = {}
    variants = [(name, exact, SHARPEN_AMOUNT) for name, exact in MATCHERS.items()]
    variants += [(f"flann_sharpen_{amount:g}", False, amount) for amount in sharpen]
    for name, exact, amount in variants:
        started = time.perf_counter()
        check = TextureCheck(
            detector.textures, detector.classes, search=detector.config.texture_search, exact=exact, sharpen=amount
        )
        built = time.perf_counter() - started
        outputs, seconds = [], 0.0
        for sample, found in zip(samples, network):
            image = read_image_rgb(sample.image_path)
            started = time.perf_counter()
            outputs.append(check.apply(image, found))
            seconds += time.perf_counter() - started
        checked[name] = outputs
        scores = evaluate_predictions(
            outputs, truth, model_classes, score_threshold=score_threshold, iou_threshold=iou_threshold, coco=False
        ).to_dict()
        result[name] = {
            "build_seconds": built,
            "seconds_per_image": seconds / max(len(samples), 1),
            "map": scores["map"],
            "map_unthresholded": scores["map_unthresholded"],
            "confirmed": int(sum(int(output["confirmed"].sum()) for output in outputs)),
        }
    result["speedup"] = result["brute_force"]["seconds_per_image"] / max(result["flann"]["seconds_per_image"], 1e-12)
    result["images_same"] = (
        float(np.mean([same_detections(a, b) for a, b in zip(checked["brute_force"], checked["flann"])]))
        if samples
        else 1.0
    )
    return result


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--model",
        type=Path,
        action="append",
        required=True,
        help="a texture-checked checkpoint; given again, the checkpoints detect as one ensemble",
    )
    parser.add_argument(
        "--set",
        type=Path,
        action="append",
        dest="sets",
        help=f"a COCO folder to score on, again for more (default: var/bench/{{{','.join(DEFAULT_SETS)}}})",
    )
    parser.add_argument("--every", type=int, default=1, help="score every N-th image of each set (default: all)")
    parser.add_argument(
        "--sharpen",
        type=float,
        action="append",
        default=[],
        metavar="AMOUNT",
        help="also check with FLANN and the image's unsharp mask at AMOUNT (0: none); again for more",
    )
    parser.add_argument("--threshold", type=float, default=0.8)
    parser.add_argument("--iou", type=float, default=0.5)
    parser.add_argument("--out", type=Path)
    args = parser.parse_args(argv)
    if args.every < 1:
        parser.error(f"--every must be at least 1, got {args.every}")
    negative = [amount for amount in args.sharpen if not amount >= 0]
    if negative:
        parser.error(f"--sharpen must be at least 0 (0: no sharpening), got {negative[0]:g}")
    sets = args.sets or [ROOT / "var" / "bench" / name for name in DEFAULT_SETS]
    missing = [str(path) for path in sets if not (path / "annotations.json").is_file()]
    if missing:
        parser.error(
            f"no COCO set (annotations.json) at {', '.join(missing)}; render bench/wild.py's with: python bench/wild.py --sets-only"
        )

    from workers.train.checkpoint import combine_detectors, load_detector
    from workers.train.texture_check import SHARPEN_AMOUNT

    detector = combine_detectors([load_detector(path, device="cpu") for path in args.model])
    if not detector.textures:
        parser.error(f"{args.model[0]} carries no textures: train with detector.texture_check: true")
    report: dict = {
        "model": [str(path) for path in args.model],
        "protocol": {"score_threshold": args.threshold, "iou_threshold": args.iou},
        "every": args.every,
        "sharpen_built": SHARPEN_AMOUNT,
        "sets": {
            path.name: compare_on_set(detector, path, args.every, args.threshold, args.iou, tuple(args.sharpen))
            for path in sets
        },
    }
    report["machine"] = machine()
    return write_report(report, args.out)


if __name__ == "__main__":
    main()
