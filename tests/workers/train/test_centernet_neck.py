"""The CenterNet's COCO-trained neck, frozen under the R-CNN heads (backbone
``mobilenet_v3_large_075_centernet``)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from foldwise.config import DetectorConfig
from tests.workers.train.test_detectors import SMALL as RCNN_SMALL
from workers.train.checkpoint import load_detector, save_checkpoint
from workers.train.detectors import build_detector
from workers.train.detectors.centernet_neck import (
    LATERALS,
    NECK_WEIGHTS_FILE,
    UPSAMPLINGS,
    CenterNetFeatures,
    CenterNetNeck,
    load_neck_weights,
    upsample2x_legacy,
)
from workers.train.detectors.convert_centernet import _resize_legacy, neck_state
from workers.train.detectors.mobilenet_v3_tf import FOLDED_BATCHNORM, mobilenet_v3_large_075_body

torch.set_num_threads(1)

SMALL = {**RCNN_SMALL, "backbone": "mobilenet_v3_large_075_centernet", "pretrained": "coco"}


@pytest.mark.parametrize("shape", [(4, 3), (5, 7), (1, 2)])
def test_the_x2_resize_is_tensorflows_legacy_bilinear(shape):
    x = torch.randn(2, 3, *shape)
    expected = _resize_legacy(x, [2 * shape[0], 2 * shape[1]])  # the converter's reading of TensorFlow's op
    torch.testing.assert_close(upsample2x_legacy(x), expected)


def test_the_shipped_neck_weights_fill_every_layer_and_a_changed_file_is_refused(tmp_path):
    neck = CenterNetNeck()
    load_neck_weights(neck)  # strict, hash checked
    state = torch.load(NECK_WEIGHTS_FILE, map_location="cpu", weights_only=True)
    assert set(state) == set(neck.state_dict())
    for name, tensor in neck.state_dict().items():
        torch.testing.assert_close(tensor, state[name].float())
    changed = tmp_path / "neck.pt"
    changed.write_bytes(NECK_WEIGHTS_FILE.read_bytes()[:-1] + b"x")
    with pytest.raises(ValueError, match="is not the one foldwise ships"):
        load_neck_weights(CenterNetNeck(), changed)
    with pytest.raises(FileNotFoundError, match="convert_centernet"):
        load_neck_weights(CenterNetNeck(), tmp_path / "absent.pt")


def test_the_converter_maps_every_graph_weight_of_the_neck():
    rng = np.random.default_rng(0)
    tensors, head, graph_head = {}, "CenternetHead", "tower_0/CenternetHead"

    def add(name, shape):
        tensors[name] = rng.standard_normal(shape).astype(np.float32)

    for name, (cin, squeezed, cout) in LATERALS.items():
        add(f"{graph_head}/{name}/1x1/Conv2D_weights", (1, 1, cin, squeezed))
        add(f"{graph_head}/{name}/1x1/Conv2D_bn_offset", (squeezed,))
        add(f"{head}/{name}/3x3/depthwise_weights", (5, 5, squeezed, 1))
        add(f"{graph_head}/{name}/3x3/separable_conv2d_weights", (1, 1, squeezed, cout))
        add(f"{graph_head}/{name}/3x3/separable_conv2d_bn_offset", (cout,))
    for name, (cin, cout) in UPSAMPLINGS.items():
        for branch, kernel in (("branch_x", 3), ("branch_y", 5)):
            add(f"{head}/{name}/{branch}_upsample_resize/depthwise_weights", (kernel, kernel, cin, 1))
            add(f"{graph_head}/{name}/{branch}_upsample_resize/separable_conv2d_weights", (1, 1, cin, cout))
            add(f"{graph_head}/{name}/{branch}_upsample_resize/separable_conv2d_bn_offset", (cout,))
    add(f"{graph_head}/conv1x1_se_a/Conv2D_weights", (1, 1, 128, 32))
    add(f"{graph_head}/conv1x1_se_a/Conv2D_bn_offset", (32,))
    add(f"{head}/conv1x1_se_b/weights", (1, 1, 32, 128))
    neck = CenterNetNeck()
    neck.load_state_dict(neck_state(tensors))  # strict: every layer filled, nothing left over
    depthwise = tensors[f"{head}/c5_upsample/branch_y_upsample_resize/depthwise_weights"]  # H, W, C, 1
    torch.testing.assert_close(neck.upsamplings["c5_upsample"].branch_y[0].weight[11, 0], torch.from_numpy(depthwise[:, :, 11, 0]))
    pointwise = tensors[f"{graph_head}/c3_reverse/3x3/separable_conv2d_weights"]  # 1, 1, in, out
    torch.testing.assert_close(neck.laterals["c3_reverse"].conv[1].weight[40, 7, 0, 0], torch.tensor(pointwise[0, 0, 7, 40]))


def test_the_neck_gives_128_channels_at_stride_4_and_stays_frozen():
    features = CenterNetFeatures(mobilenet_v3_large_075_body(FOLDED_BATCHNORM), CenterNetNeck()).eval()
    with torch.no_grad():
        out = features(torch.rand(1, 3, 64, 96) * 255)
    assert list(out) == ["0"] and tuple(out["0"].shape) == (1, 128, 16, 24)
    assert not any(p.requires_grad for p in features.neck.parameters())


@pytest.mark.parametrize("family", ["faster_rcnn", "fast_rcnn"])
def test_an_rcnn_on_the_neck_trains_its_heads_only_and_round_trips(family, tmp_path):
    torch.manual_seed(0)
    config = DetectorConfig(family=family, trainable_backbone_stages=0, **SMALL)
    model = build_detector(config, num_classes=2).train()
    assert model.roi_heads.box_roi_pool.featmap_names == ["0"]
    if family == "faster_rcnn":  # all eight anchor sizes on the one map
        assert len(model.rpn.anchor_generator.sizes) == 1 and len(model.rpn.anchor_generator.sizes[0]) == 8
    images = [torch.rand(3, 64, 64) for _ in range(2)]
    targets = [{"boxes": torch.tensor([[8.0, 10.0, 40.0, 50.0]]), "labels": torch.tensor([1])} for _ in range(2)]
    total = sum(model(images, targets).values())
    assert torch.isfinite(total)
    total.backward()
    assert not any(p.requires_grad for p in [*model.backbone.body.parameters(), *model.backbone.neck.parameters()])
    assert model.roi_heads.box_predictor.cls_score.weight.grad.abs().sum() > 0
    model.eval()
    path = tmp_path / "model.pt"
    meta = {"family": family, "backbone": config.backbone, "classes": ["a", "b"], "config": config.model_dump(mode="json")}
    save_checkpoint(model, meta, path)
    restored = load_detector(path, device="cpu").model  # rebuilt without reading the COCO files
    with torch.no_grad():
        torch.testing.assert_close(restored(images)[0]["boxes"], model(images)[0]["boxes"])


def test_the_neck_exists_only_with_its_coco_weights():
    with pytest.raises(ValueError, match="is its COCO weights, frozen; set pretrained to 'coco'"):
        DetectorConfig(backbone="mobilenet_v3_large_075_centernet", pretrained="none")
    with pytest.raises(ValueError, match="has 'coco'"):
        DetectorConfig(backbone="mobilenet_v3_large_075_centernet", pretrained="imagenet")
