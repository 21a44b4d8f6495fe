"""Celery task of the train worker: one increment of Algorithm 1 (or of Algorithm 2, `kind: learnability`).

``train_increment(model_id)``: ω_k ← train_detector(S_tr, ω_in, t), then
P_k ← evaluate_predictions(detect_object(ω_k, I_te), B_te). The model row is claimed by the
delivering task id, so a duplicate message skips while a redelivery after a lost worker
takes over; the checkpoint path is derived from the model id, so a retry overwrites it.

A trained increment whose checkpoint the artifact volume has no room for (full, over quota,
past the file size limit) is not lost: the weights wait in memory, the claim kept renewed, the
model row's ``error`` says what was refused, and the write is tried again every NO_ROOM_RETRY_S
until there is room (then the error is cleared and the increment goes on), for NO_ROOM_WAIT_S
at most; then the model fails with the error.
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

# A checkpoint write refused for want of room is tried again this often, for this long at most.
NO_ROOM_RETRY_S = 5.0
NO_ROOM_WAIT_S = 1800.0


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


class WaitForRoom:
    """``train_detector``'s ``on_no_room`` in the worker: each refused checkpoint write is
    recorded on the model row (``error``, which ``GET /models/{id}`` shows) and logged, then it
    waits ``retry_s`` and has the write tried again. It gives up (raises) once the model is no
    longer this delivery's (the experiment ended, another delivery took over) or after
    ``give_up_s`` of refusals."""

    def __init__(
        self,
        model_id: int,
        task_id: str,
        retry_s: float = NO_ROOM_RETRY_S,
        give_up_s: float = NO_ROOM_WAIT_S,
        sleep=time.sleep,
    ) -> None:
        self.model_id, self.task_id = model_id, task_id
        self.retry_s, self.give_up_s, self.sleep = retry_s, give_up_s, sleep
        self.refusals = 0
        self.first_refused: float | None = None
        self.last_error: str | None = None

    def __call__(self, error: OSError) -> None:
        now = time.monotonic()
        if self.first_refused is None:
            self.first_refused = now
        self.refusals += 1
        self.last_error = str(error)
        waited = now - self.first_refused
        if waited >= self.give_up_s:
            raise type(error)(
                error.errno,
                f"{error.strerror}; {self.refusals} writes refused over {waited:.0f} s, given up",
            ) from error
        log.warning("model %s: checkpoint write refused (%s); trying again in %g s", self.model_id, error, self.retry_s)
        with session_scope() as session:
            model = session.get(Model, self.model_id)
            ours = model is not None and model.status == ModelStatus.training and model.task_id == self.task_id
            if ours:
                times = "once" if self.refusals == 1 else f"{self.refusals} times"
                model.error = (
                    f"waiting for room to write the checkpoint: {error} "
                    f"(refused {times}; tried again every {self.retry_s:g} s)"
                )
        if not ours:
            raise error
        self.sleep(self.retry_s)

    def record(self) -> dict | None:
        """For the model's train_stats: the refused writes, when there were any."""
        if not self.refusals:
            return None
        return {"refused": self.refusals, "last_error": self.last_error}


def run_increment(model_id: int, task_id: str = "direct") -> str:
    if not _claim(model_id, task_id):
        return "skipped"
    if app.conf.task_always_eager:  # one process: no other worker to take over, nothing to renew
        return _run_claimed_increment(model_id, task_id)
    with Heartbeat(model_id, task_id, get_settings().lease_s / 4):
        return _run_claimed_increment(model_id, task_id)


def _score_photographs(detector, config: ExperimentConfig, views: dict):
    """The increment's model on the user's labelled photographs (``test_set.photographs``), at
    the loop's views; None without them."""
    if config.test_set.photographs is None:
        return None
    from workers.train.data import load_dataset
    from workers.train.evaluation import evaluate_detector

    samples, classes = load_dataset(config.test_set.photographs)
    return evaluate_detector(
        detector,
        samples,
        classes,
        score_threshold=config.evaluation.score_threshold,
        iou_threshold=config.evaluation.iou_threshold,
        batch_size=config.evaluation.batch_size,
        coco=False,
        **views,
    )


def loop_views(config: ExperimentConfig) -> dict[str, tuple]:
    """``detect_object``'s overrides for the loop's evaluation (``evaluation.views``): none (the
    detector's own views and texture check), or the network alone at its one trained view."""
    from workers.train.checkpoint import RCNN_FAMILIES

    if config.evaluation.views == "detector":
        return {}
    if config.detector.family not in RCNN_FAMILIES:
        return {"texture_check": False}
    return {"test_sizes": (), "test_turns": (), "texture_check": False}


def _run_claimed_increment(model_id: int, task_id: str = "direct") -> str:
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

    wait_for_room = WaitForRoom(model_id, task_id)
    try:
        if not train_rows:
            raise RuntimeError(f"no rendered training image for stage {stage.order} increment {model.increment}")
        started = time.perf_counter()
        catalog = load_assets(config.assets)
        stats = train_detector(
            _samples(train_rows),
            init=parent_path,
            iterations=iterations,
            config=config.detector,
            classes=classes,
            out=store.resolve(relative),
            seed=seed,
            textures=catalog.textures(classes) if config.detector.texture_check else None,
            # None where the config names none: a parent's lookalikes are inherited then.
            lookalikes=(catalog.lookalike_textures() or None) if config.detector.texture_check else None,
            on_no_room=wait_for_room,
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
        photographs = _score_photographs(detector, config, views)
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
        refused = wait_for_room.record()
        if refused:  # written once there was room: the waiting is over
            model.train_stats["checkpoint_writes_refused"] = refused
            model.error = None
        model.trained_at = utcnow()
        model.status = ModelStatus.evaluated
        evaluation = session.scalar(select(Evaluation).where(Evaluation.model_id == model_id))
        if evaluation is None:
            evaluation = Evaluation(model_id=model_id, details={}, eval_seconds=0.0)
            session.add(evaluation)
        # P: the renders' score, or the user's photographs' when they are the standard test set.
        standard = photographs if config.test_set.photographs_role == "standard" and photographs else result
        evaluation.map = finite_or_none(standard.map)
        evaluation.map_unthresholded = finite_or_none(standard.map_unthresholded)
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
        if photographs is not None:
            evaluation.details["photographs"] = {
                "role": config.test_set.photographs_role,
                **{key: value for key, value in photographs.to_dict().items() if key != "per_image"},
            }
        evaluation.eval_seconds = eval_seconds
    return "evaluated"


@app.task(name=TRAIN_TASK, bind=True)
def train_increment(self, model_id: int) -> str:
    return run_increment(model_id, task_id=self.request.id or "eager")
