"""`pretrained: imagenet` is checked before any work, without torch, against the right file."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from foldwise.weights import IMAGENET_WEIGHTS, classifier_of, missing_imagenet_weights, torch_hub_dir

REPO_ROOT = Path(__file__).resolve().parents[2]


def test_the_table_is_torchvisions():
    torchvision = pytest.importorskip("torchvision")
    for classifier, (enum_entry, filename) in IMAGENET_WEIGHTS.items():
        weights = torchvision.models.get_weight(enum_entry)
        assert weights.url.rsplit("/", 1)[-1] == filename
        assert torchvision.models.get_model_weights(classifier).IMAGENET1K_V1 == weights


def test_the_hub_dir_is_torchs(monkeypatch, tmp_path):
    torch = pytest.importorskip("torch")
    for variables in ({"TORCH_HOME": str(tmp_path / "th")}, {"XDG_CACHE_HOME": str(tmp_path / "xdg")}):
        monkeypatch.delenv("TORCH_HOME", raising=False)
        monkeypatch.delenv("XDG_CACHE_HOME", raising=False)
        for name, value in variables.items():
            monkeypatch.setenv(name, value)
        assert torch_hub_dir() == Path(torch.hub.get_dir())


@pytest.mark.parametrize(
    ("backbone", "classifier"),
    [("mobilenet_v3_large_fpn", "mobilenet_v3_large"), ("mobilenet_v3_large_320_fpn", "mobilenet_v3_large"),
     ("resnet50_fpn_v2", "resnet50"), ("resnet101", "resnet101"), ("resnet18_fpn", "resnet18"), ("vgg16", None)],
)  # fmt: skip
def test_each_backbone_maps_to_its_classifier(backbone, classifier):
    assert classifier_of(backbone) == classifier


def test_missing_weights_name_the_file_and_the_command(monkeypatch, tmp_path):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path))
    problem = missing_imagenet_weights("mobilenet_v3_large_fpn")
    assert str(tmp_path / "hub/checkpoints/mobilenet_v3_large-8738ca79.pth") in problem
    assert "get_weight('MobileNet_V3_Large_Weights.IMAGENET1K_V1')" in problem
    (tmp_path / "hub/checkpoints").mkdir(parents=True)
    (tmp_path / "hub/checkpoints/mobilenet_v3_large-8738ca79.pth").write_bytes(b"")
    assert missing_imagenet_weights("mobilenet_v3_large_fpn") is None


def _imagenet_config(tmp_path):
    config = yaml.safe_load((REPO_ROOT / "configs/smoke.yaml").read_text())
    config["detector"] = {**config.get("detector", {}), "pretrained": "imagenet"}
    path = tmp_path / "imagenet.yaml"
    path.write_text(yaml.safe_dump(config))
    return path


def test_foldwise_run_stops_before_any_work_without_the_weights(tmp_path):
    path = _imagenet_config(tmp_path)
    env = {"FOLDWISE_DATA_DIR": str(tmp_path / "data"), "TORCH_HOME": str(tmp_path / "torch"), "PATH": "/usr/bin:/bin",
           "COLUMNS": "300"}  # fmt: skip
    done = subprocess.run([sys.executable, "-m", "services.cli", "run", str(path)], cwd=REPO_ROOT, capture_output=True,
                          text=True, env=env)  # fmt: skip
    output = (done.stdout + done.stderr).strip()
    assert done.returncode == 2 and output.count("\n") == 0, output
    assert (
        output.startswith("error: detector.pretrained: 'imagenet' needs ")
        and "mobilenet_v3_large-8738ca79.pth" in output
    )
    assert not (tmp_path / "data").exists()  # nothing rendered, nothing recorded


def test_foldwise_train_stops_before_reading_the_data_without_the_weights(tmp_path):
    env = {"TORCH_HOME": str(tmp_path / "torch"), "PATH": "/usr/bin:/bin", "COLUMNS": "300"}
    done = subprocess.run([sys.executable, "-m", "services.cli", "train", "--detector", "faster_rcnn", "--data",
                           str(tmp_path / "no-such-set"), "--iterations", "1", "--out", str(tmp_path / "m.pt"),
                           "--config", str(_imagenet_config(tmp_path))], cwd=REPO_ROOT, capture_output=True, text=True,
                          env=env)  # fmt: skip
    output = (done.stdout + done.stderr).strip()
    assert done.returncode != 0 and "detector.pretrained: 'imagenet' needs " in output, output
    assert "no-such-set" not in output  # refused on the weights, before the data was looked at
