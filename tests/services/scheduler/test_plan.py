"""``plan`` is a pure function of a snapshot: the decisions for hand-made states."""

from collections import Counter
from datetime import timedelta

from db.models import ExperimentStatus, ModelStatus, RenderStatus, StageStatus
from services.scheduler.plan import (
    CloseStage,
    CreateModel,
    EnqueueRender,
    EnqueueTraining,
    Fail,
    Finish,
    OpenStage,
    SampleTraining,
    Start,
    plan,
)
from services.scheduler.snapshot import StageView
from tests.services.scheduler.plans import NOW, RENDERED, model, snapshot


def test_a_new_experiment_starts():
    assert plan(snapshot(status=ExperimentStatus.pending)) == [Start()]


def test_ended_experiments_are_left_alone():
    for status in (ExperimentStatus.finished, ExperimentStatus.failed, ExperimentStatus.cancelled):
        assert plan(snapshot(status=status, pending=[1, 2])) == []


def test_first_increment_is_sampled_with_the_next_stage_prefetched():
    decisions = plan(snapshot())
    assert SampleTraining(10, 1) in decisions and SampleTraining(10, 2) in decisions
    assert SampleTraining(11, 1) in decisions
    assert not any(isinstance(d, CreateModel) for d in decisions)


def test_training_waits_for_every_image_of_the_increment_and_the_test_set():
    counts = {("train", 10, 1): Counter({RenderStatus.rendered: 3, RenderStatus.queued: 1})}
    assert not any(isinstance(d, CreateModel) for d in plan(snapshot(counts=counts)))
    counts = {("train", 10, 1): Counter({RenderStatus.rendered: 3, RenderStatus.failed: 1})}
    assert CreateModel(10, 1, None) in plan(snapshot(counts=counts))
    busy_test = {("test", None, None): Counter({RenderStatus.rendered: 3, RenderStatus.pending: 1})}
    decisions = plan(snapshot(counts={**counts, **busy_test}, pending=[99]))
    assert EnqueueRender((99,)) in decisions and not any(isinstance(d, CreateModel) for d in decisions)


def test_the_next_increment_starts_from_the_last_model():
    counts = {("train", 10, 2): RENDERED}
    assert CreateModel(10, 2, 1) in plan(snapshot(models=[model(1, 1, score=0.2)], counts=counts))


def test_plateau_closes_the_stage_with_the_best_model():
    models = [model(1, 1, score=0.50), model(2, 2, score=0.52)]
    assert plan(snapshot(models=models)) == [CloseStage(10, "plateau", 2)]


def test_the_next_stage_opens_from_the_previous_best():
    stages = (
        StageView(10, 0, "fb", "easy", StageStatus.done, None, 7),
        StageView(11, 1, "fb", "hard", StageStatus.pending, None, None),
    )
    assert plan(snapshot(stages=stages)) == [OpenStage(11, 7)]


def test_every_stage_done_finishes_with_the_last_best():
    stages = tuple(
        StageView(10 + i, i, "fb", d, StageStatus.done, None, 20 + i) for i, d in enumerate(["easy", "hard"])
    )
    assert plan(snapshot(stages=stages)) == [Finish(21)]


def test_a_stale_training_message_is_sent_again_and_a_fresh_one_is_not():
    stale = [model(1, 1, status=ModelStatus.queued, enqueued=NOW - timedelta(hours=2))]
    assert EnqueueTraining(1, requeue=True) in plan(snapshot(models=stale))
    fresh = [model(1, 1, status=ModelStatus.queued, enqueued=NOW - timedelta(minutes=5))]
    assert not any(isinstance(d, EnqueueTraining) for d in plan(snapshot(models=fresh)))
    undecided = [model(1, 1, status=ModelStatus.pending)]
    assert EnqueueTraining(1) in plan(snapshot(models=undecided))


def test_stale_renders_are_sent_again():
    assert EnqueueRender((5, 6), requeue=True) in plan(snapshot(stale=[5, 6]))


def test_failures_fail_the_experiment_with_a_reason():
    failed_test = {("test", None, None): Counter({RenderStatus.failed: 4})}
    (decision,) = [d for d in plan(snapshot(counts=failed_test)) if isinstance(d, Fail)]
    assert "standard test set" in decision.reason
    all_rejected = {("train", 10, 1): Counter({RenderStatus.failed: 4})}
    (decision,) = [d for d in plan(snapshot(counts=all_rejected)) if isinstance(d, Fail)]
    assert "increment 1" in decision.reason and "rejected" in decision.reason
    broken = [model(1, 1, status=ModelStatus.failed, error="TrainingDiverged: NaN")]
    (decision,) = [d for d in plan(snapshot(models=broken)) if isinstance(d, Fail)]
    assert "TrainingDiverged" in decision.reason


def test_a_stage_without_a_finite_score_fails_at_the_cap():
    models = [model(i, i, score=None) for i in (1, 2, 3)]
    (decision,) = plan(snapshot(models=models))
    assert isinstance(decision, Fail) and "without a single finite mAP" in decision.reason


def test_plan_is_deterministic():
    state = snapshot(models=[model(1, 1, score=0.2)], counts={("train", 10, 2): RENDERED}, pending=[3, 4])
    assert plan(state) == plan(state)
