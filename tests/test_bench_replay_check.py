"""bench/replay_check.py: the check and the cascade replayed on stored network detections draw,
as built, the boxes detect_object draws; a variant's constants hold inside it alone; the network
runs once per set and first-view size."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import replay_check  # noqa: E402
from tests.sheet_sets import CLASSES, class_textures, sheet_set  # noqa: E402


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    from tests.workers.train.training_helpers import config
    from workers.train.training import train_detector

    folder = tmp_path_factory.mktemp("replay")
    textures = class_textures()
    samples = sheet_set(folder / "sheets", 4, textures)
    model = folder / "model.pt"
    views = config(texture_check=True, texture_search=True, test_sizes=[64, 96], test_turns=[0, 1], view_vote=0.7)
    train_detector(samples, None, 2, views, CLASSES, model, seed=0, textures=textures)
    return model, folder / "sheets", samples


def test_as_built_the_replay_draws_what_detect_object_draws(trained, tmp_path):
    from bench.calibrate import network_detections
    from workers.train.checkpoint import detect_object, load_detector
    from workers.train.data import read_image_rgb

    model, _, samples = trained
    detector = load_detector(model, device="cpu")
    assert detector.active_cascade() is not None  # two sizes, two turns and a check: the cascade runs
    images = [read_image_rgb(sample.image_path) for sample in samples]
    asked = []

    def network_for(first_size):
        asked.append(first_size)
        return network_detections(detector, samples, CLASSES, tmp_path / f"{first_size}.pkl", first_size)[0]

    found, cost = replay_check.replay(detector, images, network_for, replay_check.Variant(replay_check.AS_BUILT))
    assert asked == [96]  # the cascade's first view: the largest size
    for replayed, drawn in zip(found, detect_object(detector, images)):
        for key in ("boxes", "scores", "labels", "confirmed"):
            np.testing.assert_array_equal(replayed[key], drawn[key])
    assert 0.0 <= cost["second_pass"] <= 1.0 and cost["check_seconds_per_image"] > 0

    # Nothing can be confirmed: every image goes on to every view; the constant is restored after.
    from workers.train import texture_check

    before = texture_check.MIN_INLIERS
    strict = replay_check.parse_variant("none confirmed: texture_check.MIN_INLIERS=1000000, cascade.size=64")
    assert strict.constants == {"MIN_INLIERS": 1000000} and strict.cascade == {"size": 64}
    found, cost = replay_check.replay(detector, images, network_for, strict)
    assert asked == [96, 64] and cost["second_pass"] == 1.0
    assert not any(image["confirmed"].any() for image in found)
    assert texture_check.MIN_INLIERS == before


def test_the_report_scores_each_variant_whole_and_by_halves_and_reads_the_network_back(trained, tmp_path, capsys):
    model, sheets, _ = trained
    out = tmp_path / "replay.json"
    argv = ["--model", str(model), "--data", str(sheets), "--cache", str(tmp_path / "cache"), "--out", str(out)]
    report = replay_check.main([*argv, "--variant", "fewer checks: texture_check.FLANN_CHECKS=32"])
    capsys.readouterr()
    assert json.loads(out.read_text()) == json.loads(json.dumps(report, default=float))
    rows = report["sets"]["sheets"]["variants"]
    assert list(rows) == ["as built", "fewer checks"]
    for row in rows.values():
        assert row["images"] == 4 and set(row["parts"]) == {"even", "odd"} and row["parts"]["odd"]["images"] == 2
        assert 0.0 <= row["map"] <= 1.0 and "seconds_per_image" not in row
    assert report["variants"]["fewer checks"]["constants"] == {"FLANN_CHECKS": 32}
    assert report["headline"].startswith("sheets: as built ") and report["machine"]["cores"]
    cached = sorted(path.name for path in (tmp_path / "cache").iterdir())
    assert len(cached) == 1 and cached[0].endswith("-sheets-96.pkl")


@pytest.mark.parametrize(
    ("variant", "named"),
    [
        ("no colon at all", "expected NAME: SETTING"),
        ("x: texture_check.NO_SUCH=1", "neither a texture_check constant nor a cascade field"),
        ("x: cascade.speed=1", "neither a texture_check constant nor a cascade field"),
        ("x: texture_check.MIN_INLIERS=twelve", "is not a Python literal"),
        ("x: MIN_INLIERS", "is not texture_check.CONSTANT=VALUE"),
        ("as built: texture_check.MIN_INLIERS=3", "variant names must differ"),
    ],
)
def test_a_bad_variant_is_refused_by_name(trained, variant, named, capsys):
    model, sheets, _ = trained
    with pytest.raises(SystemExit, match=named):
        replay_check.main(["--model", str(model), "--data", str(sheets), "--variant", variant])
