"""Detector families side by side: training and inference speed, and mAP after a fixed budget or to a target.

Two modes, each printing one JSON document (also written to ``--out``):

* fixed budget (default): per family (faster_rcnn, fast_rcnn, yolo), train ``--iterations`` on
  ``--train-size`` rendered canonical images (the R-CNN families start as configs/quick.yaml's
  detector does, on its frozen COCO backbone, detecting at its input size alone; yolo, which has
  no COCO start, from random weights), then report training
  images/s (Fast R-CNN's Edge Boxes proposals are computed once per training image and cached,
  so they are not in it), inference images/s (``detect_object`` over the decoded test images,
  proposals included, timed on a second pass; the first pass's rate, which on a GPU carries
  one-off costs per batch shape, is reported beside it) and the mAP reached on a fixed
  canonical test set of ``--test-size`` images;
* target (``--target-map 0.9 --time-budget 1800 --test-size 150``): per family, train from the
  same start in chunks of ``--eval-every`` iterations (each chunk warm-starts from the last
  checkpoint, as an increment of Algorithm 1 does), evaluate after each chunk on the held-out
  canonical set, stop when mAP@0.5 under the paper's protocol (score ≥ 0.8) reaches the target or
  the time budget (training + evaluation, rendering excluded) is spent; report the iterations and
  seconds it took, or where it got.

Families run one after another, never in parallel. Images are rendered with the raster backend
(``generate_parameters(..., "canonical")`` + ``render_with_resample``) and cached as dataset
folders under ``bench/results/cache/`` (git-ignored), in ``foldwise render``'s COCO layout.

    python bench/train.py --iterations 25 --threads 2 --out bench/results/train_fixed.json
    python bench/train.py --families faster_rcnn --compare-roi-align --out bench/results/train_roi_align.json
    python bench/train.py --target-map 0.9 --time-budget 1800 --test-size 150 --eval-every 50 \
        --out bench/results/train_target.json
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import os
import sys
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.report import machine  # noqa: E402
from workers.train.evaluation import json_safe  # noqa: E402

RESULTS = REPO / "bench" / "results"
FAMILIES = ("faster_rcnn", "fast_rcnn", "yolo")
RCNN_FAMILIES = ("faster_rcnn", "fast_rcnn")
# Different seeds keep the training and test θ disjoint.
TRAIN_SEED, TEST_SEED = 1001, 2002
# Warm-up iterations of every chunk after the first in target mode.
RESTART_WARMUP = 10


def quick_settings() -> dict[str, Any]:
    """Input size and detector settings of configs/quick.yaml when it exists, else the defaults."""
    from foldwise.config import DetectorConfig, load_config

    path = REPO / "configs" / "quick.yaml"
    if path.is_file():
        config = load_config(path)
        # One view: the families compare at one inference each (quick.yaml's test_sizes and
        # test_turns multiply the R-CNNs' inference cost by the pixels of its sizes and by its
        # turns; bench/README.md), and yolo reads neither. The networks alone: the texture check
        # (which also needs the textures, not rendered here) is timed by texture_matching.py.
        detector = config.detector.model_copy(
            update={
                "test_sizes": (),
                "test_turns": (),
                "view_vote": None,
                "texture_check": False,
                "texture_search": False,
            }
        )
        return {"detector": detector, "image_size": config.render.image_size, "source": str(path.relative_to(REPO))}
    return {
        "detector": DetectorConfig(),
        "image_size": 128,
        "source": "DetectorConfig defaults (no configs/quick.yaml)",
    }


def render_canonical_set(name: str, n: int, seed: int, image_size: int) -> Path:
    """A cached dataset folder of n canonical images (COCO JSON as `foldwise render` writes it)."""
    folder = RESULTS / "cache" / f"{name}-canonical-n{n}-s{seed}-px{image_size}"
    annotations_path = folder / "annotations.json"
    if annotations_path.is_file():  # before the renderer's imports: a GPU machine may lack them
        return folder
    import cv2

    from foldwise.sampling import generate_parameters
    from workers.render.assets import load_assets
    from workers.render.pipeline import render_with_resample

    assets = load_assets()
    thetas = generate_parameters("fb", "canonical", n, seed, image_size=image_size, assets=assets)
    (folder / "images").mkdir(parents=True, exist_ok=True)
    images, annotations = [], []
    started = time.perf_counter()
    for index, theta in enumerate(thetas):
        result, rendered_theta, _reasons = render_with_resample(theta, backend="raster", assets=assets)
        file_name = f"images/{index:05d}.png"
        cv2.imwrite(str(folder / file_name), cv2.cvtColor(result.image, cv2.COLOR_RGB2BGR))
        height, width = result.image.shape[:2]
        x0, y0, x1, y1 = (float(v) for v in result.box)
        ax0, ay0, ax1, ay1 = (float(v) for v in result.amodal_box)
        images.append(
            {
                "id": index + 1,
                "file_name": file_name,
                "width": width,
                "height": height,
                "condition": rendered_theta.condition,
                "difficulty": rendered_theta.difficulty,
                "theta": rendered_theta.to_dict(),
            }
        )
        annotations.append(
            {
                "id": index + 1,
                "image_id": index + 1,
                "category_id": int(result.label) + 1,
                "bbox": [x0, y0, x1 - x0, y1 - y0],
                "area": (x1 - x0) * (y1 - y0),
                "iscrowd": 0,
                "amodal_bbox": [ax0, ay0, ax1 - ax0, ay1 - ay0],
                "visible_fraction": float(result.visible_fraction),
            }
        )
    categories = [{"id": k + 1, "name": asset.name} for k, asset in enumerate(assets.objects)]
    temporary = annotations_path.with_suffix(".tmp")
    temporary.write_text(json.dumps({"images": images, "annotations": annotations, "categories": categories}))
    temporary.replace(annotations_path)  # the cache is complete only once this file exists
    print(f"rendered {n} {name} images in {time.perf_counter() - started:.1f} s -> {folder}", file=sys.stderr)
    return folder


def family_config(base, family: str, input_size: int, threads: int, batch_size: int | None):
    from foldwise.config import DetectorConfig

    updates: dict[str, Any] = {"family": family, "input_size": input_size, "num_threads": threads}
    if family == "yolo":
        # yolo has no COCO start: it trains torchvision's MobileNetV3 from random weights.
        updates.update(backbone="mobilenet_v3_large", pretrained="none", trainable_backbone_stages=None)
    if batch_size:
        updates["batch_size"] = batch_size
    return DetectorConfig.model_validate({**base.model_dump(), **updates})


def score(checkpoint: Path, test_samples, classes, batch_size: int) -> dict[str, Any]:
    """The checkpoint's mAP on the test samples, and its inference speed (detect_object alone)."""
    from workers.train.checkpoint import detect_object, load_detector
    from workers.train.data import read_image_rgb
    from workers.train.evaluation import evaluate_predictions

    started = time.perf_counter()
    detector = load_detector(checkpoint)
    if list(detector.meta["classes"]) != list(classes):
        raise SystemExit(f"{checkpoint}: classes {detector.meta['classes']} differ from the test set's {classes}")
    # Arrays, not paths: from a path Fast R-CNN would reuse Edge Boxes proposals cached beside
    # the image by an earlier run; new images always pay for them. PNG decoding is left out.
    pictures = [read_image_rgb(sample.image_path) for sample in test_samples]
    loaded = time.perf_counter()
    # Two passes, the second timed as throughput. On a GPU the first pays one-off costs for every
    # new batch shape (CUDA's lazy kernel loading, cuDNN's choice of algorithm, the allocator's
    # growth; the last, shorter batch is a new shape): on an H100 the first pass ran YOLO at 34
    # images/s, the second at 945.
    detect_object(detector, pictures, batch_size=batch_size)
    first_pass = time.perf_counter()
    proposal_cache = getattr(detector.model, "proposal_cache", None)
    if proposal_cache is not None:  # Fast R-CNN: new images pay for their Edge Boxes, so the timed pass does too
        proposal_cache.clear()
    predictions = detect_object(detector, pictures, batch_size=batch_size)
    detected = time.perf_counter()
    result = evaluate_predictions(
        predictions,
        [{"boxes": sample.boxes, "labels": sample.labels} for sample in test_samples],
        classes,
        groups=[{"condition": sample.condition, "difficulty": sample.difficulty} for sample in test_samples],
    )
    return {
        "map": result.map,
        "map_unthresholded": result.map_unthresholded,
        "coco_ap50": result.coco.get("AP50"),
        "coco_ap": result.coco.get("AP"),
        "per_class": {name: item.ap for name, item in result.per_class.items()},
        "detections_kept": sum(item.num_detections_kept for item in result.per_class.values()),
        "true_positives": sum(item.true_positives for item in result.per_class.values()),
        "load_seconds": loaded - started,  # checkpoint and PNG decoding
        "first_pass_images_per_s": len(test_samples) / (first_pass - loaded) if first_pass > loaded else None,
        "inference_seconds": detected - first_pass,
        "inference_images_per_s": len(test_samples) / (detected - first_pass) if detected > first_pass else None,
        "eval_seconds": time.perf_counter() - started,
    }


def fixed_budget(args, base, input_size: int, train_samples, test_samples, classes, publish) -> dict[str, Any]:
    """Train each family for the same iterations; speed and the mAP it reaches.

    Training images/s comes from the difference of a 1-iteration and an N-iteration run, so the
    fixed costs inside train_detector (reading images, building the model, Edge Boxes proposals,
    saving the checkpoint) cancel out.
    """
    from workers.train.training import train_detector

    families = {}
    runs = []  # (family, report entry, on torchvision's RoIAlign kernel)
    for family in args.families:
        runs.append((family, family, False))
        if args.compare_roi_align and family in RCNN_FAMILIES:  # the same family again, right after it
            runs.append((family, f"{family}+torchvision_roi_align", True))
    for family, entry, torchvision_kernel in runs:
        config = family_config(base, family, input_size, args.threads, args.batch_size)
        checkpoint = RESULTS / "checkpoints" / f"fixed-{family}.pt"
        checkpoint.parent.mkdir(parents=True, exist_ok=True)
        print(f"[{entry}] warm-up iteration, then {args.iterations} iterations", file=sys.stderr)
        with torchvision_roi_align(torchvision_kernel):
            warmup = train_detector(train_samples, None, 1, config, classes, checkpoint, seed=args.seed)
            stats = train_detector(train_samples, None, args.iterations, config, classes, checkpoint, seed=args.seed)
        step_seconds = stats.seconds - warmup.seconds
        per_s = (
            (stats.images_seen - warmup.images_seen) / step_seconds
            if step_seconds > 0 and args.iterations > 1
            else None
        )
        scores = score(checkpoint, test_samples, classes, args.eval_batch_size)
        families[entry] = {
            "config": config.model_dump(mode="json"),
            "train": {k: v for k, v in stats.to_dict().items() if k != "losses"},
            "loss_first_last": [stats.losses[0], stats.final_loss] if getattr(stats, "losses", None) else None,
            "train_images_per_s": per_s,
            "fixed_train_overhead_s": warmup.seconds,
            **scores,
        }
        if torchvision_kernel and families[family]["train_images_per_s"] and per_s:
            families[entry]["pyramid_roi_align_train_speedup"] = families[family]["train_images_per_s"] / per_s
        summary = {
            k: families[entry].get(k)
            for k in (
                "train_images_per_s",
                "first_pass_images_per_s",
                "inference_images_per_s",
                "map",
                "map_unthresholded",
                "pyramid_roi_align_train_speedup",
            )
        }
        print(f"[{entry}] {json.dumps(json_safe(summary))}", file=sys.stderr)
        publish(families)
    return families


@contextlib.contextmanager
def torchvision_roi_align(active: bool):
    """Within it (when active), the R-CNNs' PyramidRoIAlign runs torchvision's kernel in training
    too: the baseline of ``--compare-roi-align``."""
    from torchvision.ops import MultiScaleRoIAlign

    from workers.train.detectors.roi_align import PyramidRoIAlign

    if not active:
        yield
        return
    own = PyramidRoIAlign.forward
    PyramidRoIAlign.forward = MultiScaleRoIAlign.forward
    try:
        yield
    finally:
        PyramidRoIAlign.forward = own


def target_summary(config, reached, iterations, seconds, train_seconds, images_seen, history) -> dict[str, Any]:
    best = max(history, key=lambda p: -1.0 if math.isnan(p["map"]) else p["map"])
    return {
        "config": config.model_dump(mode="json"),
        "reached": reached,
        "iterations": iterations,
        "seconds": seconds,
        "train_seconds": train_seconds,
        "train_images_per_s": images_seen / train_seconds if train_seconds > 0 else None,
        "final_map": history[-1]["map"],
        "best_map": best["map"],
        "best_at_iterations": best["iterations"],
        "history": history,
    }


def to_target(args, base, input_size: int, train_samples, test_samples, classes, publish) -> dict[str, Any]:
    from workers.train.training import train_detector

    families = {}
    for family in args.families:
        config = family_config(base, family, input_size, args.threads, args.batch_size)
        checkpoint = RESULTS / "checkpoints" / f"target-{family}.pt"
        checkpoint.parent.mkdir(parents=True, exist_ok=True)
        history, iterations, train_seconds, images_seen = [], 0, 0.0, 0
        started = time.perf_counter()
        reached = False
        chunk = 0
        while True:
            # Later chunks continue a warmed-up model: a short warm-up only re-builds momentum
            # (each chunk is one cosine cycle, so every evaluation sees an annealed snapshot).
            chunk_config = (
                config
                if not iterations
                else config.model_copy(update={"warmup_iterations": min(config.warmup_iterations, RESTART_WARMUP)})
            )
            stats = train_detector(
                train_samples,
                checkpoint if iterations else None,
                args.eval_every,
                chunk_config,
                classes,
                checkpoint,
                seed=args.seed + chunk,
            )
            chunk += 1
            iterations += stats.iterations
            train_seconds += stats.seconds
            images_seen += stats.images_seen
            scores = score(checkpoint, test_samples, classes, args.eval_batch_size)
            elapsed = time.perf_counter() - started
            point = {
                "iterations": iterations,
                "seconds": elapsed,
                "train_seconds": train_seconds,
                "final_loss": stats.final_loss,
                "nonfinite_steps": len(stats.nonfinite_steps),
                **{
                    k: scores[k]
                    for k in (
                        "map",
                        "map_unthresholded",
                        "coco_ap50",
                        "per_class",
                        "detections_kept",
                        "true_positives",
                        "eval_seconds",
                    )
                },
            }
            history.append(point)
            summary = {k: point[k] for k in ("iterations", "seconds", "map", "map_unthresholded", "final_loss")}
            print(f"[{family}] {json.dumps(json_safe(summary))}", file=sys.stderr)
            families[family] = target_summary(
                config, reached, iterations, time.perf_counter() - started, train_seconds, images_seen, history
            )
            publish(families)  # a run cut short still leaves every evaluation so far in --out
            current = scores["map"]
            if current is not None and not math.isnan(current) and current >= args.target_map:
                reached = True
                families[family]["reached"] = True
                publish(families)
                break
            if elapsed >= args.time_budget:
                break
    return families


RATES = ("train_images_per_s", "inference_images_per_s")


def compared(families: dict[str, Any], other: dict[str, Any]) -> dict[str, Any]:
    """Each family's rates over another machine's report of the same family (same settings)."""
    there = other.get("families", {})
    return {
        "machine": other.get("machine"),
        "settings": other.get("settings"),
        "ratios": {
            family: {
                rate: entry[rate] / there[family][rate]
                for rate in RATES
                if entry.get(rate) and there.get(family, {}).get(rate)
            }
            for family, entry in families.items()
        },
    }


def headline(report: dict[str, Any]) -> str:
    """One line: where it ran, and per family its rates and scores (and ratios to the compared run)."""
    where = report["machine"].get("gpu") or f"{report['machine'].get('cores')} CPU cores"
    parts = []
    for family, entry in report["families"].items():
        text = (
            f"{family} train {entry.get('train_images_per_s') or 0:.1f} img/s, "
            f"detect {entry.get('inference_images_per_s') or 0:.1f} img/s, "
            f"mAP {entry.get('map') or 0:.3f} (unthresholded {entry.get('map_unthresholded') or 0:.3f})"
        )
        ratios = report.get("compared_with", {}).get("ratios", {}).get(family)
        if ratios:
            text += " = " + ", ".join(f"{ratios[r]:.3g}x" for r in RATES if r in ratios) + " the compared run"
        parts.append(text)
    settings = report["settings"]
    budget = f"{settings['iterations']} iterations" if "iterations" in settings else "to a target"
    return f"{where}, {budget} on {settings['train_images']} canonical images: " + "; ".join(parts)


def main(argv: list[str] | None = None) -> dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--families", default=",".join(FAMILIES), help="comma-separated detector families")
    parser.add_argument("--iterations", type=int, default=200, help="fixed-budget mode: training iterations")
    parser.add_argument("--train-size", type=int, default=300, help="canonical training images")
    parser.add_argument("--test-size", type=int, default=150, help="canonical test images")
    parser.add_argument("--input-size", type=int, default=None, help="default: configs/quick.yaml's (128 px)")
    parser.add_argument(
        "--batch-size", type=int, default=None, help="training images per iteration (default: config's)"
    )
    parser.add_argument("--eval-batch-size", type=int, default=16)
    parser.add_argument("--threads", type=int, default=2, help="torch threads (the machine is shared)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--target-map", type=float, default=None, help="target mode: stop at this mAP (paper protocol)")
    parser.add_argument("--time-budget", type=float, default=1800.0, help="target mode: seconds per family")
    parser.add_argument("--eval-every", type=int, default=50, help="target mode: iterations between evaluations")
    parser.add_argument(
        "--compare-roi-align",
        action="store_true",
        help="fixed-budget mode: train each R-CNN again on torchvision's RoIAlign kernel and report the speed-up",
    )
    parser.add_argument(
        "--compare-with",
        type=Path,
        default=None,
        help="fixed-budget mode: a report of the same settings from another machine (a GPU's, say): "
        "each family's training and inference rates are also given as this run's over that one's",
    )
    parser.add_argument("--out", type=Path, default=None, help="also write the JSON here")
    args = parser.parse_args(argv)
    args.families = [f.strip() for f in args.families.split(",") if f.strip()]
    unknown = [f for f in args.families if f not in FAMILIES]
    if unknown:
        parser.error(f"unknown families {unknown}; known: {', '.join(FAMILIES)}")

    import torch

    torch.set_num_threads(args.threads)
    import torchvision  # noqa: F401  (imported up front: its import is not the first family's training time)

    from workers.train.data import load_coco_dataset
    from workers.train.detectors import fast_rcnn, faster_rcnn, yolo  # noqa: F401

    quick = quick_settings()
    base = quick["detector"]
    input_size = args.input_size or base.input_size
    image_size = quick["image_size"]
    train_dir = render_canonical_set("train", args.train_size, TRAIN_SEED, image_size)
    test_dir = render_canonical_set("test", args.test_size, TEST_SEED, image_size)
    train_samples, classes = load_coco_dataset(train_dir)
    test_samples, test_classes = load_coco_dataset(test_dir)
    if test_classes != classes:
        raise SystemExit(f"train and test sets disagree on classes: {classes} vs {test_classes}")

    mode = "target" if args.target_map is not None else "fixed_budget"
    runner = to_target if mode == "target" else fixed_budget
    report = {
        "bench": "train",
        "mode": mode,
        "settings": {
            "source": quick["source"],
            "input_size": input_size,
            "image_size": image_size,
            "train_images": len(train_samples),
            "test_images": len(test_samples),
            "classes": classes,
            "threads": args.threads,
            "seed": args.seed,
            **({"iterations": args.iterations} if mode == "fixed_budget" else {}),
            **(
                {"target_map": args.target_map, "time_budget_s": args.time_budget, "eval_every": args.eval_every}
                if mode == "target"
                else {}
            ),
            "score_threshold": 0.8,
            "iou_threshold": 0.5,
        },
        "machine": {
            **machine(),
            "torch": torch.__version__,
            "cuda": torch.cuda.is_available(),
            "gpu": torch.cuda.get_device_name(0) if torch.cuda.is_available() else None,
            "load_average_at_start": list(os.getloadavg()),
        },
        "families": {},
    }

    other = json.loads(args.compare_with.read_text()) if args.compare_with else None

    def publish(families: dict[str, Any]) -> str:
        report["families"] = families
        if other is not None:
            report["compared_with"] = compared(families, other)
        report["headline"] = headline(report)
        text = json.dumps(json_safe(report), indent=2, allow_nan=False)
        if args.out:
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text(text)
        return text

    families = runner(args, base, input_size, train_samples, test_samples, classes, publish)
    report["machine"]["load_average_at_end"] = list(os.getloadavg())
    print(publish(families))
    return report


if __name__ == "__main__":
    main()
