"""build_detector: each family follows torchvision's detection interface on small images."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from foldwise.config import DetectorConfig
from tests.workers.train.small_detectors import SMALL
from workers.train.detectors import DetectorBuildError, build_detector
from workers.train.detectors.backbones import PretrainedWeightsMissing, anchor_sizes, imagenet_weights_path
from workers.train.detectors.fast_rcnn import tensor_to_uint8
from workers.train.detectors.views import merge_detections

torch.set_num_threads(1)


def batch(size=64, seed=0, empty_second=False):
    """Two noisy images with a textured rectangle each (the second one empty if asked)."""
    rng = np.random.default_rng(seed)
    images, targets = [], []
    for index in range(2):
        pixels = rng.integers(60, 120, (size, size, 3)).astype(np.uint8)
        box = np.array([[8 + 4 * index, 10, 40 + 4 * index, 50]], np.float32)
        labels = np.array([index + 1])
        if empty_second and index == 1:
            box, labels = np.zeros((0, 4), np.float32), np.zeros((0,), np.int64)
        else:
            x0, y0, x1, y1 = box[0].astype(int)
            pixels[y0:y1, x0:x1] = rng.integers(150, 255, 3)
            pixels[y0:y1:4, x0:x1] = 0
        images.append(torch.from_numpy(pixels).permute(2, 0, 1).float() / 255)
        targets.append({"boxes": torch.from_numpy(box), "labels": torch.as_tensor(labels, dtype=torch.int64)})
    return images, targets


EXPECTED_LOSSES = {
    "faster_rcnn": {"loss_classifier", "loss_box_reg", "loss_objectness", "loss_rpn_box_reg"},
    "fast_rcnn": {"loss_classifier", "loss_box_reg"},
}


@pytest.mark.parametrize("family", ["faster_rcnn", "fast_rcnn"])
def test_training_forward_returns_finite_named_losses_that_backpropagate(family):
    torch.manual_seed(0)
    model = build_detector(DetectorConfig(family=family, **SMALL), num_classes=3)
    model.train()
    images, targets = batch()
    losses = model(images, targets)
    assert set(losses) == EXPECTED_LOSSES[family]
    assert all(value.dim() == 0 and torch.isfinite(value) for value in losses.values())
    sum(losses.values()).backward()
    head_weight = dict(model.named_parameters())["roi_heads.box_predictor.cls_score.weight"]
    assert head_weight.shape == (4, DetectorConfig(**SMALL).representation_size)  # 3 classes + background
    assert head_weight.grad is not None and torch.isfinite(head_weight.grad).all()


@pytest.mark.parametrize("family", ["faster_rcnn", "fast_rcnn"])
def test_images_without_objects_are_valid_training_data(family):
    torch.manual_seed(0)
    model = build_detector(DetectorConfig(family=family, **SMALL), num_classes=2)
    model.train()
    images, targets = batch(empty_second=True)
    losses = model(images, targets)
    assert all(torch.isfinite(value) for value in losses.values())
    only_empty = model(images[1:], targets[1:])
    assert all(torch.isfinite(value) for value in only_empty.values())
    assert float(only_empty["loss_box_reg"].detach()) == 0.0  # nothing to regress to


@pytest.mark.parametrize("family", ["faster_rcnn", "fast_rcnn"])
def test_eval_forward_gives_boxes_in_each_input_images_pixels(family):
    torch.manual_seed(0)
    config = DetectorConfig(family=family, box_score_threshold=0.0, detections_per_image=7, **SMALL)
    model = build_detector(config, num_classes=3).eval()
    rng = np.random.default_rng(1)
    # Not the input size, not square: the model resizes and maps boxes back.
    images = [
        torch.from_numpy(rng.integers(0, 256, (h, w, 3)).astype(np.uint8)).permute(2, 0, 1).float() / 255
        for h, w in [(80, 120), (50, 40)]
    ]
    with torch.no_grad():
        outputs = model(images)
    assert len(outputs) == 2
    for output, image in zip(outputs, images):
        height, width = image.shape[-2:]
        boxes, scores, labels = output["boxes"], output["scores"], output["labels"]
        assert boxes.shape[1] == 4 and len(boxes) == len(scores) == len(labels) <= 7
        assert len(boxes) > 0  # an untrained model with no score threshold still proposes
        assert (boxes[:, 0::2] <= width + 1e-3).all() and (boxes[:, 1::2] <= height + 1e-3).all()
        assert (boxes >= 0).all()
        assert labels.min() >= 1 and labels.max() <= 3  # 1-based, background never returned
        assert ((scores >= 0) & (scores <= 1)).all()


def test_fast_rcnn_proposals_come_from_the_image_only_and_are_cached():
    torch.manual_seed(0)
    model = build_detector(DetectorConfig(family="fast_rcnn", **SMALL), num_classes=2).eval()
    images, _ = batch(seed=4)
    pixels = tensor_to_uint8(images[0])
    np.testing.assert_array_equal(pixels.astype(np.float32) / 255, images[0].permute(1, 2, 0).numpy())
    cache = model.proposal_cache
    misses = cache.misses
    with torch.no_grad():
        first = model(images)
        second = model(images)
    assert cache.misses == misses + 2 and cache.hits >= 2
    for a, b in zip(first, second):
        assert torch.equal(a["boxes"], b["boxes"])
    proposals = model.proposals_for(images[0])
    assert proposals.shape[1] == 4 and len(proposals) <= SMALL["edge_boxes"]
    assert proposals[-1].tolist() == [0, 0, 64, 64]


def test_fast_rcnn_training_requires_targets():
    model = build_detector(DetectorConfig(family="fast_rcnn", **SMALL), num_classes=2).train()
    with pytest.raises(ValueError, match="targets are required"):
        model(batch()[0])


def test_mobilenet_320_variant_and_resnet_v2_build():
    torch.manual_seed(0)
    variant = build_detector(DetectorConfig(backbone="mobilenet_v3_large_320_fpn", **SMALL), num_classes=2)
    reference = build_detector(DetectorConfig(**SMALL), num_classes=2)
    assert [k for k, _ in variant.named_parameters()] == [k for k, _ in reference.named_parameters()]
    resnet = build_detector(DetectorConfig(backbone="resnet50_fpn_v2", **SMALL), num_classes=2).eval()
    with torch.no_grad():
        (output,) = resnet([torch.rand(3, 64, 64)])
    assert output["boxes"].shape[1] == 4
    assert all(p.requires_grad for p in resnet.backbone.parameters())  # random init trains every layer


def test_anchor_sizes_span_the_configured_range():
    config = DetectorConfig(input_size=128)
    sizes = anchor_sizes(config, levels=4)
    flat = [s for level in sizes for s in level]
    assert len(sizes) == 4 and all(len(level) == 2 for level in sizes)
    assert flat == sorted(flat)
    assert flat[0] == pytest.approx(0.08 * 128) and flat[-1] == pytest.approx(128)


def test_bad_configuration_is_a_clear_error():
    # The config refuses an unknown backbone (tests/foldwise/test_config.py); a config built
    # without validation meets the builder's own check.
    unvalidated = DetectorConfig(**SMALL).model_copy(update={"backbone": "vgg16"})
    with pytest.raises(DetectorBuildError, match="detector.backbone 'vgg16'"):
        build_detector(unvalidated, num_classes=2)
    with pytest.raises(DetectorBuildError, match="at least one class"):
        build_detector(DetectorConfig(**SMALL), num_classes=0)


def test_yolo_family_is_dispatched_to_its_module():
    yolo = pytest.importorskip("workers.train.detectors.yolo")
    model = build_detector(
        DetectorConfig(family="yolo", **SMALL), num_classes=2, train_boxes=np.array([[0, 0, 20, 30.0]])
    )
    assert isinstance(model, torch.nn.Module) and type(model).__module__ == yolo.__name__


def test_pretrained_imagenet_without_cached_weights_names_the_expected_file(tmp_path, monkeypatch):
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path / "hub"))
    expected, _ = imagenet_weights_path("mobilenet_v3_large")
    assert expected.parent == tmp_path / "hub" / "checkpoints"
    with pytest.raises(PretrainedWeightsMissing) as error:
        build_detector(DetectorConfig(pretrained="imagenet", **SMALL), num_classes=2)
    message = str(error.value)
    assert str(expected) in message and "never downloads" in message and "pretrained" in message


def test_pretrained_imagenet_loads_the_cached_classifier_weights(tmp_path, monkeypatch):
    import torchvision

    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path / "hub"))
    path, _ = imagenet_weights_path("mobilenet_v3_large")
    path.parent.mkdir(parents=True)
    torch.manual_seed(123)
    classifier = torchvision.models.mobilenet_v3_large(weights=None)
    torch.save(classifier.state_dict(), path)
    torch.manual_seed(0)
    model = build_detector(DetectorConfig(pretrained="imagenet", **SMALL), num_classes=2)
    body = model.backbone.body
    torch.testing.assert_close(body["0"][0].weight, classifier.features[0][0].weight)
    torch.testing.assert_close(body["16"][1].running_mean, classifier.features[16][1].running_mean)
    assert not body["0"][0].weight.requires_grad  # early stages frozen when fine-tuning
    assert body["16"][0].weight.requires_grad


def test_merging_runs_keeps_the_best_box_per_class_and_place_best_first_and_capped():
    """Views (or several detectors) merge by per-class NMS: of two overlapping boxes of one class
    the better stays; boxes of other classes at the same place stay too; the cap keeps the best.
    Arrays in, arrays out (a detector's numpy output); tensors in, tensors out (the model's)."""
    first = {
        "boxes": np.array([[0, 0, 10, 10], [20, 20, 30, 30]], np.float32),
        "scores": np.array([0.9, 0.5], np.float32),
        "labels": np.array([0, 1]),
    }
    second = {
        "boxes": np.array([[1, 1, 10, 10], [0, 0, 10, 10], [40, 40, 50, 50]], np.float32),
        "scores": np.array([0.95, 0.7, 0.6], np.float32),
        "labels": np.array([0, 2, 0]),
    }
    merged = merge_detections([first, second], 0.5, 20)
    assert isinstance(merged["boxes"], np.ndarray)
    assert merged["scores"].tolist() == pytest.approx([0.95, 0.7, 0.6, 0.5])
    assert merged["labels"].tolist() == [0, 2, 0, 1]
    assert merged["boxes"][0].tolist() == [1, 1, 10, 10]  # the 0.9 box of class 0 there is suppressed
    capped = merge_detections([first, second], 0.5, 2)
    assert capped["scores"].tolist() == pytest.approx([0.95, 0.7])
    as_tensors = merge_detections([{k: torch.as_tensor(v) for k, v in run.items()} for run in (first, second)], 0.5, 20)
    assert isinstance(as_tensors["boxes"], torch.Tensor)
    assert as_tensors["scores"].tolist() == pytest.approx(merged["scores"].tolist())
    empty = {"boxes": np.zeros((0, 4), np.float32), "scores": np.zeros(0, np.float32), "labels": np.zeros(0, np.int64)}
    assert len(merge_detections([empty, empty], 0.5, 20)["scores"]) == 0


def test_views_that_vote_rank_a_box_most_views_find_over_one_a_single_view_is_sure_of():
    """merge_detections(vote=α): a kept box scores 1 - Π (1 - α s_run) over the runs, s_run that
    run's best box it suppressed (a run's second box on the same place adds nothing, a run under
    VOTE_FLOOR abstains, a box no run scores at the floor keeps its score); the kept boxes are
    NMS's; one run keeps its scores; votes of members at α then 1 are all runs at α."""

    def run(*rows):
        return {
            "boxes": np.array([r[0] for r in rows], np.float32).reshape(-1, 4),
            "scores": np.array([r[1] for r in rows], np.float32),
            "labels": np.array([r[2] for r in rows], np.int64),
        }

    sheet, clutter, faint = [10, 10, 50, 50], [60, 60, 90, 90], [0, 60, 30, 90]
    runs = [
        run((sheet, 0.6, 0), ([11, 10, 50, 51], 0.5, 0), (clutter, 0.95, 0)),  # the clutter: this view alone
        run(([10, 11, 51, 50], 0.6, 0), (sheet, 0.6, 1)),  # class 1 at the sheet: its own box
        run(([9, 10, 50, 50], 0.6, 0), (faint, 0.2, 0)),
        run((sheet, 0.4, 0), (faint, 0.25, 0)),
        run((sheet, 0.25, 0)),  # under the floor: abstains
    ]
    voted = merge_detections(runs, 0.5, 20, vote=0.7)
    by_nms = merge_detections(runs, 0.5, 20)
    assert sorted(map(tuple, voted["boxes"].tolist())) == sorted(map(tuple, by_nms["boxes"].tolist()))
    sheet_score = 1 - (1 - 0.7 * 0.6) ** 3 * (1 - 0.7 * 0.4)
    assert voted["scores"].tolist() == pytest.approx([sheet_score, 0.7 * 0.95, 0.7 * 0.6, 0.25])
    assert voted["labels"].tolist() == [0, 0, 1, 0]
    assert by_nms["scores"][0] == pytest.approx(0.95)  # NMS: the clutter first
    alone = merge_detections(runs[:1], 0.5, 20, vote=0.7)
    assert alone["scores"].tolist() == pytest.approx([0.95, 0.6])
    members = [merge_detections(runs[:2], 0.5, 20, vote=0.7), merge_detections(runs[2:], 0.5, 20, vote=0.7)]
    assert members[1]["scores"][-1] == pytest.approx(0.25)  # the faint box: no vote in that member either
    together = merge_detections(members, 0.5, 20, vote=1.0)
    assert together["scores"].tolist() == pytest.approx(voted["scores"].tolist(), abs=1e-6)
    assert merge_detections([run(), run()], 0.5, 20, vote=0.7)["boxes"].shape == (0, 4)
    capped = merge_detections([{k: torch.as_tensor(v) for k, v in r.items()} for r in runs], 0.5, 1, vote=0.7)
    assert isinstance(capped["scores"], torch.Tensor) and capped["scores"].tolist() == pytest.approx([sheet_score])
