"""The API under a hostile client: each probe that once stalled the event loop, filled memory or
disk, or answered 500, as a test. During each stall probe /health is timed: it must answer in
under a second, since a route that parses, decodes or waits on the event loop delays every
other request."""

from __future__ import annotations

import asyncio
import json
import os
import threading
import time
from pathlib import Path

import httpx
import pytest

from foldwise import store
from foldwise.settings import get_settings
from services.api.app import create_app
from tests.services.api.helpers import AUTH, TOKEN, call_asgi, experiment_count, png_claiming

HEALTH_BUDGET_S = 1.0
# A detect with the broker unreachable is answered within this (about a second; 20 s by Celery's defaults).
UNREACHABLE_BUDGET_S = 5.0


def bomb(levels: int = 23) -> str:
    """The merge-key bomb: each line merges the one before twice, doubling what it stands for."""
    lines = ["b0: &b0 {k0: 1}"]
    lines += [f"b{n}: &b{n} {{<<: [*b{n - 1}, *b{n - 1}], k{n}: 1}}" for n in range(1, levels + 1)]
    return "name: bomb\n" + "\n".join(lines) + "\n"


def one_mib_list() -> str:
    return "name: list\ncurriculum: {conditions: [" + ", ".join(["1"] * ((1 << 20) // 3 - 100)) + "]}\n"


async def _health_latencies(client: httpx.AsyncClient, done: asyncio.Event) -> list[float]:
    """/health asked over and over until ``done``; the time each took."""
    latencies = []
    while True:
        started = time.perf_counter()
        response = await client.get("/health")
        latencies.append(time.perf_counter() - started)
        assert response.status_code == 200, response.text
        if done.is_set():
            return latencies
        await asyncio.sleep(0)


async def _during(app, probe) -> tuple[object, list[float], float]:
    """Run ``probe(client)`` while /health is timed; (its result, /health latencies, its duration)."""
    transport = httpx.ASGITransport(app=app)
    async with httpx.AsyncClient(transport=transport, base_url="http://api") as client:
        done = asyncio.Event()
        timer = asyncio.create_task(_health_latencies(client, done))
        started = time.perf_counter()
        try:
            result = await probe(client)
        finally:
            done.set()
        took = time.perf_counter() - started
        return result, await timer, took


@pytest.fixture
def app(database_url):
    return create_app(broker_timeout_s=0.3, ping_timeout_s=0.2)


# --------------------------------------------------------------------------- 1, 2: YAML


@pytest.mark.parametrize(
    ("document", "named"),
    [
        (bomb(23), "YAML merge keys (<<) are not accepted"),
        (one_mib_list(), "more than 5,000 values"),
        ("a: &a [1,1,1,1,1,1,1,1,1,1]\n" + "".join(f"{c}: &{c} [" + ",".join([f"*{p}"] * 10) + "]\n"
                                                  for p, c in zip("abcdefgh", "bcdefghi")), "more than 5,000 values"),
        ("name: x\na: &a 1\n" + "".join(f"b{i}: *a\n" for i in range(101)), "more than 100 aliases"),
    ],
    ids=["merge-bomb", "1-MiB-list", "billion-laughs", "many-aliases"],
)  # fmt: skip
def test_a_costly_yaml_document_is_a_fast_422_and_health_never_waits(app, database_url, document, named):
    async def probe(client):
        return await client.post("/experiments", content=document, headers={**AUTH, "Content-Type": "application/yaml"})

    response, latencies, took = asyncio.run(_during(app, probe))
    assert response.status_code == 422, response.text
    assert named in response.json()["detail"]
    assert max(latencies) < HEALTH_BUDGET_S, latencies
    assert took < 5.0
    assert experiment_count(database_url) == 0


def test_the_config_is_parsed_off_the_event_loop(app, monkeypatch):
    """A parse held on purpose: /health must answer meanwhile (on the loop, it could not)."""
    from services.api.routes import experiments

    entered, release = threading.Event(), threading.Event()
    parse = experiments.parse_config_body

    def held_parse(body, is_json):
        entered.set()
        assert release.wait(30)
        return parse(body, is_json)

    monkeypatch.setattr(experiments, "parse_config_body", held_parse)

    async def scenario():
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://api") as client:
            posting = asyncio.create_task(
                client.post("/experiments", json={"name": "held"}, headers=AUTH)
            )  # fmt: skip
            assert await asyncio.to_thread(entered.wait, 30)
            started = time.perf_counter()
            health = await asyncio.wait_for(client.get("/health"), timeout=10)
            latency = time.perf_counter() - started
            release.set()
            return health, latency, await posting

    health, latency, created = asyncio.run(scenario())
    assert health.status_code == 200 and latency < HEALTH_BUDGET_S
    assert created.status_code == 201, created.text


def test_a_json_body_of_a_million_values_is_a_422(client, database_url):
    body = json.dumps({"name": "big", "curriculum": {"conditions": [1] * 300_000}})
    response = client.post("/experiments", content=body, headers={**AUTH, "Content-Type": "application/json"})
    assert response.status_code == 422 and "more than 5,000 values" in response.json()["detail"]


# --------------------------------------------------------------------------- 3: streaming limit


def _endless(chunk: int = 64 << 10):
    while True:
        yield b"\0" * chunk


@pytest.mark.parametrize(
    ("path", "content_type", "limit"),
    [
        ("/experiments", "application/yaml", 1 << 20),
        ("/models/1/detect", "image/png", 8 << 20),
        ("/studies/s/detect", "image/png", 8 << 20),
    ],
)
def test_a_chunked_body_without_length_is_413_once_past_the_limit(app, path, content_type, limit):
    response = call_asgi(app, "POST", path, {**AUTH, "content-type": content_type}, _endless())
    assert response.status == 413, response.body
    assert "larger than" in json.loads(response.body)["detail"]
    assert response.body_bytes_read <= limit + (64 << 10)  # read up to the limit, not a chunk more
    assert response.headers.get("x-content-type-options") == "nosniff"


def test_an_upload_without_length_is_413_once_past_its_limit(app, monkeypatch):
    from services.api.routes import assets

    boundary = "b0undary"

    def body():
        yield f'--{boundary}\r\nContent-Disposition: form-data; name="files"; filename="a.png"\r\n\r\n'.encode()
        yield from _endless(1 << 20)

    headers = {**AUTH, "content-type": f"multipart/form-data; boundary={boundary}"}
    response = call_asgi(app, "POST", "/assets/objects", headers, body())
    assert response.status == 413, response.body
    assert response.body_bytes_read <= assets.MAX_UPLOAD_BYTES + (3 << 20)
    assert not any(p.name.startswith(".upload-") for p in _upload_root_entries())


def test_a_declared_length_over_the_limit_is_413_before_any_byte_is_read(app):
    response = call_asgi(
        app,
        "POST",
        "/experiments",
        {**AUTH, "content-type": "application/yaml", "content-length": str(1 << 30)},
        _endless(),
    )
    assert response.status == 413 and response.chunks_read == 0


# --------------------------------------------------------------------------- 4: the token first


def _upload_root_entries() -> list[Path]:
    root = store.uploaded_assets_root()
    return list(root.iterdir()) if root.exists() else []


def _write_routes(app) -> list[tuple[str, str]]:
    """(method, path) of every route that takes a body or changes something, ids filled in."""
    routes = []
    for path, operations in app.openapi()["paths"].items():
        for method in operations:
            if method in ("post", "put", "patch", "delete"):
                path = path.replace("{kind}", "objects").replace("{study}", "s")
                routes.append((method.upper(), path.replace("{experiment_id}", "1").replace("{model_id}", "1")))
    return routes


def test_every_write_route_needs_the_token(app):
    assert {path for _, path in _write_routes(app)} >= {
        "/experiments", "/experiments/1/cancel", "/models/1/detect", "/studies/s/detect", "/assets/objects",
    }  # fmt: skip


@pytest.mark.parametrize("headers", [{}, {"authorization": "Bearer wrong"}, {"authorization": "Basic eDp5"}])
def test_no_write_route_reads_a_byte_of_the_body_without_the_token(app, database_url, headers):
    for method, path in _write_routes(app):
        response = call_asgi(
            app, method, path, {**headers, "content-type": "multipart/form-data; boundary=x"}, _endless()
        )
        assert response.status == 401, (method, path, response.status, response.body)
        assert response.body_bytes_read == 0, (method, path)
    assert _upload_root_entries() == [] and experiment_count(database_url) == 0


def test_writes_are_403_without_reading_the_body_when_no_token_is_configured(database_url, monkeypatch):
    monkeypatch.delenv("FOLDWISE_API_TOKEN")
    get_settings.cache_clear()
    app = create_app()
    for method, path in _write_routes(app):
        response = call_asgi(app, method, path, {**AUTH, "content-type": "image/png"}, _endless())
        assert response.status == 403 and response.body_bytes_read == 0, (method, path)


# --------------------------------------------------------------------------- 5, 6: image headers


@pytest.mark.parametrize("path", ["/models/1/detect", "/studies/s/detect"])
@pytest.mark.parametrize(
    ("image", "named"),
    [
        (png_claiming(50_000, 50_000), "2500000000 pixels"),  # 69 bytes
        (png_claiming(16_384, 16_384), "268435456 pixels"),
        (png_claiming(5000, 5000), "5000x5000 = 25,000,000 pixels"),
    ],
    ids=["50000x50000", "16384x16384", "5000x5000"],
)
def test_an_image_over_the_pixel_limit_is_refused_from_its_header(client, monkeypatch, path, image, named):
    import PIL.ImageFile

    def no_decoding(*_args, **_kwargs):
        raise AssertionError("the image was decoded")

    monkeypatch.setattr(PIL.ImageFile.ImageFile, "load", no_decoding)
    response = client.post(path, content=image, headers={**AUTH, "Content-Type": "image/png"})
    assert response.status_code == 422, response.text
    assert named in response.json()["detail"]


def test_the_api_and_the_worker_agree_on_the_pixel_limit():
    from services.api.routes.detect import MAX_IMAGE_PIXELS
    from workers.train.serving import MAX_PIXELS

    assert MAX_IMAGE_PIXELS == MAX_PIXELS


def test_the_detect_worker_refuses_a_huge_image_without_decoding_it(monkeypatch):
    import cv2

    from workers.train import serving

    def no_decoding(*_args, **_kwargs):
        raise AssertionError("the image was decoded")

    monkeypatch.setattr(cv2, "imdecode", no_decoding)
    for side in (50_000, 16_384, 5000):
        reply = serving.detect_image("checkpoints/none.pt", png_claiming(side, side))
        assert "error" in reply and "pixels" in reply["error"], reply


def test_the_detect_worker_answers_an_opencv_error_instead_of_raising(monkeypatch):
    import foldwise.images
    from workers.train import serving

    monkeypatch.setattr(foldwise.images, "image_size", lambda *_a, **_k: (1, 1))  # a header that lies
    reply = serving.detect_image("checkpoints/none.pt", png_claiming(50_000, 50_000))
    assert "error" in reply and "does not decode" in reply["error"], reply


def test_the_detect_task_answers_bad_base64_and_huge_images():
    import base64

    from workers.train.serving import detect

    assert "not valid base64" in detect("x.pt", "%%%")["error"]
    assert "pixels" in detect("x.pt", base64.b64encode(png_claiming(50_000, 50_000)).decode())["error"]


# --------------------------------------------------------------------------- 7: asset paths


@pytest.fixture
def asset_root(tmp_path, monkeypatch, database_url):
    root = tmp_path / "assets"
    root.mkdir()
    monkeypatch.setenv("FOLDWISE_ASSET_ROOTS", str(root))
    get_settings.cache_clear()
    return root


@pytest.mark.parametrize(
    ("folder", "named"),
    [
        (lambda root: "~nosuchuser-foldwise", "there is no user 'nosuchuser-foldwise'"),
        (lambda root: str(root / (("d" * 200 + "/") * 25)), "at most 4096 are allowed"),
        (lambda root: str(root / ("n" * 300)), "is 300 bytes; at most 255 are allowed"),
        (lambda root: (os.symlink(root / "loop", root / "loop"), str(root / "loop"))[1], "is a loop of symbolic links"),
        (lambda root: (os.symlink(root / "b", root / "a"), os.symlink(root / "a", root / "b"), str(root / "a" / "x"))[2],
         "is a loop of symbolic links"),
    ],
    ids=["unknown-user", "long-path", "long-name", "self-loop", "two-link-loop"],
)  # fmt: skip
def test_an_asset_path_the_system_cannot_take_is_a_422(asset_root, database_url, folder, named):
    path = folder(asset_root)
    for what in ("objects", "backgrounds", "occluders"):
        response = asyncio.run(_post_json(create_app(), {"name": "paths", "assets": {what: path}}))
        assert response.status_code == 422, response.text
        detail = response.json()["detail"]
        assert detail.startswith(f"assets.{what}: ") and named in detail
        assert len(detail) < 600
    assert experiment_count(database_url) == 0


async def _post_json(app, body):
    async with httpx.AsyncClient(transport=httpx.ASGITransport(app=app), base_url="http://api") as client:
        return await client.post("/experiments", json=body, headers=AUTH)


def test_the_api_imports_neither_workers_render_nor_workers_train():
    import subprocess
    import sys

    from tests.services.api.helpers import REPO

    code = (
        "import sys, services.api.app, services.scheduler.service\n"
        "app = services.api.app.create_app()\n"
        "loaded = sorted(m for m in sys.modules if m.startswith(('workers.render', 'workers.train')))\n"
        "print(loaded)\n"
    )
    env = {"PATH": "/usr/bin:/bin", "FOLDWISE_BROKER_URL": "redis://127.0.0.1:1/0", "FOLDWISE_DATA_DIR": "/nonexistent"}
    result = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "[]"


# --------------------------------------------------------------------------- 8: detect backpressure


class HeldReply:
    """A Celery AsyncResult whose worker answers once ``answer`` is set (never, if it is not)."""

    made = 0
    all_sent = threading.Event()
    answer = threading.Event()
    expected = 0

    def __init__(self, args):
        type(self).made += 1
        if type(self).made >= type(self).expected:
            type(self).all_sent.set()

    def ready(self) -> bool:
        return self.answer.is_set()

    def get(self, timeout=None):
        return {"image": {"width": 64, "height": 64}, "classes": ["a"], "detections": [], "seconds": 0.01, "members": 2}

    def forget(self) -> None:
        pass


@pytest.fixture
def held_worker(monkeypatch):
    import workers.app
    from services.api.routes import detect

    previous = workers.app.app.conf.task_always_eager
    workers.app.use_eager(False)  # whatever an earlier test left

    class Reply(HeldReply):
        made = 0
        all_sent = threading.Event()
        answer = threading.Event()
        expected = detect.MAX_IN_FLIGHT

    monkeypatch.setattr(detect, "_publish", Reply)
    monkeypatch.setattr(detect, "REPLY_TIMEOUT_S", 3.0)
    yield Reply
    workers.app.use_eager(previous)


def _detect_crowd(app, replies, count: int = 45, answer: bool = False):
    png = png_claiming(64, 64)

    async def scenario():
        transport = httpx.ASGITransport(app=app)
        async with httpx.AsyncClient(transport=transport, base_url="http://api", timeout=60) as client:
            headers = {**AUTH, "Content-Type": "image/png"}
            started = time.perf_counter()
            crowd = [
                asyncio.create_task(client.post(f"/studies/s{i}/detect", content=png, headers=headers))
                for i in range(count)
            ]
            assert await asyncio.to_thread(replies.all_sent.wait, 30)
            latencies = []
            for _ in range(5):
                began = time.perf_counter()
                health = await client.get("/health")
                latencies.append(time.perf_counter() - began)
                assert health.status_code == 200
            if answer:
                replies.answer.set()
            answers = await asyncio.gather(*crowd)
            return answers, latencies, time.perf_counter() - started

    return asyncio.run(scenario())


def test_45_detects_with_no_worker_hold_no_thread_and_the_rest_are_503(app, held_worker):
    from services.api.routes import detect

    answers, latencies, took = _detect_crowd(app, held_worker)
    codes = [a.status_code for a in answers]
    assert codes.count(504) == detect.MAX_IN_FLIGHT and codes.count(503) == 45 - detect.MAX_IN_FLIGHT, codes
    refused = next(a for a in answers if a.status_code == 503)
    assert refused.headers["Retry-After"] == str(detect.RETRY_AFTER_S) and "retry in" in refused.json()["detail"]
    assert "no detect worker answered within 3 s" in next(a for a in answers if a.status_code == 504).json()["detail"]
    assert max(latencies) < HEALTH_BUDGET_S, latencies
    assert took < detect.REPLY_TIMEOUT_S + 3.0  # the documented wait, not twice it


def test_45_detects_with_a_slow_worker_get_their_answers(app, held_worker):
    from services.api.routes import detect

    answers, latencies, _ = _detect_crowd(app, held_worker, answer=True)
    codes = [a.status_code for a in answers]
    assert codes.count(200) == detect.MAX_IN_FLIGHT and codes.count(503) == 45 - detect.MAX_IN_FLIGHT, codes
    assert max(latencies) < HEALTH_BUDGET_S, latencies
    body = next(a for a in answers if a.status_code == 200).json()
    assert body["members"] == 2 and body["study"].startswith("s")
    assert getattr(app.state, "detects_in_flight", 0) == 0  # every place given back


def test_a_detect_without_a_reachable_broker_is_503(app, monkeypatch):
    import workers.app

    distributed = workers.app.create_app(
        get_settings().model_copy(update={"broker_url": f"redis://127.0.0.1:{_free_port()}/0", "eager": False})
    )
    monkeypatch.setattr(workers.app, "app", distributed)
    started = time.perf_counter()
    response = asyncio.run(_post_image(create_app(), "/studies/s/detect", png_claiming(64, 64)))
    waited = time.perf_counter() - started
    assert response.status_code == 503 and "broker is unreachable" in response.json()["detail"], response.text
    # The app as workers.app configures it: the result backend (the same Redis) gives up after
    # two more tries, where Celery's default of 20 a second apart held the request for 20 s.
    assert waited < UNREACHABLE_BUDGET_S, waited
    distributed.close()


def _free_port() -> int:
    from tests.services.api.helpers import closed_port

    return closed_port()


async def _post_image(app, path, image):
    async with httpx.AsyncClient(transport=httpx.ASGITransport(app=app), base_url="http://api") as client:
        return await client.post(path, content=image, headers={**AUTH, "Content-Type": "image/png"})


def test_waiting_replies_are_looked_for_in_one_round_trip(redis_url, monkeypatch):
    """Every reply waited for is asked about with one MGET: a result comes back as it was
    stored, a task that raised as Failed with its exception, and each collected is forgotten;
    a reply still pending is left to wait."""
    import redis
    from celery.result import AsyncResult

    import workers.app
    from services.api.routes import detect

    distributed = workers.app.create_app(get_settings().model_copy(update={"broker_url": redis_url, "eager": False}))
    backend = distributed.backend
    backend.mark_as_done("answered", {"detections": []})
    backend.mark_as_failure("raised", ValueError("no such checkpoint"))
    looks = []
    mget = type(backend).mget
    monkeypatch.setattr(type(backend), "mget", lambda self, keys: looks.append(len(keys)) or mget(self, keys))
    answered, raised, pending = (AsyncResult(i, app=distributed) for i in ("answered", "raised", "pending"))

    outcomes = detect._collect([answered, raised, pending])

    assert looks == [3]
    assert outcomes[answered] == {"detections": []} and pending not in outcomes
    assert isinstance(outcomes[raised], detect.Failed) and str(outcomes[raised].error) == "no such checkpoint"
    assert redis.Redis.from_url(redis_url).exists("celery-task-meta-answered", "celery-task-meta-raised") == 0
    distributed.close()


def test_detect_messages_expire_when_the_request_stops_waiting(database_url, redis_url, monkeypatch):
    """Through a Redis of its own with no worker: every request is a 504 or a 503 in time, and
    the messages left in the queue carry an expiry, so a worker that comes later drops them."""
    import redis

    import workers.app
    from services.api.routes import detect

    distributed = workers.app.create_app(get_settings().model_copy(update={"broker_url": redis_url, "eager": False}))
    monkeypatch.setattr(workers.app, "app", distributed)
    monkeypatch.setattr(detect, "REPLY_TIMEOUT_S", 1.5)
    app = create_app()
    png = png_claiming(64, 64)

    async def scenario():
        async with httpx.AsyncClient(
            transport=httpx.ASGITransport(app=app), base_url="http://api", timeout=30
        ) as client:
            headers = {**AUTH, "Content-Type": "image/png"}
            crowd = [
                asyncio.create_task(client.post(f"/studies/s{i}/detect", content=png, headers=headers))
                for i in range(20)
            ]
            began = time.perf_counter()
            health = await client.get("/health")
            latency = time.perf_counter() - began
            return await asyncio.gather(*crowd), health, latency

    answers, health, latency = asyncio.run(scenario())
    assert sorted({a.status_code for a in answers}) <= [503, 504]
    assert [a.status_code for a in answers].count(504) == min(20, detect.MAX_IN_FLIGHT)
    assert health.status_code == 200 and latency < HEALTH_BUDGET_S
    queue = redis.Redis.from_url(redis_url)
    try:
        messages = [json.loads(m) for m in queue.lrange(workers.app.DETECT_QUEUE, 0, -1)]
    finally:
        queue.close()
    assert len(messages) == min(20, detect.MAX_IN_FLIGHT)
    assert all(m["headers"]["expires"] for m in messages)
    distributed.close()


# --------------------------------------------------------------------------- minor


def test_figures_are_drawn_once_per_content_and_health_does_not_wait(app, seeded, database_url, monkeypatch):
    import services.report

    drawn = []
    entered, release = threading.Event(), threading.Event()

    def fake_report(experiment_id, out_dir):
        drawn.append(experiment_id)
        entered.set()
        assert release.wait(30)
        out_dir.mkdir(parents=True, exist_ok=True)
        (out_dir / f"experiment-{experiment_id}.png").write_bytes(b"\x89PNG drawn %d" % len(drawn))
        (out_dir / f"experiment-{experiment_id}.csv").write_text("stage\n")
        return services.report.ReportFiles(
            png=out_dir / f"experiment-{experiment_id}.png", csv=out_dir / f"experiment-{experiment_id}.csv", rows=[]
        )

    monkeypatch.setattr(services.report, "write_report", fake_report)
    url = f"/experiments/{seeded['experiment']}/report.png"

    async def scenario():
        async with httpx.AsyncClient(transport=httpx.ASGITransport(app=app), base_url="http://api") as client:
            crowd = [asyncio.create_task(client.get(url)) for _ in range(45)]
            assert await asyncio.to_thread(entered.wait, 30)
            began = time.perf_counter()
            health = await client.get("/health")
            latency = time.perf_counter() - began
            release.set()
            answers = await asyncio.gather(*crowd)
            again = await client.get(url)
            return answers, health, latency, again

    answers, health, latency, again = asyncio.run(scenario())
    assert {a.status_code for a in answers} == {200} and again.status_code == 200
    assert drawn == [seeded["experiment"]]  # once for 46 requests
    assert health.status_code == 200 and latency < HEALTH_BUDGET_S
    assert again.content == answers[0].content == b"\x89PNG drawn 1"

    # A new evaluation changes what the report shows: it is drawn again, once.
    from db.models import Evaluation, Model
    from db.session import get_sessionmaker

    with get_sessionmaker(database_url)() as session:
        session.add(Evaluation(model_id=seeded["models"][4], map=0.9, details={}, eval_seconds=1.0))
        session.query(Model).filter(Model.id == seeded["models"][4]).update({"status": "evaluated"})
        session.commit()

    async def twice():
        async with httpx.AsyncClient(transport=httpx.ASGITransport(app=app), base_url="http://api") as client:
            return [await client.get(url), await client.get(url)]

    first, second = asyncio.run(twice())
    assert first.status_code == second.status_code == 200
    assert len(drawn) == 2 and second.content == b"\x89PNG drawn 2"


def test_figures_of_an_unknown_experiment_are_404(client):
    assert client.get("/experiments/999/report.png").status_code == 404
    assert client.get("/experiments/999/figures/fig4.png").status_code == 404


@pytest.mark.parametrize("path", ["/", "/health", "/experiments", "/dashboard.js", "/openapi.json", "/nowhere"])
def test_every_response_carries_the_security_headers(client, path):
    response = client.get(path)
    assert response.headers["X-Content-Type-Options"] == "nosniff"
    assert response.headers["X-Frame-Options"] == "DENY"
    policy = response.headers["Content-Security-Policy"]
    assert "default-src 'self'" in policy and "frame-ancestors 'none'" in policy and "script-src 'self';" in policy


def test_the_dashboard_runs_under_its_policy(client):
    """The page has no inline script or handler and loads nothing from elsewhere."""
    import re

    page = client.get("/").text
    assert not re.search(r"<script(?![^>]*\bsrc=)", page)
    assert not re.search(r"\son[a-z]+=", page)
    assert not re.search(r"(src|href)=\"(https?:)?//", page)
    docs = client.get("/docs")
    assert "https://cdn.jsdelivr.net" in docs.headers["Content-Security-Policy"]


def test_health_tells_anonymous_callers_only_up_or_down(client):
    anonymous = client.get("/health")
    assert anonymous.status_code == 200 and anonymous.json() == {"status": "degraded"}
    wrong = client.get("/health", headers={"Authorization": "Bearer wrong"})
    assert wrong.json() == {"status": "degraded"}
    with_token = client.get("/health", headers=AUTH).json()
    assert with_token["database"]["status"] == "ok" and with_token["broker"]["status"] == "error"
    assert "127.0.0.1" in with_token["broker"]["url"]
    assert TOKEN not in json.dumps(with_token)


@pytest.mark.parametrize("character", ["\x85", "\x9b", "\u202a", "\u202e", "\u2066", "\u2069"])
def test_names_refuse_c1_controls_and_bidi_overrides(client, database_url, character):
    name = f"report{character}gpj.exe"
    response = client.post("/experiments", json={"name": name}, headers=AUTH)
    assert response.status_code == 422 and "name" in response.text, response.text
    study = client.post("/experiments", json={"name": "ok"}, params={"study": name}, headers=AUTH)
    assert study.status_code == 422 and "study" in study.text
    listed = client.get("/experiments", params={"study": name})
    assert listed.status_code == 422
    detect = client.post(f"/studies/{name}/detect", content=b"x", headers={**AUTH, "Content-Type": "image/png"})
    assert detect.status_code == 422
    assert experiment_count(database_url) == 0


def test_a_figure_of_a_running_stage_is_not_redrawn_as_the_clock_moves(client, seeded, monkeypatch):
    import services.figures

    drawn = []

    def fake_figures(experiment_ids, out_dir, names):
        drawn.append(names)
        out_dir.mkdir(parents=True, exist_ok=True)
        paths = [out_dir / f"{names[0]}-experiments-{experiment_ids[0]}.{suffix}" for suffix in ("png", "svg", "csv")]
        for path in paths:
            path.write_bytes(b"drawn")
        return {names[0]: paths}

    monkeypatch.setattr(services.figures, "write_figures", fake_figures)
    url = f"/experiments/{seeded['experiment']}/figures/fig4"
    first = client.get(f"{url}.png")
    later = [client.get(f"{url}.{suffix}") for suffix in ("png", "svg", "csv")]  # the stage's seconds have grown
    assert first.status_code == 200 and all(r.status_code == 200 for r in later)
    assert drawn == [("fig4",)]


def test_a_broker_lost_while_a_detect_waits_is_a_503(app, held_worker, monkeypatch):
    class Lost(held_worker):
        def ready(self) -> bool:
            raise ConnectionError("Connection refused")

        def forget(self) -> None:
            raise ConnectionError("Connection refused")

    import services.api.routes.detect as detect

    monkeypatch.setattr(detect, "_publish", Lost)
    response = asyncio.run(_post_image(app, "/studies/s/detect", png_claiming(64, 64)))
    assert response.status_code == 503 and "broker stopped answering" in response.json()["detail"], response.text
    assert getattr(app.state, "detects_in_flight", 0) == 0
