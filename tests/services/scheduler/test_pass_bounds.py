"""A scheduler pass is bounded: one message per task per pass, at most MAX_STEPS_PER_PASS steps.

A lapsed claim once made every step of a pass re-send the same model (4,112 messages in 60 s)."""

from __future__ import annotations

from collections import Counter
from datetime import timedelta

from sqlalchemy import select

from db.models import Experiment, ExperimentStatus, Model, ModelStatus, utcnow
from db.session import session_scope
from foldwise.settings import get_settings
from services.embedded import start_experiment
from services.scheduler import service
from services.scheduler.plan import OpenStage
from services.scheduler.service import MAX_STEPS_PER_PASS, reconcile_until_idle
from tests.services.flow_helpers import config, in_flight


def test_a_pass_sends_each_task_at_most_once_even_when_every_step_asks_again(monkeypatch, sent):
    experiment_id = start_experiment(config())
    in_flight(experiment_id)
    with session_scope() as session:
        model = session.scalar(select(Model).where(Model.experiment_id == experiment_id))
        model.status, model.task_id = ModelStatus.training, "dead-worker"
        model.claimed_at = model.enqueued_at = utcnow() - timedelta(hours=1)
        model_id = model.id
    # A lease so short that the re-send of a step has lapsed again by the next step.
    monkeypatch.setenv("FOLDWISE_LEASE_S", "0.000001")
    get_settings.cache_clear()
    try:
        sent.clear()
        steps = reconcile_until_idle(experiment_id)
    finally:
        monkeypatch.delenv("FOLDWISE_LEASE_S")
        get_settings.cache_clear()
    per_task = Counter((send.kind, i) for send in sent for i in send.ids)
    assert per_task[("train", model_id)] == 1
    assert max(per_task.values()) == 1, per_task
    assert steps < MAX_STEPS_PER_PASS  # it stopped because nothing new was left, not at the bound


def test_a_pass_stops_after_the_step_bound(monkeypatch):
    calls: list[int] = []

    def always_more(experiment_id, sent=None):
        calls.append(experiment_id)
        return [OpenStage(1, None)]  # a decision that (through some bug) repeats forever

    monkeypatch.setattr(service, "reconcile_once", always_more)
    monkeypatch.setattr(service, "experiment_status", lambda experiment_id: None)
    assert reconcile_until_idle(7) == MAX_STEPS_PER_PASS == 50
    assert len(calls) == 50


def test_a_stored_config_this_version_refuses_fails_the_experiment_once_with_the_reason(sent):
    # Recorded before the bound on m existed: every pass raised, and the experiment stayed live.
    experiment_id = start_experiment(config())
    in_flight(experiment_id)
    with session_scope() as session:
        experiment = session.get(Experiment, experiment_id)
        experiment.config = {
            **experiment.config,
            "active_learning": {**experiment.config["active_learning"], "m": 10**9},
        }
    sent.clear()
    assert reconcile_until_idle(experiment_id) == 1
    with session_scope() as session:
        experiment = session.get(Experiment, experiment_id)
        assert experiment.status == ExperimentStatus.failed
        assert "stored config" in experiment.error and "active_learning.m" in experiment.error
        open_models = session.scalars(
            select(Model).where(
                Model.experiment_id == experiment_id, Model.status.in_([ModelStatus.queued, ModelStatus.training])
            )
        ).all()
    assert open_models == [] and sent == []  # its open work discarded, nothing sent
    assert reconcile_until_idle(experiment_id) == 0  # a failed experiment is left alone
