"""What the scheduler's decision depends on, and nothing else: a :class:`Snapshot` of one
experiment's rows (``load_snapshot``), read in the transaction that will apply the decision."""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from datetime import datetime, timedelta

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from db.models import (
    Evaluation,
    Experiment,
    ExperimentStatus,
    Model,
    ModelStatus,
    ParameterSet,
    RenderStatus,
    Split,
    Stage,
    StageStatus,
    utcnow,
)
from foldwise.config import ExperimentConfig
from foldwise.settings import get_settings
from services.scheduler.broker_view import Held

OPEN_RENDERS = (RenderStatus.pending, RenderStatus.queued)  # sent or about to be: not rendered yet


# ---------------------------------------------------------------------------------------
# Snapshot: what the decision depends on, and nothing else.


@dataclass(frozen=True)
class StageView:
    id: int
    order: int
    condition: str
    difficulty: str
    status: StageStatus
    init_model_id: int | None
    best_model_id: int | None


@dataclass(frozen=True)
class ModelView:
    id: int
    stage_id: int
    increment: int
    parent_id: int | None
    status: ModelStatus
    score: float | None  # P (evaluation.loop_score); None when not evaluated or not finite
    error: str | None
    enqueued_at: datetime | None
    claimed_at: datetime | None


@dataclass(frozen=True)
class Snapshot:
    experiment_id: int
    status: ExperimentStatus
    seed: int
    config: ExperimentConfig
    stages: tuple[StageView, ...]
    models: tuple[ModelView, ...]
    # (split, stage_id, increment) -> status -> count
    theta_counts: dict[tuple[str, int | None, int | None], Counter]
    pending_theta_ids: tuple[int, ...]
    # Queued θ to send again: those nobody holds (see held_model_ids), or without a broker view
    # those queued longer than requeue_after.
    stale_theta_ids: tuple[int, ...]
    now: datetime
    requeue_after: timedelta
    lease: timedelta = timedelta(seconds=60)
    # Queued θ with no sign of life for a while (see _quiet): what the broker is asked about.
    quiet_theta_ids: tuple[int, ...] = ()
    # The models whose message someone holds (in a queue, or in a live worker), from the broker's
    # view; None when there is none (eager mode, RabbitMQ, broker unreachable, nothing asked).
    held_model_ids: frozenset[int] | None = None

    def counts(self, split: Split, stage_id: int | None = None, increment: int | None = None) -> Counter:
        return self.theta_counts.get((split.value, stage_id, increment), Counter())

    def test_counts(self) -> Counter:
        total: Counter = Counter()
        for (split, _, _), counts in self.theta_counts.items():
            if split == Split.test.value:
                total.update(counts)
        return total

    def stale(self, when: datetime | None) -> bool:
        return when is not None and when < self.now - self.requeue_after

    def lapsed(self, model: ModelView) -> bool:
        """A claimed model whose worker stopped renewing its lease (and that was not re-sent
        within the lease either): its worker is gone."""
        return model.claimed_at is not None and _latest(model.claimed_at, model.enqueued_at) < self.now - self.lease

    def quiet(self, model: ModelView) -> bool:
        """A sent model with no sign of life for a while: the broker is asked whether anyone holds it."""
        return model.status in (ModelStatus.queued, ModelStatus.training) and _quiet(
            model.enqueued_at, model.claimed_at, self.now, self.lease
        )

    def needs_broker_view(self) -> bool:
        return bool(self.quiet_theta_ids) or any(self.quiet(m) for m in self.models)

    def lost(self, model: ModelView) -> bool:
        """A sent model whose message nobody holds: send it again."""
        if self.held_model_ids is not None:
            return self.quiet(model) and model.id not in self.held_model_ids
        # No broker view: a lapsed claim still proves its worker gone; an unclaimed message is
        # called lost only after requeue_after (RabbitMQ redelivers what it loses itself).
        if model.status == ModelStatus.training:
            return self.lapsed(model)
        return model.status == ModelStatus.queued and self.stale(model.enqueued_at)


def load_snapshot(
    session: Session,
    experiment: Experiment,
    now: datetime | None = None,
    held: Held | None = None,
    config: ExperimentConfig | None = None,
) -> Snapshot:
    """The experiment's state; with ``held`` (the broker's view), the quiet θ and models nobody
    holds are the ones to send again. ``config``: its stored config, when the caller has read it."""
    settings = get_settings()
    now = now or utcnow()
    requeue_after = timedelta(seconds=settings.requeue_after_s)
    lease = timedelta(seconds=settings.lease_s)
    stages = tuple(
        StageView(st.id, st.order, st.condition, st.difficulty, st.status, st.init_model_id, st.best_model_id)
        for st in session.scalars(select(Stage).where(Stage.experiment_id == experiment.id).order_by(Stage.order))
    )
    if config is None:
        config = ExperimentConfig.model_validate(experiment.config)
    score_column = getattr(Evaluation, config.evaluation.loop_score)
    model_rows = session.execute(
        select(Model, score_column)
        .outerjoin(Evaluation, Evaluation.model_id == Model.id)
        .where(Model.experiment_id == experiment.id)
    ).all()
    models = tuple(
        ModelView(
            m.id,
            m.stage_id,
            m.increment,
            m.parent_id,
            m.status,
            score if m.status == ModelStatus.evaluated else None,
            m.error,
            m.enqueued_at,
            m.claimed_at,
        )
        for m, score in model_rows
    )
    theta_counts: dict[tuple[str, int | None, int | None], Counter] = {}
    for split, stage_id, increment, status, count in session.execute(
        select(ParameterSet.split, ParameterSet.stage_id, ParameterSet.increment, ParameterSet.status, func.count())
        .where(ParameterSet.experiment_id == experiment.id)
        .group_by(ParameterSet.split, ParameterSet.stage_id, ParameterSet.increment, ParameterSet.status)
    ):
        theta_counts.setdefault((split.value, stage_id, increment), Counter())[status] += count
    pending = tuple(
        session.scalars(
            select(ParameterSet.id)
            .where(ParameterSet.experiment_id == experiment.id, ParameterSet.status == RenderStatus.pending)
            .order_by(ParameterSet.id)
        )
    )
    quiet = tuple(
        theta_id
        for theta_id, enqueued_at, claimed_at in session.execute(
            select(ParameterSet.id, ParameterSet.enqueued_at, ParameterSet.claimed_at)
            .where(
                ParameterSet.experiment_id == experiment.id,
                ParameterSet.status == RenderStatus.queued,
                ParameterSet.enqueued_at < now - grace(lease),
            )
            .order_by(ParameterSet.id)
        )
        if _quiet(enqueued_at, claimed_at, now, lease)
    )
    if held is not None:
        stale = tuple(theta_id for theta_id in quiet if theta_id not in held.render)
    else:
        stale = tuple(
            session.scalars(
                select(ParameterSet.id)
                .where(
                    ParameterSet.experiment_id == experiment.id,
                    ParameterSet.status == RenderStatus.queued,
                    ParameterSet.enqueued_at < now - requeue_after,
                )
                .order_by(ParameterSet.id)
            )
        )
    return Snapshot(
        experiment_id=experiment.id,
        status=experiment.status,
        seed=experiment.seed,
        config=config,
        stages=stages,
        models=models,
        theta_counts=theta_counts,
        pending_theta_ids=pending,
        stale_theta_ids=stale,
        now=now,
        requeue_after=requeue_after,
        lease=lease,
        quiet_theta_ids=quiet,
        held_model_ids=held.train if held is not None else None,
    )


def grace(lease: timedelta) -> timedelta:
    """How long sent work may show no sign of life (not claimed since it was sent, or a claim
    that missed two beats of lease/4) before the broker is asked whether anyone holds it: half
    a lease, so that lost work is sent again well within a minute with the default lease."""
    return lease / 2


def _quiet(enqueued_at: datetime | None, claimed_at: datetime | None, now: datetime, lease: timedelta) -> bool:
    """No sign of life for the grace: neither sent nor claimed or renewed since."""
    latest = _latest(enqueued_at, claimed_at)
    return latest is not None and latest < now - grace(lease)


def _latest(*moments: datetime | None) -> datetime | None:
    known = [moment for moment in moments if moment is not None]
    return max(known) if known else None
