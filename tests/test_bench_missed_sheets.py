"""bench/missed_sheets.py: for each true sheet, what the texture check has to work with, and
whether the detector draws it; the drawn and the missed counted apart."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import missed_sheets  # noqa: E402
from tests.sheet_sets import CLASSES, class_textures, sheet_set  # noqa: E402


def _trained(tmp_path, texture_check: bool) -> Path:
    from tests.workers.train.training_helpers import config
    from workers.train.training import train_detector

    textures = class_textures()
    samples = sheet_set(tmp_path / f"train-{texture_check}", 2, textures)
    model = tmp_path / f"model-{texture_check}.pt"
    checked = config(family="faster_rcnn", texture_check=texture_check, texture_search=texture_check)
    train_detector(samples, None, 1, checked, CLASSES, model, seed=0, textures=textures)
    return model


def test_a_printed_sheet_is_drawn_and_a_box_on_bare_ground_is_missed_for_want_of_matches(tmp_path, capsys):
    model = _trained(tmp_path, texture_check=True)
    data = tmp_path / "sheets"
    sheet_set(data, 2, class_textures())
    # A third true box on the first image's bare ground (the sheet lies left of x = 170): nothing
    # of a texture to match there.
    coco = json.loads((data / "annotations.json").read_text())
    coco["annotations"].append({"id": 3, "image_id": 1, "category_id": 1, "bbox": [170.0, 115.0, 29.0, 34.0]})
    (data / "annotations.json").write_text(json.dumps(coco))

    out = tmp_path / "missed.json"
    report = missed_sheets.main(["--model", str(model), "--data", str(data), "--out", str(out)])
    capsys.readouterr()
    assert json.loads(out.read_text()) == json.loads(json.dumps(report))
    printed = [row for row in report["sheets"] if row["side_px"] > 60]
    (bare,) = [row for row in report["sheets"] if row["side_px"] < 60]
    assert len(printed) == 2
    for row in printed:  # a plain printed sheet: matched, fitted given its box, found by the search, drawn
        assert row["class_matches"] >= missed_sheets.FEW_MATCHES and row["fits_given_true_box"]
        assert row["fit_outline_iou"] >= 0.5 and row["found_by_search"] and row["drawn"]
    assert bare["class_matches"] == 0 and not bare["fits_given_true_box"] and bare["fit_outline_iou"] is None
    assert not bare["drawn"] and not bare["found_by_search"]
    drawn, missed = report["groups"]["drawn"], report["groups"]["missed"]
    assert (drawn["sheets"], drawn["fit_given_true_box"], drawn["found_by_search"]) == (2, 2, 2)
    assert (missed["sheets"], missed["under_few_matches"], missed["fit_given_true_box"]) == (1, 1, 0)
    assert report["headline"].startswith("2 of 3 true sheets drawn at 0.8; of the 1 missed, 1 hold under 6")
    assert report["machine"]["cores"]


def test_a_detector_without_a_texture_check_or_a_missing_set_is_refused_by_name(tmp_path):
    model = _trained(tmp_path, texture_check=False)
    data = tmp_path / "sheets"
    sheet_set(data, 1, class_textures())
    with pytest.raises(SystemExit, match="has no texture check"):
        missed_sheets.main(["--model", str(model), "--data", str(data)])
    with pytest.raises(SystemExit, match="no annotations.json"):
        missed_sheets.main(["--model", str(model), "--data", str(tmp_path)])
    with pytest.raises(SystemExit, match="no such checkpoint"):
        missed_sheets.main(["--model", str(tmp_path / "gone.pt"), "--data", str(data)])
