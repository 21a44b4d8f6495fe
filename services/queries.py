"""Reads and writes of the experiment record shared by the CLI, the API and the report.

Reads that only the API serves return its schema models (:mod:`services.api.schemas`); those
the CLI and the report share (summary, stages, history) return plain dictionaries of the same
shape.
"""

from __future__ import annotations

import logging
import re
from datetime import UTC, datetime
from typing import Any

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
    Stage,
    StageStatus,
)
from foldwise.config import ExperimentConfig
from services.api.schemas import EvaluationDetail, ExperimentListItem, ModelDetail, StageRef

log = logging.getLogger(__name__)

# Ids are 32-bit INTEGER columns: a number outside 1..MAX_ID names no row, and the databases
# raise on one instead of finding nothing (PostgreSQL past 2**31 - 1, SQLite past 2**63 - 1).
MAX_ID = 2**31 - 1
# A study name is printed in tables and stored in a text column (PostgreSQL refuses NUL): one
# line of 1 to 200 printable characters.
STUDY_NAME = re.compile(r"^[^\x00-\x1f\x7f-\x9f\u202a-\u202e\u2066-\u2069]{1,200}$")


class NotFound(LookupError):
    pass


def create_experiment(session: Session, config: ExperimentConfig, study: str | None = None) -> Experiment:
    experiment = Experiment(name=config.name, study=study, config=config.model_dump(mode="json"), seed=config.seed)
    session.add(experiment)
    session.flush()
    return experiment


def cancel_experiment(session: Session, experiment_id: int) -> Experiment:
    """Cancel a pending or running experiment; one that has ended keeps its status.

    A conditional UPDATE, not read-then-write: a scheduler finishing the experiment at the same
    moment either commits first (the WHERE no longer matches, and `finished` stands) or waits
    on the row until the cancel commits (and then plans nothing for a cancelled experiment).
    """
    get_experiment(session, experiment_id)
    cancelled = session.execute(
        update(Experiment)
        .where(
            Experiment.id == experiment_id, Experiment.status.in_((ExperimentStatus.pending, ExperimentStatus.running))
        )
        .values(status=ExperimentStatus.cancelled, finished_at=datetime.now(UTC))
        .execution_options(synchronize_session=False)
    ).rowcount
    if cancelled:
        discard_open_work(session, experiment_id)
    experiment = get_experiment(session, experiment_id)
    session.refresh(experiment)
    return experiment


def fail_experiment(session: Session, experiment_id: int, reason: str) -> bool:
    """Mark a pending or running experiment failed with ``reason`` (its process died, say); one
    that has ended keeps its status (a conditional UPDATE, as in ``cancel_experiment``).
    Returns whether it was marked."""
    failed = session.execute(
        update(Experiment)
        .where(
            Experiment.id == experiment_id, Experiment.status.in_((ExperimentStatus.pending, ExperimentStatus.running))
        )
        .values(status=ExperimentStatus.failed, error=reason, finished_at=datetime.now(UTC))
        .execution_options(synchronize_session=False)
    ).rowcount
    if failed:
        discard_open_work(session, experiment_id)
    return bool(failed)


def discard_open_work(session: Session, experiment_id: int) -> dict[str, int]:
    """An ended experiment leaves nothing queued or running: θ sampled ahead and models not yet
    trained become ``discarded`` (workers skip them if their message still arrives); the
    messages of models already sent are revoked where a broker is reachable."""
    thetas = session.execute(
        update(ParameterSet)
        .where(
            ParameterSet.experiment_id == experiment_id,
            ParameterSet.status.in_((RenderStatus.pending, RenderStatus.queued)),
        )
        .values(status=RenderStatus.discarded)
        .execution_options(synchronize_session=False)
    ).rowcount
    open_models = (ModelStatus.pending, ModelStatus.queued, ModelStatus.training)
    task_ids = list(
        session.scalars(
            select(Model.task_id).where(
                Model.experiment_id == experiment_id, Model.status.in_(open_models), Model.task_id.is_not(None)
            )
        )
    )
    models = session.execute(
        update(Model)
        .where(Model.experiment_id == experiment_id, Model.status.in_(open_models))
        .values(status=ModelStatus.discarded, error="the experiment ended before this model was trained")
        .execution_options(synchronize_session=False)
    ).rowcount
    if task_ids:
        _revoke(task_ids)
    return {"parameter_sets": thetas, "models": models}


def _revoke(task_ids: list[str]) -> None:
    """Best effort: a message that is not revoked finds its row discarded and does nothing."""
    try:
        from workers.app import app

        if not app.conf.task_always_eager:
            app.control.revoke(task_ids)
    except Exception as error:  # no broker reachable: the workers' status checks suffice
        log.warning("could not revoke %d task(s): %s", len(task_ids), error)


def get_experiment(session: Session, experiment_id: int) -> Experiment:
    experiment = session.get(Experiment, experiment_id) if 1 <= experiment_id <= MAX_ID else None
    if experiment is None:
        raise NotFound(f"experiment {experiment_id} does not exist")
    return experiment


def _iso(when: datetime | None) -> str | None:
    return when.isoformat() if when else None


def _seconds_between(start: datetime | None, end: datetime | None) -> float | None:
    if start is None:
        return None
    end = end or datetime.now(UTC)
    return (end - start).total_seconds()


def _experiment_column(session: Session, experiment_id: int, column):
    """One column of an experiment's row, read without loading the row (its config, its
    classes); NotFound if it does not exist."""
    row = (
        session.execute(select(column).where(Experiment.id == experiment_id)).first()
        if 1 <= experiment_id <= MAX_ID
        else None
    )
    if row is None:
        raise NotFound(f"experiment {experiment_id} does not exist")
    return row[0]


def history(session: Session, experiment_id: int) -> list[dict[str, Any]]:
    """P: one entry per evaluated model, in the order the scores arrived."""
    started_at = _experiment_column(session, experiment_id, Experiment.started_at)
    render_seconds = {
        (stage_id, k): seconds
        for stage_id, k, seconds in session.execute(
            select(ParameterSet.stage_id, ParameterSet.increment, func.sum(ParameterSet.render_seconds))
            .where(ParameterSet.experiment_id == experiment_id, ParameterSet.stage_id.is_not(None))
            .group_by(ParameterSet.stage_id, ParameterSet.increment)
        )
    }
    # The columns the entries show, not the rows: an evaluation's details and a model's
    # training statistics are documents of their own, decoded for nothing here.
    rows = session.execute(
        select(
            Stage.id,
            Stage.order,
            Stage.condition,
            Stage.difficulty,
            Model.increment,
            Model.id,
            Model.parent_id,
            Model.train_seconds,
            Evaluation.map,
            Evaluation.map_unthresholded,
            Evaluation.eval_seconds,
            Evaluation.created_at,
        )  # fmt: skip
        .join(Evaluation, Evaluation.model_id == Model.id)
        .join(Stage, Stage.id == Model.stage_id)
        .where(Model.experiment_id == experiment_id)
        .order_by(Evaluation.created_at, Model.id)
    ).all()
    return [
        {
            "stage": order,
            "condition": condition,
            "difficulty": difficulty,
            "k": k,
            "model_id": model_id,
            "parent_id": parent_id,
            "map": score,
            "map_unthresholded": unthresholded,
            "render_seconds": render_seconds.get((stage_id, k)),
            "train_seconds": train_seconds,
            "eval_seconds": eval_seconds,
            "wall_seconds": _seconds_between(started_at, created_at),
            "evaluated_at": _iso(created_at),
        }
        for (
            stage_id,
            order,
            condition,
            difficulty,
            k,
            model_id,
            parent_id,
            train_seconds,
            score,
            unthresholded,
            eval_seconds,
            created_at,
        ) in rows  # fmt: skip
    ]


def test_set_render_seconds(session: Session, experiment_id: int) -> float:
    total = session.scalar(
        select(func.sum(ParameterSet.render_seconds)).where(
            ParameterSet.experiment_id == experiment_id, ParameterSet.stage_id.is_(None)
        )
    )
    return float(total or 0.0)


def loop_score(experiment: Experiment) -> str:
    """The evaluation column P was read from (``evaluation.loop_score``): one key of the stored
    config, which holds every key (model_dump), read without validating the config."""
    return (experiment.config.get("evaluation") or {}).get("loop_score", "map")


def stages(session: Session, experiment_id: int) -> list[dict[str, Any]]:
    experiment = get_experiment(session, experiment_id)
    loop_score_column = loop_score(experiment)
    scores: dict[int, list[tuple[int, float | None, int]]] = {}
    p_of: dict[int, float | None] = {}  # each model's P, the score its loop read
    for stage_id, increment, model_id, score, p in session.execute(
        select(Model.stage_id, Model.increment, Model.id, Evaluation.map, getattr(Evaluation, loop_score_column))
        .join(Evaluation, Evaluation.model_id == Model.id)
        .where(Model.experiment_id == experiment_id)
        .order_by(Model.increment)
    ):
        scores.setdefault(stage_id, []).append((increment, score, model_id))
        p_of[model_id] = p
    failed_images = dict(
        session.execute(
            select(ParameterSet.stage_id, func.count())
            .where(ParameterSet.experiment_id == experiment_id, ParameterSet.status == RenderStatus.failed)
            .group_by(ParameterSet.stage_id)
        ).all()
    )
    out = []
    for stage in session.scalars(select(Stage).where(Stage.experiment_id == experiment_id).order_by(Stage.order)):
        entries = scores.get(stage.id, [])
        best = next((s for _, s, m in entries if m == stage.best_model_id), None)
        finite = [s for _, s, _ in entries if s is not None]
        out.append(
            {
                "order": stage.order,
                "condition": stage.condition,
                "difficulty": stage.difficulty,
                "status": stage.status.value,
                "end_reason": stage.end_reason.value if stage.end_reason else None,
                "increments": len(entries),
                "init_model_id": stage.init_model_id,
                "best_model_id": stage.best_model_id,
                "best_map": best if best is not None else (max(finite) if finite else None),
                # P (evaluation.loop_score) of the model the stage started from and of its best:
                # a stage that learned raised it.
                "loop_score": loop_score_column,
                "start_p": p_of.get(stage.init_model_id) if stage.init_model_id is not None else None,
                "best_p": p_of.get(stage.best_model_id)
                if stage.best_model_id is not None
                else max((p_of[m] for _, _, m in entries if p_of.get(m) is not None), default=None),
                "failed_images": failed_images.get(stage.id, 0),
                "started_at": _iso(stage.started_at),
                "finished_at": _iso(stage.finished_at),
                "seconds": _seconds_between(stage.started_at, stage.finished_at) if stage.started_at else None,
            }
        )
    return out


REJECTED_PREFIX = "every resample rejected; last reason: "


def failure_reason(error: str | None) -> str:
    """A failed θ's error as a reason to count: the rejection's reason, or the exception type."""
    if not error:
        return "unknown"
    if error.startswith(REJECTED_PREFIX):
        return "rejected: " + error[len(REJECTED_PREFIX) :].split(" (")[0][:80]
    return error.split(":", 1)[0][:80]


def failed_by_reason(session: Session, experiment_id: int, stage_id: int | None = None) -> dict[str, int]:
    query = select(ParameterSet.error).where(
        ParameterSet.experiment_id == experiment_id, ParameterSet.status == RenderStatus.failed
    )
    if stage_id is not None:
        query = query.where(ParameterSet.stage_id == stage_id)
    reasons: dict[str, int] = {}
    for error in session.scalars(query):
        reason = failure_reason(error)
        reasons[reason] = reasons.get(reason, 0) + 1
    return dict(sorted(reasons.items(), key=lambda item: (-item[1], item[0])))


def summary(session: Session, experiment_id: int) -> dict[str, Any]:
    experiment = get_experiment(session, experiment_id)
    theta_counts: dict[str, dict[str, int]] = {}
    for split, status, count in session.execute(
        select(ParameterSet.split, ParameterSet.status, func.count())
        .where(ParameterSet.experiment_id == experiment_id)
        .group_by(ParameterSet.split, ParameterSet.status)
    ):
        theta_counts.setdefault(split.value, {})[status.value] = count
    model_counts = {
        status.value: count
        for status, count in session.execute(
            select(Model.status, func.count()).where(Model.experiment_id == experiment_id).group_by(Model.status)
        )
    }
    # The running stage with its newest increment, and the two counts, one statement each.
    current = session.execute(
        select(
            Stage.order,
            Stage.condition,
            Stage.difficulty,
            select(func.max(Model.increment)).where(Model.stage_id == Stage.id).scalar_subquery(),
        )
        .where(Stage.experiment_id == experiment_id, Stage.status == StageStatus.running)
        .order_by(Stage.order)
        .limit(1)
    ).first()
    evaluations, stage_count = session.execute(
        select(
            select(func.count())
            .select_from(Evaluation)
            .join(Model, Model.id == Evaluation.model_id)
            .where(Model.experiment_id == experiment_id)
            .scalar_subquery(),
            select(func.count()).select_from(Stage).where(Stage.experiment_id == experiment_id).scalar_subquery(),
        )
    ).one()
    best = session.execute(
        select(Evaluation.map, Model.id)
        .join(Model, Model.id == Evaluation.model_id)
        .where(Model.experiment_id == experiment_id, Evaluation.map.is_not(None))
        .order_by(Evaluation.map.desc(), Model.id)
        .limit(1)
    ).first()
    return {
        "id": experiment.id,
        "name": experiment.name,
        "study": experiment.study,
        "status": experiment.status.value,
        "error": experiment.error,
        "seed": experiment.seed,
        "classes": experiment.classes,
        "current_stage": (
            {"order": current[0], "condition": current[1], "difficulty": current[2], "k": current[3]}
            if current
            else None
        ),
        "counts": {
            "parameter_sets": theta_counts,
            "models": model_counts,
            "evaluations": evaluations,
            "stages": stage_count,
        },
        "failed_by_reason": failed_by_reason(session, experiment_id),
        "best": {"map": best[0], "model_id": best[1]} if best else None,
        "final_model_id": experiment.final_model_id,
        "created_at": _iso(experiment.created_at),
        "started_at": _iso(experiment.started_at),
        "finished_at": _iso(experiment.finished_at),
        "elapsed_seconds": _seconds_between(experiment.started_at, experiment.finished_at),
    }


def list_experiments(session: Session) -> list[ExperimentListItem]:
    return [
        ExperimentListItem(
            id=e.id,
            name=e.name,
            study=e.study,
            status=e.status,
            created_at=_iso(e.created_at),
            finished_at=_iso(e.finished_at),
        )
        for e in session.scalars(select(Experiment).order_by(Experiment.id))
    ]


def model_detail(session: Session, model_id: int) -> ModelDetail:
    model = session.get(Model, model_id) if 1 <= model_id <= MAX_ID else None
    if model is None:
        raise NotFound(f"model {model_id} does not exist")
    stage = session.get(Stage, model.stage_id)
    evaluation = model.evaluation
    return ModelDetail(
        id=model.id,
        experiment_id=model.experiment_id,
        stage=StageRef(order=stage.order, condition=stage.condition, difficulty=stage.difficulty),
        k=model.increment,
        parent_id=model.parent_id,
        detector=model.detector,
        status=model.status,
        iterations=model.iterations,
        checkpoint_path=model.checkpoint_path,
        train_seconds=model.train_seconds,
        train_stats=model.train_stats,
        attempts=model.attempts,
        error=model.error,
        evaluation=(
            EvaluationDetail(
                map=evaluation.map,
                map_unthresholded=evaluation.map_unthresholded,
                eval_seconds=evaluation.eval_seconds,
                details=evaluation.details,
            )
            if evaluation
            else None
        ),
    )
