"""`foldwise finetune` on a stand-in real set (skimage photographs with object prints warped
onto them, bench/standin_real.py): VOC and COCO import, classes matched by name, a subset of
the model's classes, an unknown class named, and a sweep with its fresh baseline and Fig. 11."""

from __future__ import annotations

import csv
import json
import sys
from pathlib import Path

import numpy as np
import pytest
import typer
from typer.testing import CliRunner

from foldwise.config import DetectorConfig
from workers.train.cli import register
from workers.train.data import DatasetError, load_dataset
from workers.train.finetune import match_classes, split
from workers.train.training import train_detector

REPO_ROOT = Path(__file__).resolve().parents[3]
sys.path.insert(0, str(REPO_ROOT))
from bench.standin_real import make_standin_set  # noqa: E402

MODEL_CLASSES = ["astronaut", "coffee", "chelsea"]
app = typer.Typer()
register(app)


@pytest.fixture(scope="module")
def standin(tmp_path_factory):
    return make_standin_set(tmp_path_factory.mktemp("standin"), n=12, classes=["coffee", "astronaut"], size=(96, 72))


@pytest.fixture(scope="module")
def tiny_model(standin, tmp_path_factory):
    """A 3-class model (the real set holds 2 of them, in another order): 2 iterations at 64 px."""
    samples, classes = load_dataset(standin / "voc")
    samples = match_classes(samples, classes, MODEL_CLASSES)
    path = tmp_path_factory.mktemp("model") / "tiny.pt"
    config = DetectorConfig(family="yolo", input_size=64, batch_size=2, num_threads=1)
    train_detector(samples[:4], init=None, iterations=2, config=config, classes=MODEL_CLASSES, out=path)
    return path


def test_voc_and_coco_give_the_same_set_matched_to_the_models_classes(standin):
    voc, voc_classes = load_dataset(standin / "voc")
    coco, coco_classes = load_dataset(standin / "coco.json")
    assert len(voc) == len(coco) == 12 and set(voc_classes) == set(coco_classes) == {"coffee", "astronaut"}
    voc, coco = match_classes(voc, voc_classes, MODEL_CLASSES), match_classes(coco, coco_classes, MODEL_CLASSES)
    for a, b in zip(sorted(voc, key=lambda s: s.image_path.name), sorted(coco, key=lambda s: s.image_path.name)):
        assert a.image_path.resolve() == b.image_path.resolve()
        np.testing.assert_allclose(a.boxes, b.boxes, atol=0.051)  # VOC's one decimal
        assert sorted(a.labels.tolist()) == sorted(b.labels.tolist()) and set(a.labels.tolist()) <= {0, 1}


def test_an_unknown_class_is_named_with_the_known_ones(standin):
    samples, classes = load_dataset(standin / "voc")
    with pytest.raises(DatasetError, match=r"class\(es\) \['coffee'\] .* its classes: astronaut, rocket"):
        match_classes(samples, classes, ["astronaut", "rocket"])


def test_the_split_is_seeded_and_disjoint(standin):
    samples, _ = load_dataset(standin / "voc")
    pool, test = split(samples, 0.5, seed=3)
    again, _ = split(samples, 0.5, seed=3)
    assert [s.image_path for s in pool] == [s.image_path for s in again]
    assert not {s.image_path for s in pool} & {s.image_path for s in test} and len(pool) + len(test) == 12


def test_finetune_sweeps_beside_a_fresh_baseline_and_draws_fig11(standin, tiny_model, tmp_path):
    out = tmp_path / "finetune"
    result = CliRunner().invoke(app, [
        "finetune", "--model", str(tiny_model), "--data", str(standin / "coco.json"), "--sweep", "0,3",
        "--iterations", "2", "--out", str(out),
    ])  # fmt: skip
    assert result.exit_code == 0, result.output
    assert "n =    0: fine-tuned mAP" in result.output and "n =    3: fine-tuned mAP" in result.output
    rows = list(csv.DictReader(open(out / "fig11.csv")))
    assert [int(row["n"]) for row in rows] == [0, 3]
    assert rows[0]["fresh_map"] == "" and rows[1]["fresh_map"] != ""
    assert all(0.0 <= float(row["finetuned_map"]) <= 1.0 for row in rows)
    assert (out / "fig11.png").stat().st_size > 0 and "real training images" in (out / "fig11.svg").read_text()
    assert (out / "finetuned-3.pt").is_file() and (out / "fresh-3.pt").is_file()
    # A yolo detector takes no runtime graph: the command says so, and its detection runs in torch.
    assert "no runtime graph: the yolo detector has no runtime graph" in result.output
    assert not list(out.glob("*.onnx"))


def test_finetune_writes_the_runtime_graph_of_the_model_it_hands_over(standin, tmp_path):
    """As `foldwise run` does for its model, the model fine-tuned on the most images gets its
    runtime graph beside it, which detection then uses; --no-runtime-graph writes none."""
    from workers.train.checkpoint import load_detector

    samples, classes = load_dataset(standin / "voc")
    samples = match_classes(samples, classes, MODEL_CLASSES)
    model = tmp_path / "faster.pt"
    config = DetectorConfig(family="faster_rcnn", input_size=64, batch_size=2, num_threads=1)
    train_detector(samples[:2], init=None, iterations=1, config=config, classes=MODEL_CLASSES, out=model)
    for flag, written in (("--runtime-graph", True), ("--no-runtime-graph", False)):
        out = tmp_path / flag
        result = CliRunner().invoke(app, [
            "finetune", "--model", str(model), "--data", str(standin / "coco.json"), "--sweep", "2",
            "--iterations", "1", "--out", str(out), flag,
        ])  # fmt: skip
        assert result.exit_code == 0, result.output
        assert sorted(path.name for path in out.glob("*.onnx")) == (["finetuned-2.pt.onnx"] if written else [])
        assert (load_detector(out / "finetuned-2.pt").runtime is not None) is written
        assert ("runtime graph: " in result.output) is written


def test_finetune_refuses_an_unknown_class_and_a_folder_that_is_no_set_in_one_line(standin, tmp_path):
    other = tmp_path / "no-coffee.pt"
    config = DetectorConfig(family="yolo", input_size=64, batch_size=2, num_threads=1)
    train_detector([], init=None, iterations=0, config=config, classes=["astronaut", "rocket"], out=other)
    for data, message in (
        (standin / "voc", "its classes: astronaut, rocket"),
        (tmp_path, "not a dataset"),
        (tmp_path / "nowhere", "no such file or folder"),
    ):
        result = CliRunner().invoke(
            app, ["finetune", "--model", str(other), "--data", str(data), "--out", str(tmp_path / "o")]
        )
        assert result.exit_code == 2 and message in result.output and result.output.strip().count("\n") == 0, (
            result.output
        )


def test_evaluate_reads_a_real_set_as_a_voc_folder_or_a_coco_file_alike(standin, tiny_model, tmp_path):
    """Labelling tools export VOC folders and COCO files kept anywhere: `foldwise evaluate` scores
    the model on either (the set holding two of its three classes), the same as on the other."""
    payloads = []
    for name, data in (("voc", standin / "voc"), ("coco", standin / "coco.json")):
        target = tmp_path / f"{name}.json"
        result = CliRunner().invoke(
            app, ["evaluate", "--model", str(tiny_model), "--data", str(data), "--json", str(target)]
        )
        assert result.exit_code == 0, result.output
        payloads.append(json.loads(target.read_text()))
    voc, coco = payloads
    assert voc["num_images"] == coco["num_images"] == 12 and voc["num_ground_truth"] == coco["num_ground_truth"] > 0
    assert voc["classes"] == coco["classes"] == MODEL_CLASSES
    assert voc["per_class"]["chelsea"]["num_ground_truth"] == 0  # the model's class the set does not hold
    assert voc["map_unthresholded"] == pytest.approx(
        coco["map_unthresholded"], abs=0.02
    )  # VOC's boxes keep one decimal


# --------------------------------------------------------------------------- photographs, an ensemble

import photo_sets  # noqa: E402  (tests/workers/train is on sys.path)

from foldwise.config import AugmentationConfig  # noqa: E402
from workers.train.checkpoint import load_detector, save_ensemble  # noqa: E402


@pytest.fixture(scope="module")
def photo_set(tmp_path_factory):
    """Portrait, landscape and EXIF-turned JPEGs, one without any object, as a COCO export."""
    photos = photo_sets.photos(9, seed=4)
    photos.append(
        photo_sets.Photo(
            "lookalike", photos[1].pixels[:, ::-1].copy(), np.zeros((0, 4), np.float32), np.zeros(0, np.int64), 6
        )
    )
    return photo_sets.write_coco(tmp_path_factory.mktemp("photos"), photos)


@pytest.fixture(scope="module")
def photo_ensemble(photo_set, tmp_path_factory):
    """What `make run` hands over: an ensemble of two members (other seeds), trained with
    quarter turns and crops."""
    samples, classes = load_dataset(photo_set)
    folder = tmp_path_factory.mktemp("ensemble")
    augmentation = AugmentationConfig(enabled=True, quarter_turn=1.0, crop=0.5, zoom=0.5)
    config = DetectorConfig(family="yolo", input_size=64, batch_size=3, num_threads=1, augmentation=augmentation)
    members = []
    for seed in (1, 2):
        path = folder / f"member{seed}.pt"
        train_detector(samples[:4], init=None, iterations=1, config=config, classes=classes, out=path, seed=seed)
        members.append(path)
    return save_ensemble(members, folder / "ensemble.pt")


def test_finetune_takes_an_ensemble_and_mixed_photos_and_hands_back_an_ensemble(photo_set, photo_ensemble, tmp_path):
    out = tmp_path / "finetune"
    result = CliRunner().invoke(app, [
        "finetune", "--model", str(photo_ensemble), "--data", str(photo_set), "--sweep", "0,5",
        "--iterations", "2", "--out", str(out),
    ])  # fmt: skip
    assert result.exit_code == 0, result.output
    assert result.exception is None or isinstance(result.exception, SystemExit)
    assert "an ensemble of 2 detectors" in result.output and "n =    5: fine-tuned mAP" in result.output
    for kind in ("finetuned", "fresh"):
        joined = load_detector(out / f"{kind}-5.pt")
        assert len(joined.meta["members"]) == 2 and joined.classes == photo_sets.CLASSES
    rows = list(csv.DictReader(open(out / "fig11.csv")))
    assert [int(row["n"]) for row in rows] == [0, 5] and rows[1]["fresh_map"] != ""
    assert "ensemble of 2" in (out / "fig11.svg").read_text()
