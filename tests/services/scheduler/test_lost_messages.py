"""Lost messages are found from the broker's view within a lease, and sent again exactly once.

A θ or model that was sent and shows no sign of life (unclaimed past the grace, or a claim not
renewed for a lease) is looked for in the broker: a message in a queue or in a live worker is
left alone; one that nobody holds (a broker restarted empty, a whole worker killed) is re-sent."""

from __future__ import annotations

import base64
import json
from datetime import timedelta

from sqlalchemy import select, update

from db.models import Model, ModelStatus, ParameterSet, RenderStatus, utcnow
from db.session import session_scope
from services.embedded import start_experiment
from services.scheduler import broker_view, reconcile
from services.scheduler.broker_view import Held, held_messages
from services.scheduler.reconcile import reconcile_once
from tests.services.flow_helpers import config, in_flight
from workers.app import RENDER_TASK, TRAIN_TASK


def _age_queued(experiment_id: int, seconds: float, claimed: bool = False) -> list[int]:
    """Every queued θ sent ``seconds`` ago (and claimed then too, if ``claimed``); their ids."""
    then = utcnow() - timedelta(seconds=seconds)
    with session_scope() as session:
        ids = list(
            session.scalars(
                select(ParameterSet.id).where(
                    ParameterSet.experiment_id == experiment_id, ParameterSet.status == RenderStatus.queued
                )
            )
        )
        session.execute(
            update(ParameterSet)
            .where(ParameterSet.id.in_(ids))
            .values(enqueued_at=then, claimed_at=then if claimed else None, task_id="dead" if claimed else None)
        )
    return ids


def _sends(ids) -> dict[int, int]:
    with session_scope() as session:
        return dict(session.execute(select(ParameterSet.id, ParameterSet.sends).where(ParameterSet.id.in_(ids))).all())


def _resent(messages) -> list[int]:
    return sorted(i for send in messages if send.kind == "render" for i in send.ids)


def test_unclaimed_theta_nobody_holds_is_sent_again_once_and_held_ones_are_left(monkeypatch, sent):
    experiment_id = start_experiment(config())
    in_flight(experiment_id)
    queued = _age_queued(experiment_id, seconds=40)  # past the grace (30 s of the 60 s lease)
    waiting_in_queue, lost = set(queued[:3]), set(queued[3:])
    asked: list[set[int]] = []

    def view(snapshot):
        asked.append(set(snapshot.quiet_theta_ids))
        return Held(render=frozenset(waiting_in_queue), train=frozenset())

    monkeypatch.setattr(reconcile, "_broker_view", view)
    sent.clear()
    reconcile_once(experiment_id)
    assert asked == [set(queued)]
    assert _resent(sent) == sorted(lost)
    assert all(n == 2 for n in _sends(lost).values()) and all(n == 1 for n in _sends(waiting_in_queue).values())

    # Just re-sent: not quiet any more, so nothing is asked and nothing sent again.
    sent.clear()
    asked.clear()
    reconcile_once(experiment_id)
    assert _resent(sent) == [] and asked == [set(waiting_in_queue)]


def test_a_live_claim_is_left_alone_and_a_dead_one_is_sent_again_with_its_claim_released(monkeypatch, sent):
    holder: set[int] = set()
    monkeypatch.setattr(reconcile, "_broker_view", lambda snapshot: Held(frozenset(holder), frozenset()))
    experiment_id = start_experiment(config())
    in_flight(experiment_id)
    claimed = _age_queued(experiment_id, seconds=20, claimed=True)  # renewed 20 s ago: a beat missed, no more
    sent.clear()
    reconcile_once(experiment_id)
    assert _resent(sent) == []
    # Two beats (of lease/4 = 15 s) missed, but a live worker has the batch active: left alone.
    holder.update(claimed)
    _age_queued(experiment_id, seconds=31, claimed=True)
    reconcile_once(experiment_id)
    assert _resent(sent) == []
    # Its worker is gone: sent again, and the dead claim released for the next delivery.
    holder.clear()
    reconcile_once(experiment_id)
    assert _resent(sent) == sorted(claimed)
    with session_scope() as session:
        rows = session.scalars(select(ParameterSet).where(ParameterSet.id.in_(claimed))).all()
        assert {(row.task_id, row.claimed_at, row.sends) for row in rows} == {(None, None, 2)}


def test_a_training_model_whose_worker_is_gone_goes_back_to_queued_and_is_sent_again(monkeypatch, sent):
    from workers.train.tasks import _claim

    monkeypatch.setattr(reconcile, "_broker_view", lambda snapshot: Held(frozenset(), frozenset()))
    experiment_id = start_experiment(config())
    in_flight(experiment_id)
    with session_scope() as session:
        model_id = session.scalar(select(Model.id).where(Model.experiment_id == experiment_id))
    assert _claim(model_id, "dead-worker")
    with session_scope() as session:
        session.get(Model, model_id).claimed_at = utcnow() - timedelta(seconds=31)
        session.get(Model, model_id).enqueued_at = utcnow() - timedelta(seconds=31)
    sent.clear()
    reconcile_once(experiment_id)
    assert [send.ids for send in sent if send.kind == "train"] == [(model_id,)]
    with session_scope() as session:
        model = session.get(Model, model_id)
        assert (model.status, model.task_id, model.claimed_at, model.sends) == (ModelStatus.queued, None, None, 2)
    assert _claim(model_id, "next-worker")  # taken at once, 31 s after the last beat


def test_without_a_broker_view_only_the_hour_old_are_sent_again(monkeypatch, sent):
    monkeypatch.setattr(reconcile, "_broker_view", lambda snapshot: None)  # RabbitMQ, or unreachable
    experiment_id = start_experiment(config())
    in_flight(experiment_id)
    queued = _age_queued(experiment_id, seconds=40)
    sent.clear()
    reconcile_once(experiment_id)
    assert _resent(sent) == []
    _age_queued(experiment_id, seconds=3601)
    reconcile_once(experiment_id)
    assert _resent(sent) == sorted(queued)


def test_a_queued_model_nobody_holds_is_sent_again_and_a_held_one_is_not(monkeypatch, sent):
    experiment_id = start_experiment(config())
    in_flight(experiment_id)
    with session_scope() as session:
        model = session.scalar(select(Model).where(Model.experiment_id == experiment_id))
        assert model.status == ModelStatus.queued and model.sends == 1
        model.enqueued_at = utcnow() - timedelta(seconds=40)
        model_id = model.id
    trains = lambda: [send.ids[0] for send in sent if send.kind == "train"]  # noqa: E731
    monkeypatch.setattr(reconcile, "_broker_view", lambda s: Held(frozenset(), frozenset({model_id})))
    sent.clear()
    reconcile_once(experiment_id)
    assert trains() == []
    monkeypatch.setattr(reconcile, "_broker_view", lambda s: Held(frozenset(), frozenset()))
    reconcile_once(experiment_id)
    assert trains() == [model_id]
    with session_scope() as session:
        assert session.get(Model, model_id).sends == 2


def _kombu_message(task: str, args: list) -> bytes:
    body = base64.b64encode(json.dumps([args, {}, {}]).encode()).decode()
    return json.dumps(
        {"body": body, "headers": {"task": task, "id": "x"}, "properties": {"body_encoding": "base64"}}
    ).encode()


class FakeRedis:
    def __init__(self, lists):
        self.lists = lists

    def lrange(self, key, start, end):
        return self.lists.get(key, [])

    def close(self):
        pass


class FakeInspect:
    calls: list[str] = []

    def __init__(self, active, reserved):
        self._active, self._reserved = active, reserved

    def active(self):
        FakeInspect.calls.append("active")
        return self._active

    def reserved(self):
        FakeInspect.calls.append("reserved")
        return self._reserved


def test_held_messages_reads_the_queues_then_asks_the_workers_only_when_needed(monkeypatch):
    import redis

    from workers.app import app

    lists = {
        "render": [_kombu_message(RENDER_TASK, [[1, 2]]), b"not json"],
        "train\x06\x163": [_kombu_message(TRAIN_TASK, [7])],
    }
    monkeypatch.setattr(redis.Redis, "from_url", classmethod(lambda cls, url, **kw: FakeRedis(lists)))
    inspector = FakeInspect(
        active={"render-1@h": [{"name": RENDER_TASK, "args": [[3, 4]]}]},
        reserved={"train-1@h": [{"name": TRAIN_TASK, "args": "(8,)"}], "render-2@h": []},
    )
    monkeypatch.setattr(app.control, "inspect", lambda timeout: inspector)
    monkeypatch.setattr(app.conf, "broker_url", "redis://127.0.0.1:1/0")
    FakeInspect.calls = []
    # Everything asked about waits in a queue: no broadcast to the workers.
    assert held_messages(app, {1, 2}, {7}) == Held(frozenset({1, 2}), frozenset({7}))
    assert FakeInspect.calls == []
    # θ 5 is in no queue: the live workers are asked, and nobody has it.
    held = held_messages(app, {1, 5}, set())
    assert held == Held(frozenset({1, 2, 3, 4}), frozenset({7, 8}))
    assert 5 not in held.render and FakeInspect.calls == ["active", "reserved"]


def test_no_broker_view_on_rabbitmq_or_an_unreachable_redis(monkeypatch):
    from workers.app import app

    monkeypatch.setattr(app.conf, "broker_url", "amqp://guest@127.0.0.1//")
    assert held_messages(app, {1}, set()) is None
    monkeypatch.setattr(app.conf, "broker_url", "redis://127.0.0.1:1/0")  # nothing listens on port 1
    assert held_messages(app, {1}, set()) is None
    assert broker_view.INSPECT_TIMEOUT_S <= 2


def test_a_render_batch_skips_theta_another_live_delivery_holds_and_takes_over_lapsed_ones(monkeypatch, database):
    from workers.render.tasks import claim_batch

    monkeypatch.setattr(reconcile, "_send", lambda send: None)
    experiment_id = start_experiment(config())
    in_flight(experiment_id)
    with session_scope() as session:
        a, b, c = session.scalars(
            select(ParameterSet.id).where(ParameterSet.status == RenderStatus.queued).order_by(ParameterSet.id).limit(3)
        ).all()
        session.get(ParameterSet, b).task_id, session.get(ParameterSet, b).claimed_at = "live", utcnow()
        session.get(ParameterSet, c).task_id = "dead"
        session.get(ParameterSet, c).claimed_at = utcnow() - timedelta(seconds=61)
    mine, held = claim_batch([a, b, c], "mine")
    assert mine == [a, c] and held == [b]
    with session_scope() as session:
        assert {session.get(ParameterSet, i).task_id for i in (a, c)} == {"mine"}
        assert session.get(ParameterSet, b).task_id == "live"
    # The same delivery redelivered (its worker lost after the claim) takes its own θ back.
    assert claim_batch([a], "mine") == ([a], [])


def test_a_late_duplicate_of_a_rendered_batch_or_a_trained_model_does_nothing(monkeypatch, database):
    from foldwise import store
    from workers.render.tasks import render_batch
    from workers.train.tasks import _claim

    monkeypatch.setattr(reconcile, "_send", lambda send: None)
    experiment_id = start_experiment(config())
    in_flight(experiment_id)
    with session_scope() as session:
        theta = session.scalar(select(ParameterSet).where(ParameterSet.status == RenderStatus.rendered))
        theta.image_path = store.image_path(experiment_id, theta.id)
        store.atomic_write_bytes(store.resolve(theta.image_path), b"the first render")
        theta_id, before = theta.id, (theta.attempts, theta.task_id, theta.claimed_at)
        model = session.scalar(select(Model).where(Model.experiment_id == experiment_id))
        model.status, model_id = ModelStatus.evaluated, model.id
    assert render_batch.apply(args=[[theta_id]]).get() == {"skipped": 1}
    with session_scope() as session:
        row = session.get(ParameterSet, theta_id)
        assert (row.attempts, row.task_id, row.claimed_at) == before and row.status == RenderStatus.rendered
    assert store.resolve(store.image_path(experiment_id, theta_id)).read_bytes() == b"the first render"
    assert _claim(model_id, "late-duplicate") is False
    with session_scope() as session:
        assert session.get(Model, model_id).attempts == 0
