"""bench/shown_share.py: what the shown-share rule would withdraw of true sheets, on a set."""

from __future__ import annotations

import json

import pytest

from bench import shown_share
from tests.sheet_sets import class_textures, sheet_set


def test_small_sheets_on_grain_are_confirmed_and_the_rule_as_built_withdraws_none(tmp_path, capsys):
    sheet_set(tmp_path / "set", 2, class_textures())
    out = tmp_path / "shown.json"
    report = shown_share.main(
        ["--data", str(tmp_path / "set"), "--keypoints", "2", "20", "--thresholds", "0.55", "--out", str(out)]
    )
    capsys.readouterr()
    assert json.loads(out.read_text()) == json.loads(json.dumps(report))
    assert report["true_sheets"] == 2 and report["confirmed"] == 2
    assert set(report["withdrawn"]) == {"keypoints 2, below 0.55", "keypoints 20, below 0.55"}
    assert report["withdrawn"]["keypoints 20, below 0.55"] == 0  # as built: grain is no unexplained print
    assert report["headline"].startswith("2 of 2 true sheets confirmed") and report["machine"]["cores"]


def test_a_folder_without_annotations_is_refused_by_name(tmp_path):
    with pytest.raises(SystemExit, match="no annotations.json"):
        shown_share.main(["--data", str(tmp_path)])
