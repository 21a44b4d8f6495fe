"""bench/detect_speed.py: on each set, the detector's views one forward each, run together and
through the runtime graph find the same boxes; the cascade (its views in onnxruntime or torch),
its first view alone and the keypoint recipe beside them, each timed against the recipe."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import detect_speed  # noqa: E402
from tests.sheet_sets import CLASSES, class_textures, sheet_set  # noqa: E402


def test_every_way_of_running_the_views_is_scored_on_each_set_against_the_keypoint_recipe(tmp_path, capsys):
    import cv2

    from tests.workers.train.training_helpers import config
    from workers.train.checkpoint import load_detector, save_ensemble
    from workers.train.data import read_image_rgb
    from workers.train.training import train_detector

    textures = class_textures()
    # Two images a set, one sheet of each class: every row detects and checks each image of each set.
    samples = sheet_set(tmp_path / "sheets", 2, textures)
    views = {"test_sizes": [64, 96], "test_turns": [0, 1], "view_vote": 0.7}
    checked = config(family="faster_rcnn", texture_check=True, texture_search=True, **views)
    members = []
    for seed in (0, 1):
        members.append(tmp_path / f"member{seed}.pt")
        train_detector(samples, None, 2, checked, CLASSES, members[-1], seed=seed, textures=textures)
    model = save_ensemble(members, tmp_path / "pair.pt")
    large = tmp_path / "large"  # the same scenes at twice the size
    (large / "images").mkdir(parents=True)
    document = json.loads((tmp_path / "sheets" / "annotations.json").read_text())
    for image in document["images"]:
        pixels = cv2.imread(str(tmp_path / "sheets" / image["file_name"]))
        cv2.imwrite(str(large / image["file_name"]), cv2.resize(pixels, None, fx=2, fy=2))
        image["width"], image["height"] = 2 * image["width"], 2 * image["height"]
    for annotation in document["annotations"]:
        annotation["bbox"] = [2 * v for v in annotation["bbox"]]
    (large / "annotations.json").write_text(json.dumps(document))

    out = tmp_path / "speed.json"
    report = detect_speed.main(
        ["--model", str(model), "--data", str(tmp_path / "sheets"), str(large), "--out", str(out)]
    )
    capsys.readouterr()
    assert json.loads(out.read_text()) == json.loads(json.dumps(report, default=float))
    assert report["views"] == {"sizes": [64, 96], "turns": [0, 1]} and report["members"] == 2
    assert report["runtime_graph"] == f"{model}.onnx" and Path(report["runtime_graph"]).is_file()  # written
    assert report["runtime_graph_open_seconds"] > 0
    assert list(report["sets"]) == ["sheets", "large"]
    assert [report["sets"][name]["frame"] for name in ("sheets", "large")] == ["200x150", "400x300"]
    for entry in report["sets"].values():
        rows = entry["rows"]
        assert entry["check_keypoints_seconds_per_image"] > 0
        assert list(rows) == list(detect_speed.ROWS)  # every row, in the table's order
        # Drawing every name a sheet is given draws at least the boxes one name per sheet does.
        # Each rule only takes boxes from over the cut: without it at least as many are drawn.
        for name in ("cascade, every name drawn", "cascade, unmatched drawn"):
            assert rows[name]["at_threshold"]["drawn"] >= rows["cascade"]["at_threshold"]["drawn"]
        # The views one forward each, together, and through the runtime graph: one answer; so is
        # the cascade's with its views in torch or in onnxruntime.
        for name in ("every view together", "every view, onnxruntime"):
            assert rows[name]["map"] == rows["every view alone"]["map"]
            assert rows[name]["at_threshold"] == rows["every view alone"]["at_threshold"]
        assert rows["cascade, torch"]["map"] == rows["cascade"]["map"]
        assert rows["cascade, torch"]["at_threshold"] == rows["cascade"]["at_threshold"]
        assert 0.0 <= rows["cascade"]["second_pass"] <= 1.0
        assert rows["keypoints"]["times_keypoints"] == 1.0
        for values in rows.values():
            assert values["images"] == 2 and values["seconds_per_image"] > 0
            assert values["times_keypoints"] == values["seconds_per_image"] / rows["keypoints"]["seconds_per_image"]
    assert "sheets (2 images, 200x150): every view alone" in report["headline"]
    assert {"cpu", "cores", "commit"} <= set(report["machine"])

    # --rows runs the rows named (';' between them: their names hold commas), in the table's
    # order; a row that does not exist is named.
    some = detect_speed.main(["--model", str(model), "--data", str(large), "--rows", "keypoints; cascade, torch"])
    capsys.readouterr()
    assert list(some["sets"]["large"]["rows"]) == ["cascade, torch", "keypoints"]
    assert some["sets"]["large"]["rows"]["cascade, torch"]["map"] == report["sets"]["large"]["rows"]["cascade"]["map"]
    with pytest.raises(SystemExit):
        detect_speed.main(["--model", str(model), "--data", str(large), "--rows", "cascade;fastest"])
    assert "no row ['fastest']" in capsys.readouterr().err

    # The plain row is the detector's own answer, box for box.
    from workers.train.checkpoint import detect_object

    detector = load_detector(model)
    detector.cascade = None
    images = [read_image_rgb(sample.image_path) for sample in samples]
    for alone, together in zip(detect_speed.views_alone(detector, images), detect_object(detector, images)):
        assert len(alone["scores"]) > 0
        for key in ("boxes", "scores", "labels", "confirmed"):
            np.testing.assert_allclose(alone[key], together[key], rtol=0, atol=1e-4)
