"""``plan`` for ``kind: canonical_baseline`` (the paper's Table 2): one canonical stage, a fixed
number of increments with no stopping rule, and the LAST model as the experiment's final one."""

from collections import Counter
from datetime import UTC, datetime, timedelta

from sqlalchemy import select

from db.models import (
    ExperimentStatus,
    ModelStatus,
    ParameterSet,
    RenderStatus,
    Split,
    Stage,
    StageEndReason,
    StageStatus,
)
from db.session import session_scope
from foldwise.config import parse_config
from services.scheduler.plan import CloseStage, CreateModel, Finish, SampleTraining, plan
from services.scheduler.snapshot import ModelView, Snapshot, StageView
from tests.services.kinds import kind_config

NOW = datetime(2026, 1, 1, tzinfo=UTC)
INCREMENTS = 4
CONFIG = parse_config(kind_config("canonical_baseline", "b", {"increments": INCREMENTS}))
RENDERED = Counter({RenderStatus.rendered: 4})
STAGE = 10


def snapshot(status, models=(), counts=None, config=CONFIG):
    return Snapshot(
        experiment_id=1, status=ExperimentStatus.running, seed=0, config=config,
        stages=(StageView(STAGE, 0, "canonical", "canonical", status, None, None),), models=tuple(models),
        theta_counts={("test", None, None): RENDERED, **(counts or {})},
        pending_theta_ids=(), stale_theta_ids=(), now=NOW, requeue_after=timedelta(hours=1),
    )  # fmt: skip


def scored(scores, first_id=1):
    return [
        ModelView(first_id + k, STAGE, k + 1, None, ModelStatus.evaluated, score, None, NOW, None)
        for k, score in enumerate(scores)
    ]


def test_a_flat_history_that_algorithm_1_would_stop_trains_on_to_the_fixed_increments():
    # The paper's stopping rule (M = 3, N = 8, τ = 0.02, the defaults) ends a flat stage at k = 11.
    long = parse_config({**CONFIG.model_dump(mode="json"), "canonical_baseline": {"increments": 14}})
    flat, counts = scored([0.5] * 13), {("train", STAGE, 14): RENDERED}
    algorithm_1 = parse_config({**long.model_dump(mode="json"), "kind": "active_learning", "canonical_baseline": {}})
    assert CloseStage(STAGE, StageEndReason.plateau, 1) in plan(
        snapshot(StageStatus.running, flat, counts, algorithm_1)
    )
    decisions = plan(snapshot(StageStatus.running, flat, counts, long))
    assert not any(isinstance(d, CloseStage) for d in decisions)
    assert CreateModel(STAGE, 14, flat[-1].id) in decisions


def test_the_stage_closes_after_its_increments_and_nothing_is_sampled_past_them():
    models = scored([0.1, 0.7, 0.3])
    counts = {("train", STAGE, k): RENDERED for k in range(1, INCREMENTS + 1)}
    training = models + [ModelView(9, STAGE, INCREMENTS, 3, ModelStatus.training, None, None, NOW, NOW)]
    assert not any(isinstance(d, SampleTraining) for d in plan(snapshot(StageStatus.running, training, counts)))
    assert plan(snapshot(StageStatus.running, scored([0.1, 0.7, 0.3, 0.2]))) == [
        CloseStage(STAGE, StageEndReason.increments, 2)  # ω_be is recorded, as for every stage
    ]


def test_the_final_model_is_the_last_trained_not_the_best_scored():
    # Table 2 scores the model at the end of its fixed training; picking it by test score would fit the test set.
    assert plan(snapshot(StageStatus.done, scored([0.1, 0.9, 0.3, 0.2]))) == [Finish(4)]


def test_start_records_one_canonical_stage_canonical_training_images_and_the_curriculum_test_set(database, sent):
    from services import queries
    from services.scheduler.reconcile import reconcile_once

    small = parse_config({
        **CONFIG.model_dump(mode="json"), "assets": {"n_objects": 2}, "render": {"image_size": 64},
        "test_set": {"per_stage": 2}, "active_learning": {"m": 3, "t": 1},
    })  # fmt: skip
    with session_scope() as session:
        experiment_id = queries.create_experiment(session, small).id
    reconcile_once(experiment_id)  # Start
    reconcile_once(experiment_id)  # open the stage
    reconcile_once(experiment_id)  # sample its first increment, and the next one ahead
    with session_scope() as session:
        (stage,) = session.scalars(select(Stage)).all()
        assert (stage.condition, stage.difficulty, stage.status) == ("canonical", "canonical", StageStatus.running)
        assert stage.init_model_id is None  # the detector's initial weights
        rows = session.scalars(select(ParameterSet)).all()
        test = Counter((r.condition, r.difficulty) for r in rows if r.split == Split.test)
        assert test == {("fb", "easy"): 2, ("fb", "hard"): 2, ("po", "easy"): 2, ("po", "hard"): 2}
        train = [r for r in rows if r.split == Split.train]
        assert {r.increment for r in train} == {1, 2} and len(train) == 6
        # every training image is canonical: no condition varies from its canonical value
        assert {(r.condition, r.difficulty, r.theta["difficulty"]) for r in train} == {
            ("canonical", "canonical", "canonical")
        }
        assert all(r.theta["focus_blur_pct"] == 0 and r.theta["visible_fraction"] == 1 for r in train)
