"""An ended experiment leaves no row queued or running; cancel and finish never overwrite each
other; a re-sent training message is not re-sent again on every pass."""

from __future__ import annotations

import threading
from collections import Counter
from datetime import timedelta

import pytest
from sqlalchemy import select, text

from db.models import Experiment, ExperimentStatus, Model, ModelStatus, ParameterSet, RenderStatus
from db.session import session_scope
from services import queries
from services.embedded import start_experiment
from services.scheduler.plan import EnqueueTraining, Finish, plan
from services.scheduler.reconcile import apply, reconcile_once
from tests.services.flow_helpers import config, in_flight
from tests.services.scheduler.plans import NOW, model, snapshot
from tests.waiting import poll


def _statuses(experiment_id: int) -> tuple[Counter, Counter]:
    with session_scope() as session:
        thetas = Counter(
            s.value
            for s in session.scalars(select(ParameterSet.status).where(ParameterSet.experiment_id == experiment_id))
        )
        models = Counter(
            s.value for s in session.scalars(select(Model.status).where(Model.experiment_id == experiment_id))
        )
    return thetas, models


def test_cancel_discards_what_was_queued_and_workers_skip_it(sent):
    experiment_id = start_experiment(config())
    in_flight(experiment_id)
    thetas, models = _statuses(experiment_id)
    assert thetas["queued"] > 0 and models["queued"] == 1

    with session_scope() as session:
        assert queries.cancel_experiment(session, experiment_id).status == ExperimentStatus.cancelled
    thetas, models = _statuses(experiment_id)
    assert thetas["queued"] == thetas["pending"] == 0 and thetas["discarded"] > 0
    assert set(models) == {"discarded"}
    with session_scope() as session:
        summary = queries.summary(session, experiment_id)
        queued_id = session.scalar(select(ParameterSet.id).where(ParameterSet.status == RenderStatus.discarded))
        model_id = session.scalar(select(Model.id))
    assert summary["counts"]["parameter_sets"]["train"]["discarded"] > 0

    # A message that was already on its way finds its row discarded and does nothing.
    from workers.render.tasks import render_parameter_set
    from workers.train.tasks import _claim

    assert render_parameter_set(queued_id) == "skipped"
    assert _claim(model_id, "late-delivery") is False
    assert _statuses(experiment_id)[1] == Counter({"discarded": 1})


def test_finish_discards_the_renders_sampled_ahead(sent):
    experiment_id = start_experiment(config())
    in_flight(experiment_id)
    with session_scope() as session:
        experiment = session.get(Experiment, experiment_id)
        apply(session, experiment, [Finish(None)], config())
    thetas, models = _statuses(experiment_id)
    assert thetas["queued"] == thetas["pending"] == 0 and thetas["discarded"] > 0
    assert models == Counter({"discarded": 1})
    assert reconcile_once(experiment_id) == []  # nothing left to decide, nothing re-sent


def test_cancel_after_finish_keeps_finished(database):
    experiment_id = start_experiment(config())
    with session_scope() as session:
        session.get(Experiment, experiment_id).status = ExperimentStatus.finished
    with session_scope() as session:
        assert queries.cancel_experiment(session, experiment_id).status == ExperimentStatus.finished


def test_a_resent_training_message_waits_a_whole_window_before_the_next():
    # Claimed 2 h ago by a worker that died; re-sent 1 min ago: the old claim must not re-send
    # it again (it did on every pass: 4,112 messages in 60 s).
    claimed_long_ago = model(1, 1, status=ModelStatus.training, enqueued=NOW - timedelta(seconds=30))
    claimed_long_ago = claimed_long_ago.__class__(
        **{**claimed_long_ago.__dict__, "claimed_at": NOW - timedelta(hours=2)}
    )
    assert not any(isinstance(d, EnqueueTraining) for d in plan(snapshot(models=[claimed_long_ago])))
    lapsed = claimed_long_ago.__class__(**{**claimed_long_ago.__dict__, "enqueued_at": NOW - timedelta(hours=2)})
    assert EnqueueTraining(1, requeue=True) in plan(snapshot(models=[lapsed]))


@pytest.mark.parametrize("scheduler_decides", ["finish", "nothing"])
def test_cancel_waits_for_a_scheduler_holding_the_row_and_never_overwrites_finish(postgres_database, scheduler_decides):
    experiment_id = start_experiment(config())
    with session_scope() as session:
        session.get(Experiment, experiment_id).status = ExperimentStatus.running
    holding = threading.Event()
    outcome: dict = {}
    # Lock requests waiting on a lock this session holds, as PostgreSQL's lock manager has them
    # now (pg_locks is read live; pg_stat_activity would be frozen for the transaction).
    blocked_by_me = text(
        "SELECT count(*) FROM pg_locks WHERE NOT granted AND pg_backend_pid() = ANY(pg_blocking_pids(pid))"
    )

    def scheduler() -> None:
        with session_scope() as session:
            experiment = session.scalar(select(Experiment).where(Experiment.id == experiment_id).with_for_update())
            holding.set()
            # The cancel arrives while the scheduler holds the row: it is seen waiting on the lock.
            outcome["cancel_waited"] = poll(lambda: session.scalar(blocked_by_me) > 0, timeout=10)
            if scheduler_decides == "finish":
                experiment.status = ExperimentStatus.finished

    thread = threading.Thread(target=scheduler)
    thread.start()
    assert holding.wait(5)
    with session_scope() as session:
        outcome["status"] = queries.cancel_experiment(session, experiment_id).status
    thread.join()
    assert outcome["cancel_waited"], "the cancel did not wait for the row the scheduler holds"
    expected = ExperimentStatus.finished if scheduler_decides == "finish" else ExperimentStatus.cancelled
    assert outcome["status"] == expected
    with session_scope() as session:
        assert session.get(Experiment, experiment_id).status == expected
