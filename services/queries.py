"""Reads and writes of the experiment record shared by the CLI, the API and the report.

Reads that only the API serves return its schema models (:mod:`services.api.schemas`); those
the CLI and the report share (summary, stages, history) return plain dictionaries of the same
shape.
"""

from __future__ import annotations

from datetime import datetime, timezone
from typing import Any

from sqlalchemy import func, select
from sqlalchemy.orm import Session

from db.models import (
    Evaluation,
    Experiment,
    ExperimentStatus,
    Model,
    ParameterSet,
    Stage,
    StageStatus,
)
from foldwise.config import ExperimentConfig
from services.api.schemas import EvaluationDetail, ExperimentListItem, ModelDetail, StageRef


class NotFound(LookupError):
    pass


def create_experiment(session: Session, config: ExperimentConfig) -> Experiment:
    experiment = Experiment(name=config.name, config=config.model_dump(mode="json"), seed=config.seed)
    session.add(experiment)
    session.flush()
    return experiment


def cancel_experiment(session: Session, experiment_id: int) -> Experiment:
    experiment = get_experiment(session, experiment_id)
    if experiment.status in (ExperimentStatus.pending, ExperimentStatus.running):
        experiment.status = ExperimentStatus.cancelled
        experiment.finished_at = datetime.now(timezone.utc)
    return experiment


def get_experiment(session: Session, experiment_id: int) -> Experiment:
    experiment = session.get(Experiment, experiment_id)
    if experiment is None:
        raise NotFound(f"experiment {experiment_id} does not exist")
    return experiment


def _iso(when: datetime | None) -> str | None:
    return when.isoformat() if when else None


def _seconds_between(start: datetime | None, end: datetime | None) -> float | None:
    if start is None:
        return None
    end = end or datetime.now(timezone.utc)
    return (end - start).total_seconds()


def history(session: Session, experiment_id: int) -> list[dict[str, Any]]:
    """P: one entry per evaluated model, in the order the scores arrived."""
    experiment = get_experiment(session, experiment_id)
    render_seconds = {
        (stage_id, k): seconds
        for stage_id, k, seconds in session.execute(
            select(ParameterSet.stage_id, ParameterSet.increment, func.sum(ParameterSet.render_seconds))
            .where(ParameterSet.experiment_id == experiment_id, ParameterSet.stage_id.is_not(None))
            .group_by(ParameterSet.stage_id, ParameterSet.increment)
        )
    }
    rows = session.execute(
        select(Model, Evaluation, Stage)
        .join(Evaluation, Evaluation.model_id == Model.id)
        .join(Stage, Stage.id == Model.stage_id)
        .where(Model.experiment_id == experiment_id)
        .order_by(Evaluation.created_at, Model.id)
    ).all()
    return [
        {
            "stage": stage.order,
            "condition": stage.condition,
            "difficulty": stage.difficulty,
            "k": model.increment,
            "model_id": model.id,
            "parent_id": model.parent_id,
            "map": evaluation.map,
            "map_unthresholded": evaluation.map_unthresholded,
            "render_seconds": render_seconds.get((stage.id, model.increment)),
            "train_seconds": model.train_seconds,
            "eval_seconds": evaluation.eval_seconds,
            "wall_seconds": _seconds_between(experiment.started_at, evaluation.created_at),
            "evaluated_at": _iso(evaluation.created_at),
        }
        for model, evaluation, stage in rows
    ]


def test_set_render_seconds(session: Session, experiment_id: int) -> float:
    total = session.scalar(
        select(func.sum(ParameterSet.render_seconds)).where(
            ParameterSet.experiment_id == experiment_id, ParameterSet.stage_id.is_(None)
        )
    )
    return float(total or 0.0)


def stages(session: Session, experiment_id: int) -> list[dict[str, Any]]:
    get_experiment(session, experiment_id)
    scores: dict[int, list[tuple[int, float | None, int]]] = {}
    for model, score in session.execute(
        select(Model, Evaluation.map)
        .join(Evaluation, Evaluation.model_id == Model.id)
        .where(Model.experiment_id == experiment_id)
        .order_by(Model.increment)
    ):
        scores.setdefault(model.stage_id, []).append((model.increment, score, model.id))
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
                "started_at": _iso(stage.started_at),
                "finished_at": _iso(stage.finished_at),
                "seconds": _seconds_between(stage.started_at, stage.finished_at) if stage.started_at else None,
            }
        )
    return out


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
    current = session.scalar(
        select(Stage)
        .where(Stage.experiment_id == experiment_id, Stage.status == StageStatus.running)
        .order_by(Stage.order)
    )
    current_k = None
    if current is not None:
        current_k = session.scalar(select(func.max(Model.increment)).where(Model.stage_id == current.id))
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
        "status": experiment.status.value,
        "error": experiment.error,
        "seed": experiment.seed,
        "classes": experiment.classes,
        "current_stage": (
            {"order": current.order, "condition": current.condition, "difficulty": current.difficulty, "k": current_k}
            if current
            else None
        ),
        "counts": {
            "parameter_sets": theta_counts,
            "models": model_counts,
            "evaluations": session.scalar(
                select(func.count())
                .select_from(Evaluation)
                .join(Model, Model.id == Evaluation.model_id)
                .where(Model.experiment_id == experiment_id)
            ),
            "stages": session.scalar(select(func.count()).select_from(Stage).where(Stage.experiment_id == experiment_id)),
        },
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
            status=e.status,
            created_at=_iso(e.created_at),
            finished_at=_iso(e.finished_at),
        )
        for e in session.scalars(select(Experiment).order_by(Experiment.id))
    ]


def model_detail(session: Session, model_id: int) -> ModelDetail:
    model = session.get(Model, model_id)
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
