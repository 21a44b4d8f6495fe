"""What the scheduler's tests share: a small config, stand-ins for the render and train workers
that write the rows the real tasks write, and ways to put an experiment in a given state."""

from __future__ import annotations

import math

from sqlalchemy import select

from db.models import Evaluation, Model, ModelStatus, ParameterSet, RenderStatus, Stage, utcnow
from db.session import session_scope
from foldwise import store
from foldwise.config import parse_config
from services.scheduler.reconcile import reconcile_once

BASE = {
    "name": "flow",
    "seed": 3,
    "assets": {"n_objects": 2},
    "render": {"image_size": 64, "batch_size": 5},
    "curriculum": {"conditions": ["fb", "sc"], "difficulties": ["easy", "hard"]},
    "test_set": {"per_stage": 3},
    "active_learning": {"m": 4, "t": 1, "M": 1, "N": 2, "tau": 0.02, "max_increments": 6},
}


def config(**overrides):
    data = {key: (dict(value) if isinstance(value, dict) else value) for key, value in BASE.items()}
    for section, values in overrides.items():
        data[section] = {**data.get(section, {}), **values} if isinstance(values, dict) else values
    return parse_config(data)


class Fakes:
    """Stand-ins for the render and train workers, scripted per (stage order, k)."""

    def __init__(self, scores=None, default=0.5, cell_scores=None):
        self.scores = scores or {}
        self.default = default
        # AP per "condition/difficulty" written into each evaluation's breakdown, as the real
        # evaluation does (what failure-driven sampling reads); None: no breakdown.
        self.cell_scores = cell_scores
        self.rendered: list[int] = []
        self.trained: list[int] = []

    def render(self, parameter_set_id: int) -> str:
        with session_scope() as session:
            row = session.get(ParameterSet, parameter_set_id)
            if row.status == RenderStatus.rendered:
                return "skipped"
            relative = store.image_path(row.experiment_id, row.id)
            store.atomic_write_bytes(store.resolve(relative), b"png")
            row.status, row.image_path = RenderStatus.rendered, relative
            row.rendered_theta, row.rejections = row.theta, []
            row.label, row.box, row.amodal_box, row.visible_fraction = 0, [1, 1, 9, 9], [1, 1, 9, 9], 1.0
            row.render_seconds, row.rendered_at = 0.001, utcnow()
        self.rendered.append(parameter_set_id)
        return "rendered"

    def train(self, model_id: int, task_id: str = "direct") -> str:
        from workers.train.tasks import _claim

        if not _claim(model_id, task_id):
            return "skipped"
        self.trained.append(model_id)
        with session_scope() as session:
            model = session.get(Model, model_id)
            stage = session.get(Stage, model.stage_id)
            score = self.scores.get((stage.order, model.increment), self.default)
            if score == "fail":
                model.status, model.error = ModelStatus.failed, "TrainingDiverged: loss was NaN 5 times"
                return "failed"
            model.status = ModelStatus.evaluated
            model.checkpoint_path = store.checkpoint_path(model.experiment_id, model.id)
            model.train_seconds, model.trained_at = 0.01, utcnow()
            finite = score is not None and math.isfinite(score)
            session.add(
                Evaluation(
                    model_id=model.id, map=score if finite else None, map_unthresholded=score if finite else None,
                    details=self._details(), eval_seconds=0.001,
                )
            )  # fmt: skip
        return "evaluated"

    def _details(self) -> dict:
        if self.cell_scores is None:
            return {}
        cells = {key: {"map": ap, "map_unthresholded": ap} for key, ap in self.cell_scores.items()}
        return {"breakdown": {"condition/difficulty": cells}}


def stage_models(experiment_id):
    with session_scope() as session:
        rows = session.execute(
            select(Stage.order, Model.increment, Model.id, Model.parent_id, Evaluation.map)
            .join(Model, Model.stage_id == Stage.id)
            .outerjoin(Evaluation, Evaluation.model_id == Model.id)
            .where(Stage.experiment_id == experiment_id)
            .order_by(Stage.order, Model.increment)
        ).all()
    return rows


def in_flight(experiment_id: int) -> None:
    """Reconcile until θ are queued and a model is waiting for a worker that never comes."""
    for _ in range(10):
        reconcile_once(experiment_id)
    with session_scope() as session:
        # The test set and increment 1 rendered, so that a model is created and queued.
        for row in session.scalars(select(ParameterSet).where(ParameterSet.experiment_id == experiment_id)):
            if row.split.value == "test" or row.increment == 1:
                row.status, row.image_path, row.box, row.label = RenderStatus.rendered, "x.png", [1, 1, 9, 9], 0
    for _ in range(3):
        reconcile_once(experiment_id)
