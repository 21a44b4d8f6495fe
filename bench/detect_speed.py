"""Detection's speed against its accuracy: the detector's ways of running its views side by side
on the same images, at 320×240 and 640×480, beside the keypoint recipe (JSON out).

Each row detects every image of each ``--data`` set (COCO folders: ``bench/wild.py --sets-only``
renders them) one image per call, as the REST detect route does (``--batch-size``), with the
model's texture check, and reports seconds per image (network and check, images read
beforehand), the paper's mAP, precision and recall at the threshold, and its time as a multiple
of the keypoint recipe's on the same images. Rows:

- ``every view alone``: the model's views (``make run``'s ensemble: 5 sizes × 4 turns × 2
  members), each member, view and image one R-CNN forward in torch, as the views ran before they
  were batched (40 forwards an image);
- ``every view together``: the same views and detections, run together in torch
  (``detect_at_views``: one trunk pass per view for both members, the turns of one shape in one
  batch);
- ``every view, onnxruntime``: the same views through the checkpoint's runtime graph
  (``workers/train/export.py``; the bench writes it beside the model where it is missing, and
  reports the seconds opening it took, once, as ``runtime_graph_open_seconds``);
- ``cascade``: the detector as built (``checkpoint.Cascade``): one view and the check first,
  every view (through the runtime graph) only for the images that leave a box unsure;
  ``second_pass`` is the share of images that went on;
- ``cascade, torch``: the same with the views in torch (no runtime graph);
- ``cascade, every name drawn``: the cascade, with a sheet the texture did not confirm drawn under
  each class the network names it (``TextureCheck.every_name``) instead of once;
- ``cascade, unmatched drawn``: the cascade, with a box whose many keypoints match nothing of its
  texture left over the cut (``TextureCheck.unmatched_drawn``) instead of dropped under it;
- ``one view``: the cascade's first pass alone (the largest size, upright, both members);
- ``keypoints``: bench/keypoint_baseline.py.

``--rows`` names the rows to run, separated by ``;`` (default: all).

Beside the rows, each set's ``check_keypoints_seconds_per_image``: the texture check's keypoints
and matches alone (every row but the recipe's finds them once an image).

    python bench/detect_speed.py --model var/studies/S/ensemble.pt \\
        --data var/bench/wild-ood-apart var/bench/wild-ood-large --out bench/results/detect_speed.json
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

ROWS = (
    "every view alone",
    "every view together",
    "every view, onnxruntime",
    "cascade",
    "cascade, torch",
    "cascade, every name drawn",
    "cascade, unmatched drawn",
    "one view",
    "keypoints",
)


def views_alone(detector, images: list[np.ndarray]) -> list[dict[str, np.ndarray]]:
    """The detector's views the plain way: every member, view and image one eval forward of its
    own (torchvision's), boxes turned back, each member's views merged, then the members, then the
    texture check: the detections ``detect_object`` gives, at one forward per view."""
    import torch
    from torchvision.models.detection.generalized_rcnn import GeneralizedRCNN

    from workers.train.checkpoint import _found, torch_threads
    from workers.train.detectors.views import merge_detections, turn_image, unturn_boxes

    model = detector.model
    members = list(getattr(model, "members", [model]))
    checker = detector.texture_check()
    threads = int(detector.meta.get("config", {}).get("num_threads", 0))
    results = []
    with torch.no_grad(), torch_threads(threads):
        for array in images:
            image = torch.from_numpy(array).permute(2, 0, 1).float().div_(255)
            runs = []
            for member in members:
                saved = member.transform.min_size, member.transform.max_size
                views = []
                try:
                    for turn in member.test_turns or (0,):
                        for size in member.test_sizes or (None,):
                            if size is not None:
                                member.transform.min_size, member.transform.max_size = (size,), size
                            (output,) = GeneralizedRCNN.forward(member, [turn_image(image, turn)])
                            views.append({**output, "boxes": unturn_boxes(output["boxes"], turn, *image.shape[-2:])})
                finally:
                    member.transform.min_size, member.transform.max_size = saved
                heads = member.roi_heads
                runs.append(merge_detections(views, heads.nms_thresh, heads.detections_per_img, member.view_vote))
            merged = runs[0] if len(runs) == 1 else merge_detections(runs, model.iou, model.limit, model.vote)
            found = _found(merged)
            results.append(checker.apply(array, found) if checker is not None else found)
    return results


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", type=Path, required=True)
    parser.add_argument("--data", type=Path, nargs="+", required=True, help="COCO folders")
    parser.add_argument("--batch-size", type=int, default=1, help="images per detect_object call")
    parser.add_argument("--threshold", type=float, default=0.8)
    parser.add_argument("--iou", type=float, default=0.5)
    parser.add_argument("--out", type=Path)
    parser.add_argument(
        "--rows",
        type=lambda text: [name.strip() for name in text.split(";")],
        default=list(ROWS),
        help=f"rows to run, separated by ';' (their names hold commas; default: all of {'; '.join(ROWS)})",
    )
    args = parser.parse_args(argv)
    unknown = [name for name in args.rows if name not in ROWS]
    if unknown:
        parser.error(f"--rows: no row {unknown}; the rows are {'; '.join(ROWS)}")

    from dataclasses import asdict

    from bench.keypoint_baseline import KeypointBaseline
    from workers.train.checkpoint import Cascade, detect_object, load_detector
    from workers.train.data import load_coco_dataset, read_image_rgb
    from workers.train.export import runtime_graph_path, write_runtime_graph

    def opened():
        """The detector with its runtime graph opened, before any row is timed, and the seconds that took."""
        detector = load_detector(args.model, device="cpu")
        started = time.perf_counter()
        runtime = detector.runtime
        return detector, runtime, time.perf_counter() - started

    detector, runtime, runtime_open_seconds = opened()
    if runtime is None:  # none, or stale: make run hands over a matching one
        write_runtime_graph(args.model, detector)
        detector, runtime, runtime_open_seconds = opened()
    cascade = detector.cascade or Cascade()
    went_on: list[bool] = []

    class Counted(Cascade):
        """The cascade's rule, each answer kept (the share of images that go on to every view)."""

        def again(self, checked) -> bool:
            went_on.append(super().again(checked))
            return went_on[-1]

    classes = detector.classes
    model = detector.model
    detector.texture_check()  # built (or read from the cache) before any row is timed
    report: dict = {
        "model": str(args.model),
        "views": {"sizes": list(model.test_sizes), "turns": list(model.test_turns)},
        "members": len(getattr(model, "members", [model])),
        "cascade": asdict(cascade),
        "runtime_graph": str(runtime_graph_path(args.model)),
        "runtime_graph_open_seconds": runtime_open_seconds,
        "batch_size": args.batch_size,
        "sets": {},
    }
    first_size = cascade.first_size(model.test_sizes)
    headline = []
    for data in args.data:
        samples, set_classes = load_coco_dataset(data)
        to_model = np.array([classes.index(name) for name in set_classes], np.int64)
        truth = [{"boxes": s.boxes, "labels": to_model[np.asarray(s.labels, np.int64)]} for s in samples]
        groups = [{"condition": s.condition, "difficulty": s.difficulty} for s in samples]
        images = [read_image_rgb(s.image_path) for s in samples]
        frame = f"{images[0].shape[1]}x{images[0].shape[0]}" if images else "-"
        rows = {}

        def row(name, detect):
            if name not in args.rows:
                return
            started = time.perf_counter()
            found = detect()
            seconds = time.perf_counter() - started
            rows[name] = _scores(found, truth, classes, groups, args.threshold, args.iou, seconds)

        def in_torch(detect):
            """``detect`` run with the detector's views in torch (its runtime graph set aside)."""
            detector.runtime = None
            try:
                return detect()
            finally:
                detector.runtime = runtime

        def every_view():
            return detect_object(detector, images, batch_size=args.batch_size, every_view=True)

        def cascaded():
            return detect_object(detector, images, batch_size=args.batch_size)

        # Warm: the first calls of torch and onnxruntime allocate.
        detect_object(detector, images[:1], test_sizes=(first_size,), test_turns=())
        detect_object(detector, images[:1], every_view=True)
        row("every view alone", lambda: views_alone(detector, images))
        row("every view together", lambda: in_torch(every_view))
        row("every view, onnxruntime", every_view)
        detector.cascade = Counted(**asdict(cascade))
        went_on.clear()
        row("cascade", cascaded)
        if "cascade" in rows:
            rows["cascade"]["second_pass"] = float(np.mean(went_on)) if went_on else 0.0
        row("cascade, torch", lambda: in_torch(cascaded))
        checker = detector.texture_check()
        for switch, name in (
            ("every_name", "cascade, every name drawn"),
            ("unmatched_drawn", "cascade, unmatched drawn"),
        ):
            setattr(checker, switch, True)
            row(name, cascaded)
            setattr(checker, switch, False)
        detector.cascade = cascade
        row(
            "one view",
            lambda: detect_object(
                detector, images, batch_size=args.batch_size, test_sizes=(first_size,), test_turns=()
            ),
        )
        baseline = KeypointBaseline(detector.textures, classes)
        row("keypoints", lambda: [baseline.detect(image) for image in images])
        if "keypoints" in rows:
            keypoint_seconds = rows["keypoints"]["seconds_per_image"]
            for values in rows.values():
                values["times_keypoints"] = values["seconds_per_image"] / keypoint_seconds
        # What every row but the recipe's spends before any box is checked: the texture check's
        # keypoints of the image and their matches (SIFT on the image enlarged, FLANN).
        check = detector.texture_check()
        started = time.perf_counter()
        for image in images:
            check.matches(image)
        matching = (time.perf_counter() - started) / max(len(images), 1)
        report["sets"][data.name] = {
            "data": str(data),
            "frame": frame,
            "images": len(samples),
            "check_keypoints_seconds_per_image": matching,
            "rows": rows,
        }
        headline.append(
            f"{data.name} ({len(samples)} images, {frame}): "
            + "; ".join(
                f"{name} {values['seconds_per_image']:.2f} s/image, mAP {values['map']:.3f}"
                for name, values in rows.items()
            )
        )
    report["headline"] = " · ".join(headline)
    report["machine"] = machine()
    return write_report(report, args.out)


if __name__ == "__main__":
    main()
