"""What /health costs: the broker probe keeps its connection, the schema check reads one row, and a
status read hands over to a worker thread once (services/api/probes.py, services/api/deps.py)."""

from __future__ import annotations

import pytest
from sqlalchemy import text

from db.session import get_sessionmaker
from foldwise.settings import get_settings
from services.api.app import create_app
from services.api.probes import BrokerProbe, SchemaCheck
from tests.services.api.helpers import AUTH, OwnRedis, TestClient


@pytest.fixture
def own_redis():
    server = OwnRedis()
    try:
        server.start()
        yield server
    finally:
        server.stop()


def probe_of(url: str) -> BrokerProbe:
    return BrokerProbe(get_settings().model_copy(update={"broker_url": url}), timeout_s=0.5, ping_timeout_s=0.3)


def test_the_broker_probe_keeps_one_connection(database_url, own_redis):
    probe = probe_of(own_redis.url)
    before = own_redis.connections_received()
    for _ in range(5):
        assert probe.check()["status"] == "ok"
        assert probe.queue_depths(("render", "train"))["queues"] == {"render": 0, "train": 0}
    # Ten calls, one connection; the other is the second question's own.
    assert own_redis.connections_received() - before == 1 + 1


def test_the_broker_probe_follows_the_broker_down_and_up(database_url, own_redis):
    probe = probe_of(own_redis.url)
    assert probe.check()["status"] == "ok"
    own_redis.stop()
    down = probe.check()
    assert down["status"] == "error" and "refused" in down["detail"].lower()
    own_redis.start()
    assert probe.check()["status"] == "ok"
    # Restarted between two checks: the pooled connection the old server closed is replaced at
    # once, not reported as an outage.
    own_redis.stop()
    own_redis.start()
    assert probe.check()["status"] == "ok"


def test_the_schema_check_reads_the_recorded_revision(database_url, tmp_path):
    check = SchemaCheck(database_url)
    with get_sessionmaker(database_url)() as session:
        assert check.check(session) == {"status": "ok", "revision": check.head}
        session.execute(text("UPDATE alembic_version SET version_num = 'older'"))
        session.commit()
        behind = check.check(session)
    assert behind["status"] == "error" and behind["revision"] == "older" and behind["head"] == check.head
    assert "foldwise db upgrade" in behind["detail"]

    empty = f"sqlite:///{tmp_path / 'empty.db'}"
    with get_sessionmaker(empty)() as session:
        unmigrated = SchemaCheck(empty).check(session)
    assert unmigrated["status"] == "error" and unmigrated["revision"] is None


@pytest.fixture
def hand_overs(monkeypatch):
    """Every function the app hands to a worker thread (the shared pool's or an executor's), in order."""
    import asyncio.base_events

    import anyio.to_thread

    calls: list[str] = []
    run_sync = anyio.to_thread.run_sync
    run_in_executor = asyncio.base_events.BaseEventLoop.run_in_executor

    def name(function) -> str:
        return getattr(getattr(function, "func", function), "__qualname__", repr(function))

    async def counted(function, *args, **kwargs):
        calls.append(name(function))
        return await run_sync(function, *args, **kwargs)

    def counted_in_executor(loop, executor, function, *args):
        calls.append(name(function))
        return run_in_executor(loop, executor, function, *args)

    monkeypatch.setattr(anyio.to_thread, "run_sync", counted)
    monkeypatch.setattr(asyncio.base_events.BaseEventLoop, "run_in_executor", counted_in_executor)
    return calls


@pytest.mark.parametrize(
    "path", ["/health", "/experiments/{id}", "/experiments/{id}/stages", "/experiments/{id}/history"]
)
def test_a_status_read_hands_over_to_a_thread_once(database_url, seeded, hand_overs, path):
    """Each hand-over to a worker thread waits for the event loop twice (there and back): under
    load that wait, not the read, was most of a status route's latency."""
    client = TestClient(create_app(broker_timeout_s=0.5, ping_timeout_s=0.3))
    client.get("/health")  # the first request builds the engine and reads the migration head
    hand_overs.clear()
    response = client.get(path.format(id=seeded["experiment"]), headers=AUTH)
    assert response.status_code == 200
    assert hand_overs == ["health.<locals>.probe" if path == "/health" else "read_with.<locals>.run"]


def test_starting_the_api_compiles_the_status_reads_before_the_first_request(seeded, database_url):
    """The lifespan runs the status reads once on the newest experiment: the crowd that polls a
    freshly started API finds their SQL compiled instead of each compiling it at once."""
    from db.session import get_engine

    engine = get_engine(database_url)
    before = len(engine._compiled_cache)
    with TestClient(create_app(broker_timeout_s=0.5, ping_timeout_s=0.3)) as client:
        prepared = len(engine._compiled_cache)
        assert prepared > before
        for path in ("", "/stages", "/history"):
            assert client.get(f"/experiments/{seeded['finished']}{path}").status_code == 200
        assert len(engine._compiled_cache) == prepared  # nothing left to compile


def test_the_api_starts_on_a_database_that_cannot_answer(tmp_path):
    """Preparing the reads is best effort: an unreachable database is /health's to report."""
    settings = get_settings().model_copy(
        update={"database_url": f"sqlite:///{tmp_path / 'missing' / 'api.db'}", "broker_url": "memory://"}
    )
    with TestClient(create_app(settings, broker_timeout_s=0.5, ping_timeout_s=0.3)) as client:
        health = client.get("/health")
    assert health.status_code == 503 and health.json()["status"] == "error"
