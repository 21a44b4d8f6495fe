"""``foldwise train``, ``evaluate``, ``detect``, ``export``: the train worker's commands.

Each command imports torch, OpenCV and the detectors inside its body, so that registering them
on the root ``foldwise`` app (``services/cli.py``) keeps ``foldwise --help`` light.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from enum import Enum
from pathlib import Path
from typing import Annotated, Any, NoReturn

import typer

from foldwise.progress import CommandProgress, command_console

# Off a terminal, a progress line at most this often (a line per step would flood a log).
PROGRESS_INTERVAL_S = 5.0


class Family(str, Enum):
    faster_rcnn = "faster_rcnn"
    fast_rcnn = "fast_rcnn"
    yolo = "yolo"


def _fail(message: str) -> NoReturn:
    typer.secho(f"error: {message}", fg=typer.colors.RED, err=True)
    raise typer.Exit(code=1)


def _parsed_option(option: str, text: str | None, parse: Callable[[str], Any]) -> Any:
    """``parse(text)``, None when the option was not given; a bad value fails naming the option."""
    if text is None:
        return None
    try:
        return parse(text)
    except ValueError as error:
        _fail(f"{option} {error}")


def _set_threads(threads: int) -> None:
    if threads > 0:
        import torch

        torch.set_num_threads(threads)


DATA_HELP = "A dataset folder (`foldwise render --out DIR`), a COCO JSON file, or a Pascal VOC folder."


def _load_samples(data: Path):
    """The dataset at ``data`` (a folder written by ``foldwise render``, a COCO JSON file or a
    Pascal VOC folder: ``load_dataset``), or a clear exit."""
    from workers.train.data import DatasetError, load_dataset

    if not data.exists():
        _fail(f"dataset {data} does not exist (no such folder or file)")
    try:
        samples, classes = load_dataset(data)
    except (DatasetError, KeyError, TypeError, ValueError) as error:
        detail = f"missing field {error}" if isinstance(error, KeyError) else str(error)
        _fail(f"cannot read dataset {data}: {detail}")
    if not samples:
        _fail(f"dataset {data} is empty: annotations.json lists no images")
    return samples, classes


def _load_model(path: Path, device: str | None = None):
    """A trained detector, or a clear exit for a missing or unreadable checkpoint."""
    from workers.train.checkpoint import load_detector

    if not path.is_file():
        _fail(f"checkpoint {path} does not exist")
    try:
        return load_detector(path, device=device)
    except Exception as error:  # torch.load and the model builders raise many kinds; all mean "unusable"
        _fail(f"cannot load checkpoint {path}: {type(error).__name__}: {error}")


def _fmt(value: Any, digits: int = 4) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "–"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


# --------------------------------------------------------------------------- train


def train(
    detector: Annotated[Family, typer.Option("--detector", help="Detector family.")],
    data: Annotated[Path, typer.Option("--data", help=DATA_HELP)],
    iterations: Annotated[int, typer.Option("--iterations", min=1, help="Training iterations (mini-batches).")],
    out: Annotated[Path, typer.Option("--out", help="Checkpoint to write.")],
    init: Annotated[
        Path | None, typer.Option("--init", help="Warm start from this checkpoint (ω_in); default: fresh weights.")
    ] = None,
    input_size: Annotated[
        int | None, typer.Option("--input-size", min=32, max=2048, help="Network input side, px.")
    ] = None,
    backbone: Annotated[str | None, typer.Option("--backbone", help="Backbone name (default: the config's).")] = None,
    seed: Annotated[int, typer.Option("--seed", help="Seed of weights init and batch order.")] = 0,
    config: Annotated[
        Path | None, typer.Option("--config", help="Experiment YAML whose `detector` section is the base settings.")
    ] = None,
    batch_size: Annotated[int | None, typer.Option("--batch-size", min=1, help="Images per iteration.")] = None,
    threads: Annotated[int, typer.Option("--threads", min=0, help="Torch CPU threads (0: torch decides).")] = 0,
) -> None:
    """Train a detector on a rendered dataset and write a self-describing checkpoint."""
    from foldwise.config import AssetsConfig, ConfigError, DetectorConfig, load_config

    base, assets = DetectorConfig(), AssetsConfig()
    if config is not None:
        try:
            loaded = load_config(config)
        except ConfigError as error:
            _fail(str(error))
        base, assets = loaded.detector, loaded.assets
    updates: dict[str, Any] = {"family": detector.value}
    for key, value in (("input_size", input_size), ("backbone", backbone), ("batch_size", batch_size)):
        if value is not None:
            updates[key] = value
    if threads:
        updates["num_threads"] = threads
    try:
        detector_config = DetectorConfig.model_validate({**base.model_dump(), **updates})
    except Exception as error:
        _fail(f"invalid detector settings: {error}")
    if init is not None and not init.is_file():
        _fail(f"--init checkpoint {init} does not exist")
    if init is None and detector_config.pretrained == "imagenet":
        from foldwise.weights import missing_imagenet_weights

        if problem := missing_imagenet_weights(detector_config.backbone):
            _fail(problem)  # before the dataset is read, not at the first training step
    samples, classes = _load_samples(data)
    if not any(len(sample.boxes) for sample in samples):
        _fail(f"dataset {data} has no annotated box: nothing to train on")
    textures = None
    if detector_config.texture_check and init is None:
        textures = _catalog_textures(assets, classes)
    _set_threads(threads)

    from workers.train.training import train_detector

    out.parent.mkdir(parents=True, exist_ok=True)
    typer.echo(
        f"training {detector.value} ({detector_config.backbone}, {detector_config.input_size} px) on "
        f"{len(samples)} images of {len(classes)} classes for {iterations} iterations"
    )
    try:
        progress = CommandProgress(command_console(), "training", iterations, "iterations", PROGRESS_INTERVAL_S)
        with progress as bar:
            stats = train_detector(
                samples, init=init, iterations=iterations, config=detector_config, classes=classes, out=out, seed=seed,
                on_step=lambda done: bar.update(done), textures=textures,
            )  # fmt: skip
    except Exception as error:
        _fail(f"training failed: {type(error).__name__}: {error}")
    throughput = stats.images_seen / stats.seconds if stats.seconds > 0 else float("nan")
    typer.echo(
        f"done: {stats.iterations} iterations in {stats.seconds:.1f} s on {stats.device}, "
        f"{throughput:.2f} images/s (set-up included), final loss {stats.final_loss:.4f}"
    )
    if stats.nonfinite_steps:
        typer.secho(f"{len(stats.nonfinite_steps)} non-finite loss steps were skipped", fg=typer.colors.YELLOW)
    typer.echo(f"checkpoint: {out}")


# --------------------------------------------------------------------------- evaluate


def _result_tables(result) -> list:
    from rich.table import Table

    threshold = f"score ≥ {result.score_threshold:g}"
    per_class = Table(
        title=f"Per class: VOC AP at IoU ≥ {result.iou_threshold:g}; paper protocol keeps detections with {threshold}",
        title_justify="left",
    )
    for column in ("class", "GT", "dets", "kept", "TP", "AP paper", "AP all", "COCO AP50"):
        per_class.add_column(column, justify="left" if column == "class" else "right", no_wrap=True)
    coco_per_class = result.coco.get("per_class", {}) if result.coco else {}
    for name, item in result.per_class.items():
        per_class.add_row(
            name,
            str(item.num_ground_truth),
            str(item.num_detections),
            str(item.num_detections_kept),
            str(item.true_positives),
            _fmt(item.ap),
            _fmt(item.ap_unthresholded),
            _fmt(coco_per_class.get(name, {}).get("AP50")),
        )
    per_class.add_section()
    per_class.add_row(
        "mAP",
        str(result.num_ground_truth),
        str(result.num_detections),
        "",
        "",
        _fmt(result.map),
        _fmt(result.map_unthresholded),
        _fmt(result.coco.get("AP50") if result.coco else None),
    )
    tables = [per_class]
    titles = {"condition": "Per condition", "difficulty": "Per difficulty", "condition/difficulty": "Per stage (c/δ)"}
    for field, groups in result.breakdown.items():
        if not groups:
            continue
        table = Table(title=titles.get(field, f"Per {field}"), title_justify="left")
        for column in (field, "images", "GT", "mAP paper", "mAP all"):
            table.add_column(column, justify="left" if column == field else "right", no_wrap=True)
        for value, group in groups.items():
            table.add_row(
                value,
                str(group.num_images),
                str(group.num_ground_truth),
                _fmt(group.map),
                _fmt(group.map_unthresholded),
            )
        tables.append(table)
    return tables


def evaluate(
    model: Annotated[Path, typer.Option("--model", help="Checkpoint written by `foldwise train`.")],
    data: Annotated[Path, typer.Option("--data", help=DATA_HELP)],
    json_out: Annotated[Path | None, typer.Option("--json", help="Also write the full result as JSON here.")] = None,
    score_threshold: Annotated[
        float, typer.Option("--threshold", min=0.0, max=1.0, help="The paper's confidence cut.")
    ] = 0.8,
    iou_threshold: Annotated[float, typer.Option("--iou", min=0.01, max=1.0, help="IoU for a match.")] = 0.5,
    batch_size: Annotated[int, typer.Option("--batch-size", min=1, help="Images per forward pass.")] = 16,
    device: Annotated[
        str | None, typer.Option("--device", help="cpu or cuda (default: the checkpoint's choice).")
    ] = None,
    threads: Annotated[int, typer.Option("--threads", min=0, help="Torch CPU threads (0: torch decides).")] = 0,
    report: Annotated[
        Path | None,
        typer.Option(
            "--report",
            help="Write a page to look at here: DIR/index.html with the worst images (most false boxes plus "
            "objects missed at --threshold), each a PNG with the true boxes and the detections drawn.",
        ),
    ] = None,
    worst: Annotated[int, typer.Option("--worst", min=1, max=500, help="Images in the --report.")] = 12,
) -> None:
    """Score a checkpoint on a dataset: VOC mAP (paper protocol and unthresholded), COCO metrics,
    precision and recall at the threshold and the confusion between classes."""
    import time

    samples, classes = _load_samples(data)
    _set_threads(threads)
    detector = _load_model(model, device)

    from workers.train.evaluation import detector_predictions, evaluate_predictions, precision_recall_at

    console = command_console()
    started = time.perf_counter()
    try:
        with CommandProgress(console, "evaluating", len(samples), "images", PROGRESS_INTERVAL_S) as bar:
            predictions, truth, groups, model_classes = detector_predictions(
                detector, samples, classes, batch_size=batch_size, on_batch=lambda done: bar.update(done)
            )
        result = evaluate_predictions(
            predictions,
            truth,
            model_classes,
            score_threshold=score_threshold,
            iou_threshold=iou_threshold,
            groups=groups,
        )
        at_threshold = precision_recall_at(predictions, truth, model_classes, score_threshold, iou_threshold)
    except ValueError as error:
        _fail(str(error))
    seconds = time.perf_counter() - started
    for table in _result_tables(result) + _threshold_tables(at_threshold):
        console.print(table)
    console.print(
        f"at score ≥ {score_threshold:g}, IoU ≥ {iou_threshold:g}: precision {_fmt(at_threshold.precision, 3)} "
        f"({at_threshold.true_positives} of {at_threshold.true_positives + at_threshold.false_positives} boxes right), "
        f"recall {_fmt(at_threshold.recall, 3)} ({at_threshold.true_positives} of "
        f"{at_threshold.true_positives + at_threshold.false_negatives} objects found)"
    )
    console.print(
        f"mAP (paper protocol: score ≥ {score_threshold:g}, IoU ≥ {iou_threshold:g}): {_fmt(result.map)}   "
        f"mAP (unthresholded): {_fmt(result.map_unthresholded)}   "
        f"COCO AP: {_fmt(result.coco.get('AP'))}   COCO AP50: {_fmt(result.coco.get('AP50'))}"
    )
    console.print(f"{len(samples)} images in {seconds:.1f} s ({len(samples) / max(seconds, 1e-9):.1f} images/s)")
    if result.num_ground_truth == 0:
        typer.secho("warning: the dataset has no annotated box; mAP is undefined", fg=typer.colors.YELLOW, err=True)
    if json_out is not None:
        payload = {
            "model": str(model), "data": str(data), "seconds": seconds, **result.to_dict(), "at_threshold": at_threshold.to_dict(),
        }  # fmt: skip
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(json.dumps(payload, indent=2, allow_nan=False))
        console.print(f"wrote {json_out}")
    if report is not None:
        try:
            page = write_report(
                report, samples, predictions, truth, at_threshold, worst, title=f"{model.name} on {data.name}"
            )
        except OSError as error:
            _fail(f"cannot write the report to {report}: {error}")
        console.print(f"report: {page}")


def _threshold_tables(result) -> list:
    """Precision and recall per class at the threshold, and the confusion of the false boxes."""
    from rich.table import Table

    cut = f"score ≥ {result.score_threshold:g}, IoU ≥ {result.iou_threshold:g}"
    per_class = Table(
        title=f"At the threshold ({cut}): boxes right (TP), false (FP), objects missed (FN)", title_justify="left"
    )
    for column in ("class", "TP", "FP", "FN", "precision", "recall"):
        per_class.add_column(column, justify="left" if column == "class" else "right", no_wrap=True)
    for name, item in result.per_class.items():
        per_class.add_row(
            name, str(item["tp"]), str(item["fp"]), str(item["fn"]), _fmt(item["precision"], 3), _fmt(item["recall"], 3)
        )
    per_class.add_section()
    per_class.add_row(
        "all", str(result.true_positives), str(result.false_positives), str(result.false_negatives),
        _fmt(result.precision, 3), _fmt(result.recall, 3),
    )  # fmt: skip
    tables = [per_class]
    if result.confusion:
        from workers.train.evaluation import NO_OBJECT

        truths = [name for name in result.classes if any(name in row for row in result.confusion.values())]
        truths += [NO_OBJECT] if any(NO_OBJECT in row for row in result.confusion.values()) else []
        confusion = Table(
            title="False boxes: the class given (rows) against the object they overlap most (columns; "
            f"the same class: a second box on an object found already; {NO_OBJECT}: IoU < {result.iou_threshold:g} with every object)",
            title_justify="left",
        )
        confusion.add_column("given \\ true", no_wrap=True)
        for name in truths:
            confusion.add_column(name, justify="right", no_wrap=True)
        for given in result.classes:
            if given in result.confusion:
                confusion.add_row(given, *(str(result.confusion[given].get(name, 0)) for name in truths))
        tables.append(confusion)
    return tables


# Ground truth is drawn white over a black outline, so that it shows on any photo beside the
# detections' class colours.
_TRUTH_COLOURS = ((0, 0, 0), (255, 255, 255))
REPORT_MIN_SIDE = 480


def write_report(folder: Path, samples, predictions, truth, at_threshold, count: int, title: str) -> Path:
    """``folder/index.html``: the ``count`` worst images at the threshold, each drawn as a PNG
    (true boxes white, labelled "true"; the detections kept at the threshold as ``foldwise
    detect`` draws them) with its errors listed; returns the page."""
    import html

    import cv2
    import numpy as np

    from workers.train.data import read_image_rgb

    folder.mkdir(parents=True, exist_ok=True)
    classes = at_threshold.classes
    rows = []
    for rank, item in enumerate(at_threshold.worst_images(count), start=1):
        sample = samples[item.index]
        canvas = read_image_rgb(sample.image_path)
        # Small images are blown up (whole pixels) so that the labels stay readable.
        zoom = max(1, REPORT_MIN_SIDE // max(canvas.shape[:2]))
        if zoom > 1:
            canvas = cv2.resize(canvas, None, fx=zoom, fy=zoom, interpolation=cv2.INTER_NEAREST)
        found = {**predictions[item.index], "boxes": np.asarray(predictions[item.index]["boxes"]) * zoom}
        thickness = max(1, round(min(canvas.shape[:2]) / 200))
        for box, label in zip(np.asarray(truth[item.index]["boxes"]) * zoom, np.asarray(truth[item.index]["labels"])):
            x0, y0, x1, y1 = (int(round(float(v))) for v in box)
            for colour, width in zip(_TRUTH_COLOURS, (thickness + 2, thickness)):
                cv2.rectangle(canvas, (x0, y0), (x1, y1), colour, width)
            cv2.putText(canvas, f"true {classes[int(label)]}", (x0 + 2, max(y1 - 4, 10)), cv2.FONT_HERSHEY_SIMPLEX,
                        max(0.3, min(canvas.shape[:2]) / 600), (255, 255, 255), 1, cv2.LINE_AA)  # fmt: skip
        drawn = draw_detections(canvas, found, classes, at_threshold.score_threshold)
        name = f"{rank:03d}-{sample.image_path.stem}.png"
        if not cv2.imwrite(str(folder / name), cv2.cvtColor(drawn, cv2.COLOR_RGB2BGR)):
            raise OSError(f"cannot write {folder / name}")
        caption = (
            f"{html.escape(str(sample.image_path))}: {item.false_positives} false box(es), {item.false_negatives} object(s) "
            f"missed, {item.true_positives} found"
        )
        rows.append(
            f'<figure><img src="{html.escape(name)}" alt="{html.escape(name)}"><figcaption>{caption}</figcaption></figure>'
        )
    cut = f"score ≥ {at_threshold.score_threshold:g}, IoU ≥ {at_threshold.iou_threshold:g}"
    summary = (
        f"precision {_fmt(at_threshold.precision, 3)}, recall {_fmt(at_threshold.recall, 3)} at {cut}: "
        f"{at_threshold.true_positives} boxes right, {at_threshold.false_positives} false, {at_threshold.false_negatives} objects missed"
    )
    body = "\n".join(rows) if rows else "<p>No image has a false box or a missed object at this threshold.</p>"
    page = folder / "index.html"
    page.write_text(
        '<!doctype html>\n<html><head><meta charset="utf-8"><title>' + html.escape(title) + "</title><style>"
        "body{font-family:sans-serif;margin:1em}figure{display:inline-block;margin:.5em;vertical-align:top}"
        "img{max-width:480px;max-height:480px;border:1px solid #ccc}figcaption{max-width:480px;font-size:90%}</style></head><body>"
        f"<h1>{html.escape(title)}</h1><p>{html.escape(summary)}</p>"
        '<p>The worst images first (false boxes plus objects missed). True boxes: white, labelled "true"; '
        "detections at the threshold: coloured by class, solid where the texture check confirmed them, dashed where not.</p>"
        f"{body}</body></html>\n"
    )
    return page


# --------------------------------------------------------------------------- detect

# Distinct BGR colours per class (OpenCV draws in BGR).
_PALETTE = [(48, 48, 255), (48, 200, 48), (255, 128, 0), (0, 200, 255), (200, 0, 200), (255, 255, 0), (128, 0, 255)]


def _catalog_textures(assets, classes: list[str]) -> dict:
    """The classes' textures from the config's asset catalog, for ``detector.texture_check``; a
    class the catalog lacks is a clear failure."""
    from workers.render.assets import AssetError, load_assets

    try:
        return load_assets(assets).textures(classes)
    except AssetError as error:
        _fail(f"detector.texture_check needs each class's texture from the config's assets: {error}")


def draw_detections(image_rgb, detections: dict, classes: list[str], score_threshold: float):
    """A copy of the image (RGB) with every detection at or above the threshold boxed and labelled.
    Where the texture check ran (``confirmed`` in the detections), a box it confirmed is drawn
    solid and one on the network's word alone dashed."""
    import cv2
    import numpy as np

    from workers.render.cli import dashed_rectangle

    canvas = cv2.cvtColor(np.ascontiguousarray(image_rgb), cv2.COLOR_RGB2BGR)
    height, width = canvas.shape[:2]
    thickness = max(1, round(min(height, width) / 200))
    font_scale = max(0.3, min(height, width) / 500)
    keep = np.asarray(detections["scores"]) >= score_threshold
    confirmed = np.asarray(detections.get("confirmed", np.ones(len(keep), bool)), bool)
    labels_drawn: list[tuple[int, int, int, int]] = []
    for box, score, label, solid in zip(
        np.asarray(detections["boxes"])[keep],
        np.asarray(detections["scores"])[keep],
        np.asarray(detections["labels"])[keep],
        confirmed[keep],
    ):
        colour = _PALETTE[int(label) % len(_PALETTE)]
        x0, y0, x1, y1 = (int(round(float(v))) for v in box)
        if solid:
            cv2.rectangle(canvas, (x0, y0), (x1, y1), colour, thickness)
        else:
            dashed_rectangle(
                canvas, (x0, y0, x1, y1), colour, dash=3 * thickness + 2, thickness=thickness, pixel_edges=False
            )
        name = classes[int(label)] if 0 <= int(label) < len(classes) else str(int(label))
        text = f"{name} {float(score):.2f}"
        (text_w, text_h), baseline = cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, font_scale, 1)
        left, top = _label_position(x0, y0, y1, text_w, text_h + baseline, width, height, labels_drawn)
        labels_drawn.append((left, top, left + text_w, top + text_h + baseline))
        cv2.rectangle(canvas, labels_drawn[-1][:2], labels_drawn[-1][2:], colour, -1)
        cv2.putText(
            canvas, text, (left, top + text_h), cv2.FONT_HERSHEY_SIMPLEX, font_scale, (255, 255, 255), 1, cv2.LINE_AA
        )
    return cv2.cvtColor(canvas, cv2.COLOR_BGR2RGB)


def _label_position(
    x0: int, y0: int, y1: int, label_w: int, label_h: int, width: int, height: int, taken: list
) -> tuple[int, int]:
    """Top-left corner of a box's label: above the box's top-left corner, or, where an earlier
    label is there (nested boxes share corners), the first free place down the box's left edge;
    the first place if none is free."""
    left = min(max(0, x0), max(0, width - label_w))
    places = [max(0, y0 - label_h)] + list(range(max(0, y0), max(y0, y1 - label_h) + 1, label_h))
    for top in places:
        top = min(top, max(0, height - label_h))
        if not any(left < r1 and r0 < left + label_w and top < b1 and b0 < top + label_h for r0, b0, r1, b1 in taken):
            return left, top
    return left, min(places[0], max(0, height - label_h))


def detect(
    model: Annotated[
        list[Path],
        typer.Option(
            "--model",
            help="Checkpoint written by `foldwise train` or an experiment; given again (one class list), "
            "the detectors detect as one ensemble, their detections merged.",
        ),
    ],
    images: Annotated[list[Path], typer.Argument(help="Image files to run the detector on.")],
    out_dir: Annotated[
        Path,
        typer.Option(
            "--out",
            "--out-dir",
            help="Folder for the drawn copies (one PNG per image, named after it); default: detections/ in the working directory.",
        ),
    ] = Path("detections"),
    score_threshold: Annotated[
        float, typer.Option("--threshold", min=0.0, max=1.0, help="Draw detections at or above this score.")
    ] = 0.8,
    batch_size: Annotated[int, typer.Option("--batch-size", min=1)] = 8,
    device: Annotated[
        str | None, typer.Option("--device", help="cpu or cuda (default: the checkpoint's choice).")
    ] = None,
    threads: Annotated[int, typer.Option("--threads", min=0, help="Torch CPU threads (0: torch decides).")] = 0,
    sizes: Annotated[
        str | None,
        typer.Option(
            "--sizes",
            help="Input sizes to detect at, merged, e.g. 128,256 or 128 alone for speed "
            "(R-CNN families; default: the checkpoint's detector.test_sizes, else its input size).",
        ),
    ] = None,
    turns: Annotated[
        str | None,
        typer.Option(
            "--turns",
            help="Quarter turns of each image to detect on too, merged, e.g. 0,1,2,3, or 0 for speed "
            "(R-CNN families; default: the checkpoint's detector.test_turns).",
        ),
    ] = None,
    every_view: Annotated[
        bool,
        typer.Option(
            "--every-view",
            help="Run every view on every image: off the checkpoint's cascade (detector.cascade), which "
            "runs one view and the texture check first and the rest only where the texture confirmed nothing.",
        ),
    ] = False,
    json_path: Annotated[
        Path | None,
        typer.Option(
            "--json",
            help="Also write the detections at or above --threshold as JSON: per image its path, size, "
            "annotated copy and boxes (x0, y0, x1, y1 in the pixels of the photo as displayed, EXIF orientation "
            "applied, at full size) with class, score and texture confirmation.",
        ),
    ] = None,
) -> None:
    """Detect the object in images; write copies with boxes, class names and scores drawn."""
    import cv2
    import numpy as np

    from foldwise.config import parse_test_sizes, parse_test_turns
    from foldwise.images import ImageError, image_size, read_image
    from workers.train.data import PHOTO_MAX_SIDE

    test_sizes = _parsed_option("--sizes", sizes, parse_test_sizes)
    test_turns = _parsed_option("--turns", turns, parse_test_turns)
    missing = [str(path) for path in images if not path.is_file()]
    if missing:
        _fail(f"image file(s) not found: {', '.join(missing)}")
    # Photos as displayed (EXIF orientation applied), large ones shrunk: boxes are reported in
    # the displayed photo's own pixels (scaled back), drawn on the shrunk copy.
    pictures, scales = [], []
    for path in images:
        try:
            picture, scale = read_image(path, max_side=PHOTO_MAX_SIDE)
        except ImageError as error:
            _fail(f"cannot read image {error}")
        pictures.append(picture)
        scales.append(scale)
    _set_threads(threads)
    detectors = [_load_model(path, device) for path in model]
    classes = [str(name) for name in detectors[0].meta.get("classes", [])]

    from workers.train.checkpoint import detect_ensemble, detection_records

    try:
        detections = detect_ensemble(
            detectors,
            pictures,
            batch_size=batch_size,
            test_sizes=test_sizes,
            test_turns=test_turns,
            every_view=every_view,
        )
    except ValueError as error:  # e.g. --sizes or --turns for a yolo detector, or ensemble members of other classes
        _fail(str(error))
    out_dir.mkdir(parents=True, exist_ok=True)
    used: set[str] = set()
    records: list[dict[str, Any]] = []
    for path, picture, scale, found in zip(images, pictures, scales, detections):
        name = f"{path.stem}.png"
        counter = 1
        while name in used:  # same file name from two folders: keep both
            name = f"{path.stem}_{counter}.png"
            counter += 1
        used.add(name)
        drawn = draw_detections(picture, found, classes, score_threshold)
        target = out_dir / name
        if not cv2.imwrite(str(target), cv2.cvtColor(drawn, cv2.COLOR_RGB2BGR)):
            _fail(f"cannot write {target}")
        full_size = (picture.shape[1], picture.shape[0])
        if scale != 1.0:
            full_size = image_size(path)
            ratio = np.array([full_size[0] / picture.shape[1], full_size[1] / picture.shape[0]] * 2)
            found = {**found, "boxes": np.asarray(found["boxes"]) * ratio}
        kept = detection_records(found, classes, score_threshold)
        said = [
            f"{record['class'] if record['class'] is not None else record['label']} {record['score']:.2f}"
            + (" (texture confirmed)" if record["confirmed"] else "")
            for record in kept
        ]
        typer.echo(f"{path} -> {target}: {len(said)} detection(s){': ' + ', '.join(said) if said else ''}")
        records.append(
            {
                "path": str(path),
                "width": int(full_size[0]),
                "height": int(full_size[1]),
                "annotated": str(target),
                "detections": kept,
            }
        )
    if json_path is not None:
        document = {
            "models": [str(path) for path in model],
            "classes": classes,
            "threshold": score_threshold,
            "images": records,
        }
        try:
            json_path.parent.mkdir(parents=True, exist_ok=True)
            json_path.write_text(json.dumps(document, indent=2))
        except OSError as error:
            _fail(f"cannot write {json_path}: {error}")
        typer.echo(f"detections: {json_path}")


# --------------------------------------------------------------------------- ensemble


def ensemble(
    model: Annotated[
        list[Path],
        typer.Option(
            "--model",
            help="A checkpoint to join (two or more, one class list): final models of runs with other seeds, say.",
        ),
    ],
    out: Annotated[Path, typer.Option("--out", help="The ensemble file to write, e.g. ensemble.pt.")],
) -> None:
    """Join detectors into one ensemble file that detects as one (their detections merged), as
    `foldwise run --members` does with its curricula' final models."""
    from workers.train.checkpoint import CheckpointError, save_ensemble

    if len(model) < 2:
        _fail("--model: an ensemble joins two or more checkpoints")
    missing = [str(path) for path in model if not path.is_file()]
    if missing:
        _fail(f"checkpoint(s) not found: {', '.join(missing)}")
    try:
        written = save_ensemble(model, out)
    except CheckpointError as error:
        _fail(str(error))
    typer.echo(f"wrote {written} ({written.stat().st_size / 1e6:.1f} MB): an ensemble of {len(model)} detectors")


def calibrate(
    model: Annotated[
        Path, typer.Option("--model", help="The checkpoint or ensemble to calibrate (make run's ensemble.pt, say).")
    ],
    data: Annotated[
        Path,
        typer.Option(
            "--data",
            help="Labelled images: a COCO JSON file or folder, or a Pascal VOC folder (your photographs, with lookalikes among them).",
        ),
    ],
    out: Annotated[Path, typer.Option("--out", help="Where to write the calibrated model (may be --model itself).")],
    iou: Annotated[float, typer.Option("--iou", help="IoU at which a detection counts as finding its target.")] = 0.5,
) -> None:
    """Fit the detector's score calibration on labelled images and record it in the model: its
    scores then read as the chance a box is true (at 0.8, about four in five drawn boxes true or
    more). Use images the detector will meet, with other sheets of the same kind among them."""
    from workers.train.calibration import calibrate_detector
    from workers.train.checkpoint import write_calibration

    if not 0 < iou <= 1:
        _fail(f"--iou must be in (0, 1], got {iou}")
    samples, classes = _load_samples(data)
    detector = _load_model(model)
    try:
        calibration = calibrate_detector(detector, samples, classes, iou=iou, fitted_on=str(data))
    except ValueError as error:
        _fail(str(error))
    written = write_calibration(model, calibration, out)
    weights = ", ".join(f"{name} {weight:+.2f}" for name, weight in zip(calibration.features, calibration.weights))
    typer.echo(f"wrote {written}: scores calibrated on {len(samples)} images (bias {calibration.bias:+.2f}; {weights})")


def lookalikes(
    model: Annotated[Path, typer.Option("--model", help="The checkpoint or ensemble whose texture check learns them.")],
    folder: Annotated[
        Path,
        typer.Option(
            "--folder",
            help="Flat images of sheets of your objects' kind that are none of them: your other forms, covers, labels.",
        ),
    ],
    out: Annotated[Path, typer.Option("--out", help="Where to write the model (may be --model itself).")],
) -> None:
    """Give the texture check the lookalikes it must not confirm: a keypoint one of them shares
    with an object (a letterhead, a table head, a logo) stops counting as evidence for the object.
    Fewer lookalikes are confirmed, and sheets that show little but what they share are confirmed
    less often (bench/README.md, "The keypoint recipe, documents and calibrated scores")."""
    from foldwise.asset_check import AssetError, image_files
    from workers.train.checkpoint import write_lookalikes
    from workers.train.data import DatasetError, read_image_rgb

    detector = _load_model(model)
    if not detector.textures:
        _fail(
            f"{model} carries no textures (detector.texture_check off): there is no texture check to give lookalikes to"
        )
    try:
        files = image_files(folder, "lookalikes")
        sheets = {path.stem: read_image_rgb(path) for path in files}
    except (AssetError, DatasetError) as error:
        _fail(str(error))
    written = write_lookalikes(model, sheets, out)
    typer.echo(f"wrote {written}: its texture check knows {len(sheets)} lookalike(s) from {folder}")


# --------------------------------------------------------------------------- export


def export(
    model: Annotated[Path, typer.Option("--model", help="Checkpoint written by `foldwise train` or an experiment.")],
    out: Annotated[Path | None, typer.Option("--out", help="File to write, e.g. model.onnx.")] = None,
    export_format: Annotated[str, typer.Option("--format", help="Export format: onnx.")] = "onnx",
    image_size: Annotated[
        str | None,
        typer.Option(
            "--image-size", help="HxW (or N) the yolo family is exported at (at most its input size; default that)."
        ),
    ] = None,
    runtime: Annotated[
        bool,
        typer.Option(
            "--runtime",
            help="Write the checkpoint's runtime graph beside it (<model>.onnx) instead of --out: foldwise detect, "
            "evaluate and the REST routes then run the network at its views through onnxruntime (faster_rcnn).",
        ),
    ] = False,
) -> None:
    """Export a detector to run without foldwise (ONNX: faster_rcnn any size, yolo one size; not fast_rcnn)."""
    from workers.train.export import FORMATS, ExportError, export_onnx, write_runtime_graph

    if export_format not in FORMATS:
        _fail(f"unknown export format {export_format!r}; known: {', '.join(FORMATS)}")
    if runtime:
        if out is not None or image_size is not None:
            _fail("--runtime writes the graph beside the checkpoint at its own views: no --out or --image-size")
        detector = _load_model(model, "cpu")
        try:
            written = write_runtime_graph(model, detector)
        except ExportError as error:
            _fail(str(error))
        typer.echo(
            f"wrote {written} ({written.stat().st_size / 1e6:.1f} MB): the runtime graph of {model}, "
            "which detection now runs the network through (onnxruntime)"
        )
        return
    if out is None:
        _fail("--out: the file to write (or --runtime, to write the graph beside the checkpoint)")
    size = None
    if image_size is not None:
        parts = image_size.lower().split("x")
        if len(parts) not in (1, 2) or not all(part.isdigit() for part in parts):
            _fail(f"--image-size {image_size!r}: expected N or HxW, e.g. 128 or 96x128")
        size = (int(parts[0]), int(parts[-1]))
    detector = _load_model(model, "cpu")
    try:
        written = export_onnx(detector, out, image_size=size)
    except ExportError as error:
        _fail(str(error))
    classes = ", ".join(detector.classes)
    typer.echo(f"wrote {written} ({written.stat().st_size / 1e6:.1f} MB): {detector.meta['family']}, classes {classes}")
    if (check := detector.texture_check()) is not None:
        what = (
            "texture check and search (detector.texture_check, texture_search)"
            if check.search
            else "texture check (detector.texture_check)"
        )
        typer.echo(
            f"note: the graph holds the network only; this detector's {what} "
            "runs in foldwise detect, evaluate and the REST routes, not in the ONNX model"
        )


# --------------------------------------------------------------------------- finetune


def finetune(
    model: Annotated[
        Path,
        typer.Option(
            "--model",
            help="The foldwise checkpoint to fine-tune; an ensemble (`make run`'s) is fine-tuned member by member.",
        ),
    ],
    data: Annotated[Path, typer.Option("--data", help=f"Real images. {DATA_HELP}")],
    out: Annotated[Path, typer.Option("--out", help="Folder for the models, the table and Fig. 11.")],
    sweep: Annotated[
        str, typer.Option("--sweep", help="Real training images per point, e.g. 0,25,50,100,200.")
    ] = "0,25,50,100,200",
    iterations: Annotated[int, typer.Option("--iterations", min=1, max=1_000_000, help="Iterations per model.")] = 200,
    test_fraction: Annotated[
        float, typer.Option("--test-fraction", min=0.05, max=0.95, help="Share held out for testing.")
    ] = 0.5,
    seed: Annotated[int, typer.Option("--seed", help="Seed of the split, weights and batch order.")] = 0,
    runtime_graph: Annotated[
        bool,
        typer.Option(
            "--runtime-graph/--no-runtime-graph",
            help="Write the runtime graph of the model fine-tuned on the most images beside it, as `foldwise run` "
            "does for the model it hands over: detection then runs its views through onnxruntime.",
        ),
    ] = True,
) -> None:
    """Fine-tune a foldwise model on real photographs: a sweep over the number of real training
    images, a fresh-initialisation baseline beside it, both scored on a held-out real split (Fig. 11)."""
    from workers.train.data import DatasetError, load_dataset
    from workers.train.finetune import match_classes, split, write_fig11
    from workers.train.finetune import sweep as run_sweep

    def bad_input(message: str) -> NoReturn:
        typer.secho(f"error: {message}", fg=typer.colors.RED, err=True)
        raise typer.Exit(code=2)

    try:
        sizes = sorted({int(part) for part in sweep.split(",") if part.strip()})
    except ValueError:
        bad_input(f"--sweep: {sweep!r} is not a comma list of whole numbers")
    if not sizes or sizes[0] < 0:
        bad_input(f"--sweep: {sweep!r} needs one or more counts >= 0")
    detector = _load_model(model)
    members = len(detector.meta.get("members", [])) or 1
    model_classes = [str(name) for name in detector.meta["classes"]]
    try:
        samples, classes = load_dataset(data)
        samples = match_classes(samples, classes, model_classes)
        pool, test = split(samples, test_fraction, seed)
    except DatasetError as error:
        bad_input(str(error))
    typer.echo(f"{len(samples)} real images of {', '.join(classes)}: {len(pool)} to train from, {len(test)} to test on")
    what = f"an ensemble of {members} detectors, each fine-tuned and joined again" if members > 1 else "one detector"
    typer.echo(f"{model.name}: {what}")

    def report(point) -> None:
        fresh = "—" if point.fresh_map is None else f"{point.fresh_map:.3f}"
        line = f"n = {point.n:4d}: fine-tuned mAP {point.finetuned_map:.3f}, fresh initialisation {fresh}"
        typer.echo(line)

    from workers.train.checkpoint import CheckpointError
    from workers.train.training import TrainingDiverged

    try:
        points = run_sweep(model, pool, test, sizes, iterations, out, seed=seed, on_point=report)
    except DatasetError as error:
        bad_input(str(error))
    except (CheckpointError, TrainingDiverged, ValueError) as error:
        _fail(f"fine-tuning failed: {error}")
    title = f"{model.name}{f' (ensemble of {members})' if members > 1 else ''} on {data.name}"
    paths = write_fig11(points, out, title=title)
    largest = max(sizes)
    if largest > 0:
        kind = f"an ensemble of {members}" if members > 1 else "one detector"
        handed_over = out / f"finetuned-{largest}.pt"
        typer.echo(f"fine-tuned on {largest} images ({kind}): {handed_over}")
        if runtime_graph:
            from workers.train.export import write_runtime_graph_told

            typer.echo(write_runtime_graph_told(handed_over))
    typer.echo("Fig. 11: " + "  ".join(str(path) for path in paths))


def register(app: typer.Typer) -> None:
    app.command("finetune")(finetune)
    app.command("train")(train)
    app.command("evaluate")(evaluate)
    app.command("detect")(detect)
    app.command("export")(export)
    app.command("ensemble")(ensemble)
    app.command("calibrate")(calibrate)
    app.command("lookalikes")(lookalikes)
