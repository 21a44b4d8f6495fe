"""bench/train.py's settings: every family compares at one view, built from configs/quick.yaml."""

from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import pytest  # noqa: E402

from bench import train  # noqa: E402
from foldwise.config import load_config  # noqa: E402


def test_the_families_compare_at_one_view_of_quick_yamls_detector():
    quick = load_config(ROOT / "configs" / "quick.yaml").detector
    assert quick.test_sizes and quick.test_turns  # what there is to strip
    settings = train.quick_settings()
    base = settings["detector"]
    assert settings["source"] == "configs/quick.yaml"
    assert base.test_sizes == () and base.test_turns == ()  # one inference per image for every family
    # The networks alone: quick.yaml's texture check would need the textures, which the bench's
    # canonical sets do not carry (training refused to start without them).
    assert quick.texture_check and not base.texture_check and not base.texture_search
    for family in ("faster_rcnn", "fast_rcnn", "yolo"):  # yolo reads neither: its config must validate
        config = train.family_config(base, family, input_size=128, threads=1, batch_size=None)
        assert config.family == family and config.test_sizes == () and config.test_turns == ()
        assert not config.texture_check


def test_score_times_a_second_pass_and_reports_the_first_beside_it(tmp_path, monkeypatch):
    """Throughput is a warm pass: a first pass over every image runs untimed (on a GPU it pays
    one-off costs per batch shape), and its own rate is reported apart; the mAP comes from the
    timed pass's detections."""
    from tests.workers.train.training_helpers import CLASSES, config, synthetic_samples
    from workers.train import checkpoint as checkpoint_module
    from workers.train.training import train_detector

    samples = synthetic_samples(tmp_path / "images", n=5)
    weights = tmp_path / "yolo.pt"
    train_detector(
        samples,
        None,
        1,
        config(family="yolo", backbone="mobilenet_v3_small", pretrained="none"),
        CLASSES,
        weights,
        seed=0,
    )
    passes = []
    real_detect = checkpoint_module.detect_object

    def counting_detect(detector, images, **options):
        passes.append(len(images))
        return real_detect(detector, images, **options)

    monkeypatch.setattr(checkpoint_module, "detect_object", counting_detect)
    result = train.score(weights, samples, CLASSES, batch_size=2)
    assert passes == [5, 5]  # every image twice, the second pass timed
    assert result["first_pass_images_per_s"] > 0 and result["inference_images_per_s"] > 0
    assert result["inference_images_per_s"] == pytest.approx(5 / result["inference_seconds"])
    assert 0.0 <= result["map_unthresholded"] <= 1.0


def test_the_roi_align_baseline_runs_torchvisions_kernel_and_then_ours_again(monkeypatch):
    """--compare-roi-align's baseline: inside the context a training PyramidRoIAlign does not
    gather; after it (an exception included) it does."""
    from collections import OrderedDict

    import torch

    import workers.train.detectors.roi_align as roi_align

    gathered = []
    real = roi_align.pyramid_roi_align
    monkeypatch.setattr(roi_align, "pyramid_roi_align", lambda *a, **k: gathered.append(1) or real(*a, **k))
    pool = roi_align.PyramidRoIAlign(["0"], 7, 1).train()
    features = OrderedDict([("0", torch.randn(1, 4, 16, 16, requires_grad=True))])
    boxes = [torch.tensor([[4.0, 4.0, 60.0, 90.0]])]

    with train.torchvision_roi_align(True):
        baseline = pool(features, boxes, [(128, 128)])
    assert gathered == []
    with pytest.raises(RuntimeError), train.torchvision_roi_align(True):
        raise RuntimeError("a failed run")
    ours = pool(features, boxes, [(128, 128)])
    assert gathered == [1]
    torch.testing.assert_close(ours, baseline, rtol=1e-4, atol=1e-4)


def test_a_run_compared_with_another_machines_gives_each_familys_rate_ratios_in_its_headline():
    here = {
        "faster_rcnn": {"train_images_per_s": 10.0, "inference_images_per_s": 40.0, "map": 0.5},
        "yolo": {"train_images_per_s": 20.0, "inference_images_per_s": None, "map": 0.25},
    }
    there = {
        "machine": {"gpu": "a GPU"},
        "families": {"faster_rcnn": {"train_images_per_s": 100.0, "inference_images_per_s": 200.0}},
    }
    comparison = train.compared(here, there)
    assert comparison["ratios"] == {
        "faster_rcnn": {"train_images_per_s": 0.1, "inference_images_per_s": 0.2},
        "yolo": {},
    }
    report = {
        "machine": {"gpu": None, "cores": 2},
        "settings": {"iterations": 100, "train_images": 300},
        "families": here,
        "compared_with": comparison,
    }
    line = train.headline(report)
    assert line.startswith("2 CPU cores, 100 iterations on 300 canonical images: ")
    assert (
        "faster_rcnn train 10.0 img/s, detect 40.0 img/s, mAP 0.500" in line and "0.1x, 0.2x the compared run" in line
    )
    assert "yolo train 20.0 img/s" in line and line.count("the compared run") == 1
