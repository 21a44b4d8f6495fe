"""Celery task of the train worker: one increment of Algorithm 1 (or of Algorithm 2, `kind: learnability`).

``train_increment(model_id)``: ω_k ← train_detector(S_tr, ω_in, t), then
P_k ← evaluate_predictions(detect_object(ω_k, I_te), B_te). The model row is claimed by the
delivering task id, so a duplicate message skips while a redelivery after a lost worker
takes over; the checkpoint path is derived from the model id, so a retry overwrites it.
"""

from __future__ import annotations

import functools
import logging
import math
import time
from datetime import timedelta

import numpy as np
from sqlalchemy import select, update

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
    utcnow,
)
from db.session import session_scope
from foldwise import store
from foldwise.config import ExperimentConfig, view_count
from foldwise.seeds import derive_seed
from foldwise.settings import get_settings
from foldwise.theta import CANONICAL
from workers import lease
from workers.app import TRAIN_TASK, app

log = logging.getLogger(__name__)


def _claim(model_id: int, task_id: str) -> bool:
    """Take the model for this delivery, or say another live delivery has it (its lease renewed
    within ``lease_s``)."""
    stale_before = utcnow() - timedelta(seconds=get_settings().lease_s)
    with session_scope() as session:
        model = session.get(Model, model_id, with_for_update=True)
        if model is None or model.status in (ModelStatus.evaluated, ModelStatus.failed, ModelStatus.discarded):
            return False
        experiment = session.get(Experiment, model.experiment_id)
        if experiment.status in (ExperimentStatus.cancelled, ExperimentStatus.failed):
            return False
        if (
            model.status == ModelStatus.training
            and model.task_id != task_id
            and model.claimed_at is not None
            and model.claimed_at > stale_before
        ):
            return False
        cap = ExperimentConfig.model_validate(experiment.config).tasks.max_deliveries
        if model.attempts >= cap:
            # Every earlier delivery started and never finished: killed (out of memory?) or past
            # its hard time limit. Another would do the same.
            model.status = ModelStatus.failed
            model.error = (
                f"started {model.attempts} times (tasks.max_deliveries = {cap}) without finishing: "
                "its worker was killed or it ran past its time limit each time"
            )
            return False
        model.status = ModelStatus.training
        model.task_id = task_id
        model.claimed_at = utcnow()
        model.attempts += 1
        return True


def _samples(rows):
    """Training or test samples of rendered θ rows: every target of each image (0..n)."""
    from workers.train.data import Sample

    samples = []
    for row in rows:
        targets = (
            row.objects if row.objects is not None else ([{"box": row.box, "label": row.label}] if row.box else [])
        )
        boxes = np.asarray([t["box"] for t in targets], dtype=np.float32).reshape(-1, 4)
        labels = np.asarray([t["label"] for t in targets], dtype=np.int64)
        samples.append(
            Sample(
                image_path=store.resolve(row.image_path),
                boxes=boxes,
                labels=labels,
                condition=row.condition,
                difficulty=row.difficulty,
            )
        )
    return samples


def _renew_claim(model_id: int, task_id: str) -> None:
    with session_scope() as session:
        session.execute(
            update(Model)
            .where(Model.id == model_id, Model.task_id == task_id, Model.status == ModelStatus.training)
            .values(claimed_at=utcnow())
        )


class Heartbeat(lease.Heartbeat):
    """Renews this delivery's claim on a model every ``interval_s`` while the increment runs."""

    def __init__(self, model_id: int, task_id: str, interval_s: float) -> None:
        super().__init__(f"model-{model_id}", functools.partial(_renew_claim, model_id, task_id), interval_s)


def run_increment(model_id: int, task_id: str = "direct") -> str:
    if not _claim(model_id, task_id):
        return "skipped"
    if app.conf.task_always_eager:  # one process: no other worker to take over, nothing to renew
        return _run_claimed_increment(model_id)
    with Heartbeat(model_id, task_id, get_settings().lease_s / 4):
        return _run_claimed_increment(model_id)


def loop_views(config: ExperimentConfig) -> dict[str, tuple]:
    """``detect_object``'s overrides for the loop's evaluation (``evaluation.views``): none (the
    detector's own views and texture check), or the network alone at its one trained view."""
    from workers.train.checkpoint import RCNN_FAMILIES

    if config.evaluation.views == "detector":
        return {}
    if config.detector.family not in RCNN_FAMILIES:
        return {"texture_check": False}
    return {"test_sizes": (), "test_turns": (), "texture_check": False}


def _run_claimed_increment(model_id: int) -> str:
    from workers.render.assets import load_assets
    from workers.train.checkpoint import detect_object, load_detector
    from workers.train.evaluation import detection_samples, evaluate_predictions
    from workers.train.training import train_detector

    with session_scope() as session:
        model = session.get(Model, model_id)
        stage = session.get(Stage, model.stage_id)
        experiment = session.get(Experiment, model.experiment_id)
        config = ExperimentConfig.model_validate(experiment.config)
        classes = list(experiment.classes or [])
        parent_path = None
        if model.parent_id is not None:
            parent = session.get(Model, model.parent_id)
            parent_path = store.resolve(parent.checkpoint_path)
        increments = (
            [model.increment]
            if config.stage_active_learning(stage.condition).training_set == "reset"
            else list(range(1, model.increment + 1))
        )
        train_rows = session.scalars(
            select(ParameterSet)
            .where(
                ParameterSet.stage_id == stage.id,
                ParameterSet.split == Split.train,
                ParameterSet.increment.in_(increments),
                ParameterSet.status == RenderStatus.rendered,
            )
            .order_by(ParameterSet.id)
        ).all()
        test_query = select(ParameterSet).where(
            ParameterSet.experiment_id == experiment.id,
            ParameterSet.split == Split.test,
            ParameterSet.status == RenderStatus.rendered,
        )
        if config.kind == "learnability" and stage.condition != CANONICAL:
            # Algorithm 2 scores a condition on its own test set (every difficulty of it) only;
            # the shared canonical stage (start: canonical) is scored on all of it, as Table 2.
            test_query = test_query.where(ParameterSet.condition == stage.condition)
        test_rows = session.scalars(test_query.order_by(ParameterSet.id)).all()
        test_ids = [row.id for row in test_rows]
        seed = derive_seed(experiment.seed, 7, stage.order, model.increment)
        relative = store.checkpoint_path(experiment.id, model.id)
        iterations = model.iterations  # t of this stage (a mixed stage may have its own)

    try:
        if not train_rows:
            raise RuntimeError(f"no rendered training image for stage {stage.order} increment {model.increment}")
        started = time.perf_counter()
        stats = train_detector(
            _samples(train_rows),
            init=parent_path,
            iterations=iterations,
            config=config.detector,
            classes=classes,
            out=store.resolve(relative),
            seed=seed,
            textures=load_assets(config.assets).textures(classes) if config.detector.texture_check else None,
        )
        train_seconds = time.perf_counter() - started

        started = time.perf_counter()
        detector = load_detector(store.resolve(relative))
        test_samples = _samples(test_rows)
        views = loop_views(config)
        predictions = detect_object(
            detector, [s.image_path for s in test_samples], batch_size=config.evaluation.batch_size, **views
        )
        result = evaluate_predictions(
            predictions,
            [{"boxes": s.boxes, "labels": s.labels} for s in test_samples],
            classes,
            score_threshold=config.evaluation.score_threshold,
            iou_threshold=config.evaluation.iou_threshold,
            groups=[{"condition": s.condition, "difficulty": s.difficulty} for s in test_samples],
            coco=config.evaluation.coco,
        )
        eval_seconds = time.perf_counter() - started
    except Exception as error:  # recorded, then the scheduler fails the experiment with it
        log.exception("increment of model %s failed", model_id)
        with session_scope() as session:
            model = session.get(Model, model_id)
            if model.status == ModelStatus.discarded:
                return "skipped"
            model.status = ModelStatus.failed
            model.error = f"{type(error).__name__}: {error}"
        return "failed"

    def finite_or_none(value: float) -> float | None:
        return float(value) if value is not None and math.isfinite(value) else None

    with session_scope() as session:
        model = session.get(Model, model_id)
        if model.status == ModelStatus.discarded:  # the experiment ended while it trained
            return "skipped"
        model.checkpoint_path = relative
        model.train_seconds = train_seconds
        # How many images the increment trained on: m, or every increment's so far with "grow".
        model.train_stats = {**stats.to_dict(), "training_images": len(train_rows)}
        model.trained_at = utcnow()
        model.status = ModelStatus.evaluated
        evaluation = session.scalar(select(Evaluation).where(Evaluation.model_id == model_id))
        if evaluation is None:
            evaluation = Evaluation(model_id=model_id, details={}, eval_seconds=0.0)
            session.add(evaluation)
        evaluation.map = finite_or_none(result.map)
        evaluation.map_unthresholded = finite_or_none(result.map_unthresholded)
        # With a few test images' detections, for the dashboard (θ ids: GET /experiments/{id}/images/{θ}).
        sizes = list(views.get("test_sizes", config.detector.test_sizes))
        turns = list(views.get("test_turns", config.detector.test_turns))
        checked = bool(views.get("texture_check", config.detector.texture_check))
        evaluation.details = {
            **result.to_dict(),
            "views": {
                "test_sizes": sizes,
                "test_turns": turns,
                # One view has nothing to vote with (merge_detections keeps its scores).
                "view_vote": config.detector.view_vote if view_count(sizes, turns) > 1 else None,
                "texture_check": checked,
                "texture_search": checked and config.detector.texture_search,
            },
            "test_detections": detection_samples(
                test_ids, predictions, [{"condition": s.condition, "difficulty": s.difficulty} for s in test_samples]
            ),
        }
        evaluation.eval_seconds = eval_seconds
    return "evaluated"


@app.task(name=TRAIN_TASK, bind=True)
def train_increment(self, model_id: int) -> str:
    return run_increment(model_id, task_id=self.request.id or "eager")
