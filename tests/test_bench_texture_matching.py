"""bench/texture_matching.py: the texture check's two matchers check the same network detections
on each set, and the report gives each one's time, mAP and confirmations, their speed ratio and
the share of images they check alike; each --sharpen amount adds FLANN's check at that sharpening."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import texture_matching  # noqa: E402
from tests.sheet_sets import CLASSES, class_textures, sheet_set  # noqa: E402
from workers.train import texture_check  # noqa: E402


def test_both_matchers_check_the_same_detections_and_the_report_compares_them(tmp_path, capsys):
    from tests.workers.train.training_helpers import config
    from workers.train.training import train_detector

    textures = class_textures()
    samples = sheet_set(tmp_path / "sheets", 2, textures)  # one sheet of each class
    model = tmp_path / "checked.pt"
    searching = config(family="faster_rcnn", texture_check=True, texture_search=True)
    train_detector(samples, None, 1, searching, CLASSES, model, seed=0, textures=textures)
    out = tmp_path / "matching.json"
    report = texture_matching.main(
        [
            "--model",
            str(model),
            "--set",
            str(tmp_path / "sheets"),
            "--out",
            str(out),
            "--sharpen",
            "1",
            "--sharpen",
            "2",
        ]
    )
    assert json.loads(out.read_text()) == json.loads(json.dumps(report, default=float))
    result = report["sets"]["sheets"]
    assert result["images"] == 2
    brute_force, flann = result["brute_force"], result["flann"]
    assert report["sharpen_built"] == texture_check.SHARPEN_AMOUNT
    for matcher in (brute_force, flann, result["flann_sharpen_1"], result["flann_sharpen_2"]):
        assert matcher["seconds_per_image"] > 0 and matcher["build_seconds"] > 0
        # Every sheet is plain to see: the search finds each, whatever the barely trained network says.
        assert matcher["confirmed"] >= 2 and matcher["map"] == pytest.approx(1.0)
    assert result["speedup"] == pytest.approx(brute_force["seconds_per_image"] / flann["seconds_per_image"])
    assert 0.0 <= result["images_same"] <= 1.0

    # A set that is not there is named, with the command that renders bench/wild.py's sets.
    with pytest.raises(SystemExit):
        texture_matching.main(["--model", str(model), "--set", str(tmp_path / "nowhere")])
    error = capsys.readouterr().err
    assert "nowhere" in error and "python bench/wild.py --sets-only" in error
    # A negative sharpening is refused by name.
    with pytest.raises(SystemExit):
        texture_matching.main(["--model", str(model), "--set", str(tmp_path / "sheets"), "--sharpen", "-1"])
    assert "--sharpen must be at least 0" in capsys.readouterr().err


def test_outputs_are_the_same_only_with_the_same_boxes_classes_and_confirmations():
    first = {"boxes": np.array([[0, 0, 10, 10]], np.float32), "labels": np.array([1]), "confirmed": np.array([True])}
    assert texture_matching.same_detections(first, {**first, "boxes": first["boxes"] + 0.4})
    assert not texture_matching.same_detections(first, {**first, "boxes": first["boxes"] + 2})
    assert not texture_matching.same_detections(first, {**first, "labels": np.array([0])})
    assert not texture_matching.same_detections(first, {**first, "confirmed": np.array([False])})
    empty = {"boxes": np.zeros((0, 4), np.float32), "labels": np.zeros(0, np.int64), "confirmed": np.zeros(0, bool)}
    assert not texture_matching.same_detections(first, empty) and texture_matching.same_detections(empty, empty)
