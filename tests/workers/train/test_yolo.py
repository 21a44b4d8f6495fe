"""The YOLOv2-style detector: anchors, target geometry, losses, inference and checkpoints.

Small and fast on purpose: 64–96 px inputs, MobileNetV3-small, one torch thread, and
synthetic images (textured rectangles on noise) made here.
"""

from __future__ import annotations

import io

import numpy as np
import pytest
import torch
from torchvision.ops import box_iou

from foldwise.config import DetectorConfig
from workers.train.detectors.yolo import (
    DEFAULT_NUM_ANCHORS,
    YOLOv2Detector,
    assign_targets,
    build_yolo,
    centred_iou,
    decode_boxes,
    default_anchors,
    encode_targets,
    kmeans_anchors,
    letterbox,
)


@pytest.fixture(autouse=True)
def _one_thread():
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


def _config(input_size: int = 64, backbone: str = "mobilenet_v3_small", **kwargs) -> DetectorConfig:
    return DetectorConfig(family="yolo", backbone=backbone, input_size=input_size, **kwargs)


def _textured_image(height: int, width: int, box, pattern: int, generator: torch.Generator) -> torch.Tensor:
    """Dim noise with one bright, class-specific textured rectangle at ``box`` (xyxy pixels)."""
    image = torch.rand(3, height, width, generator=generator) * 0.5
    x0, y0, x1, y1 = (int(v) for v in box)
    yy, xx = torch.meshgrid(torch.arange(y1 - y0), torch.arange(x1 - x0), indexing="ij")
    texture = [(xx // 4 + yy // 4) % 2, (xx // 2) % 2, (yy // 3) % 2][pattern].float()
    colour = torch.tensor([[1.0, 0.2, 0.2], [0.2, 1.0, 0.2], [0.2, 0.2, 1.0]])[pattern]
    image[:, y0:y1, x0:x1] = colour[:, None, None] * (0.5 + 0.5 * texture)
    return image


def _target(box, label: int) -> dict[str, torch.Tensor]:
    return {"boxes": torch.tensor([box], dtype=torch.float32), "labels": torch.tensor([label])}


# ---- anchors ---------------------------------------------------------------------------------


def test_kmeans_recovers_planted_clusters_and_is_deterministic():
    rng = np.random.default_rng(3)
    planted = np.array([[0.1, 0.15], [0.4, 0.2], [0.3, 0.7]])
    wh = np.concatenate([centre * rng.uniform(0.95, 1.05, size=(200, 2)) for centre in planted])
    rng.shuffle(wh)

    anchors = kmeans_anchors(wh, 3, seed=0)

    assert anchors.shape == (3, 2)
    areas = anchors.prod(axis=1)
    assert np.all(np.diff(areas) >= 0), "anchors are sorted by area"
    # Each planted shape has an anchor of centred IoU > 0.95 with it.
    assert centred_iou(planted, anchors).max(axis=1).min() > 0.95
    np.testing.assert_array_equal(anchors, kmeans_anchors(wh, 3, seed=0))
    # The same shapes in another order converge to the same clusters.
    np.testing.assert_allclose(anchors, kmeans_anchors(wh[::-1].copy(), 3, seed=0), rtol=0, atol=1e-12)


def test_kmeans_without_boxes_falls_back_to_default_anchors():
    np.testing.assert_array_equal(kmeans_anchors(np.zeros((0, 2)), 5), default_anchors(5))
    for k in (1, 3, 5, 9):
        anchors = default_anchors(k)
        assert anchors.shape == (k, 2)
        assert np.all(anchors > 0) and np.all(anchors <= 1)
        assert len(np.unique(anchors, axis=0)) == k


def test_kmeans_with_fewer_distinct_boxes_than_anchors_keeps_them_and_adds_distinct_shapes():
    wh = np.array([[0.3, 0.4]] * 10 + [[0.6, 0.2]] * 5)
    anchors = kmeans_anchors(wh, 5)
    assert anchors.shape == (5, 2)
    assert len(np.unique(anchors, axis=0)) == 5
    for shape in ([0.3, 0.4], [0.6, 0.2]):
        assert np.isclose(anchors, shape).all(axis=1).any(), f"{shape} must be an anchor"


def test_kmeans_drops_degenerate_and_nonfinite_shapes():
    good = np.array([[0.2, 0.3], [0.21, 0.29], [0.5, 0.5], [0.52, 0.48]])
    bad = np.array([[0.0, 0.3], [-0.1, 0.2], [np.nan, 0.1], [np.inf, 0.4], [0.3, 0.0]])
    anchors = kmeans_anchors(np.concatenate([good, bad]), 2)
    assert np.all(np.isfinite(anchors)) and np.all(anchors > 0)
    np.testing.assert_allclose(anchors, kmeans_anchors(good, 2))
    # Only degenerate shapes: nothing to cluster.
    np.testing.assert_array_equal(kmeans_anchors(bad, 4), default_anchors(4))
    with pytest.raises(ValueError, match="at least 1"):
        kmeans_anchors(good, 0)


def test_build_yolo_clusters_train_boxes_relative_to_their_images():
    boxes = np.array([[0, 0, 32, 64], [10, 10, 42, 74]] * 3, dtype=np.float32)  # 32 × 64 px
    model = build_yolo(_config(64), 3, boxes, num_anchors=2)
    assert model.anchors.shape == (2, 2)
    assert torch.isclose(model.anchors, torch.tensor([0.5, 1.0])).all(dim=1).any()
    # The same boxes in 128-px images are a quarter of the area.
    sizes = np.full((len(boxes), 2), 128)
    model = build_yolo(_config(64), 3, boxes, num_anchors=2, train_image_sizes=sizes)
    assert torch.isclose(model.anchors, torch.tensor([0.25, 0.5])).all(dim=1).any()
    with pytest.raises(ValueError, match="train_image_sizes"):
        build_yolo(_config(64), 3, boxes, train_image_sizes=sizes[:2])
    with pytest.raises(ValueError, match="train_image_sizes"):
        build_yolo(_config(64), 3, boxes, train_image_sizes=np.zeros_like(sizes))
    with pytest.raises(ValueError, match=r"train_boxes must be \(n, 4\)"):
        build_yolo(_config(64), 3, np.zeros((4, 3)))
    # No training boxes at all: the default anchors.
    empty = build_yolo(_config(64), 3, np.zeros((0, 4)))
    torch.testing.assert_close(empty.anchors, torch.tensor(default_anchors(), dtype=torch.float32))


# ---- geometry --------------------------------------------------------------------------------


@pytest.mark.parametrize("cell_margin, anchor_match_iou", [(0.0, 1.0), (0.5, 0.5)])
def test_encode_decode_round_trip(cell_margin, anchor_match_iou):
    generator = torch.Generator().manual_seed(0)
    stride, grid = 16, (6, 8)  # a 96 × 128 canvas
    anchors = torch.tensor(default_anchors(5), dtype=torch.float32) * 128
    # 20 boxes centred in distinct cells (so none loses its slot), of sizes from 1 to 90 px.
    cells = torch.randperm(grid[0] * grid[1], generator=generator)[:20]
    centre = (torch.stack([cells % grid[1], cells // grid[1]], dim=1) + torch.rand(20, 2, generator=generator)) * stride
    wh = 1 + torch.rand(20, 2, generator=generator) * 89
    boxes = torch.cat([centre - wh / 2, centre + wh / 2], dim=1)

    box_index, rows, cols, anchor_index = assign_targets(
        boxes, anchors, stride, grid, cell_margin=cell_margin, anchor_match_iou=anchor_match_iou
    )
    t = encode_targets(boxes[box_index], rows, cols, anchor_index, anchors, stride, cell_margin)
    raw = torch.zeros(*grid, len(anchors), 4, dtype=torch.float64)
    raw[rows, cols, anchor_index] = t.double()
    decoded = decode_boxes(raw, anchors.double(), stride, cell_margin)[rows, cols, anchor_index]

    torch.testing.assert_close(decoded.float(), boxes[box_index], atol=1e-3, rtol=0)
    assert set(box_index.tolist()) == set(range(20)), "every box has a responsible prediction"


def test_yolov2_assignment_is_the_centre_cell_and_best_anchor():
    anchors = torch.tensor([[10.0, 10.0], [30.0, 15.0], [20.0, 40.0]])
    boxes = torch.tensor([[0.0, 0.0, 12.0, 12.0], [40.0, 20.0, 70.0, 34.0], [100.0, 70.0, 119.0, 111.0]])
    box_index, rows, cols, anchor_index = assign_targets(boxes, anchors, 16, (8, 8))
    assert box_index.tolist() == [0, 1, 2]
    assert list(zip(rows.tolist(), cols.tolist())) == [(0, 0), (1, 3), (5, 6)]
    assert anchor_index.tolist() == [0, 1, 2]


def test_centred_object_on_an_even_grid_gets_both_cells_around_the_border():
    # A 64-px object centred in a 128-px canvas: its centre (64, 64) lies on four cells' corner.
    anchors = torch.tensor([[60.0, 60.0], [62.0, 66.0], [10.0, 10.0]])
    box = torch.tensor([[32.0, 32.0, 96.0, 96.0]])
    _, rows, cols, anchor_index = assign_targets(box, anchors, 16, (8, 8), cell_margin=0.5, anchor_match_iou=0.5)
    cells = set(zip(rows.tolist(), cols.tolist()))
    assert {(4, 4), (3, 4), (4, 3)} <= cells
    assert set(anchor_index.tolist()) == {0, 1}, "both near-identical anchors answer; the small one does not"


def test_letterbox_keeps_aspect_and_reports_exact_scales():
    image = torch.rand(3, 50, 100)
    canvas, (sx, sy) = letterbox(image, 64, 64)
    assert canvas.shape == (3, 64, 64)
    assert (sx, sy) == (64 / 100, 32 / 50)
    assert torch.all(canvas[:, 32:, :] == 0.5), "padding below the resized image"
    same, scale = letterbox(image[:, :, :50], 50, 64)
    assert scale == (1.0, 1.0) and torch.equal(same[:, :50, :50], image[:, :, :50])


# ---- model: training -------------------------------------------------------------------------


def test_overfits_two_images_until_the_right_detection_appears():
    torch.manual_seed(0)
    generator = torch.Generator().manual_seed(0)
    boxes = [(8, 10, 40, 54), (21, 16, 60, 48)]
    labels = [1, 3]
    images = [_textured_image(64, 64, box, label - 1, generator) for box, label in zip(boxes, labels)]
    targets = [_target(box, label) for box, label in zip(boxes, labels)]
    model = build_yolo(_config(64, learning_rate=0.01), 3, np.array(boxes, dtype=np.float32))
    optimiser = torch.optim.SGD(model.parameters(), lr=0.01, momentum=0.9, weight_decay=1e-4)

    totals, found = [], False
    for step in range(150):
        model.train()
        losses = model(images, targets)
        assert set(losses) == {"loss_box", "loss_objectness", "loss_classifier"}
        total = sum(losses.values())
        assert torch.isfinite(total)
        totals.append(total.item())
        optimiser.zero_grad()
        total.backward()
        optimiser.step()
        if step >= 30 and step % 10 == 0:
            model.eval()
            with torch.no_grad():
                outputs = model(images)
            top_hits = []
            for output, box, label in zip(outputs, boxes, labels):
                if len(output["scores"]) == 0:
                    top_hits.append(False)
                    continue
                best = output["scores"].argmax()
                iou = box_iou(output["boxes"][best : best + 1], torch.tensor([box], dtype=torch.float32))
                top_hits.append(bool(output["labels"][best] == label) and iou.item() > 0.5)
            if all(top_hits):
                found = True
                break
    assert np.mean(totals[-5:]) < 0.5 * np.mean(totals[:5]), "the loss must fall"
    assert totals[30] < totals[0]
    assert found, "the top detection of each image must be its object (right class, IoU > 0.5)"


def test_images_without_objects_only_pay_the_no_object_loss():
    torch.manual_seed(0)
    model = build_yolo(_config(64), 3, None)
    images = [torch.rand(3, 64, 64), torch.rand(3, 48, 80)]
    empty = {"boxes": torch.zeros(0, 4), "labels": torch.zeros(0, dtype=torch.int64)}
    losses = model(images, [empty, empty])
    assert losses["loss_box"].item() == 0.0
    assert losses["loss_classifier"].item() == 0.0
    assert losses["loss_objectness"].item() > 0.0
    sum(losses.values()).backward()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)
    # Mixed batch: one image with an object, one without.
    losses = model(images, [_target((10, 10, 40, 50), 2), empty])
    assert losses["loss_box"].item() > 0.0 and losses["loss_classifier"].item() > 0.0


def test_extreme_boxes_give_finite_losses_and_gradients():
    torch.manual_seed(0)
    model = build_yolo(_config(64), 2, np.array([[0, 0, 64, 64], [10, 10, 11, 60]], dtype=np.float32))
    images = [torch.rand(3, 64, 64) for _ in range(4)]
    targets = [
        {  # 1 px wide, and dtypes other than float32 / int64
            "boxes": torch.tensor([[10.0, 5.0, 11.0, 60.0]], dtype=torch.float64),
            "labels": torch.tensor([1], dtype=torch.int32),
        },
        _target((0.0, 0.0, 64.0, 64.0), 2),  # the full image
        _target((63.0, 63.0, 64.0, 64.0), 1),  # one pixel in the corner
        {
            "boxes": torch.tensor([[0.0, 0.0, 64.0, 64.0], [0.0, 0.0, 64.0, 64.0], [30.0, 30.0, 30.5, 30.5]]),
            "labels": torch.tensor([1, 2, 1]),
        },  # duplicates and a sub-pixel box
    ]
    losses = model(images, targets)
    total = sum(losses.values())
    assert torch.isfinite(total)
    total.backward()
    for name, parameter in model.named_parameters():
        assert torch.isfinite(parameter.grad).all(), name


def test_no_object_loss_ignores_good_boxes_that_are_not_responsible(monkeypatch):
    model = build_yolo(_config(64), 2, None, cell_margin=0.0, anchor_match_iou=1.0)
    anchors_px = model.anchors * model.input_size
    box = torch.tensor([[8.0, 8.0, 40.0, 40.0]])  # centre (24, 24): cell (1, 1)
    _, rows, cols, anchor_index = assign_targets(box, anchors_px, 16, (4, 4))
    assert (rows.item(), cols.item()) == (1, 1)
    planted = torch.zeros(1, 4, 4, model.num_anchors, 5 + 2)
    planted[..., 4] = 3.0  # every slot claims an object
    # Another anchor of the same cell predicts the ground truth box, without being responsible.
    other = (anchor_index + 1) % model.num_anchors
    planted[0, 1, 1, other.item(), :4] = encode_targets(box, rows, cols, other, anchors_px, 16)[0]
    planted.requires_grad_(True)
    monkeypatch.setattr(model, "_raw_predictions", lambda batch: planted)

    losses = model([torch.rand(3, 64, 64)], [_target(box[0].tolist(), 1)])
    losses["loss_objectness"].backward()
    objectness_grad = planted.grad[0, ..., 4]

    assert objectness_grad[1, 1, other.item()] == 0, "IoU > 0.6 with a ground truth: ignored"
    assert objectness_grad[3, 3, 0] > 0, "an empty cell is pushed down"
    assert objectness_grad[1, 1, anchor_index.item()] < 0, "the responsible slot is pushed up"


def test_bad_inputs_are_named():
    model = build_yolo(_config(64), 3, None)
    image = torch.rand(3, 64, 64)
    with pytest.raises(ValueError, match="needs targets"):
        model([image])
    with pytest.raises(ValueError, match=r"labels'\] must be in 1\.\.3"):
        model([image], [_target((1, 1, 20, 20), 0)])
    with pytest.raises(ValueError, match=r"labels'\] must be in 1\.\.3"):
        model([image], [_target((1, 1, 20, 20), 4)])
    with pytest.raises(ValueError, match="positive width and height"):
        model([image], [_target((20, 1, 20, 20), 1)])
    with pytest.raises(ValueError, match="non-finite"):
        model([image], [_target((float("nan"), 1, 20, 20), 1)])
    with pytest.raises(ValueError, match=r"images\[0\] must be a \(3, H, W\)"):
        model([torch.rand(1, 64, 64)], [_target((1, 1, 20, 20), 1)])
    with pytest.raises(ValueError, match="float"):
        model([torch.zeros(3, 64, 64, dtype=torch.uint8)], [_target((1, 1, 20, 20), 1)])
    with pytest.raises(ValueError, match="2 images but 1 targets"):
        model([image, image], [_target((1, 1, 20, 20), 1)])


# ---- model: inference ------------------------------------------------------------------------


def test_eval_output_is_in_original_pixels_for_non_square_images(monkeypatch):
    model = build_yolo(_config(96), 4, None, detections_per_image=7).eval()
    anchors_px = model.anchors * model.input_size
    images = [torch.rand(3, 60, 150), torch.rand(3, 200, 80), torch.rand(3, 96, 96)]
    # Each image's box in its own pixels, and its letterbox scale (input 96 px).
    truths = [
        torch.tensor([[30.0, 12.0, 120.0, 50.0]]),
        torch.tensor([[5.0, 40.0, 70.0, 180.0]]),
        torch.tensor([[10.0, 20.0, 50.0, 90.0]]),
    ]
    scales = [(96 / 150, round(60 * 96 / 150) / 60), (round(80 * 96 / 200) / 80, 96 / 200), (1.0, 1.0)]

    # Plant one confident prediction of class 2 per image at its responsible slot.
    planted = torch.full((3, 6, 6, model.num_anchors, 5 + 4), -12.0)
    for index, (box, (sx, sy)) in enumerate(zip(truths, scales)):
        box_in = box * torch.tensor([sx, sy, sx, sy])
        _, rows, cols, anchor_index = assign_targets(box_in, anchors_px, 16, (6, 6), cell_margin=model.cell_margin)
        t = encode_targets(box_in, rows[:1], cols[:1], anchor_index[:1], anchors_px, 16, model.cell_margin)
        planted[index, rows[0], cols[0], anchor_index[0], :4] = t[0]
        planted[index, rows[0], cols[0], anchor_index[0], 4] = 8.0
        planted[index, rows[0], cols[0], anchor_index[0], 5 + 1] = 8.0
    monkeypatch.setattr(model, "_raw_predictions", lambda batch: planted)

    outputs = model(images)

    assert len(outputs) == 3
    for output, truth, image in zip(outputs, truths, images):
        assert set(output) == {"boxes", "scores", "labels"}
        assert output["boxes"].shape[1] == 4 and output["boxes"].dtype == torch.float32
        assert output["labels"].dtype == torch.int64
        assert len(output["boxes"]) == len(output["scores"]) == len(output["labels"]) <= 7
        assert torch.all(output["scores"][:-1] >= output["scores"][1:]), "sorted by score"
        assert torch.all(output["scores"] > model.score_threshold)
        height, width = image.shape[1:]
        assert torch.all(output["boxes"][:, 0::2] <= width) and torch.all(output["boxes"][:, 1::2] <= height)
        assert output["labels"][0].item() == 2
        assert output["scores"][0].item() > 0.99
        torch.testing.assert_close(output["boxes"][0], truth[0], atol=1e-3, rtol=0)


def test_inference_settings_come_from_the_config_unless_overridden():
    config = _config(64, box_score_threshold=0.3, detections_per_image=9)
    model = build_yolo(config, 2, None)
    assert (model.score_threshold, model.detections_per_image) == (0.3, 9)
    model = build_yolo(config, 2, None, score_threshold=0.01)
    assert (model.score_threshold, model.detections_per_image) == (0.01, 9)


def test_random_model_eval_shapes_and_detection_cap():
    torch.manual_seed(0)
    model = build_yolo(_config(80), 5, None, score_threshold=0.0, detections_per_image=11).eval()
    assert model.canvas_size == 96  # padded up to a multiple of 32
    with torch.no_grad():
        outputs = model([torch.rand(3, 80, 80), torch.rand(3, 33, 47)])
    for output in outputs:
        assert output["boxes"].shape == (11, 4)
        assert output["labels"].min() >= 1 and output["labels"].max() <= 5


# ---- checkpoints and backbones ---------------------------------------------------------------


def test_state_dict_round_trip_through_a_rebuild_without_train_boxes():
    torch.manual_seed(0)
    boxes = np.array([[5, 5, 30, 50], [0, 10, 60, 40], [20, 20, 28, 30], [3, 3, 60, 60]], dtype=np.float32)
    config = _config(64)
    trained = build_yolo(config, 3, boxes, num_anchors=3, score_threshold=0.0)
    trained.train()
    image = torch.rand(3, 64, 64)
    trained([image, torch.rand(3, 64, 64)], [_target((5, 5, 30, 50), 1), _target((0, 10, 60, 40), 2)])  # BN stats
    trained.eval()

    buffer = io.BytesIO()
    torch.save(trained.state_dict(), buffer)
    buffer.seek(0)
    state = torch.load(buffer, weights_only=True)
    assert "anchors" in state

    rebuilt = build_yolo(config, 3, None, num_anchors=3, score_threshold=0.0)
    assert not torch.equal(rebuilt.anchors, trained.anchors)
    rebuilt.load_state_dict(state)
    rebuilt.eval()
    torch.testing.assert_close(rebuilt.anchors, trained.anchors)
    with torch.no_grad():
        expected, actual = trained([image]), rebuilt([image])
    for key in ("boxes", "scores", "labels"):
        torch.testing.assert_close(actual[0][key], expected[0][key], rtol=0, atol=0)
    # A rebuild with the default anchor count cannot silently take a 3-anchor checkpoint.
    with pytest.raises(RuntimeError, match="anchors"):
        build_yolo(config, 3, None).load_state_dict(state)
    assert build_yolo(config, 3, None).anchors.shape == (DEFAULT_NUM_ANCHORS, 2)


@pytest.mark.parametrize(
    "backbone", ["mobilenet_v3_large_fpn", "mobilenet_v3_large_320_fpn", "resnet18", "resnet50_fpn_v2"]
)
def test_backbone_names_map_to_a_stride_16_grid(backbone):
    model = build_yolo(_config(64, backbone=backbone), 2, None)
    with torch.no_grad():
        raw = model.eval()._raw_predictions(torch.zeros(1, 3, 64, 64))
    assert raw.shape == (1, 4, 4, DEFAULT_NUM_ANCHORS, 5 + 2)


@pytest.mark.parametrize("grid_stride, cells", [(32, 2), (8, 8)])
def test_grid_stride_sets_the_grid(grid_stride, cells):
    model = build_yolo(_config(64), 2, None, grid_stride=grid_stride)
    with torch.no_grad():
        raw = model.eval()._raw_predictions(torch.zeros(1, 3, 64, 64))
    assert raw.shape == (1, cells, cells, DEFAULT_NUM_ANCHORS, 5 + 2)


def test_unsupported_grid_stride_is_named():
    with pytest.raises(ValueError, match="grid_stride"):
        build_yolo(_config(64), 2, None, grid_stride=4)


def test_unknown_backbone_is_named():
    unvalidated = _config(64).model_copy(update={"backbone": "vgg16"})  # the config itself refuses it
    with pytest.raises(ValueError, match="'vgg16'.*known: mobilenet_v3_large"):
        build_yolo(unvalidated, 2, None)


def test_imagenet_weights_missing_from_the_cache_fail_without_downloading(tmp_path, monkeypatch):
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))

    def no_download(*args, **kwargs):
        raise AssertionError("must not download")

    monkeypatch.setattr(torch.hub, "load_state_dict_from_url", no_download)
    monkeypatch.setattr(torch.hub, "download_url_to_file", no_download)
    with pytest.raises(FileNotFoundError, match=r"mobilenet_v3_small-047dcff4\.pth is missing"):
        build_yolo(_config(64, pretrained="imagenet"), 2, None)


def test_imagenet_weights_in_the_cache_are_loaded(tmp_path, monkeypatch):
    import torchvision

    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))
    reference = torchvision.models.mobilenet_v3_small()
    (tmp_path / "checkpoints").mkdir()
    torch.save(reference.state_dict(), tmp_path / "checkpoints" / "mobilenet_v3_small-047dcff4.pth")
    model = build_yolo(_config(64, pretrained="imagenet"), 2, None)
    torch.testing.assert_close(model.backbone.to_stride8[0][0].weight, reference.features[0][0].weight)
    torch.testing.assert_close(model.backbone.to_stride8[0][1].running_mean, reference.features[0][1].running_mean)


def test_invalid_model_arguments_are_rejected():
    with pytest.raises(ValueError, match="num_classes"):
        YOLOv2Detector("mobilenet_v3_small", 0, default_anchors(), 64)
    with pytest.raises(ValueError, match="anchors"):
        YOLOv2Detector("mobilenet_v3_small", 2, np.array([[0.1, 0.0]]), 64)
