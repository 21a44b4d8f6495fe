"""bench/detect_startup.py: fresh processes detect one image without the texture check's cache,
with an empty one and with the one the cold run wrote; the cache changes nothing they find, and
the warm run reads it without writing."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import detect_startup  # noqa: E402
from tests.sheet_sets import CLASSES, class_textures, sheet_set  # noqa: E402


def test_each_case_runs_in_its_own_process_and_the_cache_changes_the_time_not_the_answer(tmp_path, capsys):
    from tests.workers.train.training_helpers import config
    from workers.train.training import train_detector

    textures = class_textures()
    samples = sheet_set(tmp_path / "sheets", 2, textures)
    model = tmp_path / "checked.pt"
    train_detector(
        samples,
        None,
        1,
        config(family="faster_rcnn", texture_check=True, texture_search=True),
        CLASSES,
        model,
        seed=0,
        textures=textures,
    )
    out = tmp_path / "startup.json"
    report = detect_startup.main(
        ["--model", str(model), "--image", str(samples[0].image_path), "--repeats", "1", "--out", str(out)]
    )
    assert json.loads(out.read_text()) == json.loads(json.dumps(report, default=float))
    for case in detect_startup.CASES:
        result = report[case]
        assert result["texture_checked"] and len(result["runs"]) == 1
        assert set(result["median_seconds"]) == set(detect_startup.PHASES)
        assert all(value > 0 for value in result["median_seconds"].values())
        assert result["median_wall_seconds"] >= sum(result["median_seconds"].values())
    # The search finds the plain sheet whatever the network says: the same box in every case.
    assert report["same_detections"] and report["cache_warm"]["detections"] == [
        report["without_cache"]["detections"][0]
    ] != [0]
    assert report["cache_files_written"] == [2] and report["warm_run_wrote"] is False
    assert report["texture_check_speedup"] == pytest.approx(
        report["without_cache"]["median_seconds"]["texture_check"]
        / report["cache_warm"]["median_seconds"]["texture_check"]
    )

    with pytest.raises(SystemExit):
        detect_startup.main(["--model", str(tmp_path / "missing.pt"), "--image", str(samples[0].image_path)])
    assert "missing.pt" in capsys.readouterr().err
