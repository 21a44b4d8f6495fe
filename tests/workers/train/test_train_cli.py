"""foldwise train / evaluate / detect on a tiny COCO dataset written here (no renderer needed)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from workers.train.cli import _PALETTE, draw_detections, register

CLASSES = ["red_card", "blue_card"]
COLOURS = [(220, 40, 40), (40, 60, 220)]
IMAGE_SIZE = 96


def make_app() -> typer.Typer:
    app = typer.Typer()
    register(app)
    return app


runner = CliRunner()


def write_dataset(directory: Path, n_images: int = 6, seed: int = 0, category_order=(1, 2)) -> Path:
    """A dataset folder in `foldwise render`'s layout: noisy backgrounds, one striped card each."""
    rng = np.random.default_rng(seed)
    (directory / "images").mkdir(parents=True, exist_ok=True)
    images, annotations = [], []
    conditions = ["fb", "po"]
    for i in range(n_images):
        picture = rng.integers(0, 256, (IMAGE_SIZE, IMAGE_SIZE, 3), dtype=np.uint8)
        label = i % 2
        w, h = rng.integers(30, 60, 2)
        x, y = rng.integers(0, IMAGE_SIZE - w), rng.integers(0, IMAGE_SIZE - h)
        picture[y : y + h, x : x + w] = COLOURS[label]
        picture[y : y + h : 4, x : x + w] = 255  # stripes: some texture
        name = f"images/{i:03d}.png"
        cv2.imwrite(str(directory / name), cv2.cvtColor(picture, cv2.COLOR_RGB2BGR))
        images.append(
            {
                "id": i + 1,
                "file_name": name,
                "width": IMAGE_SIZE,
                "height": IMAGE_SIZE,
                "condition": conditions[(i // 2) % 2],
                "difficulty": "easy",
                "theta": {"seed": i},
            }
        )
        annotations.append(
            {
                "id": i + 1,
                "image_id": i + 1,
                "category_id": category_order[label],
                "bbox": [float(x), float(y), float(w), float(h)],
                "area": float(w * h),
                "iscrowd": 0,
                "amodal_bbox": [float(x), float(y), float(w), float(h)],
                "visible_fraction": 1.0,
            }
        )
    categories = [{"id": category_order[k], "name": CLASSES[k]} for k in range(len(CLASSES))]
    document = {"images": images, "annotations": annotations, "categories": categories}
    (directory / "annotations.json").write_text(json.dumps(document))
    return directory


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    return write_dataset(tmp_path_factory.mktemp("data"))


# --------------------------------------------------------------------------- clear errors (no training)


def test_missing_dataset_folder_is_a_clear_error(tmp_path):
    missing = tmp_path / "nowhere"
    for args in (
        ["train", "--detector", "yolo", "--data", str(missing), "--iterations", "1", "--out", str(tmp_path / "m.pt")],
        ["evaluate", "--model", str(tmp_path / "m.pt"), "--data", str(missing)],
    ):
        result = runner.invoke(make_app(), args)
        assert result.exit_code == 1
        assert f"dataset {missing} does not exist (no such folder or file)" in result.output


def test_folder_without_annotations_is_a_clear_error(tmp_path):
    result = runner.invoke(
        make_app(),
        ["train", "--detector", "yolo", "--data", str(tmp_path), "--iterations", "1", "--out", str(tmp_path / "m.pt")],
    )
    assert result.exit_code == 1
    assert "no annotations.json" in result.output


def test_empty_dataset_is_a_clear_error(tmp_path):
    (tmp_path / "annotations.json").write_text(
        json.dumps({"images": [], "annotations": [], "categories": [{"id": 1, "name": "a"}]})
    )
    result = runner.invoke(
        make_app(),
        [
            "train",
            "--detector",
            "faster_rcnn",
            "--data",
            str(tmp_path),
            "--iterations",
            "1",
            "--out",
            str(tmp_path / "m.pt"),
        ],
    )
    assert result.exit_code == 1
    assert "is empty" in result.output


def test_unknown_detector_family_is_rejected(tmp_path, dataset):
    result = runner.invoke(
        make_app(),
        ["train", "--detector", "ssd", "--data", str(dataset), "--iterations", "1", "--out", str(tmp_path / "m.pt")],
    )
    assert result.exit_code == 2
    assert "ssd" in result.output


def test_missing_init_checkpoint_is_a_clear_error(tmp_path, dataset):
    result = runner.invoke(
        make_app(),
        [
            "train",
            "--detector",
            "yolo",
            "--data",
            str(dataset),
            "--iterations",
            "1",
            "--init",
            str(tmp_path / "absent.pt"),
            "--out",
            str(tmp_path / "m.pt"),
        ],
    )
    assert result.exit_code == 1
    assert "--init checkpoint" in result.output and "does not exist" in result.output


def test_unreadable_checkpoint_is_a_clear_error(tmp_path, dataset):
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"this is not a checkpoint")
    result = runner.invoke(make_app(), ["evaluate", "--model", str(garbage), "--data", str(dataset)])
    assert result.exit_code == 1
    assert f"cannot load checkpoint {garbage}" in result.output
    missing = runner.invoke(make_app(), ["evaluate", "--model", str(tmp_path / "nope.pt"), "--data", str(dataset)])
    assert missing.exit_code == 1 and "does not exist" in missing.output
    image = next((dataset / "images").glob("*.png"))
    drawn = runner.invoke(make_app(), ["detect", "--model", str(garbage), str(image), "--out-dir", str(tmp_path / "d")])
    assert drawn.exit_code == 1 and "cannot load checkpoint" in drawn.output


def test_detect_missing_or_unreadable_image_is_a_clear_error(tmp_path):
    not_an_image = tmp_path / "notes.png"
    not_an_image.write_text("hello")
    result = runner.invoke(make_app(), ["detect", "--model", str(tmp_path / "m.pt"), str(tmp_path / "x.png")])
    assert result.exit_code == 1 and "not found" in result.output
    result = runner.invoke(make_app(), ["detect", "--model", str(tmp_path / "m.pt"), str(not_an_image)])
    assert result.exit_code == 1 and "cannot read image" in result.output


def test_draw_detections_boxes_and_labels_only_above_threshold():
    image = np.zeros((64, 64, 3), np.uint8)
    found = {
        "boxes": np.array([[10, 20, 40, 50], [2, 2, 8, 8]], np.float32),
        "scores": np.array([0.9, 0.3], np.float32),
        "labels": np.array([1, 0], np.int64),
    }
    drawn = draw_detections(image, found, CLASSES, score_threshold=0.8)
    assert drawn.shape == image.shape and drawn.dtype == np.uint8
    assert image.sum() == 0  # the input is not drawn on
    assert drawn[35, 10].any() and drawn[50, 25].any()  # left and bottom edges of the kept box
    assert not drawn[5, 5].any() and not drawn[2, 5].any()  # the 0.3 detection is not drawn
    assert not drawn[35, 25].any()  # inside the box stays untouched
    everything = draw_detections(image, found, CLASSES, score_threshold=0.0)
    assert everything[2, 5].any()


def test_draw_detections_draws_texture_confirmed_boxes_solid_and_the_others_dashed():
    image = np.zeros((200, 200, 3), np.uint8)
    box = [20, 60, 180, 180]
    drawn = {}
    for confirmed in (True, False):
        found = {
            "boxes": np.array([box], np.float32),
            "scores": np.array([0.95], np.float32),
            "labels": np.array([0], np.int64),
            "confirmed": np.array([confirmed]),
        }
        drawn[confirmed] = draw_detections(image, found, CLASSES, score_threshold=0.8)
    bottom_solid, bottom_dashed = drawn[True][180, 20:181].any(1), drawn[False][180, 20:181].any(1)
    assert bottom_solid.all()  # every pixel of the bottom edge
    assert 0.3 < bottom_dashed.mean() < 0.8  # dashes and gaps along the same edge
    without_check = {key: value for key, value in found.items() if key != "confirmed"}
    np.testing.assert_array_equal(draw_detections(image, without_check, CLASSES, 0.8), drawn[True])  # no check: solid


def test_draw_detections_keeps_the_labels_of_nested_boxes_apart():
    # Boxes sharing a top-left corner (a sheet and a piece of it) once drew their labels on the
    # same spot: the later hid the earlier.
    image = np.zeros((200, 200, 3), np.uint8)
    found = {
        "boxes": np.array([[20, 60, 180, 180], [20, 60, 120, 140], [20, 60, 90, 100]], np.float32),
        "scores": np.array([0.95, 0.9, 0.85], np.float32),
        "labels": np.array([0, 1, 0], np.int64),
    }
    drawn = cv2.cvtColor(draw_detections(image, found, CLASSES, score_threshold=0.8), cv2.COLOR_RGB2BGR)
    box_edges = {60, 100, 140, 180}
    label_fills = []  # rows filled with a class's colour across a label's width, box edges aside
    for colour in _PALETTE[:2]:
        rows = np.flatnonzero((drawn == colour).all(-1).sum(1) > 20)
        label_fills.append({int(row) for row in rows} - box_edges)
    first, second = label_fills
    assert first and second
    assert any(row < 60 for row in first)  # the best box's label sits above its corner
    assert all(row >= 60 for row in second)  # the next one moved down, inside the box
    assert len(first) >= 2 * len(second)  # both labels of class 0 drawn in full, one below the other


# --------------------------------------------------------------------------- train → evaluate → detect


@pytest.fixture(scope="module")
def trained(tmp_path_factory, dataset) -> dict[str, Path]:
    """One tiny checkpoint per detector family: one iteration of one 64-px image each (the
    commands' plumbing is under test here, not learning)."""
    out = tmp_path_factory.mktemp("models")
    checkpoints, outputs = {}, {}
    for family in ("faster_rcnn", "fast_rcnn", "yolo"):
        path = out / f"{family}.pt"
        result = runner.invoke(
            make_app(),
            [
                "train",
                "--detector",
                family,
                "--data",
                str(dataset),
                "--iterations",
                "1",
                "--input-size",
                "64",
                "--batch-size",
                "1",
                "--seed",
                "1",
                "--threads",
                "2",
                "--out",
                str(path),
            ],
        )
        assert result.exit_code == 0, result.output
        checkpoints[family] = path
        outputs[family] = result.output
    return {"checkpoints": checkpoints, "outputs": outputs}


@pytest.mark.parametrize("family", ["faster_rcnn", "fast_rcnn", "yolo"])
def test_train_writes_checkpoint_and_reports_throughput_and_loss(trained, family):
    path = trained["checkpoints"][family]
    output = trained["outputs"][family]
    assert path.is_file() and path.stat().st_size > 0
    assert "1 iterations" in output
    assert "images/s" in output
    # Not a terminal: the progress bar is a plain line, no control codes
    assert "training: 1/1 iterations (100%)" in output and "\x1b" not in output
    loss = float(output.split("final loss ")[1].split()[0])
    assert math.isfinite(loss)


def test_train_warm_start_from_checkpoint(trained, dataset, tmp_path):
    result = runner.invoke(
        make_app(),
        [
            "train",
            "--detector",
            "yolo",
            "--data",
            str(dataset),
            "--iterations",
            "1",
            "--input-size",
            "64",
            "--init",
            str(trained["checkpoints"]["yolo"]),
            "--threads",
            "2",
            "--out",
            str(tmp_path / "next.pt"),
        ],
    )
    assert result.exit_code == 0, result.output
    assert (tmp_path / "next.pt").is_file()


def test_evaluate_prints_tables_and_writes_json(trained, dataset, tmp_path):
    target = tmp_path / "eval" / "result.json"
    result = runner.invoke(
        make_app(),
        [
            "evaluate",
            "--model",
            str(trained["checkpoints"]["faster_rcnn"]),
            "--data",
            str(dataset),
            "--json",
            str(target),
            "--threads",
            "2",
        ],
    )
    assert result.exit_code == 0, result.output
    for text in (
        "Per class",
        "Per condition",
        "Per difficulty",
        "mAP (paper protocol",
        "mAP (unthresholded)",
        *CLASSES,
    ):
        assert text in result.output
    assert "evaluating: 6/6 images (100%)" in result.output and "\x1b" not in result.output
    payload = json.loads(target.read_text())
    assert payload["num_images"] == 6 and payload["num_ground_truth"] == 6
    assert payload["classes"] == CLASSES
    assert set(payload["breakdown"]["condition"]) == {"fb", "po"}
    assert payload["breakdown"]["condition/difficulty"]["fb/easy"]["num_images"] == 4
    assert payload["map"] is None or 0.0 <= payload["map"] <= 1.0
    assert payload["map"] is None or payload["map"] <= payload["map_unthresholded"] + 1e-12
    assert "AP50" in payload["coco"]


def test_detect_writes_annotated_copies(trained, dataset, tmp_path):
    images = sorted((dataset / "images").glob("*.png"))[:2]
    out_dir = tmp_path / "drawn"
    result = runner.invoke(
        make_app(),
        [
            "detect",
            "--model",
            str(trained["checkpoints"]["yolo"]),
            *map(str, images),
            "--out-dir",
            str(out_dir),
            "--threshold",
            "0.0",
        ],
    )
    assert result.exit_code == 0, result.output
    for image in images:
        written = cv2.imread(str(out_dir / image.name))
        assert written is not None and written.shape == (IMAGE_SIZE, IMAGE_SIZE, 3)
        assert f"{image} -> " in result.output


def test_detect_at_chosen_sizes_and_bad_sizes_named(trained, dataset, tmp_path):
    images = [str(sorted((dataset / "images").glob("*.png"))[0])]
    app, model = make_app(), ["--model", str(trained["checkpoints"]["faster_rcnn"])]
    lines = {}
    for sizes in ("64", "64,96,128"):
        result = runner.invoke(
            app, ["detect", *model, *images, "--out-dir", str(tmp_path / sizes), "--threshold", "0.0", "--sizes", sizes]
        )
        assert result.exit_code == 0, result.output
        lines[sizes] = result.output
    assert lines["64"] != lines["64,96,128"]  # more sizes, other (merged) detections
    for bad in ("64,64", "16", "big"):
        result = runner.invoke(app, ["detect", *model, *images, "--sizes", bad])
        assert result.exit_code == 1 and f"--sizes {bad!r}" in result.output
    yolo = runner.invoke(app, ["detect", "--model", str(trained["checkpoints"]["yolo"]), *images, "--sizes", "64"])
    assert yolo.exit_code == 1 and "only the R-CNN families" in yolo.output
    turned = runner.invoke(
        app,
        ["detect", *model, *images, "--out-dir", str(tmp_path / "turns"), "--threshold", "0.0", "--turns", "0,1,2,3"],
    )
    assert turned.exit_code == 0, turned.output
    assert turned.output != lines["64"]  # four views merged, other detections
    for bad, problem in (("0,0", "turns repeat"), ("4", "0, 1, 2 or 3"), ("left", "not whole numbers")):
        result = runner.invoke(app, ["detect", *model, *images, "--turns", bad])
        assert result.exit_code == 1 and f"--turns {bad!r}" in result.output and problem in result.output
    yolo = runner.invoke(app, ["detect", "--model", str(trained["checkpoints"]["yolo"]), *images, "--turns", "0,2"])
    assert yolo.exit_code == 1 and "only the R-CNN families" in yolo.output


def test_detect_with_several_models_merges_them_and_refuses_other_classes(trained, dataset, tmp_path):
    """--model given twice: one ensemble. A model with itself detects as alone; another model adds
    its boxes; members whose class lists differ are a clear error, not mixed labels."""
    import torch

    from workers.train.checkpoint import read_checkpoint

    images = [str(sorted((dataset / "images").glob("*.png"))[0])]
    faster, yolo = str(trained["checkpoints"]["faster_rcnn"]), str(trained["checkpoints"]["yolo"])
    app = make_app()

    def detect(*models: str, out: str) -> str:
        arguments = [part for model in models for part in ("--model", model)]
        result = runner.invoke(
            app, ["detect", *arguments, *images, "--out-dir", str(tmp_path / out), "--threshold", "0.0"]
        )
        assert result.exit_code == 0, result.output
        return result.output.replace(out, "OUT")

    alone = detect(faster, out="alone")
    assert detect(faster, faster, out="twice") == alone
    # The untrained yolo's boxes score below the faster R-CNN's, which fill the cap of 20.
    assert detect(yolo, faster, out="pair") != detect(yolo, out="yolo")
    checkpoint = read_checkpoint(faster)
    checkpoint["meta"]["classes"] = checkpoint["meta"]["classes"][::-1]
    reordered = tmp_path / "reordered.pt"
    torch.save(checkpoint, reordered)
    result = runner.invoke(
        app, ["detect", "--model", faster, "--model", str(reordered), *images, "--out-dir", str(tmp_path / "bad")]
    )
    assert result.exit_code == 1 and "one class list" in result.output


def test_ensemble_joins_checkpoints_into_one_file_that_detects_as_they_do_together(trained, dataset, tmp_path):
    """foldwise ensemble: one file that detects as --model given for each member; what needs one
    family (ONNX export) refuses it by name, fine-tuning takes it member by member; bad input is one line."""
    images = [str(sorted((dataset / "images").glob("*.png"))[0])]
    faster, yolo = str(trained["checkpoints"]["faster_rcnn"]), str(trained["checkpoints"]["yolo"])
    app = make_app()
    joined = tmp_path / "joined.pt"
    result = runner.invoke(app, ["ensemble", "--model", yolo, "--model", faster, "--out", str(joined)])
    assert result.exit_code == 0 and "an ensemble of 2 detectors" in result.output, result.output

    def detect(*arguments: str, out: str) -> str:
        result = runner.invoke(
            app, ["detect", *arguments, *images, "--out-dir", str(tmp_path / out), "--threshold", "0.0"]
        )
        assert result.exit_code == 0, result.output
        return result.output.replace(out, "OUT")

    assert detect("--model", str(joined), out="file") == detect("--model", yolo, "--model", faster, out="listed")
    exported = runner.invoke(app, ["export", "--model", str(joined), "--out", str(tmp_path / "e.onnx")])
    assert exported.exit_code == 1 and "several detector families (faster_rcnn, yolo)" in exported.output
    tuned = runner.invoke(
        app, ["finetune", "--model", str(joined), "--data", str(dataset), "--sweep", "0", "--out", str(tmp_path / "ft")]
    )
    assert tuned.exit_code == 0 and "an ensemble of 2 detectors, each fine-tuned" in tuned.output, tuned.output
    for arguments, problem in (
        (["--model", faster], "two or more checkpoints"),
        (["--model", faster, "--model", str(tmp_path / "absent.pt")], "not found"),
    ):
        result = runner.invoke(app, ["ensemble", *arguments, "--out", str(tmp_path / "bad.pt")])
        assert result.exit_code == 1 and problem in result.output and "Traceback" not in result.output
    assert not (tmp_path / "bad.pt").exists()


def test_detect_writes_the_drawn_detections_as_json(trained, dataset, tmp_path):
    """--json: per image its path, size and annotated copy, and the detections drawn (those at or
    above --threshold) as boxes in its pixels with class and score, the same as the detector gives."""
    from workers.train.checkpoint import detect_object, load_detector

    images = sorted((dataset / "images").glob("*.png"))[:2]
    model = trained["checkpoints"]["faster_rcnn"]
    target = tmp_path / "out" / "detections.json"
    result = runner.invoke(
        make_app(),
        [
            "detect",
            "--model",
            str(model),
            *map(str, images),
            "--out-dir",
            str(tmp_path / "drawn"),
            "--threshold",
            "0.05",
            "--json",
            str(target),
        ],
    )
    assert result.exit_code == 0, result.output
    assert f"detections: {target}" in result.output
    document = json.loads(target.read_text())
    assert document["models"] == [str(model)] and document["classes"] == CLASSES and document["threshold"] == 0.05
    assert [entry["path"] for entry in document["images"]] == [str(image) for image in images]
    for entry, found in zip(document["images"], detect_object(load_detector(model), list(map(str, images)))):
        assert (entry["width"], entry["height"]) == (IMAGE_SIZE, IMAGE_SIZE) and Path(entry["annotated"]).is_file()
        keep = found["scores"] >= 0.05
        assert [d["score"] for d in entry["detections"]] == pytest.approx(found["scores"][keep].tolist())
        assert [d["label"] for d in entry["detections"]] == found["labels"][keep].tolist()
        assert [d["class"] for d in entry["detections"]] == [CLASSES[label] for label in found["labels"][keep]]
        np.testing.assert_allclose(
            [d["box"] for d in entry["detections"]] or np.zeros((0, 4)), found["boxes"][keep], atol=0.006
        )
        assert all(d["confirmed"] is None for d in entry["detections"])  # this detector has no texture check
    assert sum(len(entry["detections"]) for entry in document["images"]) > 0


def test_detect_names_a_json_file_it_cannot_write(trained, dataset, tmp_path):
    image = str(sorted((dataset / "images").glob("*.png"))[0])
    blocked = tmp_path / "a-file"
    blocked.write_text("not a folder")
    result = runner.invoke(
        make_app(),
        [
            "detect",
            "--model",
            str(trained["checkpoints"]["faster_rcnn"]),
            image,
            "--out-dir",
            str(tmp_path / "d"),
            "--json",
            str(blocked / "d.json"),
        ],
    )
    assert result.exit_code == 1 and f"cannot write {blocked / 'd.json'}" in result.output
    assert (tmp_path / "d" / Path(image).with_suffix(".png").name).is_file()  # the drawn copies are kept


def test_calibrate_refuses_a_model_without_textures_and_a_recorded_calibration_is_read_back(trained, dataset, tmp_path):
    """foldwise calibrate needs the texture evidence it calibrates (a one-line error without it);
    a calibration written into a checkpoint or an ensemble comes back with the detector it loads."""
    from workers.train.calibration import FEATURES, Calibration
    from workers.train.checkpoint import load_detector, save_ensemble, write_calibration

    faster = trained["checkpoints"]["faster_rcnn"]
    result = runner.invoke(
        make_app(), ["calibrate", "--model", str(faster), "--data", str(dataset), "--out", str(tmp_path / "c.pt")]
    )
    assert result.exit_code == 1 and "carries no textures" in result.output and "Traceback" not in result.output
    assert not (tmp_path / "c.pt").exists()
    calibration = Calibration(
        weights=tuple(float(i) for i in range(len(FEATURES))), bias=-1.0, fitted_on="labelled photographs"
    )
    single = write_calibration(faster, calibration, tmp_path / "single.pt")
    assert load_detector(single).calibration == calibration
    assert load_detector(faster).calibration is None  # the source is left as it was
    pair = write_calibration(save_ensemble([faster, faster], tmp_path / "pair.pt"), calibration, tmp_path / "pair.pt")
    assert load_detector(pair).calibration == calibration


def test_lookalikes_are_refused_for_a_model_without_textures_and_written_into_one_that_has_them(
    trained, dataset, tmp_path
):
    from workers.train.checkpoint import load_detector, save_ensemble, write_lookalikes

    faster = trained["checkpoints"]["faster_rcnn"]
    folder = dataset / "images"
    result = runner.invoke(
        make_app(), ["lookalikes", "--model", str(faster), "--folder", str(folder), "--out", str(tmp_path / "l.pt")]
    )
    assert result.exit_code == 1 and "carries no textures" in result.output and not (tmp_path / "l.pt").exists()
    sheets = {"other form": np.full((40, 30, 3), 200, np.uint8)}
    pair = write_lookalikes(save_ensemble([faster, faster], tmp_path / "pair.pt"), sheets, tmp_path / "pair.pt")
    loaded = load_detector(pair)
    assert set(loaded.lookalikes) == {"other form"} and loaded.lookalikes["other form"].shape == (40, 30)
    assert load_detector(write_lookalikes(pair, {}, tmp_path / "none.pt")).lookalikes is None


def test_detect_every_view_turns_the_cascade_off_for_the_call(trained, dataset, tmp_path, monkeypatch):
    from workers.train import checkpoint

    images = [str(sorted((dataset / "images").glob("*.png"))[0])]
    asked = []
    detect_ensemble = checkpoint.detect_ensemble
    monkeypatch.setattr(
        checkpoint,
        "detect_ensemble",
        lambda *args, **options: asked.append(options) or detect_ensemble(*args, **options),
    )
    model = ["--model", str(trained["checkpoints"]["faster_rcnn"])]
    for flag in ([], ["--every-view"]):
        result = runner.invoke(make_app(), ["detect", *model, *images, "--out-dir", str(tmp_path), *flag])
        assert result.exit_code == 0, result.output
    assert [options["every_view"] for options in asked] == [False, True]
