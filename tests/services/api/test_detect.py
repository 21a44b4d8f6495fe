"""POST /models/{id}/detect: a trained ω on an uploaded rendered image, through the detect task
(eager Celery here, as in embedded mode; a `foldwise worker detect` process otherwise)."""

from __future__ import annotations

import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from db.models import Experiment, ExperimentStatus, Model, ModelStatus, Stage, StageStatus
from db.session import session_scope
from foldwise import store
from tests.services.api.helpers import png_claiming

with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    from fastapi.testclient import TestClient

TOKEN = "detect-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
REPO = Path(__file__).resolve().parents[3]


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """A YOLO detector that has learnt eight 64-px renders of two object classes (~8 s)."""
    import torch

    from foldwise.config import AssetsConfig, DetectorConfig
    from workers.render.assets import load_assets
    from workers.render.cli import render_dataset
    from workers.train.data import load_coco_dataset
    from workers.train.training import train_detector

    folder = tmp_path_factory.mktemp("detect")
    assets = load_assets(AssetsConfig(n_objects=2))
    render_dataset(
        folder, ["fb"], ["easy"], 8, seed=5, image_size=64, backend="raster", assets=assets, echo=lambda _: None
    )
    samples, classes = load_coco_dataset(folder)
    config = DetectorConfig(
        family="yolo", backbone="mobilenet_v3_large_fpn", input_size=64, batch_size=4, num_threads=1
    )
    previous = torch.get_num_threads()
    train_detector(samples, None, 150, config, classes, folder / "model.pt", seed=0)
    torch.set_num_threads(previous)
    return {"checkpoint": folder / "model.pt", "samples": samples, "classes": classes}


@pytest.fixture
def served(database, eager, monkeypatch, trained):
    """The model as an experiment's evaluated ω in the store, and an API client."""
    from foldwise.settings import get_settings
    from services.api.app import create_app

    monkeypatch.setenv("FOLDWISE_API_TOKEN", TOKEN)
    get_settings.cache_clear()
    with session_scope() as session:
        experiment = Experiment(
            name="served", config={}, seed=0, classes=trained["classes"], status=ExperimentStatus.running
        )
        session.add(experiment)
        session.flush()
        stage = Stage(
            experiment_id=experiment.id, order=0, condition="fb", difficulty="easy", status=StageStatus.running
        )
        session.add(stage)
        session.flush()
        ready = Model(experiment_id=experiment.id, stage_id=stage.id, increment=1, detector="yolo",
                      status=ModelStatus.evaluated, iterations=150, attempts=1)  # fmt: skip
        training = Model(experiment_id=experiment.id, stage_id=stage.id, increment=2, detector="yolo",
                         status=ModelStatus.training, iterations=150, attempts=1)  # fmt: skip
        session.add_all([ready, training])
        session.flush()
        ready.checkpoint_path = store.checkpoint_path(experiment.id, ready.id)
        target = store.resolve(ready.checkpoint_path)
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(trained["checkpoint"], target)
        ids = {"ready": ready.id, "training": training.id}
    return {**ids, "client": TestClient(create_app(broker_timeout_s=0.5, ping_timeout_s=0.3))}


def box_iou(a, b) -> float:
    x0, y0 = max(a[0], b[0]), max(a[1], b[1])
    x1, y1 = min(a[2], b[2]), min(a[3], b[3])
    inter = max(0.0, x1 - x0) * max(0.0, y1 - y0)
    area = lambda r: (r[2] - r[0]) * (r[3] - r[1])  # noqa: E731
    return inter / (area(a) + area(b) - inter)


def test_detect_finds_the_rendered_object_with_its_class(served, trained):
    for sample in trained["samples"][:3]:
        image = Path(sample.image_path).read_bytes()
        response = served["client"].post(
            f"/models/{served['ready']}/detect", content=image, headers={**AUTH, "Content-Type": "image/png"}
        )
        assert response.status_code == 200, response.text
        body = response.json()
        assert body["model_id"] == served["ready"] and body["classes"] == trained["classes"]
        assert body["image"] == {"width": 64, "height": 64}
        best = body["detections"][0]
        truth = np.asarray(sample.boxes[0], dtype=float)
        assert best["class"] == trained["classes"][int(sample.labels[0])]
        assert best["label"] == int(sample.labels[0])
        assert box_iou(best["box"], truth) >= 0.7, (best, truth)
        assert all(d["score"] >= 0.5 for d in body["detections"])  # the default threshold


def test_threshold_keeps_only_detections_scoring_at_least_it(served, trained):
    image = Path(trained["samples"][0].image_path).read_bytes()
    url = f"/models/{served['ready']}/detect"
    everything = served["client"].post(
        f"{url}?threshold=0", content=image, headers={**AUTH, "Content-Type": "image/png"}
    )
    assert everything.status_code == 200
    scores = [d["score"] for d in everything.json()["detections"]]
    assert scores and scores == sorted(scores, reverse=True)
    for cut in (scores[0] - 1e-4, min(scores[0] + 1e-4, 1.0)):
        some = served["client"].post(
            f"{url}?threshold={cut}", content=image, headers={**AUTH, "Content-Type": "image/png"}
        )
        assert [d["score"] for d in some.json()["detections"]] == [s for s in scores if s >= cut]
    out_of_range = served["client"].post(
        f"{url}?threshold=2", content=image, headers={**AUTH, "Content-Type": "image/png"}
    )
    assert out_of_range.status_code == 422


def test_detect_needs_the_token(served, trained):
    image = Path(trained["samples"][0].image_path).read_bytes()
    url = f"/models/{served['ready']}/detect"
    missing = served["client"].post(url, content=image, headers={"Content-Type": "image/png"})
    assert missing.status_code == 401 and "missing token" in missing.json()["detail"]
    wrong = served["client"].post(
        url, content=image, headers={"Authorization": "Bearer nope", "Content-Type": "image/png"}
    )
    assert wrong.status_code == 401


def test_bad_images_get_a_4xx_naming_the_problem(served, trained, monkeypatch):
    from services.api.routes import detect

    client, url = served["client"], f"/models/{served['ready']}/detect"
    png = Path(trained["samples"][0].image_path).read_bytes()
    cases = [
        (b"", "image/png", 422, "empty body"),
        (b"hello, not an image", "image/png", 422, "not a PNG or JPEG"),
        # the right signature, then garbage: the header check refuses it
        (png[:8] + b"\x00" * 200, "image/png", 422, "truncated or damaged image header"),
        # a whole header over garbage: only decoding (in the worker) can tell
        (png_claiming(64, 64, b"garbage"), "image/png", 422, "not an image OpenCV can decode"),
        # a header claiming more pixels than a worker decodes: refused from the header
        (png_claiming(50_000, 50_000), "image/png", 422, "pixels"),
        (png_claiming(5000, 5000), "image/png", 422, "5000x5000 = 25,000,000 pixels"),
        (png, "text/plain", 415, "unsupported content type text/plain"),
    ]
    for body, media_type, code, message in cases:
        response = client.post(url, content=body, headers={**AUTH, "Content-Type": media_type})
        assert response.status_code == code, (message, response.text)
        assert message in response.json()["detail"]
    monkeypatch.setattr(detect, "MAX_IMAGE_BYTES", len(png) - 1)
    too_large = client.post(url, content=png, headers={**AUTH, "Content-Type": "image/png"})
    assert too_large.status_code == 413 and "larger than" in too_large.json()["detail"]


def test_a_model_without_a_checkpoint_or_that_does_not_exist(served, trained):
    image = Path(trained["samples"][0].image_path).read_bytes()
    headers = {**AUTH, "Content-Type": "image/png"}
    busy = served["client"].post(f"/models/{served['training']}/detect", content=image, headers=headers)
    assert busy.status_code == 409 and "is training" in busy.json()["detail"]
    missing = served["client"].post("/models/999/detect", content=image, headers=headers)
    assert missing.status_code == 404 and "model 999 does not exist" in missing.json()["detail"]


def test_the_detect_route_loads_no_torch():
    code = (
        "import sys, services.api.app\n"
        "assert 'torch' not in sys.modules and 'cv2' not in sys.modules\n"
        "print(sorted(services.api.app.app.openapi()['paths']['/models/{model_id}/detect']))\n"
    )
    env = {"PATH": "/usr/bin:/bin", "FOLDWISE_BROKER_URL": "redis://127.0.0.1:1/0"}
    result = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "['post']"


def test_a_jpeg_works_too(served, trained):
    import cv2

    picture = cv2.imread(str(trained["samples"][1].image_path))
    ok, jpeg = cv2.imencode(".jpg", picture, [cv2.IMWRITE_JPEG_QUALITY, 95])
    response = served["client"].post(
        f"/models/{served['ready']}/detect", content=jpeg.tobytes(), headers={**AUTH, "Content-Type": "image/jpeg"}
    )
    assert response.status_code == 200, response.text
    best = response.json()["detections"][0]
    assert best["label"] == int(trained["samples"][1].labels[0])
    assert box_iou(best["box"], trained["samples"][1].boxes[0]) >= 0.7


def test_no_detect_worker_is_a_504_that_says_what_to_start(served, trained, redis_url, monkeypatch):
    import workers.app
    from foldwise.settings import get_settings
    from services.api.routes import detect

    distributed = workers.app.create_app(get_settings().model_copy(update={"broker_url": redis_url, "eager": False}))
    monkeypatch.setattr(workers.app, "app", distributed)
    monkeypatch.setattr(detect, "REPLY_TIMEOUT_S", 1.0)
    image = Path(trained["samples"][0].image_path).read_bytes()
    response = served["client"].post(
        f"/models/{served['ready']}/detect", content=image, headers={**AUTH, "Content-Type": "image/png"}
    )
    assert response.status_code == 504
    assert "no detect worker answered within 1 s" in response.json()["detail"]
    assert "foldwise worker detect" in response.json()["detail"]
    distributed.close()


def test_a_studys_ensemble_detects_as_its_members_merged(served, trained, tmp_path):
    """POST /studies/{study}/detect serves the ensemble file `foldwise run --members` writes for
    a study: its detections are the merged members', as `foldwise detect` gives them."""
    import cv2
    import torch

    from foldwise.config import DetectorConfig
    from workers.train.checkpoint import detect_object, load_detector, save_ensemble
    from workers.train.detectors.views import merge_detections
    from workers.train.training import train_detector

    other = tmp_path / "other.pt"  # a second member: the served model warm-started a few steps
    config = DetectorConfig(
        family="yolo", backbone="mobilenet_v3_large_fpn", input_size=64, batch_size=4, num_threads=1
    )
    previous = torch.get_num_threads()
    train_detector(trained["samples"], trained["checkpoint"], 5, config, trained["classes"], other, seed=1)
    torch.set_num_threads(previous)
    study = "wild pair 2026"
    save_ensemble([trained["checkpoint"], other], store.resolve(store.ensemble_path(study)))

    sample = trained["samples"][2]
    image = Path(sample.image_path).read_bytes()
    response = served["client"].post(
        f"/studies/{study}/detect?threshold=0", content=image, headers={**AUTH, "Content-Type": "image/png"}
    )
    assert response.status_code == 200, response.text
    body = response.json()
    assert body["study"] == study and body["members"] == 2 and body["classes"] == trained["classes"]
    (expected,) = detect_object(
        load_detector(store.resolve(store.ensemble_path(study))),
        [cv2.cvtColor(cv2.imread(str(sample.image_path)), cv2.COLOR_BGR2RGB)],
    )
    assert [d["score"] for d in body["detections"]] == pytest.approx(expected["scores"].tolist())
    assert [d["label"] for d in body["detections"]] == expected["labels"].tolist()
    alone = served["client"].post(f"/models/{served['ready']}/detect?threshold=0", content=image,
                                  headers={**AUTH, "Content-Type": "image/png"})  # fmt: skip
    assert "members" not in alone.json()
    # Two networks, and the pair's detections are theirs merged (where the second finds nothing
    # better on this image, as on some CPUs, the pair answers as the first alone).
    pixels = [cv2.cvtColor(cv2.imread(str(sample.image_path)), cv2.COLOR_BGR2RGB)]
    pair = load_detector(store.resolve(store.ensemble_path(study)))
    found = [detect_object(load_detector(path), pixels)[0] for path in (trained["checkpoint"], other)]
    assert found[0]["scores"].tolist() != found[1]["scores"].tolist()
    merged = merge_detections(found, pair.model.iou, pair.model.limit)
    for key in ("boxes", "scores", "labels"):
        np.testing.assert_allclose(detect_object(pair, pixels)[0][key], merged[key], rtol=0, atol=1e-6)


def test_a_texture_checked_detector_is_served_with_its_check_and_says_so(served, trained, tmp_path):
    """A detector whose config asks for the texture check (and search) answers through it (as
    `foldwise detect` does), and the reply says whether the check and the search ran."""
    import cv2

    from workers.render.assets import load_assets
    from workers.train.checkpoint import detect_object, load_detector, read_checkpoint, save_checkpoint, save_ensemble

    payload = read_checkpoint(trained["checkpoint"])
    detector = load_detector(trained["checkpoint"])
    assert detector.texture_check() is None
    checked = tmp_path / "checked.pt"
    catalog = load_assets()
    searching = {**payload["meta"]["config"], "texture_check": True, "texture_search": True}
    save_checkpoint(
        detector.model, {**payload["meta"], "config": searching}, checked, textures=catalog.textures(trained["classes"])
    )
    study = "checked"
    save_ensemble([checked, checked], store.resolve(store.ensemble_path(study)))
    sample = trained["samples"][1]
    headers = {**AUTH, "Content-Type": "image/png"}
    body = (
        served["client"]
        .post(f"/studies/{study}/detect?threshold=0", content=Path(sample.image_path).read_bytes(), headers=headers)
        .json()
    )
    assert body["texture_check"] is True and body["texture_search"] is True
    (expected,) = detect_object(
        load_detector(store.resolve(store.ensemble_path(study))),
        [cv2.cvtColor(cv2.imread(str(sample.image_path)), cv2.COLOR_BGR2RGB)],
    )
    assert [d["score"] for d in body["detections"]] == pytest.approx(expected["scores"].tolist())
    assert [d["confirmed"] for d in body["detections"]] == expected["confirmed"].tolist()
    plain = (
        served["client"]
        .post(
            f"/models/{served['ready']}/detect?threshold=0",
            content=Path(sample.image_path).read_bytes(),
            headers=headers,
        )
        .json()
    )
    assert plain["texture_check"] is False and plain["texture_search"] is False
    assert all(d["confirmed"] is None for d in plain["detections"])


def test_a_study_without_an_ensemble_or_with_no_folder_name_is_refused(served, trained):
    image = Path(trained["samples"][0].image_path).read_bytes()
    headers = {**AUTH, "Content-Type": "image/png"}
    client = served["client"]
    missing = client.post("/studies/never-run/detect", content=image, headers=headers)
    assert missing.status_code == 404
    assert "study 'never-run' has no ensemble (studies/never-run/ensemble.pt" in missing.json()["detail"]
    assert "foldwise run CONFIG --members N" in missing.json()["detail"]
    dotted = client.post("/studies/%2E%2E/detect", content=image, headers=headers)
    assert dotted.status_code == 422 and "names no folder" in dotted.json()["detail"]
    for separator in ("%5C", "%2F"):  # a path separator: never a file outside the store's studies folder
        assert client.post(f"/studies/a{separator}b/detect", content=image, headers=headers).status_code in (404, 422)
    backslash = client.post("/studies/a%5Cb/detect", content=image, headers=headers)
    assert backslash.status_code == 422
    no_token = client.post("/studies/never-run/detect", content=image, headers={"Content-Type": "image/png"})
    assert no_token.status_code == 401
