"""Celery task of the render worker: render a batch of θ ids into the artifact store.

Idempotent: the image of θ #i is always ``experiments/<e>/images/<i>.png`` and rendering is
deterministic, so a redelivered batch skips what is done and rewrites the rest identically.
Each θ is committed on its own, so a worker lost mid-batch keeps what it finished. A batch
claims its θ and renews the claim every lease/4 while it renders (``workers.lease``): a whole
worker killed mid-batch stops renewing, and the scheduler sends the rest again within a lease.
"""

from __future__ import annotations

import functools
import logging
import time
from datetime import timedelta

from celery.exceptions import SoftTimeLimitExceeded
from sqlalchemy import select, update

from db.models import Experiment, ExperimentStatus, ParameterSet, RenderStatus, utcnow
from db.session import session_scope
from foldwise import store
from foldwise.config import ExperimentConfig
from foldwise.settings import get_settings
from workers.app import RENDER_TASK, app
from workers.lease import Heartbeat

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


def claim_batch(parameter_set_ids: list[int], task_id: str) -> tuple[list[int], list[int]]:
    """Claim the batch's open θ for this delivery: (the θ this delivery goes on with, the θ another
    live delivery holds, whose lease it renewed within ``lease_s``; those are skipped here)."""
    stale_before = utcnow() - timedelta(seconds=get_settings().lease_s)
    now = utcnow()
    mine: list[int] = []
    held: list[int] = []
    with session_scope() as session:
        rows = {
            row.id: row
            for row in session.scalars(
                select(ParameterSet)
                .where(ParameterSet.id.in_(parameter_set_ids))
                .order_by(ParameterSet.id)
                .with_for_update()
            )
        }
        for parameter_set_id in parameter_set_ids:
            row = rows.get(parameter_set_id)
            if row is not None and row.status in (RenderStatus.pending, RenderStatus.queued):
                if row.task_id not in (None, task_id) and row.claimed_at is not None and row.claimed_at > stale_before:
                    held.append(parameter_set_id)
                    continue
                row.task_id, row.claimed_at = task_id, now
            # Rows already rendered, failed, discarded or gone: render_parameter_set says which.
            mine.append(parameter_set_id)
    return mine, held


def _renew_claims(parameter_set_ids: list[int], task_id: str) -> None:
    with session_scope() as session:
        session.execute(
            update(ParameterSet)
            .where(
                ParameterSet.id.in_(parameter_set_ids),
                ParameterSet.task_id == task_id,
                ParameterSet.status.in_((RenderStatus.pending, RenderStatus.queued)),
            )
            .values(claimed_at=utcnow())
        )


@app.task(name=RENDER_TASK, bind=True)
def render_batch(self, parameter_set_ids: list[int]) -> dict[str, int]:
    task_id = self.request.id or "direct"
    mine, held = claim_batch(list(parameter_set_ids), task_id)
    if held:
        log.info("θ %s are rendered by another live delivery: skipped here", held)
    if app.conf.task_always_eager:  # one process: no other worker to take over, nothing to renew
        outcome = _render_claimed(mine)
    else:
        with Heartbeat(
            f"render-{task_id}", functools.partial(_renew_claims, mine, task_id), get_settings().lease_s / 4
        ):
            outcome = _render_claimed(mine)
    if held:
        outcome["held elsewhere"] = len(held)
    return outcome


def _render_claimed(parameter_set_ids: list[int]) -> dict[str, int]:
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
