"""Phone photographs end to end: a set of portrait, landscape and EXIF-turned JPEGs, and its
twin with every photo stored turned under an EXIF tag, give the same boxes in train,
evaluate and detect; evaluate reports precision, recall, the confusion and the worst images;
detect writes where --out says and reports a shrunk photo's boxes in its own pixels."""

from __future__ import annotations

import json

import numpy as np
import photo_sets  # tests/workers/train is on sys.path
import pytest
import torch
import typer
from PIL import Image
from typer.testing import CliRunner

from foldwise.config import DetectorConfig
from foldwise.images import read_image
from workers.train import data
from workers.train.cli import register
from workers.train.data import load_dataset
from workers.train.training import train_detector

torch.set_num_threads(1)
app = typer.Typer()
register(app)
runner = CliRunner()


def _config(**changes) -> DetectorConfig:
    small = {"family": "faster_rcnn", "input_size": 64, "batch_size": 2, "num_threads": 1, "device": "cpu", "warmup_iterations": 1,
             "rpn_proposals_train": 40, "fpn_channels": 32, "representation_size": 64, "rpn_proposals_test": 20, "roi_samples_per_image": 32}  # fmt: skip
    return DetectorConfig(**{**small, **changes})


@pytest.fixture(scope="module")
def sets(tmp_path_factory):
    """(the set as labelled, its EXIF twin): 9 photos of 3 shapes, 3 of them stored turned."""
    root = tmp_path_factory.mktemp("photos")
    original = photo_sets.write_coco(root / "original", photo_sets.photos(9, seed=7)).parent
    photo_sets.copy_with_twins(original, root / "twin", orientation=6)
    return original, root / "twin"


@pytest.fixture(scope="module")
def model(sets, tmp_path_factory):
    samples, classes = load_dataset(sets[0])
    path = tmp_path_factory.mktemp("model") / "m.pt"
    train_detector(samples, None, 3, _config(), classes, path, seed=1)
    return path


def test_the_twin_set_is_stored_turned_and_reads_the_same(sets):
    original, twin = sets
    for path in sorted((original / "images").glob("*.jpg")):
        stored = Image.open(twin / "images" / path.name)
        assert stored.getexif().get(0x0112) == 6
        np.testing.assert_array_equal(read_image(twin / "images" / path.name)[0], read_image(path)[0])


def test_train_sees_the_same_photos_and_boxes_from_either_set(sets, tmp_path):
    losses = []
    for folder in sets:
        samples, classes = load_dataset(folder)
        stats = train_detector(samples, None, 2, _config(), classes, tmp_path / f"{folder.name}.pt", seed=3)
        losses.append(stats.losses)
    assert losses[0] == losses[1]


def test_evaluate_gives_the_same_scores_for_either_set_and_writes_a_report(sets, model, tmp_path):
    payloads = []
    for folder in sets:
        target, report = tmp_path / f"{folder.name}.json", tmp_path / f"report-{folder.name}"
        result = runner.invoke(app, [
            "evaluate", "--model", str(model), "--data", str(folder), "--threshold", "0.05", "--json", str(target),
            "--report", str(report), "--worst", "4",
        ])  # fmt: skip
        assert result.exit_code == 0, result.output
        assert "At the threshold" in result.output and "precision" in result.output and "recall" in result.output
        payloads.append(json.loads(target.read_text()))
        page = (report / "index.html").read_text()
        pictures = sorted(report.glob("*.png"))
        assert 1 <= len(pictures) <= 4 and all(picture.name in page for picture in pictures)
        assert "false box" in page and "precision" in page
    for payload in payloads:
        payload.pop("seconds"), payload.pop("data")
    assert payloads[0] == payloads[1]
    at = payloads[0]["at_threshold"]
    assert at["true_positives"] + at["false_negatives"] == payloads[0]["num_ground_truth"]


def test_detect_writes_to_out_and_gives_a_photo_and_its_twin_the_same_boxes(sets, model, tmp_path):
    original, twin = sets
    found = []
    for folder in sets:
        images = sorted(str(path) for path in (folder / "images").glob("*.jpg"))
        out, target = tmp_path / f"drawn-{folder.name}", tmp_path / f"{folder.name}.json"
        result = runner.invoke(
            app,
            ["detect", "--model", str(model), *images, "--out", str(out), "--threshold", "0.0", "--json", str(target)],
        )
        assert result.exit_code == 0, result.output
        assert len(list(out.glob("*.png"))) == len(images)
        document = json.loads(target.read_text())
        found.append([(item["width"], item["height"], item["detections"]) for item in document["images"]])
    assert found[0] == found[1]
    assert any(width < height for width, height, _ in found[0]) and any(width > height for width, height, _ in found[0])


def test_detect_reports_a_shrunk_photos_boxes_in_its_own_pixels(sets, model, tmp_path, monkeypatch):
    photo = sorted((sets[1] / "images").glob("*.jpg"))[0]  # 80 x 48 as displayed, stored turned
    small = tmp_path / "small.png"
    Image.fromarray(read_image(photo, max_side=40)[0]).save(small)

    def detect(image, max_side):
        monkeypatch.setattr(data, "PHOTO_MAX_SIDE", max_side)
        target = tmp_path / f"{max_side}.json"
        result = runner.invoke(
            app,
            [
                "detect",
                "--model",
                str(model),
                str(image),
                "--out",
                str(tmp_path / "d"),
                "--threshold",
                "0",
                "--json",
                str(target),
            ],
        )
        assert result.exit_code == 0, result.output
        return json.loads(target.read_text())["images"][0]

    shrunk, reference = detect(photo, 40), detect(small, 2048)
    assert (shrunk["width"], shrunk["height"]) == (80, 48) and (reference["width"], reference["height"]) == (40, 24)
    assert len(shrunk["detections"]) == len(reference["detections"]) > 0
    for a, b in zip(shrunk["detections"], reference["detections"]):
        assert a["score"] == b["score"]
        np.testing.assert_allclose(a["box"], [2 * v for v in b["box"]], atol=0.02)


def test_finetune_gives_the_same_sweep_for_either_set(sets, model, tmp_path):
    curves = []
    for folder in sets:
        out = tmp_path / folder.name
        result = runner.invoke(
            app,
            [
                "finetune",
                "--model",
                str(model),
                "--data",
                str(folder),
                "--sweep",
                "0,3",
                "--iterations",
                "1",
                "--out",
                str(out),
            ],
        )
        assert result.exit_code == 0, result.output
        curves.append(json.loads((out / "fig11.json").read_text()))
    assert curves[0] == curves[1] and [point["n"] for point in curves[0]] == [0, 3]
