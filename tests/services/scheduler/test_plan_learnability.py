"""``plan`` for ``kind: learnability`` (Algorithm 2): κ increments, no stopping rule, ω_in ← ω_κ;
each condition's first difficulty from the initial weights, or from the shared canonical stage's
last model (``learnability.start: canonical``)."""

from collections import Counter
from datetime import UTC, datetime, timedelta

from db.models import ExperimentStatus, ModelStatus, RenderStatus, StageEndReason, StageStatus
from foldwise.config import parse_config
from services.scheduler.plan import CloseStage, CreateModel, OpenStage, SampleTraining, plan
from services.scheduler.snapshot import ModelView, Snapshot, StageView
from tests.services.kinds import kind_config

NOW = datetime(2026, 1, 1, tzinfo=UTC)
KAPPA = 4
CONFIG = parse_config(kind_config("learnability", "l", {"kappa": KAPPA}))
RENDERED = Counter({RenderStatus.rendered: 4})


def stages(*statuses):
    keys = [("fb", "easy"), ("fb", "hard"), ("po", "easy"), ("po", "hard")]
    return tuple(
        StageView(10 + i, i, c, d, status, None, None) for i, ((c, d), status) in enumerate(zip(keys, statuses))
    )


def snapshot(stage_views, models=(), counts=None, config=CONFIG):
    return Snapshot(
        experiment_id=1, status=ExperimentStatus.running, seed=0, config=config, stages=stage_views, models=tuple(models),
        theta_counts={("test", None, None): RENDERED, **(counts or {})},
        pending_theta_ids=(), stale_theta_ids=(), now=NOW, requeue_after=timedelta(hours=1),
    )  # fmt: skip


def scored(stage_id, scores, first_id):
    return [
        ModelView(first_id + k, stage_id, k + 1, None, ModelStatus.evaluated, score, None, NOW, None)
        for k, score in enumerate(scores)
    ]


def test_a_flat_history_that_algorithm_1_would_stop_goes_on_to_kappa():
    # The paper's stopping rule (M = 3, N = 8, τ = 0.02, the defaults) ends a flat stage at k = 11.
    long = parse_config({**CONFIG.model_dump(mode="json"), "learnability": {"kappa": 14}})
    running = stages(StageStatus.running, StageStatus.pending, StageStatus.pending, StageStatus.pending)
    flat = scored(10, [0.5] * 13, first_id=1)
    counts = {("train", 10, 14): RENDERED}
    algorithm_1 = parse_config({**long.model_dump(mode="json"), "kind": "active_learning", "learnability": {}})
    assert CloseStage(10, StageEndReason.plateau, 1) in plan(snapshot(running, flat, counts, algorithm_1))
    decisions = plan(snapshot(running, flat, counts, long))
    assert not any(isinstance(d, CloseStage) for d in decisions)
    assert CreateModel(10, 14, flat[-1].id) in decisions


def test_the_stage_closes_at_kappa_with_its_best_model_recorded():
    running = stages(StageStatus.running, StageStatus.pending, StageStatus.pending, StageStatus.pending)
    models = scored(10, [0.1, 0.7, 0.3, 0.2], first_id=1)
    assert CloseStage(10, StageEndReason.kappa, 2) in plan(snapshot(running, models))


def test_nothing_is_sampled_past_kappa():
    running = stages(StageStatus.running, StageStatus.pending, StageStatus.pending, StageStatus.pending)
    models = scored(10, [0.1] * (KAPPA - 1), first_id=1) + [
        ModelView(9, 10, KAPPA, 3, ModelStatus.training, None, None, NOW, NOW)
    ]
    counts = {("train", 10, k): RENDERED for k in range(1, KAPPA + 1)}
    decisions = plan(snapshot(running, models, counts))
    assert not any(isinstance(d, SampleTraining) and d.stage_id == 10 for d in decisions)
    assert SampleTraining(11, 1) in decisions  # the next stage's first increment is prefetched


def test_the_next_difficulty_opens_from_the_last_model_not_the_best():
    views = stages(StageStatus.done, StageStatus.pending, StageStatus.pending, StageStatus.pending)
    models = scored(10, [0.1, 0.9, 0.3, 0.2], first_id=1)  # the best is model 2, the last model 4
    assert plan(snapshot(views, models)) == [OpenStage(11, 4)]


def test_the_next_condition_opens_from_the_initial_weights():
    views = stages(StageStatus.done, StageStatus.done, StageStatus.pending, StageStatus.pending)
    models = scored(10, [0.1, 0.9, 0.3, 0.2], first_id=1) + scored(11, [0.5, 0.6, 0.7, 0.8], first_id=5)
    assert plan(snapshot(views, models)) == [OpenStage(12, None)]


# learnability.start: canonical: a shared canonical stage (order 0) before every condition.
CANONICAL_INCREMENTS = 3
CANONICAL_START = parse_config(
    kind_config(
        "learnability", "l", {"kappa": KAPPA, "start": "canonical", "canonical_increments": CANONICAL_INCREMENTS}
    )
)


def canonical_stages(*statuses):
    keys = [("canonical", "canonical"), ("fb", "easy"), ("fb", "hard"), ("po", "easy"), ("po", "hard")]
    return tuple(
        StageView(20 + i, i, c, d, status, None, None) for i, ((c, d), status) in enumerate(zip(keys, statuses))
    )


def test_a_canonical_start_puts_the_canonical_stage_first_and_keeps_it_out_of_the_test_set():
    assert CANONICAL_START.stage_order() == [
        ("canonical", "canonical"), ("fb", "easy"), ("fb", "hard"), ("po", "easy"), ("po", "hard"),
    ]  # fmt: skip
    assert CANONICAL_START.test_pairs() == [("fb", "easy"), ("fb", "hard"), ("po", "easy"), ("po", "hard")]
    assert CANONICAL_START.stage_increments_cap("canonical") == CANONICAL_INCREMENTS
    assert CANONICAL_START.stage_increments_cap("fb") == KAPPA
    assert CONFIG.stage_order() == [("fb", "easy"), ("fb", "hard"), ("po", "easy"), ("po", "hard")]


def test_the_canonical_stage_opens_from_the_initial_weights():
    views = canonical_stages(*[StageStatus.pending] * 5)
    assert plan(snapshot(views, config=CANONICAL_START)) == [OpenStage(20, None)]


def test_the_canonical_stage_trains_its_own_increments_not_kappa_and_ends_with_increments():
    views = canonical_stages(StageStatus.running, *[StageStatus.pending] * 4)
    assert CANONICAL_INCREMENTS != KAPPA
    short = scored(20, [0.1, 0.2], first_id=1)
    counts = {("train", 20, 3): RENDERED}
    assert CreateModel(20, 3, short[-1].id) in plan(snapshot(views, short, counts, CANONICAL_START))
    done = scored(20, [0.1, 0.9, 0.2], first_id=1)
    assert CloseStage(20, StageEndReason.increments, 2) in plan(snapshot(views, done, config=CANONICAL_START))


def test_each_condition_opens_from_the_canonical_stages_last_model():
    canonical = scored(20, [0.1, 0.9, 0.3], first_id=1)  # the best is model 2, the last model 3
    views = canonical_stages(StageStatus.done, *[StageStatus.pending] * 4)
    assert plan(snapshot(views, canonical, config=CANONICAL_START)) == [OpenStage(21, 3)]
    # the second condition too, not from the first condition's models
    fb = scored(21, [0.2] * KAPPA, first_id=4) + scored(22, [0.4] * KAPPA, first_id=8)
    views = canonical_stages(
        StageStatus.done, StageStatus.done, StageStatus.done, StageStatus.pending, StageStatus.pending
    )
    assert plan(snapshot(views, canonical + fb, config=CANONICAL_START)) == [OpenStage(23, 3)]


def test_with_a_canonical_start_the_next_difficulty_still_opens_from_the_last_model_of_the_one_before():
    canonical = scored(20, [0.1, 0.9, 0.3], first_id=1)
    fb_easy = scored(21, [0.2, 0.8, 0.1, 0.3], first_id=4)  # the best is model 5, the last model 7
    views = canonical_stages(StageStatus.done, StageStatus.done, *[StageStatus.pending] * 3)
    assert plan(snapshot(views, canonical + fb_easy, config=CANONICAL_START)) == [OpenStage(22, 7)]


def test_the_first_increment_of_a_condition_trains_from_the_canonical_model():
    views = canonical_stages(StageStatus.done, *[StageStatus.pending] * 4)
    views = (views[0], StageView(21, 1, "fb", "easy", StageStatus.running, 3, None), *views[2:])
    canonical = scored(20, [0.1, 0.9, 0.3], first_id=1)
    counts = {("train", 21, 1): RENDERED}
    assert CreateModel(21, 1, 3) in plan(snapshot(views, canonical, counts, CANONICAL_START))


def test_with_the_initial_start_every_condition_opens_from_the_initial_weights_and_has_no_canonical_stage():
    assert CONFIG.learnability.start == "initial"
    views = stages(StageStatus.pending, StageStatus.pending, StageStatus.pending, StageStatus.pending)
    assert plan(snapshot(views)) == [OpenStage(10, None)]
    assert "canonical" not in {c for c, _ in CONFIG.stage_order()}
