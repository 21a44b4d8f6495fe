"""The scheduler's decisions as a pure function of a snapshot: ``plan(snapshot)``.

A scheduler killed at any point and restarted makes the same decisions from the same rows, and
the same function drives eager tests.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

from db.models import (
    ExperimentStatus,
    ModelStatus,
    RenderStatus,
    Split,
    StageEndReason,
    StageStatus,
)
from foldwise.theta import CANONICAL
from services.scheduler.snapshot import OPEN_RENDERS, Snapshot, StageView
from services.scheduler.stopping import best_index, stopping_rule

# ---------------------------------------------------------------------------------------
# Decisions.


@dataclass(frozen=True)
class Start:
    """Fix the classes, create the stages and sample the standard test set Θ_te."""


@dataclass(frozen=True)
class SampleTraining:
    """Θ_tr ← generate_parameters(c, δ, m) for (stage, k)."""

    stage_id: int
    increment: int


@dataclass(frozen=True)
class EnqueueRender:
    ids: tuple[int, ...]
    requeue: bool = False


@dataclass(frozen=True)
class OpenStage:
    stage_id: int
    init_model_id: int | None


@dataclass(frozen=True)
class CreateModel:
    """ω_k will be trained from ω_in = parent on (stage, k)."""

    stage_id: int
    increment: int
    parent_id: int | None


@dataclass(frozen=True)
class EnqueueTraining:
    model_id: int
    requeue: bool = False


@dataclass(frozen=True)
class CloseStage:
    stage_id: int
    reason: StageEndReason
    best_model_id: int


@dataclass(frozen=True)
class Finish:
    final_model_id: int | None


@dataclass(frozen=True)
class Fail:
    reason: str


Decision = (
    Start | SampleTraining | EnqueueRender | OpenStage | CreateModel | EnqueueTraining | CloseStage | Finish | Fail
)


def plan(s: Snapshot) -> list[Decision]:
    """What must happen next for this experiment, from its state alone.

    One plan for every kind: ``learnability`` (Algorithm 2) differs from Algorithm 1 only in
    when a stage ends (after κ increments, no stopping rule) and in which model opens the next
    stage (the last of the condition's previous difficulty; at a new condition none, or with
    ``learnability.start: canonical`` the last model of the shared canonical stage trained
    first, itself a fixed number of increments). ``canonical_baseline`` (the paper's Table 2) is one stage of canonical θ that ends after its
    fixed increments, and its final model is the last one trained, not the best scored."""
    if s.status == ExperimentStatus.pending:
        return [Start()]
    if s.status != ExperimentStatus.running:
        return []

    decisions: list[Decision] = []
    if s.pending_theta_ids:
        decisions.append(EnqueueRender(s.pending_theta_ids))
    if s.stale_theta_ids:
        decisions.append(EnqueueRender(s.stale_theta_ids, requeue=True))

    test = s.test_counts()
    test_open = sum(test[status] for status in OPEN_RENDERS)
    if test_open == 0 and test[RenderStatus.rendered] == 0:
        return decisions + [Fail("no image of the standard test set could be rendered (see parameter_sets.error)")]
    lost = _lost_too_much(s)
    if lost:
        return decisions + [Fail(lost)]

    stage = next((st for st in s.stages if st.status != StageStatus.done), None)
    if stage is None:
        return decisions + [Finish(_final_model_id(s))]
    if stage.status == StageStatus.pending:
        previous = [st for st in s.stages if st.order < stage.order]
        if s.config.kind == "learnability":
            return decisions + [OpenStage(stage.id, _learnability_init(s, stage, previous[-1] if previous else None))]
        init = previous[-1].best_model_id if previous else None
        return decisions + [OpenStage(stage.id, init)]

    al = s.config.stage_active_learning(stage.condition)
    models = sorted((m for m in s.models if m.stage_id == stage.id), key=lambda m: m.increment)
    latest = models[-1] if models else None
    where = f"stage {stage.order} ({stage.condition}/{stage.difficulty})"

    def ensure_sampled(st: StageView, k: int) -> None:
        if k <= s.config.stage_increments_cap(st.condition) and not s.counts(Split.train, st.id, k):
            decisions.append(SampleTraining(st.id, k))

    if latest is not None and latest.status == ModelStatus.failed:
        return decisions + [Fail(f"model {latest.id} of {where}, increment {latest.increment}, failed: {latest.error}")]

    if latest is None or latest.status == ModelStatus.evaluated:
        scores = [m.score for m in models]
        if latest is not None:
            if s.config.kind == "learnability" and stage.condition == CANONICAL:
                # start: canonical's shared stage: a fixed length, as the canonical baseline's.
                stop = len(scores) >= s.config.learnability.canonical_increments
                reason = StageEndReason.increments
            elif s.config.kind == "learnability":
                # Algorithm 2: exactly κ increments and no stopping rule, so that every stage
                # trains as long as every other (ω_be is still recorded, for Fig. 5 and 8).
                kappa = s.config.learnability.kappa
                stop, reason = len(scores) >= kappa, StageEndReason.kappa
            elif s.config.kind == "canonical_baseline":
                # Table 2: a fixed training length, as the paper's 20,000 iterations.
                stop = len(scores) >= s.config.canonical_baseline.increments
                reason = StageEndReason.increments
            else:
                decision = stopping_rule(scores, al.M, al.N, al.tau, al.max_increments)
                stop, reason = decision.stop, StageEndReason(decision.reason) if decision.stop else None
            if stop:
                best = best_index(scores)
                if best is None:
                    return decisions + [Fail(f"{where} ended ({reason.value}) without a single finite mAP")]
                return decisions + [CloseStage(stage.id, reason, models[best].id)]
        k = latest.increment + 1 if latest else 1
        counts = s.counts(Split.train, stage.id, k)
        if not counts:
            ensure_sampled(stage, k)
        elif sum(counts[status] for status in OPEN_RENDERS) == 0 and test_open == 0:
            if counts[RenderStatus.rendered] == 0:
                return decisions + [
                    Fail(f"every training image of {where}, increment {k}, was rejected (see parameter_sets.error)")
                ]
            parent = latest.id if latest else stage.init_model_id
            decisions.append(CreateModel(stage.id, k, parent))
        # θ does not depend on the model: render increment k+1 while k trains.
        ensure_sampled(stage, k + 1)
    else:
        if latest.status == ModelStatus.pending:
            decisions.append(EnqueueTraining(latest.id))
        elif latest.status in (ModelStatus.training, ModelStatus.queued) and s.lost(latest):
            # Its worker stopped renewing the claim, or its message was lost (a broker restarted
            # empty), and nobody holds a message for it. The later of claim and re-send counts,
            # so a re-sent message waiting in the queue is not sent again.
            decisions.append(EnqueueTraining(latest.id, requeue=True))
        ensure_sampled(stage, latest.increment + 1)

    # ...and the next stage's first increment too.
    following = next((st for st in s.stages if st.order > stage.order), None)
    if following is not None:
        ensure_sampled(following, 1)
    return decisions


def _final_model_id(s: Snapshot) -> int | None:
    """The experiment's final model: the last stage's ω_be; for the canonical baseline its last
    model ω_K, the one Table 2 scores (picking the best test score would fit the test set)."""
    last = s.stages[-1] if s.stages else None
    if last is None:
        return None
    if s.config.kind == "canonical_baseline":
        return _last_evaluated_model_id(s, last)
    return last.best_model_id


def _last_evaluated_model_id(s: Snapshot, stage: StageView) -> int | None:
    trained = [m for m in s.models if m.stage_id == stage.id and m.status == ModelStatus.evaluated]
    return max(trained, key=lambda m: m.increment).id if trained else None


def _learnability_init(s: Snapshot, stage: StageView, previous: StageView | None) -> int | None:
    """ω_in of a learnability stage: the LAST model ω_κ of the condition's previous difficulty
    (Algorithm 2: ω_in ← ω_k), or, at a condition's first difficulty, the model every condition
    starts from alike (config.LearnabilityConfig says why): with ``start: initial`` none, the
    detector's initial weights; with ``start: canonical`` the LAST model of the shared canonical
    stage (which itself starts from the initial weights)."""
    if previous is not None and previous.condition == stage.condition:
        return _last_evaluated_model_id(s, previous)
    if stage.condition == CANONICAL or s.config.learnability.start != "canonical":
        return None
    canonical = next((st for st in s.stages if st.condition == CANONICAL), None)
    if canonical is None or canonical.status != StageStatus.done:
        # The plan opens stages in order, so this cannot happen; never start from a stage half trained.
        raise RuntimeError(f"learnability stage {stage.order} would open before the canonical stage is done")
    return _last_evaluated_model_id(s, canonical)


# Below this many finished renders a share says little (one failure in four is not a trend).
MIN_RENDERS_FOR_SHARE = 20


def _lost_too_much(s: Snapshot) -> str | None:
    """The reason to fail when more than render.max_failed_share of the finished renders failed."""
    done: Counter = Counter()
    for counts in s.theta_counts.values():
        done.update(counts)
    failed, finished = done[RenderStatus.failed], done[RenderStatus.failed] + done[RenderStatus.rendered]
    limit = s.config.render.max_failed_share
    if finished >= MIN_RENDERS_FOR_SHARE and failed > limit * finished:
        return (
            f"{failed} of {finished} images ({failed / finished:.0%}) failed to render, more than "
            f"render.max_failed_share = {limit:.0%}; GET /experiments/{s.experiment_id} counts them by reason"
        )
    return None
