"""bench/calibrate.py: the calibration is fitted on the even images' detections as the detector
draws them (its cascade included) and reported on the odd ones beside the tiers and the recipe."""

from __future__ import annotations

import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import calibrate  # noqa: E402
from tests.sheet_sets import CLASSES, class_textures, sheet_set  # noqa: E402


def test_the_calibration_is_fitted_on_the_cascades_detections_and_reported_beside_the_tiers(tmp_path, monkeypatch):
    from tests.workers.train.training_helpers import config
    from workers.train.calibration import Calibration
    from workers.train.checkpoint import Cascade
    from workers.train.training import train_detector

    textures = class_textures()
    sheets = tmp_path / "sheets"
    sheet_set(sheets, 6, textures)
    from workers.train.data import load_coco_dataset

    samples, _ = load_coco_dataset(sheets)
    model = tmp_path / "model.pt"
    views = config(texture_check=True, texture_search=True, test_sizes=[64, 96], test_turns=[0, 1], view_vote=0.7)
    train_detector(samples, None, 2, views, CLASSES, model, textures=textures)
    sent_on = []
    rule = Cascade.again
    monkeypatch.setattr(Cascade, "again", lambda self, checked: sent_on.append(rule(self, checked)) or sent_on[-1])

    out = tmp_path / "calibration.json"
    argv = ["--model", str(model), "--data", str(sheets), "--cache", str(tmp_path / "cache"), "--out", str(out)]
    report = calibrate.main(argv)
    assert json.loads(out.read_text()) == json.loads(json.dumps(report, default=float))
    assert report["cascade"] is True
    # Every image's first view was checked (and each odd one again with the fitted calibration).
    assert len(sent_on) == 6 + 3
    Calibration.from_dict(report["calibration"])  # a calibration this version reads
    entry = report["sets"]["sheets"]
    assert entry["report_images"] == 3
    assert set(entry) >= {"tiers", "calibrated", "confirmed_only", "keypoint_baseline"}
    # A second run reads the network's detections back from the cache and fits the same.
    again = calibrate.main(argv)
    assert again["calibration"] == report["calibration"]
