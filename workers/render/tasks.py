"""Celery task of the render worker: render a batch of θ ids into the artifact store.

Idempotent: the image of θ #i is always ``experiments/<e>/images/<i>.png`` and rendering is
deterministic, so a redelivered batch skips what is done and rewrites the rest identically.
Each θ is committed on its own, so a worker lost mid-batch keeps what it finished.
"""

from __future__ import annotations

import logging
import time

from celery.exceptions import SoftTimeLimitExceeded
from sqlalchemy import update

from db.models import Experiment, ExperimentStatus, ParameterSet, RenderStatus, utcnow
from db.session import session_scope
from foldwise import store
from foldwise.config import ExperimentConfig
from workers.app import RENDER_TASK, app

log = logging.getLogger(__name__)


def render_parameter_set(parameter_set_id: int) -> str:
    """Render one θ row; returns what happened ("rendered", "skipped", "failed", "missing")."""
    import cv2

    from workers.render.assets import load_assets  # cached per process and assets config
    from workers.render.pipeline import RenderRejected, render_with_resample

    with session_scope() as session:
        row = session.get(ParameterSet, parameter_set_id)
        if row is None:
            log.warning("θ %s does not exist (experiment deleted?)", parameter_set_id)
            return "missing"
        experiment = session.get(Experiment, row.experiment_id)
        if experiment.status in (ExperimentStatus.cancelled, ExperimentStatus.failed):
            return "skipped"
        if row.status == RenderStatus.discarded:  # the experiment ended before it was needed
            return "skipped"
        if row.status == RenderStatus.rendered and row.image_path and store.resolve(row.image_path).is_file():
            return "skipped"
        theta = dict(row.theta)
        experiment_id = row.experiment_id
        config = ExperimentConfig.model_validate(experiment.config)
        cap = config.tasks.max_deliveries
        if row.attempts >= cap:
            # Every earlier attempt started and never finished: its worker was killed (out of
            # memory?) or hit the hard time limit. Another delivery would do the same.
            row.status = RenderStatus.failed
            row.error = (
                f"started {row.attempts} times (tasks.max_deliveries = {cap}) without finishing: "
                "its worker was killed or it ran past its time limit each time"
            )
            return "failed"
        row.attempts += 1

    started = time.perf_counter()
    try:
        result, rendered_theta, rejections = render_with_resample(
            theta,
            backend=config.render.backend,
            max_resamples=config.render.max_resamples,
            assets=load_assets(config.assets),
            samples=config.render.samples,
            device=config.render.device,
        )
    except RenderRejected as rejected:
        with session_scope() as session:
            row = session.get(ParameterSet, parameter_set_id)
            if row is None or row.status == RenderStatus.discarded:
                return "skipped"
            row.status = RenderStatus.failed
            row.error = f"every resample rejected; last reason: {rejected.reason}"
            row.rejections = list(getattr(rejected, "reasons", [rejected.reason]))
            row.render_seconds = time.perf_counter() - started
        return "failed"

    relative = store.image_path(experiment_id, parameter_set_id)
    ok, encoded = cv2.imencode(".png", cv2.cvtColor(result.image, cv2.COLOR_RGB2BGR))
    if not ok:
        raise RuntimeError(f"PNG encoding failed for θ {parameter_set_id}")
    store.atomic_write_bytes(store.resolve(relative), encoded.tobytes())
    seconds = time.perf_counter() - started

    with session_scope() as session:
        row = session.get(ParameterSet, parameter_set_id)
        if row is None:
            return "missing"
        if row.status == RenderStatus.discarded:  # discarded while it rendered: it stays so
            return "skipped"
        row.status = RenderStatus.rendered
        row.image_path = relative
        row.rendered_theta = rendered_theta.to_dict()
        row.rejections = rejections
        row.objects = [obj.to_dict() for obj in result.objects]
        first = row.objects[0] if row.objects else None
        row.label = first["label"] if first else None
        row.box = first["box"] if first else None
        row.amodal_box = first["amodal_box"] if first else None
        row.visible_fraction = first["visible_fraction"] if first else None
        row.render_seconds = seconds
        row.rendered_at = utcnow()
        row.error = None
    return "rendered"


def _record_failure(parameter_set_id: int, error: Exception) -> None:
    with session_scope() as session:
        row = session.get(ParameterSet, parameter_set_id)
        if row is not None and row.status not in (RenderStatus.rendered, RenderStatus.discarded):
            row.status = RenderStatus.failed
            row.error = f"{type(error).__name__}: {error}"


def _back_to_pending(parameter_set_ids: list[int]) -> None:
    """θ a batch could not reach: the scheduler sends them again on its next pass."""
    with session_scope() as session:
        session.execute(
            update(ParameterSet)
            .where(ParameterSet.id.in_(parameter_set_ids), ParameterSet.status == RenderStatus.queued)
            .values(status=RenderStatus.pending)
        )


@app.task(name=RENDER_TASK)
def render_batch(parameter_set_ids: list[int]) -> dict[str, int]:
    outcome: dict[str, int] = {}
    for position, parameter_set_id in enumerate(parameter_set_ids):
        try:
            what = render_parameter_set(parameter_set_id)
        except SoftTimeLimitExceeded:
            # The batch's time (tasks.render_time_limit_s per θ) is spent: this θ fails with the
            # reason, the rest go back to the scheduler before the hard limit kills the task.
            _record_failure(parameter_set_id, TimeoutError("past its time limit (tasks.render_time_limit_s per θ)"))
            rest = list(parameter_set_ids[position + 1 :])
            if rest:
                _back_to_pending(rest)
            outcome["failed"] = outcome.get("failed", 0) + 1
            outcome["returned"] = len(rest)
            break
        except Exception as error:  # a broken θ or asset must not take the rest of the batch down
            log.exception("θ %s could not be rendered", parameter_set_id)
            _record_failure(parameter_set_id, error)
            what = "failed"
        outcome[what] = outcome.get(what, 0) + 1
    return outcome
