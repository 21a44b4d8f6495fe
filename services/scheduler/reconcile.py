"""One reconcile step: read an experiment's state, decide what happens next, do it.

``plan`` is a pure function of a :class:`Snapshot` of the database, so a scheduler killed at
any point and restarted makes the same decisions from the same rows, and the same function
drives eager tests. ``apply`` writes the decisions in the transaction that read the
snapshot (the experiment row is locked on PostgreSQL, so two schedulers never decide for
the same experiment at once) and returns the tasks to send once it has committed.

Task messages are sent after the commit and marked as sent afterwards (at least once): a
crash in between re-sends them on restart, which idempotent tasks absorb.
"""

from __future__ import annotations

import logging
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from datetime import datetime, timedelta

from sqlalchemy import func, select, update
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
    StageEndReason,
    StageStatus,
    utcnow,
)
from db.session import session_scope
from foldwise.conditions import load_condition_table
from foldwise.config import ExperimentConfig
from foldwise.seeds import derive_seed
from foldwise.settings import get_settings
from foldwise.theta import CANONICAL
from services.scheduler.broker_view import Held
from services.scheduler.stopping import best_index, stopping_rule

log = logging.getLogger(__name__)

_OPEN = (RenderStatus.pending, RenderStatus.queued)


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
    score: float | None  # mAP (paper protocol); None when not evaluated or not finite
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
    test_open = sum(test[status] for status in _OPEN)
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
        elif sum(counts[status] for status in _OPEN) == 0 and test_open == 0:
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


# ---------------------------------------------------------------------------------------
# Reading the snapshot and applying decisions.


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
    model_rows = session.execute(
        select(Model, Evaluation.map)
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
        config=config or ExperimentConfig.model_validate(experiment.config),
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


# The hard time limit follows the soft one by this much: time to record the failure.
HARD_LIMIT_GRACE_S = 60.0


@dataclass(frozen=True)
class Send:
    """A task message to send once the transaction that decided it has committed."""

    kind: str  # "render" | "train"
    ids: tuple[int, ...]
    soft_time_limit_s: float | None = None  # None: the worker's defaults (no limit)


def _assets(config: ExperimentConfig):
    """The names θ may carry: listed from the asset folders, no image decoded."""
    from foldwise.assets import asset_names

    return asset_names(config.assets)


def _sample(config: ExperimentConfig, condition: str, difficulty: str, n: int, seed: int) -> list[dict]:
    from foldwise.sampling import generate_parameters
    from foldwise.theta import CANONICAL

    if difficulty == CANONICAL:
        # The canonical baseline's stage: a canonical θ varies no condition, so any condition of
        # the table draws the same images; its first keeps θ.condition one the table knows.
        condition = load_condition_table().codes[0]
    thetas = generate_parameters(
        condition,
        difficulty,
        n,
        seed,
        image_size=config.render.image_size,
        assets=_assets(config),
        smooth_steps=config.render.smooth_steps,
        mixed=config.mixed_draw(),
    )
    return [theta.to_dict() for theta in thetas]


def _condition_index(table, condition: str) -> int:
    """A stable index for seeding: the table's order; the mixed stage a number of its own."""
    from foldwise.theta import MIXED

    return 1000 if condition == MIXED else table.codes.index(condition)


def apply(
    session: Session, experiment: Experiment, decisions: Sequence[Decision], config: ExperimentConfig
) -> list[Send]:
    """Write the decisions in the caller's transaction; returns the tasks to send after it commits."""
    sends: list[Send] = []
    table = load_condition_table()
    stages = {st.id: st for st in session.scalars(select(Stage).where(Stage.experiment_id == experiment.id))}
    now = utcnow()
    for decision in decisions:
        match decision:
            case Start():
                experiment.classes = list(_assets(config).classes)
                experiment.status = ExperimentStatus.running
                experiment.started_at = now
                for order, (condition, difficulty) in enumerate(config.stage_order()):
                    session.add(Stage(experiment=experiment, order=order, condition=condition, difficulty=difficulty))
                for condition, difficulty in config.test_pairs():
                    seed = derive_seed(
                        experiment.seed, 1, _condition_index(table, condition), table.difficulties.index(difficulty)
                    )
                    thetas = _sample(config, condition, difficulty, config.test_set.per_stage, seed)
                    session.add_all(
                        ParameterSet(
                            experiment_id=experiment.id,
                            key=f"test/{condition}/{difficulty}/{i}",
                            split=Split.test,
                            index=i,
                            condition=condition,
                            difficulty=difficulty,
                            seed=int(theta.get("seed", seed)),
                            theta=theta,
                        )
                        for i, theta in enumerate(thetas)
                    )
            case SampleTraining(stage_id, k):
                stage = stages[stage_id]
                seed = derive_seed(experiment.seed, 2, stage.order, k)
                thetas = _sample(
                    config, stage.condition, stage.difficulty, config.stage_active_learning(stage.condition).m, seed
                )
                session.add_all(
                    ParameterSet(
                        experiment_id=experiment.id,
                        key=f"train/{stage.order}/{k}/{i}",
                        split=Split.train,
                        stage_id=stage.id,
                        increment=k,
                        index=i,
                        condition=stage.condition,
                        difficulty=stage.difficulty,
                        seed=int(theta.get("seed", seed)),
                        theta=theta,
                    )
                    for i, theta in enumerate(thetas)
                )
            case EnqueueRender(ids, requeue):
                if requeue:
                    log.warning(
                        "experiment %s: sending θ %s again (nobody holds their message)", experiment.id, list(ids)
                    )
                    _release_claims(session, ParameterSet, ids)
                batch = config.render.batch_size
                for start in range(0, len(ids), batch):
                    chunk = ids[start : start + batch]
                    sends.append(Send("render", chunk, config.tasks.render_time_limit_s * len(chunk)))
            case OpenStage(stage_id, init_model_id):
                stage = stages[stage_id]
                stage.status = StageStatus.running
                stage.init_model_id = init_model_id
                stage.started_at = now
            case CreateModel(stage_id, k, parent_id):
                model = Model(
                    experiment_id=experiment.id,
                    stage_id=stage_id,
                    increment=k,
                    parent_id=parent_id,
                    detector=config.detector.family,
                    iterations=config.stage_active_learning(stages[stage_id].condition).t,
                    status=ModelStatus.pending,
                )
                session.add(model)
                session.flush()
                sends.append(Send("train", (model.id,), config.tasks.train_time_limit_s))
            case EnqueueTraining(model_id, requeue):
                if requeue:
                    log.warning(
                        "experiment %s: sending model %s again (nobody holds its message)", experiment.id, model_id
                    )
                    _release_claims(session, Model, (model_id,))
                sends.append(Send("train", (model_id,), config.tasks.train_time_limit_s))
            case CloseStage(stage_id, reason, best_model_id):
                stage = stages[stage_id]
                stage.status = StageStatus.done
                stage.end_reason = reason
                stage.best_model_id = best_model_id
                stage.finished_at = now
            case Finish(final_model_id):
                experiment.status = ExperimentStatus.finished
                experiment.final_model_id = final_model_id
                experiment.finished_at = now
                _discard_open_work(session, experiment.id)
            case Fail(reason):
                experiment.status = ExperimentStatus.failed
                experiment.error = reason
                experiment.finished_at = now
                log.error("experiment %s failed: %s", experiment.id, reason)
                _discard_open_work(session, experiment.id)
    return sends


def _release_claims(session: Session, table, ids: Sequence[int]) -> None:
    """Work sent again because nobody holds it: its old claim is released (committed before the
    new message goes out), so the new delivery takes it at once, and a worker that was only slow
    (not dead) stops renewing it. A model goes back to ``queued``: it waits for a worker again."""
    if table is Model:
        session.execute(
            update(Model)
            .where(Model.id.in_(ids), Model.status == ModelStatus.training)
            .values(status=ModelStatus.queued, task_id=None, claimed_at=None)
            .execution_options(synchronize_session=False)
        )
    else:
        session.execute(
            update(ParameterSet)
            .where(ParameterSet.id.in_(ids), ParameterSet.status.in_(_OPEN))
            .values(task_id=None, claimed_at=None)
            .execution_options(synchronize_session=False)
        )


def _discard_open_work(session: Session, experiment_id: int) -> None:
    from services.queries import discard_open_work

    session.flush()
    discarded = discard_open_work(session, experiment_id)
    if any(discarded.values()):
        log.info("experiment %s ended: discarded %s", experiment_id, discarded)


def _mark_sent(session: Session, send: Send) -> None:
    now = utcnow()
    table = ParameterSet if send.kind == "render" else Model
    session.execute(update(table).where(table.id.in_(send.ids)).values(sends=table.sends + 1))
    if send.kind == "render":
        session.execute(
            update(ParameterSet)
            .where(ParameterSet.id.in_(send.ids), ParameterSet.status.in_(_OPEN))
            .values(status=RenderStatus.queued, enqueued_at=now)
        )
    else:
        session.execute(
            update(Model)
            .where(Model.id.in_(send.ids), Model.status.in_((ModelStatus.pending, ModelStatus.queued)))
            .values(status=ModelStatus.queued, enqueued_at=now)
        )
        session.execute(
            update(Model).where(Model.id.in_(send.ids), Model.status == ModelStatus.training).values(enqueued_at=now)
        )


def _send(send: Send) -> None:
    from workers.app import RENDER_TASK, TRAIN_TASK, app

    name, args = (RENDER_TASK, [list(send.ids)]) if send.kind == "render" else (TRAIN_TASK, [send.ids[0]])
    if app.conf.task_always_eager:
        # send_task ignores task_always_eager: run the registered task in this process, its
        # module imported by name from the app's `include` list.
        app.loader.import_default_modules()
        app.tasks[name].apply(args=args, throw=True)
    elif send.soft_time_limit_s is None:
        app.send_task(name, args=args)
    else:
        app.send_task(
            name,
            args=args,
            soft_time_limit=send.soft_time_limit_s,
            time_limit=send.soft_time_limit_s + HARD_LIMIT_GRACE_S,
        )


def _not_sent_yet(decisions: list[Decision], sent: set[tuple[str, int]]) -> list[Decision]:
    """The decisions without the messages this pass already sent (one message per task per pass)."""
    kept: list[Decision] = []
    for decision in decisions:
        match decision:
            case EnqueueRender(ids, requeue):
                fresh = tuple(i for i in ids if ("render", i) not in sent)
                if fresh:
                    kept.append(EnqueueRender(fresh, requeue))
            case EnqueueTraining(model_id, _) if ("train", model_id) in sent:
                pass
            case _:
                kept.append(decision)
    return kept


def _broker_view(snapshot: Snapshot) -> Held | None:
    """Which of the quiet θ and models someone holds; None in eager mode (nothing is ever in
    flight) or where the broker cannot be seen."""
    from services.scheduler.broker_view import held_messages
    from workers.app import app

    if app.conf.task_always_eager:
        return None
    quiet_models = {m.id for m in snapshot.models if snapshot.quiet(m)}
    return held_messages(app, set(snapshot.quiet_theta_ids), quiet_models)


def _stored_config(experiment: Experiment) -> ExperimentConfig | str:
    """The experiment's stored config, or why this version does not accept it."""
    from foldwise.config import ConfigError, parse_config

    try:
        return parse_config(experiment.config)
    except ConfigError as error:
        return f"its stored config is not valid in this version of foldwise: {error}"


def reconcile_once(experiment_id: int, sent: set[tuple[str, int]] | None = None) -> list[Decision]:
    """Plan and apply one step for one experiment; returns the decisions taken.

    ``sent`` holds the ("render" | "train", id) of the messages sent earlier in this pass: they
    are not sent again, and are added to it. A step left with nothing else to do decides nothing.
    """
    with session_scope() as session:
        query = select(Experiment).where(Experiment.id == experiment_id)
        if session.get_bind().dialect.name == "postgresql":
            query = query.with_for_update(skip_locked=True)
        experiment = session.scalar(query)
        if experiment is None:
            return []
        config = _stored_config(experiment)
        if isinstance(config, str):
            # A stored config this version refuses (recorded before a bound existed) can never
            # plan: the experiment fails with the reason instead of raising on every pass.
            decisions = (
                [Fail(config)] if experiment.status in (ExperimentStatus.pending, ExperimentStatus.running) else []
            )
            if decisions:
                apply(session, experiment, decisions, None)
            return decisions
        snapshot = load_snapshot(session, experiment, config=config)
        if snapshot.needs_broker_view():
            held = _broker_view(snapshot)
            if held is not None:
                # Read again after asking: what a worker finished meanwhile is not sent again.
                snapshot = load_snapshot(session, experiment, held=held, config=config)
        decisions = plan(snapshot)
        if sent is not None:
            decisions = _not_sent_yet(decisions, sent)
        if not decisions:
            return []
        sends = apply(session, experiment, decisions, snapshot.config)
        # Counted in the decision's own transaction, before the message leaves: a scheduler
        # killed after sending could otherwise leave a task that a worker runs with no send on
        # record. Killed before sending, the row waits queued and quiet, and is sent again.
        for send in sends:
            _mark_sent(session, send)
    for send in sends:
        _send(send)
        if sent is not None:
            sent.update((send.kind, i) for i in send.ids)
    return decisions
