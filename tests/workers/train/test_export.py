"""`foldwise export --format onnx`: the exported graph, run by onnxruntime on rendered images,
finds what the torch detector finds.

Tolerance: boxes within 0.01 px and scores within 1e-4 of torch's, the same count and labels
(the graph runs the same operations in float32; measured difference 0.0 for faster_rcnn).
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from workers.train.cli import register

BOX_TOLERANCE_PX = 0.01
SCORE_TOLERANCE = 1e-4
runner = CliRunner()


def make_app() -> typer.Typer:
    app = typer.Typer()
    register(app)
    return app


@pytest.fixture(scope="module")
def rendered(tmp_path_factory):
    """Six 64-px renders of the real pipeline (two difficulties of focus blur)."""
    from workers.render.assets import load_assets
    from workers.render.cli import render_dataset

    out = tmp_path_factory.mktemp("rendered")
    render_dataset(
        out,
        ["fb"],
        ["easy", "hard"],
        3,
        seed=3,
        image_size=64,
        backend="raster",
        assets=load_assets(),
        echo=lambda _: None,
    )
    return out


@pytest.fixture(scope="module")
def exported(tmp_path_factory, rendered):
    """family -> (checkpoint, ONNX file): two training iterations each on the renders."""
    import yaml

    from foldwise.settings import REPO_ROOT

    folder = tmp_path_factory.mktemp("exported")
    config = yaml.safe_load((REPO_ROOT / "configs/smoke.yaml").read_text())
    # Two iterations leave yolo's scores below its default cut (0.05): keep its boxes to compare.
    config["detector"]["box_score_threshold"] = 0.001
    (folder / "config.yaml").write_text(yaml.safe_dump(config))
    files = {}
    for family in ("faster_rcnn", "yolo", "fast_rcnn"):
        checkpoint = folder / f"{family}.pt"
        trained = runner.invoke(
            make_app(),
            ["train", "--detector", family, "--data", str(rendered), "--iterations", "2", "--input-size", "64",
             "--batch-size", "2", "--seed", "2", "--threads", "1", "--config", str(folder / "config.yaml"),
             "--out", str(checkpoint)],
        )  # fmt: skip
        assert trained.exit_code == 0, trained.output
        onnx_file = folder / f"{family}.onnx"
        result = runner.invoke(
            make_app(), ["export", "--model", str(checkpoint), "--format", "onnx", "--out", str(onnx_file)]
        )
        files[family] = (checkpoint, onnx_file, result)
    return files


@pytest.fixture(scope="module")
def with_runtime_graph(tmp_path_factory, exported):
    """The faster_rcnn checkpoint with its runtime graph written beside it, once for the tests
    that copy the pair (``copy_with_graph``) to change or read it."""
    from workers.train.export import write_runtime_graph

    checkpoint = tmp_path_factory.mktemp("runtime") / "model.pt"
    shutil.copy(exported["faster_rcnn"][0], checkpoint)
    assert write_runtime_graph(checkpoint) == checkpoint.parent / "model.pt.onnx"
    return checkpoint


def copy_with_graph(checkpoint, folder):
    """``checkpoint`` and its runtime graph copied into ``folder`` (the graph names the
    checkpoint by its SHA-256, which a copy keeps); the copy's path."""
    from workers.train.export import runtime_graph_path

    copy = folder / checkpoint.name
    shutil.copy(checkpoint, copy)
    shutil.copy(runtime_graph_path(checkpoint), runtime_graph_path(copy))
    return copy


def rendered_images(folder):
    from workers.train.data import read_image_rgb

    return [read_image_rgb(path) for path in sorted((folder / "images").glob("*.png"))]


def assert_same_detections(onnx_found, torch_found):
    """Same count, and every torch detection has an ONNX one of its label, box and score.

    Order is not compared: scores equal to within float rounding (an untrained detector has
    many) may sort either way. Detections tied with the last one kept may be swapped at the
    detection cap, so those are left out of the matching.
    """
    assert len(onnx_found["boxes"]) == len(torch_found["boxes"]) > 0
    lowest = torch_found["scores"].min()
    for box, score, label in zip(torch_found["boxes"], torch_found["scores"], torch_found["labels"]):
        if score <= lowest + SCORE_TOLERANCE:
            continue
        match = (
            (onnx_found["labels"] == label)
            & (np.abs(onnx_found["boxes"] - box).max(axis=1) <= BOX_TOLERANCE_PX)
            & (np.abs(onnx_found["scores"] - score) <= SCORE_TOLERANCE)
        )
        assert match.any(), f"torch's detection {box} {score:.4f} class {label} is not in the ONNX output"


@pytest.mark.parametrize("family", ["faster_rcnn", "yolo"])
def test_exported_detector_matches_torch_on_rendered_images(exported, rendered, family):
    import cv2

    from workers.train.checkpoint import detect_object, load_detector
    from workers.train.export import OnnxDetector

    checkpoint, onnx_file, result = exported[family]
    assert result.exit_code == 0, result.output
    assert f"wrote {onnx_file}" in result.output
    detector = load_detector(checkpoint, device="cpu")
    model = OnnxDetector.load(onnx_file)
    assert model.family == family and model.classes == detector.classes
    images = rendered_images(rendered)
    assert len(images) == 6
    for image, expected in zip(images, detect_object(detector, images)):
        assert_same_detections(model.detect(image), expected)

    larger = cv2.resize(images[0], (96, 80))
    if family == "faster_rcnn":  # any size: torchvision's resize is in the graph
        assert model.image_size is None
        assert_same_detections(model.detect(larger), detect_object(detector, [larger])[0])
    else:  # traced at one size: another is refused, not silently wrong
        assert model.image_size == (64, 64)
        with pytest.raises(ValueError, match="takes 64x64 images, got 80x96"):
            model.detect(larger)


def test_a_detector_with_test_sizes_exports_its_merged_detections(exported, rendered, tmp_path):
    """The graph of a Faster R-CNN that detects at several sizes holds every size and the merge."""
    import cv2

    from workers.train.checkpoint import detect_object, load_detector, save_checkpoint
    from workers.train.export import OnnxDetector, export_onnx

    plain = load_detector(exported["faster_rcnn"][0], device="cpu")
    meta = {**plain.meta, "config": {**plain.meta["config"], "test_sizes": [64, 96]}}
    detector = load_detector(save_checkpoint(plain.model, meta, tmp_path / "multi.pt"))
    model = OnnxDetector.load(export_onnx(detector, tmp_path / "multi.onnx"))
    images = rendered_images(rendered)[:3]
    images.append(cv2.resize(images[0], (96, 80)))
    for image, expected, single in zip(images, detect_object(detector, images), detect_object(plain, images)):
        assert_same_detections(model.detect(image), expected)
        assert not np.array_equal(expected["scores"], single["scores"])


def test_a_detector_with_test_turns_exports_its_merged_detections(exported, rendered, tmp_path):
    """The graph of a Faster R-CNN that detects on quarter turns holds every turn, the boxes
    mapped back and the merge, at any image size (a non-square one included). One test size:
    turns at several sizes are the runtime graph's test below."""
    import cv2

    from workers.train.checkpoint import detect_object, load_detector, save_checkpoint
    from workers.train.export import OnnxDetector, export_onnx

    plain = load_detector(exported["faster_rcnn"][0], device="cpu")
    meta = {**plain.meta, "config": {**plain.meta["config"], "test_sizes": [64], "test_turns": [0, 1, 2, 3]}}
    detector = load_detector(save_checkpoint(plain.model, meta, tmp_path / "turns.pt"))
    model = OnnxDetector.load(export_onnx(detector, tmp_path / "turns.onnx"))
    images = rendered_images(rendered)[:2]
    images.append(cv2.resize(images[0], (96, 80)))
    for image, expected, upright in zip(
        images, detect_object(detector, images), detect_object(plain, images, test_sizes=(64,))
    ):
        assert_same_detections(model.detect(image), expected)
        assert not np.array_equal(expected["scores"], upright["scores"])


def test_an_ensemble_exports_as_one_graph_of_its_members_and_their_merge(exported, rendered, tmp_path):
    """An ensemble file of Faster R-CNNs is one graph: each member at any size, their detections
    merged by per-class NMS as torch merges them."""
    import cv2
    import torch

    from workers.train.checkpoint import detect_object, load_detector, save_checkpoint, save_ensemble
    from workers.train.export import OnnxDetector, export_onnx

    first = exported["faster_rcnn"][0]
    other = load_detector(first, device="cpu")
    with torch.no_grad():  # another network: the box head's last layer moved
        for parameter in other.model.roi_heads.box_predictor.parameters():
            parameter.add_(torch.randn_like(parameter, generator=torch.Generator().manual_seed(5)) * 0.5)
    second = save_checkpoint(other.model, other.meta, tmp_path / "other.pt")
    ensemble = load_detector(save_ensemble([first, second], tmp_path / "ensemble.pt"), device="cpu")
    model = OnnxDetector.load(export_onnx(ensemble, tmp_path / "ensemble.onnx"))
    images = rendered_images(rendered)[:3]
    images.append(cv2.resize(images[0], (96, 80)))
    alone = detect_object(load_detector(first, device="cpu"), images)
    for image, expected, single in zip(images, detect_object(ensemble, images), alone):
        assert_same_detections(model.detect(image), expected)
        assert not np.array_equal(expected["scores"], single["scores"])


def test_a_runtime_graph_beside_a_checkpoint_runs_its_views_with_the_same_detections(exported, rendered, tmp_path):
    """`foldwise export --runtime` writes the checkpoint's graph beside it; the detector read back
    runs its own views through onnxruntime (every image, none through torch) and finds what
    torch finds. Views asked for by the caller run in torch."""
    import cv2
    import torch

    from workers.train.checkpoint import detect_object, load_detector, save_checkpoint
    from workers.train.export import runtime_graph_path

    plain = load_detector(exported["faster_rcnn"][0], device="cpu")
    meta = {**plain.meta, "config": {**plain.meta["config"], "test_sizes": [64, 96], "test_turns": [0, 1]}}
    checkpoint = save_checkpoint(plain.model, meta, tmp_path / "views.pt")
    images = rendered_images(rendered)[:3]
    images.append(cv2.resize(images[0], (96, 80)))
    in_torch = load_detector(checkpoint, device="cpu")
    assert in_torch.runtime is None  # no graph beside it yet
    expected = detect_object(in_torch, images)

    result = runner.invoke(make_app(), ["export", "--model", str(checkpoint), "--runtime"])
    assert result.exit_code == 0, result.output
    assert f"wrote {runtime_graph_path(checkpoint)}" in result.output and runtime_graph_path(checkpoint).is_file()
    detector = load_detector(checkpoint, device="cpu")
    assert detector.runtime_loader is not None  # opened on first use, not before
    detect_object(detector, images[:1], test_sizes=(64,), test_turns=())
    assert detector.runtime_loader is not None  # views asked for ran in torch
    assert detector.runtime is not None and detector.runtime_loader is None
    ran, detect = [], detector.runtime.detect
    detector.runtime.detect = lambda image: ran.append(image.shape) or detect(image)

    def no_torch(*_args, **_kwargs):
        raise AssertionError("the network ran in torch")

    detector.model.forward = no_torch
    for found, wanted in zip(detect_object(detector, images), expected):
        assert_same_detections(found, wanted)
    assert ran == [image.shape for image in images]
    del detector.model.forward  # the class's own again
    with torch.no_grad():
        at_one_size = detect_object(detector, images[:1], test_sizes=(64,), test_turns=())
    assert len(ran) == len(images)  # asked views: torch
    assert_same_detections(at_one_size[0], detect_object(in_torch, images[:1], test_sizes=(64,), test_turns=())[0])


def test_a_runtime_graph_of_a_changed_checkpoint_or_unreadable_is_not_used(
    exported, with_runtime_graph, tmp_path, monkeypatch
):
    """A graph is used only for the checkpoint it was written from (its SHA-256) and by the
    onnxruntime that optimized it: otherwise torch runs. A graph onnxruntime cannot open warns,
    names the file, and torch runs. Where no graph can stand for the detector, or --runtime meets
    --out, the command says why."""
    import onnxruntime

    from workers.train.checkpoint import load_detector, save_checkpoint
    from workers.train.export import runtime_graph_path, write_runtime_graph

    checkpoint = copy_with_graph(with_runtime_graph, tmp_path)
    assert load_detector(checkpoint).runtime is not None
    detector = load_detector(checkpoint)
    meta = {**detector.meta, "iterations": detector.meta.get("iterations", 0) + 1}  # other bytes, same network
    save_checkpoint(detector.model, meta, checkpoint)
    assert load_detector(checkpoint).runtime is None

    write_runtime_graph(checkpoint)
    with monkeypatch.context() as patch:  # optimized for one onnxruntime, opened by another
        patch.setattr(onnxruntime, "__version__", "0.0.1")
        assert load_detector(checkpoint).runtime is None
    assert load_detector(checkpoint).runtime is not None

    runtime_graph_path(checkpoint).write_bytes(b"not an onnx file")
    with pytest.warns(UserWarning, match="model.pt.onnx: not a runtime graph onnxruntime can open"):
        assert load_detector(checkpoint).runtime is None

    both = runner.invoke(make_app(), ["export", "--model", str(checkpoint), "--runtime", "--out", str(tmp_path / "x")])
    assert both.exit_code == 1 and "--runtime writes the graph beside the checkpoint" in both.output
    neither = runner.invoke(make_app(), ["export", "--model", str(checkpoint)])
    assert neither.exit_code == 1 and "--out: the file to write" in neither.output
    yolo = runner.invoke(make_app(), ["export", "--model", str(exported["yolo"][0]), "--runtime"])
    assert yolo.exit_code == 1 and "the yolo detector has no runtime graph" in yolo.output
    assert not runtime_graph_path(exported["yolo"][0]).exists()


def test_a_runtime_graph_is_matched_against_the_bytes_the_model_was_read_from(
    with_runtime_graph, tmp_path, monkeypatch
):
    """The checkpoint is read once: its graph is matched against the model in memory, even where
    the file is rewritten (other bytes) between reading the model and matching the graph."""
    from workers.train import checkpoint as checkpoints
    from workers.train.checkpoint import load_detector, save_checkpoint

    path = copy_with_graph(with_runtime_graph, tmp_path)
    first = load_detector(path)
    real_load = checkpoints.torch.load

    def load_then_rewrite(*args, **kwargs):
        payload = real_load(*args, **kwargs)
        meta = {**first.meta, "iterations": first.meta.get("iterations", 0) + 1}  # other bytes
        save_checkpoint(first.model, meta, path)
        return payload

    monkeypatch.setattr(checkpoints.torch, "load", load_then_rewrite)
    assert load_detector(path).runtime is not None  # the bytes read are the graph's
    monkeypatch.setattr(checkpoints.torch, "load", real_load)
    assert load_detector(path).runtime is None  # the file as rewritten is not


def test_a_calibration_or_lookalikes_written_into_a_checkpoint_carry_its_runtime_graph(with_runtime_graph, tmp_path):
    """Neither changes the network: the checkpoint written with them has the source's runtime
    graph beside it, its own digest (and calibration) recorded, and the source keeps its own.
    A source without a graph gives none."""
    import json

    import onnx

    from foldwise.store import file_sha256
    from workers.train.calibration import shipped_calibration
    from workers.train.checkpoint import load_detector, write_calibration, write_lookalikes
    from workers.train.export import runtime_graph_path

    source = tmp_path / "model.pt"
    shutil.copy(with_runtime_graph, source)
    bare = write_calibration(source, shipped_calibration(), tmp_path / "bare-calibrated.pt")
    assert not runtime_graph_path(bare).exists()
    shutil.copy(runtime_graph_path(with_runtime_graph), runtime_graph_path(source))
    calibrated = write_calibration(source, shipped_calibration(), tmp_path / "calibrated.pt")
    sheet = np.full((40, 30, 3), 200, np.uint8)
    with_lookalikes = write_lookalikes(calibrated, {"other": sheet}, tmp_path / "with-lookalikes.pt")
    for checkpoint in (source, calibrated, with_lookalikes):
        detector = load_detector(checkpoint)
        assert detector.runtime is not None, checkpoint
        assert detector.runtime.checkpoint_sha256 == file_sha256(checkpoint)
    props = {p.key: p.value for p in onnx.load(str(runtime_graph_path(calibrated))).metadata_props}
    assert json.loads(props["foldwise.calibration"]) == shipped_calibration().to_dict()


def test_fast_rcnn_cannot_export_and_says_why(exported):
    _, onnx_file, result = exported["fast_rcnn"]
    assert result.exit_code == 1
    assert "fast_rcnn detector cannot be exported" in result.output and "Edge Boxes" in result.output
    assert not onnx_file.exists()


def test_export_refuses_an_unknown_format_or_size(exported, tmp_path):
    checkpoint = exported["yolo"][0]
    result = runner.invoke(
        make_app(), ["export", "--model", str(checkpoint), "--format", "tflite", "--out", str(tmp_path / "m")]
    )
    assert result.exit_code == 1 and "unknown export format 'tflite'" in result.output
    result = runner.invoke(
        make_app(), ["export", "--model", str(checkpoint), "--image-size", "big", "--out", str(tmp_path / "m")]
    )
    assert result.exit_code == 1 and "expected N or HxW" in result.output
    missing = runner.invoke(make_app(), ["export", "--model", str(tmp_path / "none.pt"), "--out", str(tmp_path / "m")])
    assert missing.exit_code == 1 and "does not exist" in missing.output


def test_yolo_exported_at_another_size_runs_there_and_not_above_its_input_size(exported, rendered, tmp_path):
    import cv2

    from workers.train.checkpoint import detect_object, load_detector
    from workers.train.export import OnnxDetector

    checkpoint = exported["yolo"][0]
    target = tmp_path / "yolo-40x48.onnx"
    result = runner.invoke(
        make_app(), ["export", "--model", str(checkpoint), "--image-size", "40x48", "--out", str(target)]
    )
    assert result.exit_code == 0, result.output
    image = cv2.resize(rendered_images(rendered)[1], (48, 40))
    model = OnnxDetector.load(target)
    assert model.image_size == (40, 48)
    assert_same_detections(model.detect(image), detect_object(load_detector(checkpoint, device="cpu"), [image])[0])

    larger = runner.invoke(
        make_app(), ["export", "--model", str(checkpoint), "--image-size", "96", "--out", str(target)]
    )
    assert larger.exit_code == 1 and "up to its input size 64 (got 96x96)" in larger.output


def test_a_texture_checked_detector_trained_from_the_cli_carries_its_textures_and_export_says_what_it_leaves_out(
    rendered, tmp_path
):
    """`foldwise train --config` with detector.texture_check (and texture_search) takes the
    classes' textures from the config's asset catalog; `foldwise detect` says which detections the
    texture confirmed; the ONNX graph holds the network only, and the export says so."""
    import cv2
    import yaml

    from foldwise.settings import REPO_ROOT
    from workers.render.assets import load_assets
    from workers.train.checkpoint import load_detector

    config = yaml.safe_load((REPO_ROOT / "configs/smoke.yaml").read_text())
    config["detector"].update({"texture_check": True, "texture_search": True})
    checkpoint = tmp_path / "checked.pt"

    def train(objects: int):
        config["assets"]["n_objects"] = objects
        (tmp_path / "config.yaml").write_text(yaml.safe_dump(config))
        return runner.invoke(
            make_app(),
            ["train", "--detector", "faster_rcnn", "--data", str(rendered), "--iterations", "1", "--input-size", "64",
             "--batch-size", "2", "--threads", "1", "--config", str(tmp_path / "config.yaml"), "--out", str(checkpoint)],
        )  # fmt: skip

    refused = train(2)  # the renders hold a third class the config's catalog does not
    assert refused.exit_code == 1 and "texture_check needs each class's texture" in refused.output
    assert "unknown object 'chelsea'" in refused.output and not checkpoint.exists()
    trained = train(5)
    assert trained.exit_code == 0, trained.output
    detector = load_detector(checkpoint)
    assert detector.texture_check() is not None and sorted(detector.textures) == sorted(detector.classes)
    # A photograph of the astronaut sheet: the search finds it whatever the one-step network says.
    texture = load_assets().textures(["astronaut"])["astronaut"]
    photo = np.full((300, 400, 3), 70, np.uint8)
    photo[40 : 40 + 220, 80 : 80 + 220] = cv2.resize(np.ascontiguousarray(texture[:, :, :3]), (220, 220))
    cv2.imwrite(str(tmp_path / "photo.png"), cv2.cvtColor(photo, cv2.COLOR_RGB2BGR))
    found = runner.invoke(
        make_app(),
        [
            "detect",
            "--model",
            str(checkpoint),
            str(tmp_path / "photo.png"),
            "--out-dir",
            str(tmp_path / "d"),
            "--threshold",
            "0.9",
        ],
    )
    assert found.exit_code == 0, found.output
    assert "astronaut 0.9" in found.output and "(texture confirmed)" in found.output
    result = runner.invoke(make_app(), ["export", "--model", str(checkpoint), "--out", str(tmp_path / "m.onnx")])
    assert result.exit_code == 0, result.output
    assert "the graph holds the network only" in result.output and "texture check and search" in result.output


def test_the_views_vote_exports_as_tensor_operations_right_at_any_number_of_boxes(tmp_path):
    """merge_detections with a vote (detector.view_vote) traced into ONNX gives torch's boxes,
    scores and order for runs holding other numbers of boxes than the traced ones, and none."""
    import onnxruntime
    import torch

    from workers.train.detectors.views import merge_detections

    class Merge(torch.nn.Module):
        def forward(self, *tensors):
            runs = [dict(zip(("boxes", "scores", "labels"), tensors[i : i + 3])) for i in range(0, len(tensors), 3)]
            merged = merge_detections(runs, 0.5, 8, vote=0.7)
            return merged["boxes"], merged["scores"], merged["labels"]

    def runs(counts, seed):
        rng = np.random.default_rng(seed)
        centres = np.array([[20, 20], [60, 30], [30, 70], [80, 80]], np.float32)
        tensors = []
        for count in counts:
            which = rng.integers(0, len(centres), count)
            corner = centres[which] + rng.normal(0, 2, (count, 2)).astype(np.float32)
            boxes = np.concatenate([corner, corner + 16 + rng.normal(0, 1, (count, 2)).astype(np.float32)], 1)
            scores = rng.uniform(0.05, 0.95, count).astype(np.float32)  # distinct: no ties to order either way
            tensors += [boxes, scores, (which % 2).astype(np.int64)]
        return tensors

    traced = runs((6, 4, 5), seed=0)
    names = [f"{key}{i}" for i in range(3) for key in ("boxes", "scores", "labels")]
    path = tmp_path / "merge.onnx"
    Merge()(*(torch.from_numpy(t) for t in traced))  # torchvision loads its operators eagerly, not inside a trace
    torch.onnx.export(
        Merge(), tuple(torch.from_numpy(t) for t in traced), str(path), dynamo=False, opset_version=17,
        input_names=names, output_names=["boxes", "scores", "labels"], dynamic_axes={name: {0: "n"} for name in names},
    )  # fmt: skip
    session = onnxruntime.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    for counts, seed in (((6, 4, 5), 0), ((9, 1, 12), 1), ((3, 0, 7), 2)):
        tensors = runs(counts, seed)
        expected = merge_detections(
            [dict(zip(("boxes", "scores", "labels"), tensors[i : i + 3])) for i in range(0, 9, 3)], 0.5, 8, vote=0.7
        )
        boxes, scores, labels = session.run(None, dict(zip(names, tensors)))
        np.testing.assert_allclose(scores, expected["scores"], rtol=0, atol=1e-6)
        np.testing.assert_allclose(boxes, expected["boxes"], rtol=0, atol=1e-5)
        np.testing.assert_array_equal(labels, expected["labels"])
