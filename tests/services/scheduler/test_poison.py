"""Poison tasks end: time limits per task kind from the config, and a delivery cap after which
the θ or model fails with its reason instead of being redelivered forever."""

from __future__ import annotations

import pytest
from celery.exceptions import SoftTimeLimitExceeded
from sqlalchemy import select

from db.models import Experiment, ExperimentStatus, Model, ModelStatus, ParameterSet, RenderStatus
from db.session import session_scope
from services.embedded import start_experiment
from services.scheduler import reconcile
from services.scheduler.reconcile import HARD_LIMIT_GRACE_S, reconcile_once
from tests.services.flow_helpers import config, in_flight
from tests.waiting import FakeClock, wait_until


@pytest.fixture
def broker(monkeypatch, database):
    """Messages as a broker would receive them: task name, arguments and options."""
    from workers.app import app, use_eager

    messages: list[tuple[str, list, dict]] = []
    previous = app.conf.task_always_eager
    use_eager(False)
    monkeypatch.setattr(app, "send_task", lambda name, args, **options: messages.append((name, args, options)))
    yield messages
    use_eager(previous)


def test_every_message_carries_the_time_limits_of_its_kind(broker):
    limits = {"render_time_limit_s": 30, "train_time_limit_s": 7200}
    experiment_id = start_experiment(config(tasks=limits))
    in_flight(experiment_id)
    renders = [(args, options) for name, args, options in broker if name == "foldwise.render_batch"]
    trains = [(args, options) for name, args, options in broker if name == "foldwise.train_increment"]
    assert renders and trains
    for (ids,), options in renders:
        assert options == {"soft_time_limit": 30 * len(ids), "time_limit": 30 * len(ids) + HARD_LIMIT_GRACE_S}
    for _, options in trains:
        assert options == {"soft_time_limit": 7200, "time_limit": 7200 + HARD_LIMIT_GRACE_S}


def test_a_model_killed_on_every_delivery_fails_after_the_cap(monkeypatch, database):
    import workers.train.tasks
    from foldwise.settings import get_settings
    from workers.train.tasks import _claim

    monkeypatch.setattr(reconcile, "_send", lambda send: None)
    monkeypatch.setenv("FOLDWISE_LEASE_S", "60")
    get_settings.cache_clear()
    clock = FakeClock()
    monkeypatch.setattr(workers.train.tasks, "utcnow", clock)  # the time claims are made and judged at
    experiment_id = start_experiment(config(tasks={"max_deliveries": 2}))
    in_flight(experiment_id)
    with session_scope() as session:
        model_id = session.scalar(select(Model.id).where(Model.experiment_id == experiment_id))
    # Both die mid-increment: each claim is left to lapse, the clock moved past the lease.
    assert _claim(model_id, "delivery-1")
    clock.advance(61)
    assert _claim(model_id, "delivery-2")
    clock.advance(61)
    assert not _claim(model_id, "delivery-3")
    with session_scope() as session:
        model = session.get(Model, model_id)
        assert model.status == ModelStatus.failed and model.attempts == 2
        assert "started 2 times (tasks.max_deliveries = 2) without finishing" in model.error
    reconcile_once(experiment_id)
    with session_scope() as session:
        experiment = session.get(Experiment, experiment_id)
        assert experiment.status == ExperimentStatus.failed and "max_deliveries" in experiment.error
    get_settings.cache_clear()


def test_a_theta_started_as_often_as_the_cap_is_not_rendered_again(monkeypatch, database):
    import workers.render.pipeline
    from workers.render.tasks import render_parameter_set

    monkeypatch.setattr(reconcile, "_send", lambda send: None)
    experiment_id = start_experiment(config(tasks={"max_deliveries": 3}))
    reconcile_once(experiment_id)
    with session_scope() as session:
        theta_id = session.scalar(select(ParameterSet.id).where(ParameterSet.experiment_id == experiment_id))
        session.get(ParameterSet, theta_id).attempts = 3

    def must_not_render(*args, **kwargs):
        raise AssertionError("rendered past the delivery cap")

    monkeypatch.setattr(workers.render.pipeline, "render_with_resample", must_not_render)
    assert render_parameter_set(theta_id) == "failed"
    with session_scope() as session:
        row = session.get(ParameterSet, theta_id)
        assert row.status == RenderStatus.failed and "tasks.max_deliveries = 3" in row.error


def test_a_batch_past_its_soft_limit_fails_that_theta_and_hands_the_rest_back(monkeypatch, database):
    import workers.render.tasks

    monkeypatch.setattr(reconcile, "_send", lambda send: None)
    experiment_id = start_experiment(config())
    reconcile_once(experiment_id)
    reconcile_once(experiment_id)  # marks the first batches queued
    with session_scope() as session:
        ids = list(session.scalars(select(ParameterSet.id).where(ParameterSet.status == RenderStatus.queued).limit(3)))
    assert len(ids) == 3
    done = []

    def slow_second(parameter_set_id):
        if parameter_set_id == ids[1]:
            raise SoftTimeLimitExceeded()
        done.append(parameter_set_id)
        return "rendered"

    monkeypatch.setattr(workers.render.tasks, "render_parameter_set", slow_second)
    outcome = workers.render.tasks.render_batch.run(ids)
    assert outcome == {"rendered": 1, "failed": 1, "returned": 1} and done == [ids[0]]
    with session_scope() as session:
        rows = {row.id: row for row in session.scalars(select(ParameterSet).where(ParameterSet.id.in_(ids)))}
    assert rows[ids[1]].status == RenderStatus.failed and "past its time limit" in rows[ids[1]].error
    assert rows[ids[2]].status == RenderStatus.pending  # the scheduler sends it again on its next pass
    with session_scope() as session:
        snapshot = reconcile.load_snapshot(session, session.get(Experiment, experiment_id))
    assert ids[2] in snapshot.pending_theta_ids


def test_a_live_worker_renews_its_lease_and_a_dead_one_lets_it_lapse(monkeypatch, database):
    """A task that runs for hours stays claimed while its worker beats; once the beats stop the
    claim lapses within one lease and the scheduler sends the model again. The time is the
    test's clock, moved on past the lease while the heartbeat's thread beats."""
    from datetime import timedelta

    import workers.train.tasks
    from foldwise.settings import get_settings
    from workers.train.tasks import Heartbeat, _claim

    monkeypatch.setattr(reconcile, "_send", lambda send: None)
    monkeypatch.setenv("FOLDWISE_LEASE_S", "60")
    get_settings.cache_clear()
    clock = FakeClock()
    monkeypatch.setattr(workers.train.tasks, "utcnow", clock)  # claims and beats
    experiment_id = start_experiment(config())
    in_flight(experiment_id)
    with session_scope() as session:
        model_id = session.scalar(select(Model.id).where(Model.experiment_id == experiment_id))
    assert _claim(model_id, "worker-a")

    def claimed_at():
        with session_scope() as session:
            return session.get(Model, model_id).claimed_at

    def snapshot_now():
        with session_scope() as session:
            return reconcile.load_snapshot(session, session.get(Experiment, experiment_id), now=clock())

    first = claimed_at()
    with Heartbeat(model_id, "worker-a", interval_s=0.02):
        for _ in range(4):  # two leases in all, longer than one: only the beats keep it
            clock.advance(30)
            wait_until(lambda: claimed_at() == clock(), message="no beat renewed the claim at the new time")
        assert claimed_at() > first
        assert not _claim(model_id, "worker-b")  # a live lease is not taken over
        assert not any(isinstance(d, reconcile.EnqueueTraining) for d in reconcile.plan(snapshot_now()))
    clock.advance(61)  # the worker died: no beat for more than a lease
    snapshot = snapshot_now()
    assert reconcile.EnqueueTraining(model_id, requeue=True) in reconcile.plan(snapshot)
    assert snapshot.lease == timedelta(seconds=60)
    assert _claim(model_id, "worker-b")  # the lapsed claim is taken over
    get_settings.cache_clear()
