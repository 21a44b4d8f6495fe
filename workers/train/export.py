"""A trained detector ω as an ONNX file that runs without foldwise or torch (onnxruntime).

The exported graph, for every family that can export::

    input   image   float32 (3, H, W), RGB in 0..1
    outputs boxes   float32 (n, 4) xyxy in the input image's pixels, best score first
            scores  float32 (n,)
            labels  int64 (n,), 1-based: class name = classes[label - 1]

and the file's metadata (``metadata_props``) names the family, the classes (JSON) and the
input size (``image_height``/``image_width``: 0 when the graph takes any size).

A checkpoint's **runtime graph** (``write_runtime_graph``) is that export kept beside the
checkpoint (``<checkpoint>.onnx``, its SHA-256 in the metadata), optimized once as it is written:
``load_detector`` finds it, the detector opens it with onnxruntime the first time its own views
are needed (``load_runtime_graph``), and ``detect_object`` runs the network at those views
through it, the same detections as torch's to float rounding in about half the time on 2 cores
(bench/README.md, "The network on onnxruntime"). A graph whose checkpoint changed since is not
used. ``foldwise run`` writes it for the model it hands over; ``foldwise export --runtime`` for
any checkpoint; a calibration or lookalikes written into a checkpoint carry its graph along.

Which families export, and how:

* ``faster_rcnn``: traced (torch's TorchScript exporter, opset 17) with the image height and
  width dynamic: torchvision's resize, anchors, RoIAlign and NMS all have ONNX forms.
* ``yolo``: traced at one image size (``image_size``, default the detector's input size, at
  most that): its letterbox computes the resized size in Python (``round``), which a trace
  records as a constant, so the graph is right for that size only (:class:`OnnxDetector`
  refuses others); and shrinking an image uses antialiased resampling, which has no ONNX
  operator, so a larger size cannot export.
* ``fast_rcnn`` cannot export: its proposals come from OpenCV's Edge Boxes (``cv2.ximgproc``),
  outside torch. A trace records the example image's proposals as constants, so the graph
  would score those same regions on every image (measured: boxes ~90 px off on a second image).
"""

from __future__ import annotations

import json
import os
import tempfile
import time
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from foldwise.store import file_sha256

FORMATS = ("onnx",)
OPSET = 17
# family -> whether the graph takes any image size
EXPORTABLE = {"faster_rcnn": True, "yolo": False}
NOT_EXPORTABLE = {
    "fast_rcnn": (
        "its proposals come from OpenCV's Edge Boxes (cv2.ximgproc), outside torch: a traced graph "
        "would hold the example image's proposals as constants"
    ),
}


class ExportError(ValueError):
    """A detector or a request that cannot be exported; the message says why."""


def export_onnx(
    detector: Any, out: str | Path, image_size: tuple[int, int] | None = None, metadata: dict[str, str] | None = None
) -> Path:
    """Write ``detector`` (a :class:`workers.train.checkpoint.Detector`) to ``out`` as ONNX.

    ``image_size`` (height, width) is the size a fixed-size family (yolo) is exported at;
    default the detector's input size. Families that take any size ignore it.
    ``metadata``: more entries for the file's metadata (a runtime graph's checkpoint digest and
    onnxruntime version: ``write_runtime_graph``).
    """
    import onnx
    import torch
    from torch import nn

    from workers.train.checkpoint import member_families, torch_threads

    families = sorted(set(member_families(detector)))
    if len(families) > 1:
        raise ExportError(
            f"an ensemble of several detector families ({', '.join(families)}) cannot be exported as one graph"
        )
    family = detector.meta["family"]
    if family in NOT_EXPORTABLE:
        raise ExportError(f"the {family} detector cannot be exported to ONNX: {NOT_EXPORTABLE[family]}")
    if family not in EXPORTABLE:
        raise ExportError(f"detector family {family!r} has no ONNX export; exportable: {', '.join(EXPORTABLE)}")
    any_size = EXPORTABLE[family]
    input_size = int(detector.meta["input_size"])
    height, width = image_size or (input_size, input_size)
    if min(height, width) < 16:
        raise ExportError(f"image size {height}x{width} is too small to export at (at least 16x16)")
    if not any_size and max(height, width) > input_size:
        # Shrinking needs antialiased resampling, which has no ONNX operator (opset 17).
        raise ExportError(
            f"the {family} detector exports at image sizes up to its input size {input_size} "
            f"(got {height}x{width}): shrinking uses antialiased resampling, which ONNX lacks"
        )

    class SingleImage(nn.Module):
        """One image in, three tensors out: the torchvision interface without lists and dicts."""

        def __init__(self, model: nn.Module) -> None:
            super().__init__()
            self.model = model

        def forward(self, image):
            (found,) = self.model([image])
            return found["boxes"], found["scores"], found["labels"]

    wrapper = SingleImage(detector.model.cpu()).eval()
    # An image with texture, so no step of the trace meets an empty set (e.g. no box kept).
    example = torch.from_numpy(np.random.default_rng(0).random((3, height, width), dtype=np.float32))
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    threads = int(detector.meta.get("config", {}).get("num_threads", 0))
    with torch_threads(threads), torch.no_grad(), warnings.catch_warnings():
        # The tracer warns at every Python-side shape computation; which ones matter is the
        # family's business (above), and the round-trip test checks the result.
        warnings.simplefilter("ignore")
        torch.onnx.export(
            wrapper,
            (example,),
            str(out),
            dynamo=False,
            opset_version=OPSET,
            input_names=["image"],
            output_names=["boxes", "scores", "labels"],
            dynamic_axes={"image": {1: "height", 2: "width"}} if any_size else None,
        )
    graph = onnx.load(str(out))
    metadata = {
        **(metadata or {}),
        "foldwise.family": family,
        "foldwise.backbone": str(detector.meta.get("backbone", "")),
        "foldwise.classes": json.dumps(list(detector.meta["classes"])),
        "foldwise.image_height": "0" if any_size else str(height),
        "foldwise.image_width": "0" if any_size else str(width),
    }
    if detector.meta.get("calibration"):  # the texture check runs outside the graph; its calibration travels with it
        metadata["foldwise.calibration"] = json.dumps(detector.meta["calibration"])
    onnx.helper.set_model_props(graph, metadata)
    onnx.save(graph, str(out))
    return out


@dataclass
class OnnxDetector:
    """An exported detector run with onnxruntime (no torch): ``detect(image_rgb_uint8)``."""

    session: Any
    family: str
    classes: list[str]
    image_size: tuple[int, int] | None  # (height, width) the graph needs; None: any
    checkpoint_sha256: str | None = None  # a runtime graph's checkpoint (``write_runtime_graph``)

    @classmethod
    def load(cls, path: str | Path, threads: int = 0, optimized: bool = False) -> OnnxDetector:
        """Open an exported file; ``threads``: onnxruntime's threads within an operator (0: its
        default); ``optimized``: the graph was optimized when written (a runtime graph), and is
        not again."""
        import onnxruntime

        options = onnxruntime.SessionOptions()
        options.log_severity_level = 3  # errors only: the graph's shape hints are not news
        if threads > 0:
            options.intra_op_num_threads = threads
        if optimized:
            options.graph_optimization_level = onnxruntime.GraphOptimizationLevel.ORT_DISABLE_ALL
        session = onnxruntime.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        meta = session.get_modelmeta().custom_metadata_map
        if "foldwise.family" not in meta:
            raise ExportError(f"{path} was not written by `foldwise export` (no foldwise metadata)")
        height, width = int(meta["foldwise.image_height"]), int(meta["foldwise.image_width"])
        return cls(
            session=session,
            family=meta["foldwise.family"],
            classes=json.loads(meta["foldwise.classes"]),
            image_size=(height, width) if height and width else None,
            checkpoint_sha256=meta.get("foldwise.checkpoint_sha256"),
        )

    def detect(self, image: np.ndarray) -> dict[str, np.ndarray]:
        """``detect_object``'s result for one RGB uint8 image: boxes, scores, labels (0-based)."""
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise ValueError(f"expected an RGB uint8 image (H, W, 3), got {image.dtype} {image.shape}")
        if self.image_size is not None and image.shape[:2] != self.image_size:
            raise ValueError(
                f"this {self.family} export takes {self.image_size[0]}x{self.image_size[1]} images, "
                f"got {image.shape[0]}x{image.shape[1]}: export again with --image-size"
            )
        tensor = np.ascontiguousarray(image.transpose(2, 0, 1), dtype=np.float32) / 255.0
        boxes, scores, labels = self.session.run(None, {"image": tensor})
        return {
            "boxes": boxes.astype(np.float32).reshape(-1, 4),
            "scores": scores.astype(np.float32),
            "labels": labels.astype(np.int64) - 1,
        }


def runtime_graph_path(checkpoint: str | Path) -> Path:
    """Where a checkpoint's runtime graph lies: beside it, ``<name>.onnx`` (``ensemble.pt.onnx``)."""
    checkpoint = Path(checkpoint)
    return checkpoint.with_name(checkpoint.name + ".onnx")


def write_runtime_graph(checkpoint: str | Path, detector: Any = None) -> Path:
    """Export the detector at ``checkpoint`` (``detector``: it, already read to the CPU) beside it
    as its runtime graph (see the module's docstring); an :class:`ExportError` where its family
    cannot export at any image size."""
    if detector is None:
        from workers.train.checkpoint import load_detector

        detector = load_detector(checkpoint, device="cpu")
    family = detector.meta["family"]
    if not EXPORTABLE.get(family):
        raise ExportError(
            f"the {family} detector has no runtime graph: only a graph that takes any image size can stand for it"
        )
    import onnxruntime

    out = runtime_graph_path(checkpoint)
    with tempfile.TemporaryDirectory(dir=out.parent, prefix=f".{out.name}.") as folder:
        stamp = {"foldwise.checkpoint_sha256": file_sha256(checkpoint), "foldwise.onnxruntime": onnxruntime.__version__}
        plain = export_onnx(detector, Path(folder) / "plain.onnx", metadata=stamp)
        # Optimized once here (constants folded, operators fused) and opened later without
        # optimizing again: 1 s to open instead of 6 s (bench/README.md, "The network on onnxruntime").
        options = onnxruntime.SessionOptions()
        options.log_severity_level = 3
        options.graph_optimization_level = onnxruntime.GraphOptimizationLevel.ORT_ENABLE_EXTENDED
        options.optimized_model_filepath = str(Path(folder) / "optimized.onnx")
        onnxruntime.InferenceSession(str(plain), options, providers=["CPUExecutionProvider"])
        os.replace(Path(folder) / "optimized.onnx", out)
    return out


def write_runtime_graph_told(checkpoint: str | Path) -> str:
    """Write the runtime graph of the model a command hands over (``write_runtime_graph``) and
    return the line that tells its user what happened: where it lies and how long it took, or,
    for a family that cannot export, that detection runs the network in torch."""
    started = time.perf_counter()
    try:
        written = write_runtime_graph(checkpoint)
    except ExportError as error:
        return f"no runtime graph: {error}; detection runs the network in torch"
    return (
        f"runtime graph: {written} ({time.perf_counter() - started:.0f} s): detection runs the network at its "
        "views through onnxruntime"
    )


def load_runtime_graph(
    checkpoint: str | Path, classes: list[str], threads: int = 0, sha256: str | None = None
) -> OnnxDetector | None:
    """The checkpoint's runtime graph opened with onnxruntime, or None where there is none, it
    was written for another checkpoint (its digest differs from ``sha256``, default the file's
    now: the checkpoint changed since), by another onnxruntime (it was optimized for that one)
    or its classes differ. A file onnxruntime cannot open warns and is passed over: torch runs
    instead."""
    import onnxruntime

    path = runtime_graph_path(checkpoint)
    if not path.is_file():
        return None
    try:
        graph = OnnxDetector.load(path, threads=threads, optimized=True)
    except Exception as error:  # onnxruntime's own errors have no common base class
        warnings.warn(
            f"{path}: not a runtime graph onnxruntime can open ({error}); the network runs in torch", stacklevel=2
        )
        return None
    meta = graph.session.get_modelmeta().custom_metadata_map
    if (
        graph.checkpoint_sha256 != (sha256 or file_sha256(checkpoint))
        or meta.get("foldwise.onnxruntime") != onnxruntime.__version__
        or graph.classes != list(classes)
        or graph.image_size
    ):
        return None
    return graph


def matching_runtime_graph(checkpoint: str | Path):
    """The checkpoint's runtime graph as an ONNX model (``onnx.ModelProto``) where it has one
    written for it, else None: for a checkpoint written anew with the same network
    (``carry_runtime_graph``)."""
    import onnx

    path = runtime_graph_path(checkpoint)
    if not path.is_file():
        return None
    try:
        graph = onnx.load(str(path))
    except Exception:  # a torn or foreign file: nothing to carry
        return None
    props = {prop.key: prop.value for prop in graph.metadata_props}
    return graph if props.get("foldwise.checkpoint_sha256") == file_sha256(checkpoint) else None


def carry_runtime_graph(graph, checkpoint: str | Path, calibration: dict | None = None) -> Path:
    """``graph`` (``matching_runtime_graph`` of a checkpoint whose network ``checkpoint`` holds
    unchanged: a calibration or lookalikes added) written as ``checkpoint``'s runtime graph, its
    digest (and ``calibration``, where given) now ``checkpoint``'s."""
    import onnx

    props = {prop.key: prop.value for prop in graph.metadata_props}
    props["foldwise.checkpoint_sha256"] = file_sha256(checkpoint)
    if calibration is not None:
        props["foldwise.calibration"] = json.dumps(calibration)
    del graph.metadata_props[:]
    onnx.helper.set_model_props(graph, props)
    out = runtime_graph_path(checkpoint)
    onnx.save(graph, str(out))
    return out
