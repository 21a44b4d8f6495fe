"""The faults of issue 10, each injected into a running stack at its moment and timed; one copy
for tests/integration/test_faults.py (which asserts on them, with the tests' short lease) and
bench/faults.py (which times them with compose's default settings).

- ``kill_train_worker_mid_increment``: a whole train worker (main process and pool child)
  SIGKILLed while it trains; recovered when the increment is claimed again by a live worker.
- ``kill_render_worker_mid_batch``: the render worker holding a half-done batch SIGKILLed
  whole; recovered when one of the θ it still owed is claimed by another delivery.
- ``kill_scheduler``: the scheduler SIGKILLed once the first model is evaluated, so the next
  increment waits on it; recovered when the restarted scheduler logs its first decision.
- ``restart_redis_empty``: the broker killed with batches waiting and restarted empty on the
  same port; recovered when one of the lost θ is claimed again (or already rendered).

Each killed service comes back at once, as compose's ``restart: unless-stopped`` brings it back.
Seconds count from the SIGKILL. ``audit_done_once`` then reads what the experiment did: lost
work sent exactly once more, nothing else sent twice, nothing started more often than the
fault cut it off.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import time
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from db.models import Experiment, ExperimentStatus, Model, ModelStatus, ParameterSet, RenderStatus
from foldwise import store
from tests.integration.conftest import TEST_SETTINGS, Stack, free_port, running_stack

# Issue 10's goal: lost work runs again within this long of the fault.
RECOVERY_GOAL_S = 60.0
SMOKE_CONFIG = Path(__file__).resolve().parents[2] / "configs" / "smoke.yaml"

Rows = Callable[[], AbstractContextManager[Session]]


class OwnRedis:
    """A redis-server of one's own on a free port, without persistence: a restart is empty."""

    def __init__(self, log_path: Path) -> None:
        self.port = free_port()
        self.log_path = log_path
        self.process: subprocess.Popen | None = None

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    def start(self) -> None:
        import redis

        with self.log_path.open("ab") as log:
            self.process = subprocess.Popen(
                ["redis-server", "--port", str(self.port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no"],
                stdout=log,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        deadline = time.monotonic() + 10
        while True:
            try:
                redis.Redis.from_url(self.url, socket_timeout=1).ping()
                return
            except redis.RedisError:
                if time.monotonic() > deadline or self.process.poll() is not None:
                    raise RuntimeError(f"redis-server on port {self.port} did not start; see {self.log_path}")
                time.sleep(0.05)

    def kill(self) -> None:
        self.process.send_signal(signal.SIGKILL)
        self.process.wait(timeout=10)

    def __enter__(self) -> OwnRedis:
        self.start()
        return self

    def __exit__(self, *_exc) -> None:
        if self.process is not None and self.process.poll() is None:
            self.kill()


@contextmanager
def stack_on_own_redis(
    database_url: str, own_redis: OwnRedis, root: Path, settings: dict[str, str] = TEST_SETTINGS
) -> Iterator[Stack]:
    """The compose services as processes, their broker ``own_redis`` (so that it can be killed)."""
    from celery import Celery

    control = Celery("foldwise-faults", broker=own_redis.url)
    control.conf.broker_transport_options = {"polling_interval": 0.05}
    try:
        with running_stack(database_url, control, root, broker_url=own_redis.url, settings=settings) as stack:
            yield stack
    finally:
        control.close()


def post_smoke_experiment(stack: Stack, api, name: str, **sections: dict[str, Any]) -> int:
    """configs/smoke.yaml at its easy stage only, with ``sections`` merged into its sections."""
    config = yaml.safe_load(SMOKE_CONFIG.read_text())
    config["name"] = name
    config["curriculum"]["difficulties"] = ["easy"]
    for section, values in sections.items():
        config[section] = {**config[section], **values}
    response = api.post("/experiments", json=config, headers=stack.auth_headers)
    assert response.status_code == 201, response.text
    return response.json()["id"]


def kill_whole(process) -> None:
    """SIGKILL a worker's main process and every process below it, by PID, as a killed container."""

    def descendants(pid: int) -> list[int]:
        children: list[int] = []
        for task in Path(f"/proc/{pid}/task").glob("*"):
            try:
                children += [int(c) for c in (task / "children").read_text().split()]
            except OSError:
                pass
        return children + [d for c in children for d in descendants(c)]

    victims = [process.pid, *descendants(process.pid)]
    assert len(victims) >= 2, f"{process.name} has no pool child to kill: {victims}"
    process.stopped_on_purpose = True
    for pid in victims:
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    process.process.wait(timeout=10)

    def running(pid: int) -> bool:
        try:
            return "zombie" not in Path(f"/proc/{pid}/status").read_text()
        except OSError:
            return False

    deadline = time.monotonic() + 5  # SIGKILL is delivered asynchronously
    while any(running(pid) for pid in victims) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not [pid for pid in victims if running(pid)], f"{process.name}: still running after SIGKILL"


# --------------------------------------------------------------------------- the faults


@dataclass
class Recovery:
    """A fault injected into an experiment, and the seconds until the work it lost ran again."""

    fault: str
    experiment_id: int
    seconds: float
    # What "running again" meant for this fault.
    recovered_when: str
    lost_thetas: frozenset[int] = frozenset()
    lost_models: frozenset[int] = frozenset()
    # Started before the fault and cut off by it: each may start once more.
    cut_off_thetas: frozenset[int] = frozenset()
    cut_off_models: frozenset[int] = frozenset()
    notes: dict[str, Any] = field(default_factory=dict)


def kill_train_worker_mid_increment(
    stack: Stack, api, rows: Rows, recovery_timeout_s: float = RECOVERY_GOAL_S, iterations: int = 100
) -> Recovery:
    # Increments long enough to be killed inside (~10 s at 100 iterations); two of them.
    experiment_id = post_smoke_experiment(
        stack, api, "fault-train-worker", active_learning={"t": iterations, "max_increments": 2}
    )

    def training() -> Model | None:
        with rows() as session:
            return session.scalar(
                select(Model).where(Model.experiment_id == experiment_id, Model.status == ModelStatus.training)
            )

    victim = stack.wait_for("a model to be training", training, stack.experiment_timeout_s, interval_s=0.1)
    time.sleep(0.5)  # inside the increment
    worker = stack.running("train-worker")
    killed_at = time.monotonic()
    kill_whole(worker)
    stack.restart(worker)

    def retaken() -> Model | None:
        with rows() as session:
            model = session.get(Model, victim.id)
            return model if model.attempts >= 2 else None

    taken = stack.wait_for("the killed increment to be claimed again", retaken, recovery_timeout_s, interval_s=0.1)
    return Recovery(
        "train_worker_killed_mid_increment",
        experiment_id,
        time.monotonic() - killed_at,
        "the killed increment's model started again by a live train worker",
        lost_models=frozenset({victim.id}),
        cut_off_models=frozenset({victim.id}),
        notes={"task_id_killed": victim.task_id, "task_id_again": taken.task_id},
    )


def kill_render_worker_mid_batch(
    stack: Stack, api, rows: Rows, recovery_timeout_s: float = RECOVERY_GOAL_S
) -> Recovery:
    # Batches of 40 θ at 768 px: a couple of seconds each, long enough to be killed inside.
    experiment_id = post_smoke_experiment(
        stack, api, "fault-render-worker",
        render={"image_size": 768, "batch_size": 40}, test_set={"per_stage": 80}, active_learning={"m": 8, "max_increments": 1},
    )  # fmt: skip

    def a_batch_half_done() -> str | None:
        """The task id of a delivery that claimed its θ, rendered some and has more to go."""
        with rows() as session:
            claimed = session.execute(
                select(ParameterSet.task_id, ParameterSet.status).where(
                    ParameterSet.experiment_id == experiment_id, ParameterSet.task_id.is_not(None)
                )
            ).all()
        by_task: dict[str, list[RenderStatus]] = {}
        for task_id, status in claimed:
            by_task.setdefault(task_id, []).append(status)
        for task_id, statuses in by_task.items():
            owed = statuses.count(RenderStatus.queued)
            if 10 <= owed < len(statuses):
                return task_id
        return None

    task_id = stack.wait_for("a render batch half done", a_batch_half_done, stack.experiment_timeout_s, interval_s=0.05)
    active = stack.worker_replies("active", timeout_s=1.0)
    holder = next(name for name, tasks in active.items() for task in tasks if task["id"] == task_id)
    worker = next(p for p in stack.replicas("render-worker") if p.alive() and stack.worker_name(p) == holder)
    killed_at = time.monotonic()
    kill_whole(worker)
    stack.restart(worker)
    with rows() as session:
        owed = session.execute(
            select(ParameterSet.id, ParameterSet.attempts).where(
                ParameterSet.task_id == task_id, ParameterSet.status == RenderStatus.queued
            )
        ).all()
    lost = frozenset(theta_id for theta_id, _ in owed)
    assert lost, f"the killed batch {task_id} owed no θ"

    def claimed_by_another_delivery() -> bool:
        with rows() as session:
            return bool(
                session.scalar(
                    select(ParameterSet.id).where(
                        ParameterSet.id.in_(lost), ParameterSet.task_id.is_not(None), ParameterSet.task_id != task_id
                    )
                )
            )

    stack.wait_for("a lost θ to be claimed by another delivery", claimed_by_another_delivery, recovery_timeout_s)
    return Recovery(
        "render_worker_killed_mid_batch",
        experiment_id,
        time.monotonic() - killed_at,
        "a θ the killed batch still owed claimed by another delivery",
        lost_thetas=lost,
        # The θ it was rendering: started, never finished.
        cut_off_thetas=frozenset(theta_id for theta_id, attempts in owed if attempts >= 1),
        notes={"task_id_killed": task_id},
    )


# The scheduler's log line for the decisions of one step (services/scheduler/service.py).
_DECISIONS = r"experiment {experiment_id}: ([A-Za-z]+(?:, [A-Za-z]+)*)$"


def kill_scheduler(stack: Stack, api, rows: Rows, recovery_timeout_s: float = RECOVERY_GOAL_S) -> Recovery:
    experiment_id = post_smoke_experiment(stack, api, "fault-scheduler")

    def first_model_evaluated() -> bool:
        with rows() as session:
            return bool(
                session.scalar(
                    select(func.count()).where(
                        Model.experiment_id == experiment_id, Model.status == ModelStatus.evaluated
                    )
                )
            )

    stack.wait_for(
        "the first model to be evaluated", first_model_evaluated, stack.experiment_timeout_s, interval_s=0.05
    )
    with rows() as session:
        status = session.get(Experiment, experiment_id).status
    assert status == ExperimentStatus.running, (
        f"experiment {experiment_id} was {status.value} before the scheduler could be killed"
    )
    scheduler = stack.running("scheduler")
    killed_at = time.monotonic()
    scheduler.kill_hard()  # it has no child processes: its main process is the whole of it
    restarted = stack.restart(scheduler)
    pattern = re.compile(_DECISIONS.format(experiment_id=experiment_id), re.MULTILINE)
    decided = stack.wait_for(
        "the restarted scheduler to decide",
        lambda: pattern.search(restarted.log()),
        recovery_timeout_s,
        interval_s=0.05,
    )
    return Recovery(
        "scheduler_killed",
        experiment_id,
        time.monotonic() - killed_at,
        "the restarted scheduler's first decision for the experiment (sent, and logged)",
        notes={"first_decisions": decided.group(1).split(", ")},
    )


def restart_redis_empty(
    stack: Stack, api, rows: Rows, own_redis: OwnRedis, recovery_timeout_s: float = RECOVERY_GOAL_S
) -> Recovery:
    import redis

    from services.scheduler.broker_view import _queued

    experiment_id = post_smoke_experiment(
        stack, api, "fault-redis", render={"image_size": 256, "batch_size": 4}, test_set={"per_stage": 60},
        active_learning={"m": 8, "max_increments": 1},
    )  # fmt: skip
    client = redis.Redis.from_url(own_redis.url)
    stack.wait_for(
        "batches waiting in the render queue",
        lambda: client.llen("render") >= 4,
        stack.experiment_timeout_s,
        interval_s=0.02,
    )
    # Writes paused (the workers' pops and the scheduler's pushes wait), then what waits is read and lost.
    client.execute_command("CLIENT", "PAUSE", "10000", "WRITE")
    waiting = _queued(client, "render") + _queued(client, "train")
    client.close()
    killed_at = time.monotonic()
    own_redis.kill()
    own_redis.start()  # the same port, empty
    lost = frozenset(i for kind, ids in waiting if kind == "render" for i in ids)
    lost_models = frozenset(i for kind, ids in waiting if kind == "train" for i in ids)
    assert lost, "no θ was waiting in the render queue"

    def running_again() -> bool:
        with rows() as session:
            return bool(
                session.scalar(
                    select(ParameterSet.id).where(
                        ParameterSet.id.in_(lost),
                        (ParameterSet.task_id.is_not(None)) | (ParameterSet.status == RenderStatus.rendered),
                    )
                )
            )

    stack.wait_for("a lost θ to be rendered again", running_again, recovery_timeout_s, interval_s=0.1)
    return Recovery(
        "redis_restarted_empty",
        experiment_id,
        time.monotonic() - killed_at,
        "a θ lost with the queue claimed again (or rendered) after Redis came back empty",
        lost_thetas=lost,
        lost_models=lost_models,
    )


# --------------------------------------------------------------------------- what was done, how often


@dataclass
class Audit:
    """An ended experiment against its fault: each θ rendered into its one file, the lost work
    (only that) sent twice, nothing started more often than the fault allowed."""

    finished: bool
    # Sends beyond the first, over every θ and model.
    resends: int
    # Starts beyond one per θ and model (two for those the fault cut off).
    duplicates: int
    problems: list[str]
    thetas: list[ParameterSet]
    models: list[Model]


def audit_done_once(stack: Stack, rows: Rows, recovery: Recovery) -> Audit:
    experiment_id = recovery.experiment_id
    with rows() as session:
        status = session.get(Experiment, experiment_id).status
        thetas = session.scalars(select(ParameterSet).where(ParameterSet.experiment_id == experiment_id)).all()
        models = session.scalars(select(Model).where(Model.experiment_id == experiment_id)).all()
    problems: list[str] = []
    if status != ExperimentStatus.finished:
        problems.append(f"experiment {experiment_id} is {status.value}, not finished")
    open_rows = [(t.id, t.status.value) for t in thetas if t.status in (RenderStatus.pending, RenderStatus.queued)]
    if open_rows:
        problems.append(f"θ still open: {open_rows}")
    unevaluated = [(m.id, m.status.value) for m in models if m.status != ModelStatus.evaluated]
    if unevaluated:
        problems.append(f"models not evaluated: {unevaluated}")
    rendered = [t for t in thetas if t.status == RenderStatus.rendered]
    misplaced = [(t.id, t.image_path) for t in rendered if t.image_path != store.image_path(experiment_id, t.id)]
    if misplaced:
        problems.append(f"θ rendered elsewhere than their one file: {misplaced}")
    images = stack.data_dir / f"experiments/{experiment_id}/images"
    on_disk = {p.name for p in images.iterdir()} if images.is_dir() else set()
    expected = {f"{t.id}.png" for t in rendered}
    discarded = {f"{t.id}.png" for t in thetas if t.status == RenderStatus.discarded}
    # A worker killed inside store.atomic_write_bytes leaves its temporary file: half an image,
    # never renamed, so never read. It is not a render; it may only belong to a θ that was then
    # rendered whole by the task's next delivery.
    killed_writes = {name: store.unfinished_write_target(name) for name in on_disk}
    killed_writes = {name: target for name, target in killed_writes.items() if target is not None}
    orphaned = sorted(name for name, target in killed_writes.items() if target not in expected)
    if orphaned:
        problems.append(f"temporary files of no rendered θ: {orphaned}")
    on_disk -= set(killed_writes)
    if not expected <= on_disk:
        problems.append(f"rendered θ without an image: {sorted(expected - on_disk)}")
    if on_disk - expected - discarded:
        problems.append(f"images of no rendered θ: {sorted(on_disk - expected - discarded)}")
    theta_sends = {t.id: t.sends for t in thetas if t.status != RenderStatus.discarded}
    wrong_theta_sends = {i: n for i, n in theta_sends.items() if n != (2 if i in recovery.lost_thetas else 1)}
    if wrong_theta_sends:
        problems.append(f"θ sent other than once (twice if lost): {wrong_theta_sends}")
    wrong_model_sends = {m.id: m.sends for m in models if m.sends != (2 if m.id in recovery.lost_models else 1)}
    if wrong_model_sends:
        problems.append(f"models sent other than once (twice if lost): {wrong_model_sends}")
    excess = {("θ", t.id): t.attempts - (2 if t.id in recovery.cut_off_thetas else 1) for t in thetas} | {
        ("model", m.id): m.attempts - (2 if m.id in recovery.cut_off_models else 1) for m in models
    }
    started_too_often = {key: n for key, n in excess.items() if n > 0}
    if started_too_often:
        problems.append(f"started more often than the fault allows (extra starts): {started_too_often}")
    resends = sum(max(0, n - 1) for n in theta_sends.values()) + sum(max(0, m.sends - 1) for m in models)
    return Audit(
        finished=status == ExperimentStatus.finished,
        resends=resends,
        duplicates=sum(started_too_often.values()),
        problems=problems,
        thetas=list(thetas),
        models=list(models),
    )


TERMINAL = ("finished", "failed", "cancelled")


def summary(api, experiment_id: int) -> dict:
    response = api.get(f"/experiments/{experiment_id}")
    response.raise_for_status()
    return response.json()


def wait_until_finished(stack, api, experiment_id: int) -> dict:
    def ended() -> dict | None:
        state = summary(api, experiment_id)
        return state if state["status"] in TERMINAL else None

    state = stack.wait_for(
        f"experiment {experiment_id} to end",
        ended,
        stack.experiment_timeout_s,
        interval_s=0.25,
        state=lambda: summary(api, experiment_id),
    )
    if state["status"] != "finished":
        stack.fail(f"experiment {experiment_id} ended {state['status']}: {state['error']}")
    return state
