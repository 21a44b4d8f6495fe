"""Algorithm 1 end to end through the real scheduler, database and eager Celery transport.

Rendering and training are replaced by fakes that write the same rows the real tasks write
(with scripted mAP scores), so these tests pin down the scheduler's curriculum: stage order,
ω_in hand-over, the stopping rule, the cap, failures, restarts, and idempotent redelivery.
"""

from __future__ import annotations

import math

from sqlalchemy import func, select

from db.models import (
    Experiment,
    Model,
    ParameterSet,
    RenderStatus,
)
from db.session import session_scope
from services import queries
from services.embedded import run_to_completion, start_experiment
from services.scheduler.reconcile import reconcile_once
from tests.services.flow_helpers import Fakes, config, stage_models


def test_curriculum_runs_in_order_and_hands_the_best_model_on(fakes):
    # stage 0 plateaus at k = 3 (best at k = 2), stage 1 climbs then hits the cap.
    fakes.scores = {(0, 1): 0.2, (0, 2): 0.61, (0, 3): 0.6}
    fakes.scores.update({(1, k): 0.1 * k for k in range(1, 7)})
    experiment_id = start_experiment(config())
    assert run_to_completion(experiment_id) == "finished"

    with session_scope() as session:
        stages = queries.stages(session, experiment_id)
        experiment = session.get(Experiment, experiment_id)
        final_model_id = experiment.final_model_id
    assert [(s["condition"], s["difficulty"]) for s in stages] == [
        ("fb", "easy"), ("fb", "hard"), ("sc", "easy"), ("sc", "hard")
    ]  # fmt: skip
    assert [s["end_reason"] for s in stages] == ["plateau", "cap", "plateau", "plateau"]
    assert [s["increments"] for s in stages] == [3, 6, 3, 3]

    models = stage_models(experiment_id)
    by_stage = {}
    for order, k, model_id, parent_id, score in models:
        by_stage.setdefault(order, []).append((k, model_id, parent_id, score))
    # within a stage each increment starts from the previous model...
    for order, entries in by_stage.items():
        for (k, _, parent, _), (_, previous_id, _, _) in zip(entries[1:], entries[:-1]):
            assert parent == previous_id
    # ...and each stage starts from the previous stage's best model ω_be
    assert by_stage[0][0][2] is None
    assert by_stage[1][0][2] == by_stage[0][1][1]  # k = 2 scored best in stage 0
    assert by_stage[2][0][2] == by_stage[1][5][1]  # the last, best, of the capped stage
    assert stages[0]["best_model_id"] == by_stage[0][1][1]
    assert final_model_id == stages[-1]["best_model_id"]


def test_every_record_is_kept(fakes):
    experiment_id = start_experiment(config())
    run_to_completion(experiment_id)
    with session_scope() as session:
        summary = queries.summary(session, experiment_id)
        history = queries.history(session, experiment_id)
        test_count = session.scalar(
            select(func.count())
            .select_from(ParameterSet)
            .where(ParameterSet.experiment_id == experiment_id, ParameterSet.stage_id.is_(None))
        )
        unrendered = session.scalar(
            select(func.count()).select_from(ParameterSet).where(ParameterSet.status != RenderStatus.rendered)
        )
    assert summary["status"] == "finished"
    assert test_count == 4 * 3  # n per (c, δ) of the curriculum
    assert unrendered == 0  # prefetched θ are rendered too, never left half-done
    assert len(history) == summary["counts"]["evaluations"] == sum(summary["counts"]["models"].values())
    assert [h["k"] for h in history if h["stage"] == 0] == [1, 2, 3]
    assert all(h["wall_seconds"] >= 0 for h in history)
    assert len(fakes.trained) == len(set(fakes.trained))


def test_nan_scores_never_plateau_and_the_best_finite_model_wins(fakes):
    fakes.scores = {(0, 1): 0.5, (0, 2): math.nan, (0, 3): 0.5, (0, 4): 0.5, (0, 5): 0.5}
    experiment_id = start_experiment(config(curriculum={"conditions": ["fb"], "difficulties": ["easy"]}))
    assert run_to_completion(experiment_id) == "finished"
    with session_scope() as session:
        (stage,) = queries.stages(session, experiment_id)
    # M = 1, N = 2: the windows (P_{k-2}, P_{k-1} | P_k) hold the NaN of k = 2 up to k = 4,
    # so the flat scores plateau only at k = 5.
    assert stage["increments"] == 5 and stage["end_reason"] == "plateau"
    models = stage_models(experiment_id)
    assert stage["best_model_id"] == models[0][2]


def test_a_failed_increment_fails_the_experiment_and_keeps_the_record(fakes):
    fakes.scores = {(0, 2): "fail"}
    experiment_id = start_experiment(config())
    assert run_to_completion(experiment_id) == "failed"
    with session_scope() as session:
        info = queries.summary(session, experiment_id)
        history = queries.history(session, experiment_id)
    assert "increment 2" in info["error"] and "NaN" in info["error"]
    assert len(history) == 1  # the first increment's score is still there


def test_restart_from_any_point_repeats_nothing(fakes):
    """A scheduler that dies between passes leaves rows a new one continues from."""
    experiment_id = start_experiment(config())
    passes = 0
    while True:
        decisions = reconcile_once(experiment_id)  # a "new scheduler" every pass: no memory kept
        passes += 1
        if not decisions:
            break
    assert passes > 5
    with session_scope() as session:
        assert session.get(Experiment, experiment_id).status.value == "finished"
        models = session.scalars(select(Model)).all()
    assert all(model.attempts == 1 for model in models)
    assert len(fakes.rendered) == len(set(fakes.rendered))


def test_redelivered_tasks_change_nothing(fakes):
    from workers.render.tasks import render_batch
    from workers.train.tasks import train_increment

    experiment_id = start_experiment(config(curriculum={"conditions": ["fb"], "difficulties": ["easy"]}))
    run_to_completion(experiment_id)
    with session_scope() as session:
        theta_ids = list(session.scalars(select(ParameterSet.id)))
        model_ids = list(session.scalars(select(Model.id)))
    rendered, trained = len(fakes.rendered), len(fakes.trained)
    render_batch.apply(args=[theta_ids])
    for model_id in model_ids:
        train_increment.apply(args=[model_id])
    assert (len(fakes.rendered), len(fakes.trained)) == (rendered, trained)


def test_renders_run_ahead_of_training(fakes, monkeypatch):
    """θ for k+1 are sampled and rendered before ω_k is trained (θ does not depend on ω)."""
    import workers.render.tasks
    import workers.train.tasks

    order = []

    def render(parameter_set_id):
        order.append(("render", parameter_set_id))
        return fakes.render(parameter_set_id)

    def train(model_id, task_id="direct"):
        order.append(("train", model_id))
        return fakes.train(model_id, task_id)

    monkeypatch.setattr(workers.render.tasks, "render_parameter_set", render)
    monkeypatch.setattr(workers.train.tasks, "run_increment", train)
    experiment_id = start_experiment(config(curriculum={"conditions": ["fb"], "difficulties": ["easy"]}))
    run_to_completion(experiment_id)
    with session_scope() as session:
        k2 = set(session.scalars(select(ParameterSet.id).where(ParameterSet.increment == 2)))
    first_train = next(i for i, (kind, _) in enumerate(order) if kind == "train")
    assert k2 <= {i for kind, i in order[:first_train] if kind == "render"}


def test_a_render_that_raises_is_recorded_and_the_rest_of_the_batch_renders(database, eager, monkeypatch):
    """An unexpected error in one θ marks that θ failed with the error; the batch goes on."""
    import workers.render.tasks

    fake = Fakes()
    monkeypatch.setattr(workers.train.tasks, "run_increment", fake.train)
    real_render = fake.render

    def flaky(parameter_set_id):
        with session_scope() as session:
            key = session.get(ParameterSet, parameter_set_id).key
        if key == "train/0/1/0":
            raise OSError("disk full")
        return real_render(parameter_set_id)

    monkeypatch.setattr(workers.render.tasks, "render_parameter_set", flaky)
    experiment_id = start_experiment(config(curriculum={"conditions": ["fb"], "difficulties": ["easy"]}))
    assert run_to_completion(experiment_id) == "finished"
    with session_scope() as session:
        broken = session.scalar(select(ParameterSet).where(ParameterSet.key == "train/0/1/0"))
        others = session.scalars(select(ParameterSet).where(ParameterSet.key != "train/0/1/0")).all()
    assert broken.status == RenderStatus.failed and broken.error == "OSError: disk full"
    assert all(row.status == RenderStatus.rendered for row in others)


def test_every_render_failing_fails_the_experiment_with_the_reason(database, eager, monkeypatch):
    import workers.render.tasks

    def broken(parameter_set_id):
        raise FileNotFoundError("texture astronaut.png")

    monkeypatch.setattr(workers.render.tasks, "render_parameter_set", broken)
    experiment_id = start_experiment(config())
    assert run_to_completion(experiment_id) == "failed"
    with session_scope() as session:
        error = queries.summary(session, experiment_id)["error"]
        sample = session.scalars(select(ParameterSet)).first()
    assert "standard test set" in error and "parameter_sets.error" in error
    assert sample.error == "FileNotFoundError: texture astronaut.png"


def _failing_every(monkeypatch, fake, every: int):
    """Render with the fake, but make every n-th θ (by id) fail as a rejected render would."""
    import workers.render.tasks

    monkeypatch.setattr(workers.train.tasks, "run_increment", fake.train)

    def sometimes(parameter_set_id):
        if parameter_set_id % every == 0:
            with session_scope() as session:
                row = session.get(ParameterSet, parameter_set_id)
                row.status, row.error = RenderStatus.failed, "every resample rejected; last reason: target hidden"
            return "failed"
        return fake.render(parameter_set_id)

    monkeypatch.setattr(workers.render.tasks, "render_parameter_set", sometimes)


def test_losing_more_than_the_allowed_share_of_images_fails_the_run(database, eager, monkeypatch):
    _failing_every(monkeypatch, Fakes(), every=4)  # 25% lost
    experiment_id = start_experiment(config(render={"max_failed_share": 0.1}))
    assert run_to_completion(experiment_id) == "failed"
    with session_scope() as session:
        summary = queries.summary(session, experiment_id)
    assert "failed to render, more than render.max_failed_share = 10%" in summary["error"]
    assert summary["failed_by_reason"] == {"rejected: target hidden": summary["counts"]["parameter_sets"]["test"]["failed"]
                                           + summary["counts"]["parameter_sets"].get("train", {}).get("failed", 0)}  # fmt: skip


def test_a_run_within_the_allowed_share_finishes_and_counts_what_it_lost(database, eager, monkeypatch):
    _failing_every(monkeypatch, Fakes(), every=4)
    experiment_id = start_experiment(config(render={"max_failed_share": 0.5}))
    assert run_to_completion(experiment_id) == "finished"
    with session_scope() as session:
        summary = queries.summary(session, experiment_id)
        stages = queries.stages(session, experiment_id)
    lost = summary["failed_by_reason"]["rejected: target hidden"]
    assert lost > 0 and set(summary["failed_by_reason"]) == {"rejected: target hidden"}
    assert (
        sum(stage["failed_images"] for stage in stages) == lost - summary["counts"]["parameter_sets"]["test"]["failed"]
    )
    assert all(stage["failed_images"] >= 0 for stage in stages) and any(stage["failed_images"] for stage in stages)
