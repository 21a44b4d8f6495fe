"""One reconcile step: read an experiment's state (``snapshot.load_snapshot``), decide what
happens next (``plan.plan``, a pure function of the snapshot), do it.

``apply`` writes the decisions in the transaction that read the
snapshot (the experiment row is locked on PostgreSQL, so two schedulers never decide for
the same experiment at once) and returns the tasks to send once it has committed.

Task messages are sent after the commit and marked as sent afterwards (at least once): a
crash in between re-sends them on restart, which idempotent tasks absorb.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from dataclasses import dataclass

from sqlalchemy import select, update
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
from db.session import session_scope
from foldwise.conditions import load_condition_table
from foldwise.config import ExperimentConfig
from foldwise.seeds import derive_seed
from foldwise.theta import CANONICAL, MIXED
from services.scheduler.broker_view import Held
from services.scheduler.plan import (
    CloseStage,
    CreateModel,
    Decision,
    EnqueueRender,
    EnqueueTraining,
    Fail,
    Finish,
    OpenStage,
    SampleTraining,
    Start,
    plan,
)
from services.scheduler.snapshot import OPEN_RENDERS, Snapshot, load_snapshot

log = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------------
# Applying decisions.


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


def _sample(config: ExperimentConfig, condition: str, difficulty: str, n: int, seed: int, failure=()) -> list[dict]:
    """n θ as records; ``failure``: (condition, difficulty, 1 − AP) cells a mixed draw follows."""
    from dataclasses import replace

    from foldwise.sampling import generate_parameters

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
        mixed=replace(config.mixed_draw(), failure=tuple(failure)),
    )
    return [theta.to_dict() for theta in thetas]


def _latest_failure(session: Session, experiment: Experiment) -> tuple[int | None, dict[tuple[str, str], float]]:
    """The experiment's latest scored model and its failure (1 − unthresholded AP) on each
    (condition, difficulty) of the standard test set; (None, {}) before any model is scored."""
    latest = session.execute(
        select(Model.id, Evaluation.details)
        .join(Evaluation, Evaluation.model_id == Model.id)
        .where(Model.experiment_id == experiment.id, Model.status == ModelStatus.evaluated)
        .order_by(Model.trained_at.desc(), Model.id.desc())
        .limit(1)
    ).first()
    if latest is None:
        return None, {}
    cells = (latest.details or {}).get("breakdown", {}).get("condition/difficulty", {})
    failure = {}
    for key, group in cells.items():
        condition, _, difficulty = key.partition("/")
        ap = group.get("map_unthresholded") if isinstance(group, dict) else None
        if ap is not None and condition != MIXED:
            failure[condition, difficulty] = 1.0 - float(ap)
    return latest.id, failure


def _drawn_for(thetas: Sequence[dict], model_id: int | None, failure: dict, config: ExperimentConfig) -> list[dict]:
    """Why each mixed training θ of one draw was drawn (ParameterSet.drawn_for)."""
    from foldwise.sampling import cell_probabilities

    if model_id is None:
        return [{"sampling": "uniform", "why": "no model scored yet"} for _ in thetas]
    table = load_condition_table()
    mixed = config.curriculum.mixed
    pool = list(mixed.draw_from or table.codes)
    by_difficulty = {}  # the cells' probabilities depend on θ only through its difficulty
    reasons = []
    for theta in thetas:
        difficulty = theta["difficulty"]
        if difficulty not in by_difficulty:
            levels = table.difficulties[: table.difficulties.index(difficulty) + 1]
            by_difficulty[difficulty] = cell_probabilities(pool, levels, failure, mixed.failure_share)
        probabilities = by_difficulty[difficulty]
        cells = {}
        for component in theta.get("components") or ():
            cell = (component["condition"], component["difficulty"])
            ap = 1.0 - failure[cell] if cell in failure else None
            cells["/".join(cell)] = {"ap": None if ap is None else round(ap, 4), "p": round(probabilities[cell], 5)}
        reasons.append({"sampling": "failure", "model_id": model_id, "share": mixed.failure_share, "cells": cells})
    return reasons


def _condition_index(table, condition: str) -> int:
    """A stable index for seeding: the table's order; the mixed stage a number of its own."""
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
                m = config.stage_active_learning(stage.condition).m
                if stage.condition == MIXED and config.curriculum.mixed.sampling == "failure":
                    # Where the latest scored model fails (θ is drawn while the model before
                    # trains: the increment follows the last score there is, not waiting for one).
                    source, failure = _latest_failure(session, experiment)
                    cells = tuple((c, d, value) for (c, d), value in failure.items())
                    thetas = _sample(config, stage.condition, stage.difficulty, m, seed, cells)
                    reasons = _drawn_for(thetas, source, failure, config)
                else:
                    thetas = _sample(config, stage.condition, stage.difficulty, m, seed)
                    reasons = [{"sampling": "uniform"} if stage.condition == MIXED else None for _ in thetas]
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
                        drawn_for=reason,
                    )
                    for i, (theta, reason) in enumerate(zip(thetas, reasons))
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
            .where(ParameterSet.id.in_(ids), ParameterSet.status.in_(OPEN_RENDERS))
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
            .where(ParameterSet.id.in_(send.ids), ParameterSet.status.in_(OPEN_RENDERS))
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
