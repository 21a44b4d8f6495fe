"""Embedded mode: the whole loop in one process (SQLite, eager Celery), for ``foldwise run``.

The same scheduler plan and the same tasks as the distributed system; only the transport
differs: each task runs in-process the moment the scheduler sends it.
"""

from __future__ import annotations

import os
from collections.abc import Callable

from db.migrate import upgrade
from db.session import session_scope
from foldwise.config import ExperimentConfig
from services import queries
from services.scheduler.plan import Decision
from services.scheduler.reconcile import reconcile_once
from services.scheduler.service import TERMINAL, experiment_status
from workers.app import use_eager


class Stalled(RuntimeError):
    """The scheduler decided nothing although the experiment has not ended (a bug)."""


def start_experiment(config: ExperimentConfig, study: str | None = None) -> int:
    upgrade()
    with session_scope() as session:
        return queries.create_experiment(session, config, study=study).id


def run_to_completion(
    experiment_id: int,
    on_step: Callable[[int, list[Decision]], None] | None = None,
) -> str:
    """Reconcile with in-process tasks until the experiment finishes or fails."""
    use_eager(True)
    while True:
        decisions = reconcile_once(experiment_id)
        status = experiment_status(experiment_id)
        if on_step and decisions:
            on_step(experiment_id, decisions)
        if status in TERMINAL:
            return status.value
        if not decisions:
            # Every task ran synchronously, so nothing can be outstanding.
            raise Stalled(f"experiment {experiment_id} is {status.value} but nothing is left to do")


def run_member(experiment_id: int, threads: int) -> None:
    """One curriculum of several run side by side (``foldwise run --members``), in its own
    process: torch trains and detects with ``threads`` threads (FOLDWISE_THREADS caps whatever
    the detector config asks for), OpenCV renders with as many."""
    os.environ["FOLDWISE_THREADS"] = str(threads)
    from foldwise.settings import get_settings

    get_settings.cache_clear()
    import cv2

    cv2.setNumThreads(threads)
    run_to_completion(experiment_id)
