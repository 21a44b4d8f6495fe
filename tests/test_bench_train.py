"""bench/train.py's settings: every family compares at one view, built from configs/quick.yaml."""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench import train  # noqa: E402
from foldwise.config import load_config  # noqa: E402


def test_the_families_compare_at_one_view_of_quick_yamls_detector():
    quick = load_config(ROOT / "configs" / "quick.yaml").detector
    assert quick.test_sizes and quick.test_turns  # what there is to strip
    settings = train.quick_settings()
    base = settings["detector"]
    assert settings["source"] == "configs/quick.yaml"
    assert base.test_sizes == () and base.test_turns == ()  # one inference per image for every family
    for family in ("faster_rcnn", "fast_rcnn", "yolo"):  # yolo reads neither: its config must validate
        config = train.family_config(base, family, input_size=128, threads=1, batch_size=None)
        assert config.family == family and config.test_sizes == () and config.test_turns == ()
