"""Fit the detector's score calibration on one half of out-of-domain sets and report on the other.

Per COCO set (``--data``, any number): the network detects once at the cascade's first view and
once at every view (its detections without the texture check, kept in ``--cache`` so a second run
reads them back), the texture check measures the evidence of each detection the detector draws
(the first view's where the texture confirmed a box there, every view's elsewhere, as
``detect_object``'s cascade does), and each detection is labelled true or false against the set's boxes
(``workers.train.evaluation.true_detections``, the mAP's matching). The images are split by index: even ones
fit the calibration (``workers/train/calibration.fit``), odd ones report it, so no score below
is measured on images the fit saw. Reported side by side on the odd half of each set, under the
paper's protocol and as a user drawing boxes at 0.8 sees it:

- ``tiers``: the texture check's fixed tiers (no calibration);
- ``confirmed_only``: the tiers with every box the texture did not confirm below the cut;
- ``calibrated``: the fitted calibration;
- ``keypoint_baseline``: bench/keypoint_baseline.py.

    python bench/calibrate.py --model var/studies/S/ensemble.pt --data var/bench/docs-ood \\
        --data var/bench/docs-hard --out bench/results/calibration.json [--write-model calibrated.pt]

``--write-model`` writes the model with the fitted calibration recorded in it
(``foldwise calibrate`` does the same for a user's own labelled photographs).
"""

from __future__ import annotations

import argparse
import hashlib
import pickle
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.report import machine, write_report  # noqa: E402
from bench.wild_scoring import _scores  # noqa: E402


def network_detections(detector, samples, classes, cache: Path | None, first_size: int | None) -> tuple[dict, float]:
    """The network's detections (no texture check) on ``samples``: ``{"first": ..., "every": ...}``,
    at the cascade's first view (at ``first_size``, upright; None where the detector runs no
    cascade) and at every view; read from ``cache`` when there. And the seconds the network took
    (0 when read back)."""
    from workers.train.evaluation import detector_predictions

    if cache is not None and cache.is_file():
        with open(cache, "rb") as handle:
            return pickle.load(handle), 0.0
    started = time.perf_counter()
    predictions = {"first": None}
    if first_size is not None:
        predictions["first"], *_ = detector_predictions(
            detector, samples, classes, texture_check=False, test_sizes=(first_size,), test_turns=()
        )
    predictions["every"], *_ = detector_predictions(detector, samples, classes, texture_check=False)
    seconds = time.perf_counter() - started
    if cache is not None:
        cache.parent.mkdir(parents=True, exist_ok=True)
        with open(cache, "wb") as handle:
            pickle.dump(predictions, handle)
    return predictions, seconds


def cascaded(check, image, network: dict, index: int, cascade, matches) -> dict:
    """Image ``index``'s detections as the detector draws them, with their evidence: the first
    view's, checked, unless ``cascade`` (None: none) sends the image on to every view's."""
    return cascade_pass(check, image, network, index, cascade, matches)[0]


def cascade_pass(check, image, network: dict, index: int, cascade, matches) -> tuple[dict, bool]:
    """``cascaded``'s detections, and whether the cascade sent the image on to every view."""
    if cascade is not None:
        checked = check.apply(image, network["first"][index], with_evidence=True, matches=matches)
        if not cascade.again(checked):
            return checked, False
    return check.apply(image, network["every"][index], with_evidence=True, matches=matches), cascade is not None


def _confirmed_only(checked: dict) -> dict:
    """The tiers with every box the texture did not confirm moved below the 0.8 cut (its order kept)."""
    scores = np.where(checked["confirmed"], checked["scores"], 0.75 * checked["scores"]).astype(np.float32)
    return {**checked, "scores": scores}


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--model", type=Path, required=True, action="append", help="a checkpoint or ensemble; again: joined"
    )
    parser.add_argument("--data", type=Path, required=True, action="append", help="a COCO folder (out-of-domain set)")
    parser.add_argument("--cache", type=Path, default=ROOT / "var/bench/calibration-cache")
    parser.add_argument(
        "--lookalikes",
        type=Path,
        default=None,
        help="a folder of lookalike sheets given to the texture check (foldwise lookalikes): its matches on them are no evidence",
    )
    parser.add_argument("--threshold", type=float, default=0.8)
    parser.add_argument("--iou", type=float, default=0.5)
    parser.add_argument("--out", type=Path)
    parser.add_argument("--write-model", type=Path, help="write the model with the fitted calibration recorded in it")
    parser.add_argument(
        "--ship",
        action="store_true",
        help="write the fitted calibration as the one foldwise ships (workers/train/calibration.json, detector.calibration: shipped)",
    )
    args = parser.parse_args(argv)

    from bench.keypoint_baseline import KeypointBaseline
    from workers.train.calibration import fit
    from workers.train.checkpoint import combine_detectors, load_detector
    from workers.train.data import load_coco_dataset, read_image_rgb
    from workers.train.evaluation import true_detections
    from workers.train.texture_check import TextureCheck

    detector = combine_detectors([load_detector(path, device="cpu") for path in args.model])
    config = detector.config
    classes = detector.classes
    given = None
    if args.lookalikes is not None:
        from foldwise.asset_check import image_files
        from workers.train.data import read_image_rgb as read_sheet

        given = {path.stem: read_sheet(path) for path in image_files(args.lookalikes, "lookalikes")}
    check = TextureCheck(detector.textures, classes, search=config.texture_search, lookalikes=given)
    cascade = detector.active_cascade()  # as detect_object runs the detector's views
    first_size = cascade.first_size(detector.model.test_sizes) if cascade is not None else None
    baseline = KeypointBaseline(detector.textures, classes)
    # The models' paths name their detections in the cache: the same models, the same file, in any process.
    digest = hashlib.sha256("\n".join(str(path.resolve()) for path in args.model).encode()).hexdigest()[:12]
    key = "-".join(path.stem for path in args.model) + f"-{digest}"

    sets = []
    for data in args.data:
        samples, set_classes = load_coco_dataset(data)
        network, network_seconds = network_detections(
            detector, samples, set_classes, args.cache / f"{key}-{data.name}-{first_size}.pkl", first_size
        )
        to_model = np.array([classes.index(name) for name in set_classes], np.int64)
        truth = [{"boxes": s.boxes, "labels": to_model[np.asarray(s.labels, np.int64)]} for s in samples]
        groups = [{"condition": s.condition, "difficulty": s.difficulty} for s in samples]
        images = [read_image_rgb(s.image_path) for s in samples]
        started = time.perf_counter()
        matches = [check.matches(image) for image in images]
        checked = [cascaded(check, image, network, i, cascade, matches[i]) for i, image in enumerate(images)]
        check_seconds = time.perf_counter() - started
        sets.append((data, samples, truth, groups, images, network, matches, checked, network_seconds, check_seconds))

    # Fit on the even images of every set.
    features, labels = [], []
    for _data, _samples, truth, _groups, _images, _network, _matches, checked, *_ in sets:
        for index in range(0, len(truth), 2):
            features.append(checked[index]["evidence"])
            labels.append(true_detections(checked[index], truth[index], args.iou))
    calibration = fit(
        np.concatenate(features),
        np.concatenate(labels),
        fitted_on=", ".join(str(d) for d in args.data) + " (even images)",
    )
    calibrated_check = TextureCheck(
        detector.textures, classes, search=config.texture_search, calibration=calibration, lookalikes=given
    )

    report: dict = {
        "models": [str(p) for p in args.model],
        "lookalikes": sorted(given) if given else None,
        "calibration": calibration.to_dict(),
        "cascade": first_size is not None,
        "sets": {},
    }
    for data, samples, truth, groups, images, network, matches, checked, network_seconds, check_seconds in sets:
        odd = list(range(1, len(samples), 2))
        pick = lambda items: [items[i] for i in odd]  # noqa: E731
        calibrated = [cascaded(calibrated_check, images[i], network, i, cascade, matches[i]) for i in odd]
        started = time.perf_counter()
        keypoints = [baseline.detect(images[i]) for i in odd]
        baseline_seconds = time.perf_counter() - started
        per_image = (network_seconds + check_seconds) / max(len(samples), 1)
        report["sets"][data.name] = {
            "report_images": len(odd),
            "tiers": _scores(
                pick(checked), pick(truth), classes, pick(groups), args.threshold, args.iou, per_image * len(odd)
            ),
            "calibrated": _scores(
                calibrated, pick(truth), classes, pick(groups), args.threshold, args.iou, per_image * len(odd)
            ),
            "confirmed_only": _scores(
                [_confirmed_only(checked[i]) for i in odd],
                pick(truth),
                classes,
                pick(groups),
                args.threshold,
                args.iou,
                per_image * len(odd),
            ),
            "keypoint_baseline": _scores(
                keypoints, pick(truth), classes, pick(groups), args.threshold, args.iou, baseline_seconds
            ),
        }
    report["machine"] = machine()
    if args.ship:
        import json

        from workers.train.calibration import SHIPPED

        SHIPPED.write_text(json.dumps(calibration.to_dict(), indent=2) + "\n", encoding="utf-8")
        report["shipped"] = str(SHIPPED.relative_to(ROOT))
    if args.write_model:
        from workers.train.checkpoint import save_ensemble, write_calibration

        source = args.model[0]
        if len(args.model) > 1:
            source = save_ensemble(args.model, args.write_model)
        write_calibration(source, calibration, args.write_model)
        report["written_model"] = str(args.write_model)
    return write_report(report, args.out)


if __name__ == "__main__":
    main()
