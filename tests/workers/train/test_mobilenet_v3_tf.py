"""The COCO-pretrained MobileNetV3 (TensorFlow-slim layout) that ships with foldwise."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from foldwise.config import DetectorConfig
from tests.workers.train.small_detectors import SMALL as RCNN_SMALL
from workers.train.checkpoint import load_detector, save_checkpoint
from workers.train.detectors import build_detector
from workers.train.detectors.backbones import input_normalization
from workers.train.detectors.convert_centernet import backbone_state, decode_weights
from workers.train.detectors.mobilenet_v3_tf import (
    BLOCKS,
    FEATURE_CHILDREN,
    FOLDED_BATCHNORM,
    WEIGHTS_FILE,
    _SamePad,
    load_coco_weights,
    mobilenet_v3_large_075_body,
)

torch.set_num_threads(1)

SMALL = {**RCNN_SMALL, "backbone": "mobilenet_v3_large_075_fpn"}


def frozen_body():
    return mobilenet_v3_large_075_body(FOLDED_BATCHNORM).eval()


@pytest.mark.parametrize(
    ("size", "kernel", "before", "after"), [(128, 3, 0, 1), (127, 3, 1, 1), (128, 5, 1, 2), (9, 5, 2, 2)]
)
def test_strided_convolutions_pad_as_tensorflow_same(size, kernel, before, after):
    padded = _SamePad(kernel, 2)(torch.ones(1, 1, size, size))
    assert padded.shape[-1] == size + before + after
    assert padded[0, 0, 0, :before].sum() == 0 and padded[0, 0, 0, size + before :].sum() == 0
    assert (size + before + after - kernel) // 2 + 1 == -(-size // 2)  # TensorFlow's ceil(n / stride)


def test_the_body_gives_strides_8_16_32():
    body = frozen_body()
    x, shapes = torch.rand(1, 3, 128, 96), {}
    with torch.no_grad():
        for index, child in enumerate(body):
            x = child(x)
            shapes[index] = tuple(x.shape[1:])
    assert [shapes[c] for c in FEATURE_CHILDREN] == [(32, 16, 12), (88, 8, 6), (480, 4, 3)]


def test_the_shipped_coco_weights_fill_every_layer():
    state = torch.load(WEIGHTS_FILE, map_location="cpu", weights_only=True)
    body = frozen_body()
    load_coco_weights(body)  # strict: no key missing or left over
    assert set(state) == set(body.state_dict())
    for name, tensor in body.state_dict().items():
        torch.testing.assert_close(tensor, state[name].float())
    # Folded BatchNorm: unit scale, zero mean, unit variance; the offset carries the bias.
    assert torch.all(body[1].depthwise.norm.weight == 1) and torch.all(body[1].depthwise.norm.running_var == 1)
    assert body[1].depthwise.norm.bias.abs().sum() > 0


def test_a_changed_or_missing_weights_file_is_a_clear_error(tmp_path):
    changed = tmp_path / "weights.pt"
    changed.write_bytes(WEIGHTS_FILE.read_bytes()[:-1] + b"x")
    with pytest.raises(ValueError, match="is not the one foldwise ships"):
        load_coco_weights(frozen_body(), changed)
    with pytest.raises(FileNotFoundError, match="convert_centernet"):
        load_coco_weights(frozen_body(), tmp_path / "absent.pt")


@pytest.mark.parametrize("family", ["faster_rcnn", "fast_rcnn"])
def test_a_coco_started_detector_trains_its_late_stages_only_and_round_trips(family, tmp_path):
    torch.manual_seed(0)
    config = DetectorConfig(family=family, pretrained="coco", **SMALL)
    model = build_detector(config, num_classes=2).train()
    body = model.backbone.body
    assert not any(
        p.requires_grad for child in list(body.values())[: FEATURE_CHILDREN[0] + 1] for p in child.parameters()
    )
    assert all(p.requires_grad for p in body[str(FEATURE_CHILDREN[-1])].parameters())
    images = [torch.rand(3, 64, 64) for _ in range(2)]
    targets = [{"boxes": torch.tensor([[8.0, 10.0, 40.0, 50.0]]), "labels": torch.tensor([1])} for _ in range(2)]
    losses = model(images, targets)
    total = sum(losses.values())
    assert torch.isfinite(total)
    total.backward()
    assert body["16"][0].weight.grad is not None
    model.eval()
    path = tmp_path / "model.pt"
    meta = {
        "family": family,
        "backbone": config.backbone,
        "classes": ["a", "b"],
        "config": config.model_dump(mode="json"),
    }
    save_checkpoint(model, meta, path)
    restored = load_detector(path, device="cpu").model  # rebuilt without reading the COCO file
    with torch.no_grad():
        torch.testing.assert_close(restored(images)[0]["boxes"], model(images)[0]["boxes"])


def test_the_tensorflow_mobilenet_sees_0_to_255():
    mean, std = input_normalization(DetectorConfig(backbone="mobilenet_v3_large_075_fpn"))
    assert mean == [0.0] * 3 and std == [pytest.approx(1 / 255)] * 3
    assert input_normalization(DetectorConfig())[0] == [0.485, 0.456, 0.406]


@pytest.mark.parametrize(
    ("family", "backbone", "pretrained", "problem"),
    [
        ("faster_rcnn", "mobilenet_v3_large_fpn", "coco", "backbone 'mobilenet_v3_large_fpn' has 'imagenet'"),
        ("faster_rcnn", "mobilenet_v3_large_075_fpn", "imagenet", "backbone 'mobilenet_v3_large_075_fpn' has 'coco'"),
        ("yolo", "resnet18", "coco", "the yolo detector starts from ImageNet weights or none"),
    ],
)
def test_weights_a_backbone_does_not_have_are_refused_by_the_config(family, backbone, pretrained, problem):
    with pytest.raises(ValueError, match=problem):
        DetectorConfig(family=family, backbone=backbone, pretrained=pretrained)
    DetectorConfig(family="fast_rcnn", backbone="mobilenet_v3_large_075_fpn", pretrained="coco")


def _graph_constants(rng):
    """TensorFlow-named constants of the right shapes, as the npm package's graph names them."""
    tensors, cin = {}, 16
    tf = "tower_0/MobilenetV3"

    def add(name, shape):
        tensors[name] = rng.standard_normal(shape).astype(np.float32)

    add(f"{tf}/Conv/Conv2D_weights", (3, 3, 3, 16))
    add(f"{tf}/Conv/Conv2D_bn_offset", (16,))
    for index, (expanded, cout, kernel, _stride, squeeze, _act) in enumerate(BLOCKS):
        block = "expanded_conv" if index == 0 else f"expanded_conv_{index}"
        if expanded != cin:
            add(f"{tf}/{block}/expand/Conv2D_weights", (1, 1, cin, expanded))
            add(f"{tf}/{block}/expand/Conv2D_bn_offset", (expanded,))
        add(f"{tf}/{block}/depthwise/depthwise_weights", (kernel, kernel, expanded, 1))
        add(f"{tf}/{block}/depthwise/depthwise_bn_offset", (expanded,))
        if squeeze:
            se = f"MobilenetV3/{block}/squeeze_excite"
            add(f"{se}/Conv/weights", (1, 1, expanded, squeeze))
            add(f"{se}/Conv/biases", (squeeze,))
            add(f"{se}/Conv_1/weights", (1, 1, squeeze, expanded))
            add(f"{se}/Conv_1/biases", (expanded,))
        add(f"{tf}/{block}/project/Conv2D_weights", (1, 1, expanded, cout))
        add(f"{tf}/{block}/project/Conv2D_bn_offset", (cout,))
        cin = cout
    add("tower_0/extern1/Conv2D_weights", (1, 1, cin, 480))
    add("tower_0/extern1/Conv2D_bn_offset", (480,))
    return tensors


def test_the_converter_maps_every_graph_weight_to_its_layer():
    tensors = _graph_constants(np.random.default_rng(0))
    body = frozen_body()
    body.load_state_dict(backbone_state(tensors))  # strict
    depthwise = tensors["tower_0/MobilenetV3/expanded_conv_3/depthwise/depthwise_weights"]  # H, W, C, 1
    torch.testing.assert_close(body[4].depthwise.conv.weight[7, 0], torch.from_numpy(depthwise[:, :, 7, 0]))
    pointwise = tensors["tower_0/MobilenetV3/expanded_conv_3/project/Conv2D_weights"]  # 1, 1, in, out
    torch.testing.assert_close(body[4].project.conv.weight[5, 9, 0, 0], torch.tensor(pointwise[0, 0, 9, 5]))
    torch.testing.assert_close(
        body[4].project.norm.bias,
        torch.from_numpy(tensors["tower_0/MobilenetV3/expanded_conv_3/project/Conv2D_bn_offset"]),
    )


def test_float16_weights_are_widened_and_a_short_file_is_refused():
    values = np.array([0.5, -2.0, 1 / 6], np.float16)
    graph = {
        "weightsManifest": [
            {
                "paths": ["x.bin"],
                "weights": [
                    {"name": "w", "shape": [3], "dtype": "float32", "quantization": {"dtype": "float16"}},
                    {"name": "k", "shape": [], "dtype": "int32"},
                ],
            }
        ]
    }
    blob = values.tobytes() + np.array(7, np.int32).tobytes()
    tensors = decode_weights(graph, blob)
    assert tensors["w"].dtype == np.float32 and tensors["w"].tolist() == values.astype(np.float32).tolist()
    assert int(tensors["k"]) == 7
    with pytest.raises(ValueError, match="covers 10 bytes of a 14-byte file"):
        decode_weights(graph, blob + b"\0" * 4)


@pytest.mark.parametrize(("stages", "first_trained"), [(None, 7), (0, None), (1, 16), (3, 7), (6, 0)])
def test_trainable_backbone_stages_count_from_the_last(stages, first_trained):
    config = DetectorConfig(pretrained="coco", trainable_backbone_stages=stages, **SMALL)
    body = build_detector(config, num_classes=2).backbone.body
    trained = [index for index, child in enumerate(body.values()) if any(p.requires_grad for p in child.parameters())]
    assert trained == ([] if first_trained is None else list(range(first_trained, 17)))


def test_trainable_backbone_stages_apply_to_torchvisions_backbones_too():
    mobilenet = build_detector(
        DetectorConfig(trainable_backbone_stages=1, **{**SMALL, "backbone": "mobilenet_v3_large_fpn"}), 2
    )
    assert [
        i for i, c in enumerate(mobilenet.backbone.body.values()) if any(p.requires_grad for p in c.parameters())
    ] == [16]
    resnet = build_detector(DetectorConfig(trainable_backbone_stages=2, **{**SMALL, "backbone": "resnet50_fpn_v2"}), 2)
    trained = {name.split(".")[0] for name, p in resnet.backbone.body.named_parameters() if p.requires_grad}
    assert trained == {"layer4", "layer3"}
    with pytest.raises(ValueError, match="trainable_backbone_stages: only read by the R-CNN families"):
        DetectorConfig(family="yolo", trainable_backbone_stages=2)
