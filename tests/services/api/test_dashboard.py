"""The dashboard at / and the artifact routes it reads, against a smoke experiment run here.

The browser test drives Debian's chromium (with chromium-driver) through Selenium against a
live API server, and skips, saying why, where either is missing.
"""

from __future__ import annotations

import shutil
import socket
import threading
import warnings
from datetime import timedelta

import pytest
from sqlalchemy import select

from db.models import Evaluation, Model, ModelStatus, Stage
from db.session import reset_engines, session_scope
from foldwise.settings import REPO_ROOT, get_settings
from tests.waiting import poll, wait_until

with warnings.catch_warnings():
    warnings.simplefilter("ignore")
    from fastapi.testclient import TestClient

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
CHROMEDRIVER = shutil.which("chromedriver")


@pytest.fixture(scope="module")
def smoke(tmp_path_factory):
    """configs/smoke.yaml run to the end in this process (SQLite, eager Celery): its id."""
    from db.migrate import upgrade
    from foldwise.config import load_config
    from services.embedded import run_to_completion, start_experiment
    from workers.app import app, use_eager

    folder = tmp_path_factory.mktemp("dashboard")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("FOLDWISE_DATA_DIR", str(folder / "data"))
        patch.setenv("FOLDWISE_DATABASE_URL", f"sqlite:///{folder / 'foldwise.db'}")
        patch.delenv("FOLDWISE_API_TOKEN", raising=False)
        get_settings.cache_clear()
        reset_engines()
        upgrade()
        eager = app.conf.task_always_eager
        experiment_id = start_experiment(load_config(REPO_ROOT / "configs/smoke.yaml"))
        assert run_to_completion(experiment_id) == "finished"
        use_eager(eager)
        yield experiment_id
        reset_engines()
    get_settings.cache_clear()


@pytest.fixture(scope="module")
def client(smoke):
    from services.api.app import create_app

    return TestClient(create_app())


def test_dashboard_lists_experiments_without_a_token(client, smoke):
    page = client.get("/")
    assert page.status_code == 200 and page.headers["content-type"].startswith("text/html")
    assert f'href="/?experiment={smoke}"' in page.text and "smoke" in page.text
    assert f'data-experiment="{smoke}"' in page.text  # the newest is shown
    assert client.get("/dashboard.js").status_code == 200 and client.get("/dashboard.css").status_code == 200
    assert client.get("/?experiment=999").status_code == 404


def test_training_images_default_to_the_newest_increment_with_their_boxes(client, smoke):
    images = client.get(f"/experiments/{smoke}/images").json()
    last = client.get(f"/experiments/{smoke}/history").json()[-1]
    # the last increment a model trained on, not the one rendered ahead of it
    assert images["split"] == "train" and (images["stage"], images["k"]) == (last["stage"], last["k"]) == (1, 2)
    assert images["images"] and all(
        image["condition"] == "fb" and image["difficulty"] == "hard" for image in images["images"]
    )
    for image in images["images"]:
        (target,) = image["objects"]
        x0, y0, x1, y1 = target["box"]
        assert 0 <= x0 < x1 <= 64 and 0 <= y0 < y1 <= 64
        png = client.get(image["url"])
        assert png.status_code == 200 and png.content[:4] == b"\x89PNG"
    first_stage = client.get(f"/experiments/{smoke}/images?stage=0&k=1").json()
    assert first_stage["images"] and all(image["difficulty"] == "easy" for image in first_stage["images"])
    test = client.get(f"/experiments/{smoke}/images?split=test").json()
    assert len(test["images"]) == 8  # 4 per stage


def test_downloads(client, smoke):
    coco = client.get(f"/experiments/{smoke}/coco?split=test")
    assert coco.status_code == 200 and "attachment" in coco.headers["content-disposition"]
    document = coco.json()
    assert len(document["images"]) == 8 and len(document["annotations"]) == 8
    assert {c["name"] for c in document["categories"]} == {"astronaut", "coffee"}
    assert client.get(document["images"][0]["file_name"]).status_code == 200
    final = client.get(f"/experiments/{smoke}").json()["final_model_id"]
    checkpoint = client.get(f"/models/{final}/checkpoint")
    assert checkpoint.status_code == 200 and len(checkpoint.content) > 1_000_000
    report = client.get(f"/experiments/{smoke}/report.csv")
    assert report.status_code == 200 and report.text.startswith("stage,condition")
    assert client.get(f"/experiments/{smoke}/report.png").content[:4] == b"\x89PNG"
    figure = client.get(f"/experiments/{smoke}/figures/fig7.svg")
    assert figure.status_code == 200 and figure.headers["content-type"].startswith("image/svg+xml")
    assert "standard test set mAP across the curriculum" in figure.text
    numbers = client.get(f"/experiments/{smoke}/figures/fig8.csv")
    assert numbers.text.startswith("experiment,condition,difficulty,best_model_id,best_map")


def test_artifact_routes_say_what_is_missing(client, smoke):
    assert "is not part of experiment" in client.get(f"/experiments/{smoke}/images/999999.png").json()["detail"]
    assert client.get("/experiments/999/images").status_code == 404
    assert client.get("/models/999/checkpoint").json()["detail"] == "model 999 does not exist"
    assert client.get(f"/experiments/{smoke}/report.pdf").status_code == 422
    assert client.get(f"/experiments/{smoke}/figures/fig9.png").status_code == 422
    assert client.get("/experiments/999/figures/fig4.png").status_code == 404


def test_every_evaluation_keeps_a_few_test_images_detections(client, smoke):
    history = client.get(f"/experiments/{smoke}/history").json()
    model = client.get(f"/models/{history[-1]['model_id']}").json()
    samples = model["evaluation"]["details"]["test_detections"]
    assert [(s["condition"], s["difficulty"]) for s in samples] == [("fb", "easy"), ("fb", "hard")]
    test_ids = {image["id"] for image in client.get(f"/experiments/{smoke}/images?split=test").json()["images"]}
    for sample in samples:
        assert sample["image_id"] in test_ids
        assert len(sample["boxes"]) == len(sample["scores"]) == len(sample["labels"]) <= 5
        assert sample["scores"] == sorted(sample["scores"], reverse=True)


# --------------------------------------------------------------------------- in a browser


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@pytest.fixture
def served(smoke, monkeypatch):
    """The API on a free port, in a thread of this process, refreshing the page every 0.5 s."""
    import uvicorn

    from services.api.app import create_app
    from services.api.routes import dashboard

    monkeypatch.setattr(dashboard, "REFRESH_MS", 500)
    server = uvicorn.Server(uvicorn.Config(create_app(), host="127.0.0.1", port=free_port(), log_level="warning"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    wait_until(
        lambda: server.started or not thread.is_alive(),
        timeout=20,
        interval=0.05,
        message="the API server did not start",
    )
    assert server.started, "the API server did not start"
    yield f"http://127.0.0.1:{server.config.port}"
    server.should_exit = True
    thread.join(timeout=10)


@pytest.fixture
def browser():
    if CHROMIUM is None or CHROMEDRIVER is None:
        pytest.skip("the browser test needs chromium and chromium-driver (apt-get install chromium chromium-driver)")
    webdriver = pytest.importorskip("selenium.webdriver", reason="selenium is not installed (the dev extra)")
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = CHROMIUM
    for argument in (
        "--headless=new",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-dev-shm-usage",
        "--window-size=1300,1400",
    ):
        options.add_argument(argument)
    driver = webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)
    yield driver
    driver.quit()


def wait_for(driver, script: str, expected, timeout: float = 15.0):
    """What ``script`` returns in the page once it returns ``expected``; after ``timeout``
    seconds, what it returns then (the caller's assertion shows it)."""
    return poll(lambda: driver.execute_script(script), lambda value: value == expected, timeout, interval=0.1)


def land_an_evaluation(experiment_id: int) -> int:
    """A new ω and its score in P, as a train worker records them: what the page must pick up."""
    with session_scope() as session:
        stage = session.scalars(
            select(Stage).where(Stage.experiment_id == experiment_id).order_by(Stage.order.desc())
        ).first()
        last = session.scalars(select(Model).where(Model.stage_id == stage.id).order_by(Model.increment.desc())).first()
        model = Model(experiment_id=experiment_id, stage_id=stage.id, increment=last.increment + 1, parent_id=last.id,
                      detector=last.detector, status=ModelStatus.evaluated, iterations=last.iterations,
                      checkpoint_path=last.checkpoint_path, train_seconds=1.0, attempts=1)  # fmt: skip
        session.add(model)
        session.flush()
        details = dict(last.evaluation.details)
        details["breakdown"] = {**details["breakdown"], "condition/difficulty": {
            key: {**group, "map": 0.75} for key, group in details["breakdown"]["condition/difficulty"].items()}}  # fmt: skip
        session.add(Evaluation(model_id=model.id, map=0.75, map_unthresholded=0.8, details=details, eval_seconds=0.5,
                               created_at=last.evaluation.created_at + timedelta(seconds=3)))  # fmt: skip
        return model.id


# Last in the module: it adds an entry to the smoke experiment's P.
def test_the_dashboard_in_a_browser_shows_the_experiment_and_follows_it(served, browser, smoke, client, tmp_path):
    history = client.get(f"/experiments/{smoke}/history").json()
    stages = client.get(f"/experiments/{smoke}/stages").json()
    browser.get(f"{served}/?experiment={smoke}")
    assert wait_for(browser, "return document.body.dataset.historyLength", str(len(history))) == str(len(history))

    # the P curve has a point per entry of P, coloured per stage
    points = browser.execute_script(
        "return [...document.querySelectorAll('#p-curve circle.point')].map(p => [p.dataset.model, p.getAttribute('stroke')])"
    )
    assert [int(model) for model, _ in points] == [entry["model_id"] for entry in history]
    assert len({colour for _, colour in points}) == len(stages)
    # the heat map has a cell per (c, δ) of the curriculum, showing the latest model's mAP
    cells = browser.execute_script(
        "return [...document.querySelectorAll('#heatmap td.cell')].map(c => [c.dataset.key, c.textContent])"
    )
    assert sorted(key for key, _ in cells) == sorted(f"{s['condition']}/{s['difficulty']}" for s in stages)
    # the stage table, the summary, the downloads
    assert browser.execute_script("return document.querySelectorAll('#stages tbody tr').length") == len(stages)
    assert "finished" in browser.find_element("css selector", "#summary").text
    links = browser.execute_script(
        "return [...document.querySelectorAll('#downloads a')].map(a => a.getAttribute('href'))"
    )
    final = client.get(f"/experiments/{smoke}").json()["final_model_id"]
    assert f"/models/{final}/checkpoint" in links and f"/experiments/{smoke}/coco?split=test" in links
    assert all(client.get(link).status_code == 200 for link in links)

    # every image of both strips loads (training images with boxes, test images with detections)
    loaded = "const i = [...document.querySelectorAll('.strip img')]; return i.length > 0 && i.every(x => x.complete && x.naturalWidth > 0)"
    assert wait_for(browser, loaded, True) is True
    assert browser.execute_script("return document.querySelectorAll('#train-strip svg rect.truth').length") > 0
    assert browser.execute_script("return document.querySelectorAll('#test-strip .thumb').length") == 2
    browser.save_screenshot(str(tmp_path / "dashboard.png"))

    # a new evaluation lands: the page picks it up on its own
    new_model = land_an_evaluation(smoke)
    assert (
        wait_for(browser, "return document.querySelectorAll('#p-curve circle.point').length", len(history) + 1)
        == len(history) + 1
    )
    assert browser.execute_script(
        "return [...document.querySelectorAll('#p-curve circle.point')].pop().dataset.model"
    ) == str(new_model)
    assert wait_for(
        browser, "return [...document.querySelectorAll('#heatmap td.cell')].every(c => c.textContent === '0.75')", True
    )
    assert f"ω {new_model}" in browser.find_element("css selector", "#heatmap-model").text
