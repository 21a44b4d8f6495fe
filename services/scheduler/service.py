"""The scheduler service: reconcile every live experiment, forever.

Stateless between passes: everything it knows is read from the database each time, so it
can be killed (even SIGKILL) and restarted at any point, and a database that restarts (or is
out of reach for a while) only costs the passes it is away.
"""

from __future__ import annotations

import logging
import signal
import time
from collections.abc import Callable

from sqlalchemy import select

from db.models import Experiment, ExperimentStatus
from db.session import session_scope
from foldwise.settings import get_settings
from services.scheduler.plan import Decision
from services.scheduler.reconcile import reconcile_once

log = logging.getLogger(__name__)

LIVE = (ExperimentStatus.pending, ExperimentStatus.running)
TERMINAL = (ExperimentStatus.finished, ExperimentStatus.failed, ExperimentStatus.cancelled)


def live_experiment_ids() -> list[int]:
    with session_scope() as session:
        return list(session.scalars(select(Experiment.id).where(Experiment.status.in_(LIVE)).order_by(Experiment.id)))


def experiment_status(experiment_id: int) -> ExperimentStatus | None:
    with session_scope() as session:
        experiment = session.get(Experiment, experiment_id)
        return experiment.status if experiment else None


# Plan/apply steps in one pass over an experiment. A healthy pass needs a handful (start, open a
# stage, sample, send); the bound keeps a decision that repeats itself from looping, and the
# next pass (scheduler_poll_s later) goes on where this one stopped.
MAX_STEPS_PER_PASS = 50


def reconcile_until_idle(
    experiment_id: int, max_steps: int = MAX_STEPS_PER_PASS, on_decisions: Callable | None = None
) -> int:
    """One pass: reconcile until a step decides nothing (waiting on workers), the experiment ends
    or ``max_steps`` steps were taken. Each task gets at most one message per pass."""
    steps = 0
    sent: set[tuple[str, int]] = set()
    while steps < max_steps:
        decisions: list[Decision] = reconcile_once(experiment_id, sent)
        if not decisions:
            break
        steps += 1
        if on_decisions:
            on_decisions(experiment_id, decisions)
        if experiment_status(experiment_id) in TERMINAL:
            break
    return steps


def serve(poll_s: float | None = None, once: bool = False) -> None:
    poll_s = poll_s if poll_s is not None else get_settings().scheduler_poll_s
    stopping = False

    def _stop(signum, _frame):
        nonlocal stopping
        log.info("signal %s: stopping after this pass", signum)
        stopping = True

    signal.signal(signal.SIGTERM, _stop)
    signal.signal(signal.SIGINT, _stop)
    log.info("scheduler started (poll every %.1fs)", poll_s)
    while not stopping:
        try:
            experiment_ids = live_experiment_ids()
        except Exception as error:  # the database restarting or unreachable: the next pass reads it again
            log.warning("cannot read the live experiments; retrying next pass: %s", str(error).splitlines()[0])
            experiment_ids = []
        for experiment_id in experiment_ids:
            try:
                reconcile_until_idle(
                    experiment_id,
                    on_decisions=lambda e, ds: log.info(
                        "experiment %s: %s", e, ", ".join(type(d).__name__ for d in ds)
                    ),
                )
            except Exception:  # one broken experiment must not stop the others
                log.exception("reconcile of experiment %s failed; retrying next pass", experiment_id)
        if once:
            break
        time.sleep(poll_s)
