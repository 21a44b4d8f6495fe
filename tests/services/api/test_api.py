"""The REST API against a temporary SQLite database: every endpoint, every error path, the token rules."""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time
import warnings
from datetime import UTC, datetime

import pytest

from db.migrate import upgrade
from db.models import (
    Experiment,
    ExperimentStatus,
)
from db.session import get_engine, get_sessionmaker
from foldwise.config import ExperimentConfig
from foldwise.settings import get_settings
from services.api.app import create_app

with warnings.catch_warnings():
    # Starlette's test client asks for the `httpx2` fork; plain httpx works and is what is installed.
    warnings.simplefilter("ignore")
    from fastapi.testclient import TestClient

from tests.services.api.helpers import (
    AUTH,
    REPO,
    T0,
    TOKEN,
    client_with,
    closed_port,
    experiment_count,
    stored_experiment,
)

# --------------------------------------------------------------------------- reads


def test_list_experiments_and_status_filter(client, seeded):
    listed = client.get("/experiments")
    assert listed.status_code == 200
    assert [(e["id"], e["name"], e["status"]) for e in listed.json()] == [
        (seeded["experiment"], "seeded", "running"),
        (seeded["finished"], "done", "finished"),
    ]
    assert [e["id"] for e in client.get("/experiments?status=finished").json()] == [seeded["finished"]]
    assert client.get("/experiments?status=cancelled").json() == []
    bad = client.get("/experiments?status=sleeping")
    assert bad.status_code == 422 and "pending" in json.dumps(bad.json())


def test_list_is_empty_on_a_fresh_database(client):
    response = client.get("/experiments")
    assert response.status_code == 200 and response.json() == []


def test_experiment_summary(client, seeded):
    response = client.get(f"/experiments/{seeded['experiment']}")
    assert response.status_code == 200
    body = response.json()
    assert body["status"] == "running"
    assert body["classes"] == ["astronaut", "coffee"]
    assert body["current_stage"] == {"order": 1, "condition": "fb", "difficulty": "medium", "k": 2}
    assert body["counts"]["models"] == {"evaluated": 4, "training": 1}
    assert body["counts"]["evaluations"] == 4
    assert body["counts"]["stages"] == 2
    assert body["counts"]["parameter_sets"] == {"train": {"rendered": 2}, "test": {"queued": 1}}
    assert body["best"] == {"map": 0.70, "model_id": seeded["models"][1]}
    # Still running: elapsed counts up to now from the start.
    assert body["elapsed_seconds"] >= (datetime.now(UTC) - T0).total_seconds() - 5

    finished = client.get(f"/experiments/{seeded['finished']}").json()
    assert finished["elapsed_seconds"] == pytest.approx(3600.0)
    assert finished["current_stage"] is None and finished["best"] is None


def test_stages(client, seeded):
    response = client.get(f"/experiments/{seeded['experiment']}/stages")
    assert response.status_code == 200
    easy, medium = response.json()
    assert (easy["order"], easy["condition"], easy["difficulty"]) == (0, "fb", "easy")
    assert easy["status"] == "done" and easy["end_reason"] == "plateau"
    assert easy["increments"] == 3
    assert easy["best_model_id"] == seeded["models"][1] and easy["best_map"] == pytest.approx(0.70)
    assert easy["seconds"] == pytest.approx(35.0)
    assert (medium["order"], medium["difficulty"], medium["status"]) == (1, "medium", "running")
    assert medium["end_reason"] is None
    assert medium["increments"] == 1  # k = 2 is still training: not in P yet
    assert medium["init_model_id"] == seeded["models"][1]


def test_history_is_P_in_arrival_order(client, seeded):
    response = client.get(f"/experiments/{seeded['experiment']}/history")
    assert response.status_code == 200
    history = response.json()
    assert [(h["condition"], h["difficulty"], h["k"], h["map"], h["model_id"]) for h in history] == [
        ("fb", "easy", 1, 0.40, seeded["models"][0]),
        ("fb", "easy", 2, 0.70, seeded["models"][1]),
        ("fb", "easy", 3, 0.60, seeded["models"][2]),
        ("fb", "medium", 1, 0.65, seeded["models"][3]),
    ]
    assert [h["wall_seconds"] for h in history] == pytest.approx([10.0, 20.0, 30.0, 40.0])
    assert history[0]["render_seconds"] == pytest.approx(4.0)
    assert history[1]["parent_id"] == seeded["models"][0]


def test_history_and_stages_of_an_experiment_without_any(client, seeded):
    assert client.get(f"/experiments/{seeded['finished']}/history").json() == []
    assert client.get(f"/experiments/{seeded['finished']}/stages").json() == []


def test_model_detail(client, seeded):
    best = seeded["models"][1]
    response = client.get(f"/models/{best}")
    assert response.status_code == 200
    body = response.json()
    assert body["id"] == best and body["k"] == 2 and body["parent_id"] == seeded["models"][0]
    assert body["stage"] == {"order": 0, "condition": "fb", "difficulty": "easy"}
    assert body["status"] == "evaluated" and body["checkpoint_path"] == "checkpoints/0/2.pt"
    assert body["evaluation"]["map"] == pytest.approx(0.70)
    assert body["evaluation"]["map_unthresholded"] == pytest.approx(0.75)

    training = client.get(f"/models/{seeded['models'][4]}").json()
    assert training["status"] == "training" and training["evaluation"] is None


@pytest.mark.parametrize(
    "path, message",
    [
        ("/experiments/4242", "experiment 4242 does not exist"),
        ("/experiments/4242/stages", "experiment 4242 does not exist"),
        ("/experiments/4242/history", "experiment 4242 does not exist"),
        ("/models/4242", "model 4242 does not exist"),
    ],
)
def test_unknown_ids_are_404_naming_the_id(client, seeded, path, message):
    response = client.get(path)
    assert response.status_code == 404
    assert response.json() == {"detail": message}


@pytest.mark.parametrize("bad_id", ["0", "-3", str(2**31), str(2**63), str(10**40)])
def test_ids_outside_the_id_range_are_404_not_500(client, bad_id):
    # 2**31 is one past PostgreSQL's INTEGER: asking the database for it was a 500.
    paths = (f"/experiments/{bad_id}", f"/models/{bad_id}", f"/experiments/{bad_id}/history",
             f"/experiments/{bad_id}/images/{bad_id}.png", f"/models/{bad_id}/checkpoint")  # fmt: skip
    for path in paths:
        response = client.get(path)
        assert response.status_code == 404, path
        assert bad_id in response.json()["detail"] and "does not exist" in response.json()["detail"]


@pytest.mark.parametrize("bad_id", ["abc", "1.5", "1e3"])
def test_ids_that_are_not_whole_numbers_are_422(client, bad_id):
    for path in (f"/experiments/{bad_id}", f"/models/{bad_id}", f"/experiments/{bad_id}/history"):
        response = client.get(path)
        assert response.status_code == 422, path
        assert response.json()["detail"][0]["loc"][-1] in ("experiment_id", "model_id")


def test_reads_need_no_token(client, seeded):
    for path in ("/experiments", f"/experiments/{seeded['experiment']}", f"/models/{seeded['models'][0]}", "/health"):
        assert client.get(path).status_code == 200, path


def test_every_request_returns_its_session(client, seeded, database_url):
    client.get(f"/experiments/{seeded['experiment']}")
    client.get("/experiments/4242")
    client.post(f"/experiments/{seeded['finished']}/cancel", headers=AUTH)  # 409
    client.post("/experiments", json={"name": "x", "seed": -1}, headers=AUTH)  # 422
    client.post("/experiments", json={"name": "x"}, headers=AUTH)  # 201
    client.get("/health", headers=AUTH)
    assert get_engine(database_url).pool.checkedout() == 0


def test_responses_carry_the_query_results_unchanged(client, seeded, database_url):
    """The typed response models document the queries' dictionaries; they must not drop or reshape a key."""
    from services import queries

    with get_sessionmaker(database_url)() as session:
        expected = {
            "/experiments": queries.list_experiments(session),
            f"/experiments/{seeded['finished']}": queries.summary(session, seeded["finished"]),
            f"/experiments/{seeded['experiment']}/stages": queries.stages(session, seeded["experiment"]),
            f"/experiments/{seeded['experiment']}/history": queries.history(session, seeded["experiment"]),
            f"/models/{seeded['models'][1]}": queries.model_detail(session, seeded["models"][1]),
            f"/models/{seeded['models'][4]}": queries.model_detail(session, seeded["models"][4]),
        }

    def settled(value):
        # A running stage's duration counts up between the two reads.
        if isinstance(value, list):
            return [settled(item) for item in value]
        if isinstance(value, dict) and value.get("finished_at", "") is None and "seconds" in value:
            return {**value, "seconds": "running"}
        return value

    for path, result in expected.items():
        plain = result.model_dump(mode="json") if hasattr(result, "model_dump") else result
        if isinstance(plain, list):
            plain = [item.model_dump(mode="json") if hasattr(item, "model_dump") else item for item in plain]
        assert settled(client.get(path).json()) == settled(json.loads(json.dumps(plain))), path


# --------------------------------------------------------------------------- creating


def test_create_from_json(client, database_url):
    config = {"name": "json run", "seed": 11, "active_learning": {"m": 7, "M": 2, "N": 4}}
    response = client.post("/experiments", json=config, headers=AUTH)
    assert response.status_code == 201
    body = response.json()
    assert body["name"] == "json run" and body["status"] == "pending" and body["seed"] == 11
    assert response.headers["location"] == f"/experiments/{body['id']}"
    # The Location answers with the same record.
    assert client.get(response.headers["location"]).json()["id"] == body["id"]
    stored = stored_experiment(database_url, body["id"])
    assert stored.config == ExperimentConfig(**config).model_dump(mode="json")
    assert stored.config["active_learning"]["m"] == 7
    assert stored.status == ExperimentStatus.pending


@pytest.mark.parametrize(
    "content_type", ["application/yaml", "text/yaml", "application/x-yaml", "text/yaml; charset=utf-8"]
)
def test_create_from_yaml(client, database_url, content_type):
    document = "name: yaml run\nseed: 5\ncurriculum:\n  conditions: [mb, po]\n  difficulties: [hard]\n"
    response = client.post("/experiments", content=document.encode(), headers={**AUTH, "Content-Type": content_type})
    assert response.status_code == 201, response.text
    stored = stored_experiment(database_url, response.json()["id"])
    assert stored.name == "yaml run" and stored.seed == 5
    assert stored.config["curriculum"] == {
        "conditions": ["mb", "po"],
        "difficulties": ["hard"],
        "mixed": None,
        "single_condition_stages": True,
    }


def test_recorded_config_has_the_defaults_filled_in(client, seeded):
    document = "name: defaults\nactive_learning:\n  tau: 0.05\n"
    created = client.post("/experiments", content=document, headers={**AUTH, "Content-Type": "text/yaml"}).json()
    response = client.get(f"/experiments/{created['id']}/config")
    assert response.status_code == 200
    config = response.json()
    assert config["active_learning"]["tau"] == 0.05
    assert config["active_learning"]["M"] == 3 and config["active_learning"]["N"] == 8  # the paper's defaults
    assert config == ExperimentConfig(name="defaults", active_learning={"tau": 0.05}).model_dump(mode="json")
    missing = client.get("/experiments/4242/config")
    assert missing.status_code == 404 and missing.json()["detail"] == "experiment 4242 does not exist"


def test_two_creations_get_distinct_ids(client):
    first = client.post("/experiments", json={"name": "same"}, headers=AUTH).json()["id"]
    second = client.post("/experiments", json={"name": "same"}, headers=AUTH).json()["id"]
    assert first != second
    assert [e["id"] for e in client.get("/experiments").json()] == [first, second]


@pytest.mark.parametrize(
    "content_type, body, named",
    [
        ("application/json", json.dumps({"name": "x", "active_learning": {"mm": 3}}), "active_learning.mm: unknown"),
        ("application/json", json.dumps({"name": "x", "active_learning": {"tau": 2}}), "active_learning.tau"),
        ("application/json", json.dumps({"seed": 3}), "name: Field required"),
        ("application/json", json.dumps({"name": "x", "render": {"backend": "povray"}}), "render.backend"),
        ("application/yaml", "name: x\ncurriculum:\n  conditions: [zz]\n", "unknown condition 'zz'"),
        ("application/yaml", "name: x\ndetector:\n  family: rcnn9000\n", "detector.family"),
        ("application/json", json.dumps(["name", "x"]), "expected a mapping at the top level, got list"),
        ("application/yaml", "- just\n- a list\n", "expected a mapping at the top level, got list"),
        ("application/json", '{"name": "x",', "not JSON"),
        ("application/yaml", "name: [unclosed\n", "not YAML"),
        ("application/yaml", "name: a\n---\nname: b\n", "not YAML"),
        ("application/json", "   ", "empty body"),
        # JSON has no NaN or Infinity (Python's parser would take them; PostgreSQL's JSON would not).
        ("application/json", '{"name": "x", "detector": {"learning_rate": Infinity}}', "Infinity is not a JSON number"),
        ("application/json", '{"name": "x", "evaluation": {"score_threshold": NaN}}', "NaN is not a JSON number"),
        (
            "application/yaml",
            "name: x\ndetector:\n  learning_rate: .inf\n",
            "detector.learning_rate: Input should be a finite number",
        ),
    ],
)
def test_invalid_configs_are_422_naming_the_problem(client, seeded, database_url, content_type, body, named):
    before = experiment_count(database_url)
    response = client.post("/experiments", content=body.encode(), headers={**AUTH, "Content-Type": content_type})
    assert response.status_code == 422
    assert named in response.json()["detail"]
    assert experiment_count(database_url) == before


def test_body_that_is_not_utf8_is_422(client, database_url):
    headers = {**AUTH, "Content-Type": "application/yaml"}
    response = client.post("/experiments", content=b"name: \xff\xfe", headers=headers)
    assert response.status_code == 422 and "UTF-8" in response.json()["detail"]
    assert experiment_count(database_url) == 0


def test_oversized_body_is_413(client, database_url):
    padding = "#" + "x" * (1 << 20) + "\nname: big\n"
    headers = {**AUTH, "Content-Type": "application/yaml"}
    response = client.post("/experiments", content=padding.encode(), headers=headers)
    assert response.status_code == 413
    assert experiment_count(database_url) == 0


@pytest.mark.parametrize("content_type", [None, "text/plain", "application/x-www-form-urlencoded", "application/xml"])
def test_unsupported_content_type_is_415(client, database_url, content_type):
    headers = dict(AUTH)
    if content_type:
        headers["Content-Type"] = content_type
    response = client.post("/experiments", content=b'{"name": "x"}', headers=headers)
    assert response.status_code == 415
    detail = response.json()["detail"]
    assert (content_type or "(none)") in detail and "application/yaml" in detail
    assert experiment_count(database_url) == 0


# --------------------------------------------------------------------------- the token


def test_missing_token_is_401_with_a_bearer_challenge(client, database_url):
    response = client.post("/experiments", json={"name": "x"})
    assert response.status_code == 401
    assert response.headers["www-authenticate"] == "Bearer"
    assert "Authorization: Bearer" in response.json()["detail"]
    assert experiment_count(database_url) == 0


@pytest.mark.parametrize(
    "header, detail",
    [
        (f"Bearer {TOKEN}x", "wrong token"),
        (f"Bearer {TOKEN[:-1]}", "wrong token"),
        ("Bearer ", "must be 'Bearer <token>'"),
        (f"Basic {TOKEN}", "must be 'Bearer <token>'"),
        (TOKEN, "must be 'Bearer <token>'"),
    ],
)
def test_wrong_token_is_401(client, seeded, database_url, header, detail):
    create = client.post("/experiments", json={"name": "x"}, headers={"Authorization": header})
    cancel = client.post(f"/experiments/{seeded['experiment']}/cancel", headers={"Authorization": header})
    for response in (create, cancel):
        assert response.status_code == 401
        assert detail in response.json()["detail"]
    assert experiment_count(database_url) == 2
    assert stored_experiment(database_url, seeded["experiment"]).status == ExperimentStatus.running


def test_the_token_is_checked_before_the_body(client):
    # An anonymous caller learns nothing about what the API would accept.
    response = client.post("/experiments", content=b"<xml/>", headers={"Content-Type": "application/xml"})
    assert response.status_code == 401


@pytest.mark.parametrize("unset", [None, ""])
def test_writes_are_403_when_no_token_is_configured(seeded, database_url, unset):
    client = client_with(api_token=unset)
    for headers in ({}, AUTH, {"Authorization": "Bearer "}):
        create = client.post("/experiments", json={"name": "x"}, headers=headers)
        cancel = client.post(f"/experiments/{seeded['experiment']}/cancel", headers=headers)
        for response in (create, cancel):
            assert response.status_code == 403
            assert "FOLDWISE_API_TOKEN is not set" in response.json()["detail"]
    assert experiment_count(database_url) == 2
    assert stored_experiment(database_url, seeded["experiment"]).status == ExperimentStatus.running
    # Reads still work.
    assert client.get(f"/experiments/{seeded['experiment']}").status_code == 200


def test_token_from_the_environment(seeded, monkeypatch):
    monkeypatch.setenv("FOLDWISE_API_TOKEN", "from-env")
    get_settings.cache_clear()
    client = TestClient(create_app())
    assert client.post("/experiments", json={"name": "x"}, headers=AUTH).status_code == 401
    accepted = client.post("/experiments", json={"name": "x"}, headers={"Authorization": "Bearer from-env"})
    assert accepted.status_code == 201


# --------------------------------------------------------------------------- cancelling


def test_cancel_a_running_experiment(client, seeded, database_url):
    response = client.post(f"/experiments/{seeded['experiment']}/cancel", headers=AUTH)
    assert response.status_code == 200
    body = response.json()
    assert body["status"] == "cancelled" and body["finished_at"] is not None
    stored = stored_experiment(database_url, seeded["experiment"])
    assert stored.status == ExperimentStatus.cancelled
    # The record of what ran stays.
    assert len(client.get(f"/experiments/{seeded['experiment']}/history").json()) == 4


def test_cancel_a_pending_experiment_then_again_is_409(client, database_url):
    created = client.post("/experiments", json={"name": "to cancel"}, headers=AUTH).json()["id"]
    first = client.post(f"/experiments/{created}/cancel", headers=AUTH)
    assert first.status_code == 200 and first.json()["status"] == "cancelled"
    again = client.post(f"/experiments/{created}/cancel", headers=AUTH)
    assert again.status_code == 409
    assert again.json()["detail"].startswith(f"experiment {created} is already cancelled")


@pytest.mark.parametrize("ended", ["finished", "failed"])
def test_cancel_an_ended_experiment_is_409_and_changes_nothing(client, seeded, database_url, ended):
    with get_sessionmaker(database_url)() as session:
        session.get(Experiment, seeded["finished"]).status = ExperimentStatus(ended)
        session.commit()
    before = stored_experiment(database_url, seeded["finished"])
    response = client.post(f"/experiments/{seeded['finished']}/cancel", headers=AUTH)
    assert response.status_code == 409
    assert f"already {ended}" in response.json()["detail"]
    after = stored_experiment(database_url, seeded["finished"])
    assert (after.status, after.finished_at) == (before.status, before.finished_at)


def test_cancel_unknown_experiment_is_404(client, seeded):
    response = client.post("/experiments/4242/cancel", headers=AUTH)
    assert response.status_code == 404
    assert response.json()["detail"] == "experiment 4242 does not exist"


# --------------------------------------------------------------------------- health


def test_health_with_the_broker_unreachable_answers_quickly(client):
    started = time.perf_counter()
    response = client.get("/health", headers=AUTH)
    elapsed = time.perf_counter() - started
    assert response.status_code == 200  # the API still serves the record
    body = response.json()
    assert body["status"] == "degraded"
    assert body["database"]["status"] == "ok" and body["database"]["revision"]
    assert body["broker"]["status"] == "error"
    assert "refused" in body["broker"]["detail"].lower()
    assert elapsed < 5.0  # a bound against hanging on retries, not a benchmark


@pytest.fixture
def silent_broker_url():
    """A port that accepts connections and never answers: the broker hung, not down."""
    with socket.socket() as listener:
        listener.bind(("127.0.0.1", 0))
        listener.listen(8)
        yield f"redis://127.0.0.1:{listener.getsockname()[1]}/0"


def test_a_silent_broker_is_an_error_after_the_timeout_not_a_hang(database_url, silent_broker_url):
    client = client_with(broker_url=silent_broker_url, broker_timeout_s=0.2)
    started = time.perf_counter()
    health = client.get("/health", headers=AUTH)
    queues = client.get("/queues")
    elapsed = time.perf_counter() - started
    assert health.status_code == 200 and health.json()["broker"]["status"] == "error"
    assert "timeout" in health.json()["broker"]["detail"].lower()
    assert queues.status_code == 503 and "unreachable" in queues.json()["detail"]
    assert elapsed < 5.0


def test_health_skips_the_broker_in_eager_mode(database_url):
    response = client_with(eager=True).get("/health", headers=AUTH)
    assert response.status_code == 200
    assert response.json()["status"] == "ok"
    assert response.json()["broker"]["status"] == "skipped"
    assert "FOLDWISE_EAGER" in response.json()["broker"]["detail"]


def test_health_reports_an_unmigrated_database(tmp_path, database_url):
    empty = f"sqlite:///{tmp_path / 'empty.db'}"
    response = client_with(database_url=empty, eager=True).get("/health", headers=AUTH)
    assert response.status_code == 503
    body = response.json()
    assert body["status"] == "error" and body["database"]["status"] == "error"
    assert body["database"]["revision"] is None
    assert "foldwise db upgrade" in body["database"]["detail"]


def test_health_reports_an_unreachable_database_without_its_password(database_url):
    url = f"postgresql+psycopg://foldwise:hunter2@127.0.0.1:{closed_port()}/foldwise"
    started = time.perf_counter()
    response = client_with(database_url=url, eager=True).get("/health", headers=AUTH)
    assert time.perf_counter() - started < 10.0
    assert response.status_code == 503
    assert response.json()["database"]["status"] == "error"
    assert "unreachable" in response.json()["database"]["detail"]
    assert "hunter2" not in response.text


# --------------------------------------------------------------------------- queues


def test_queues_with_the_broker_unreachable_is_503(client):
    started = time.perf_counter()
    response = client.get("/queues")
    assert time.perf_counter() - started < 5.0
    assert response.status_code == 503
    body = response.json()
    assert "unreachable" in body["detail"] and body["broker"]["status"] == "error"


def test_queues_never_show_the_broker_password(database_url):
    response = client_with(broker_url=f"redis://:hunter2@127.0.0.1:{closed_port()}/0").get("/queues")
    assert response.status_code == 503
    assert "hunter2" not in response.text
    health = client_with(broker_url=f"redis://:hunter2@127.0.0.1:{closed_port()}/0").get("/health", headers=AUTH)
    assert "hunter2" not in health.text and health.json()["broker"]["status"] == "error"


def test_queues_in_eager_mode_and_with_a_non_redis_broker(database_url):
    eager = client_with(eager=True).get("/queues")
    assert eager.status_code == 503 and "FOLDWISE_EAGER" in eager.json()["detail"]
    amqp = client_with(broker_url=f"amqp://guest:guest@127.0.0.1:{closed_port()}//").get("/queues")
    assert amqp.status_code == 501 and "Redis" in amqp.json()["detail"]
    assert "guest:guest" not in amqp.text
    health = client_with(broker_url=f"amqp://guest:guest@127.0.0.1:{closed_port()}//").get("/health", headers=AUTH)
    assert health.json()["broker"]["status"] == "error"


def test_queues_against_a_live_redis_with_a_worker(database_url, redis_url):
    import redis
    from celery import Celery
    from celery.contrib.testing.worker import start_worker

    broker = redis.Redis.from_url(redis_url)
    broker.rpush("render", "m1", "m2")
    broker.rpush("render\x06\x163", "m3")  # kombu's key for priority 3 of the render queue
    broker.rpush("train", "m4")
    broker.rpush("unrelated", "m5")
    broker.hset("unacked", "tag-1", "{}")
    client = client_with(broker_url=redis_url)

    idle = client.get("/queues")
    assert idle.status_code == 200
    assert idle.json()["queues"] == {"render": 3, "train": 1}
    assert idle.json()["unacked"] == 1
    assert idle.json()["workers"] == []
    assert client.get("/health", headers=AUTH).json()["broker"]["status"] == "ok"

    # A worker listening on another queue, so it answers the ping without draining ours.
    worker_app = Celery("api-test-worker", broker=redis_url)
    worker_app.conf.task_default_queue = "api-test"
    with start_worker(worker_app, perform_ping_check=False, hostname="render@api-test"):
        busy = client.get("/queues").json()
    assert busy["workers"] == ["render@api-test"]
    assert busy["queues"] == {"render": 3, "train": 1}
    broker.close()


# --------------------------------------------------------------------------- dependency overrides


class FakeBroker:
    """Stands in for the broker probe: a Redis broker that answers with fixed depths and workers."""

    skipped_reason = None
    is_redis = True
    display_url = "redis://fake:6379/0"
    ping_timeout_s = 0.25

    def __init__(self, workers=("render@a", "train@b"), down: bool = False) -> None:
        self.workers, self.down = list(workers), down

    def check(self):
        return {"status": "error", "detail": "fake outage"} if self.down else {"status": "ok", "url": self.display_url}

    def queue_depths(self, queues):
        from services.api.probes import BrokerUnavailable

        if self.down:
            raise BrokerUnavailable("broker redis://fake:6379/0 is unreachable: fake outage")
        return {"queues": {queue: 10 * (i + 1) for i, queue in enumerate(queues)}, "unacked": 2}

    def ping_workers(self):
        return self.workers


def test_queues_reads_the_broker_it_is_given(client):
    from services.api import deps

    client.app.dependency_overrides[deps.get_broker] = FakeBroker
    body = client.get("/queues", headers=AUTH).json()
    assert body == {
        "broker": {"status": "ok", "url": "redis://fake:6379/0"},
        "queues": {"render": 10, "train": 20},
        "unacked": 2,
        "workers": ["render@a", "train@b"],
        "ping_timeout_s": 0.25,
    }
    client.app.dependency_overrides[deps.get_broker] = lambda: FakeBroker(down=True)
    down = client.get("/queues", headers=AUTH)
    assert down.status_code == 503 and "fake outage" in down.json()["detail"]
    assert client.get("/health", headers=AUTH).json()["status"] == "degraded"


def test_queues_tell_an_anonymous_caller_nothing_of_the_broker_s_whereabouts(client, database_url):
    """Anyone reads the depths and the workers; the broker's URL, and the error that names its
    host and port, only a caller with the token (as /health)."""
    from services.api import deps

    client.app.dependency_overrides[deps.get_broker] = FakeBroker
    for headers in ({}, {"Authorization": "Bearer not-the-token"}, {"Authorization": f"Basic {TOKEN}"}):
        anonymous = client.get("/queues", headers=headers)
        assert anonymous.status_code == 200
        assert anonymous.json() == {
            "broker": {"status": "ok"},
            "queues": {"render": 10, "train": 20},
            "unacked": 2,
            "workers": ["render@a", "train@b"],
            "ping_timeout_s": 0.25,
        }
        assert "fake:6379" not in anonymous.text
    client.app.dependency_overrides[deps.get_broker] = lambda: FakeBroker(down=True)
    down = client.get("/queues")
    assert down.status_code == 503
    assert down.json() == {"detail": "the broker is unreachable", "broker": {"status": "error"}}
    client.app.dependency_overrides.clear()

    port = closed_port()
    unreachable = client_with(broker_url=f"redis://:hunter2@127.0.0.1:{port}/0")
    hidden = unreachable.get("/queues")
    assert hidden.status_code == 503 and hidden.json()["broker"] == {"status": "error"}
    assert str(port) not in hidden.text and "127.0.0.1" not in hidden.text
    shown = unreachable.get("/queues", headers=AUTH)
    assert shown.status_code == 503 and shown.json()["broker"]["url"].endswith(f"127.0.0.1:{port}/0")
    assert "hunter2" not in shown.text  # the password never, not even to the token's holder

    amqp = client_with(broker_url=f"amqp://guest:secret@broker.internal:{port}//")
    assert amqp.get("/queues").json() == {"detail": "queue depth is read from Redis; the broker is not Redis"}
    with_token = amqp.get("/queues", headers=AUTH)
    assert with_token.status_code == 501 and "broker.internal" in with_token.json()["detail"]
    assert "secret" not in with_token.text


def test_health_is_503_when_the_schema_check_fails(client):
    from services.api import deps

    class Unmigrated:
        def check(self, _session):
            return {"status": "error", "revision": None, "detail": "run `foldwise db upgrade`"}

    client.app.dependency_overrides[deps.get_schema_check] = Unmigrated
    client.app.dependency_overrides[deps.get_broker] = FakeBroker
    response = client.get("/health", headers=AUTH)
    assert response.status_code == 503
    assert response.json()["status"] == "error" and response.json()["broker"]["status"] == "ok"


def test_the_token_comes_from_the_apps_settings(client, database_url):
    from services.api import deps

    client.app.dependency_overrides[deps.get_app_settings] = lambda: get_settings().model_copy(
        update={"api_token": "overridden"}
    )
    assert client.post("/experiments", json={"name": "x"}, headers=AUTH).status_code == 401
    created = client.post("/experiments", json={"name": "x"}, headers={"Authorization": "Bearer overridden"})
    assert created.status_code == 201 and experiment_count(database_url) == 1


def test_routes_use_the_session_they_are_given(client, seeded, database_url, tmp_path):
    """Every route reads through the session dependency: another database behind it, another record."""
    from services.api import deps

    other = tmp_path / "other.db"
    upgrade(f"sqlite:///{other}")

    def other_session():
        session = get_sessionmaker(f"sqlite:///{other}")()
        try:
            yield session
        finally:
            session.close()

    assert len(client.get("/experiments").json()) == 2
    client.app.dependency_overrides[deps.get_session] = other_session
    assert client.get("/experiments").json() == []
    assert client.get(f"/experiments/{seeded['experiment']}").status_code == 404
    assert client.get(f"/models/{seeded['models'][0]}").status_code == 404


# --------------------------------------------------------------------------- the module


def test_openapi_documents_both_config_media_types(client):
    spec = client.get("/openapi.json").json()
    assert {
        "/health",
        "/experiments",
        "/experiments/{experiment_id}",
        "/experiments/{experiment_id}/cancel",
        "/experiments/{experiment_id}/config",
        "/experiments/{experiment_id}/stages",
        "/experiments/{experiment_id}/history",
        "/models/{model_id}",
        "/queues",
    } <= set(spec["paths"])
    content = spec["paths"]["/experiments"]["post"]["requestBody"]["content"]
    assert {"application/json", "application/yaml", "text/yaml"} <= set(content)
    config_schema = spec["components"]["schemas"]["ExperimentConfig"]
    assert "active_learning" in config_schema["properties"]

    def refs(node):
        if isinstance(node, dict):
            if isinstance(node.get("$ref"), str):
                yield node["$ref"]
            for value in node.values():
                yield from refs(value)
        elif isinstance(node, list):
            for value in node:
                yield from refs(value)

    # Every reference resolves inside the document (the config's sections included).
    for ref in set(refs(spec)):
        assert ref.startswith("#/components/schemas/"), ref
        assert ref.rsplit("/", 1)[1] in spec["components"]["schemas"], ref


def test_import_loads_neither_torch_nor_bpy_and_touches_nothing(tmp_path):
    data_dir = tmp_path / "never-created"
    code = (
        "import services.api.app, sys\n"
        "assert 'torch' not in sys.modules and 'bpy' not in sys.modules\n"
        "from fastapi import FastAPI\n"
        "assert isinstance(services.api.app.app, FastAPI)\n"
    )
    env = {"PATH": "/usr/bin:/bin", "FOLDWISE_DATA_DIR": str(data_dir), "FOLDWISE_BROKER_URL": "redis://127.0.0.1:1/0"}
    result = subprocess.run([sys.executable, "-c", code], cwd=REPO, env=env, capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    # Building the module-level app connects to nothing: no database file appears.
    assert not data_dir.exists()
