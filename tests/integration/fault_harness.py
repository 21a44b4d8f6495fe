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
- ``restart_postgres_mid_increment``: the database (a PostgreSQL server of the fault's own,
  :class:`OwnPostgres`) killed whole while a model trains, and started again on the same port
  and data folder; recovered when that increment's progress is recorded (its model evaluated,
  or claimed again if the outage cost it its delivery).
- ``artifact_volume_full_at_checkpoint``: no room for the next checkpoint (the train worker's
  RLIMIT_FSIZE lowered under the checkpoint's size: its write fails with EFBIG, as a full
  volume fails it with ENOSPC); room given back as soon as the refusal is recorded; recovered
  when the checkpoint is written whole.
- ``kill_train_worker_mid_write``: a whole train worker stopped and SIGKILLed while it writes
  a checkpoint (its temporary file half written); recovered when the increment is claimed
  again by a live worker.

Each killed service comes back at once, as compose's ``restart: unless-stopped`` brings it back.
Seconds count from the SIGKILL (the refused write for the full volume). ``audit_done_once``
then reads what the experiment did: lost work sent exactly once more, nothing else sent twice,
nothing started more often than the fault cut it off, every checkpoint the record points at
whole (it loads).
"""

from __future__ import annotations

import ctypes
import os
import re
import resource
import select as select_module
import shutil
import signal
import struct
import subprocess
import tempfile
import time
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml
from sqlalchemy import func, select
from sqlalchemy.orm import Session

from db.models import Evaluation, Experiment, ExperimentStatus, Model, ModelStatus, ParameterSet, RenderStatus
from foldwise import store
from tests.integration.conftest import (
    TEST_SETTINGS,
    Stack,
    free_port,
    load_compose,
    running_stack,
    service_environment,
)

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


def postgres_bindir() -> Path | None:
    """The folder of PostgreSQL's server programs (initdb, postgres): initdb's on PATH, else the
    newest /usr/lib/postgresql/<version>/bin; None when neither has them."""
    folders = []
    initdb = shutil.which("initdb")
    if initdb:
        folders.append(Path(initdb).resolve().parent)
    versions = [p for p in Path("/usr/lib/postgresql").glob("*/bin") if p.parent.name.isdigit()]
    folders += sorted(versions, key=lambda p: int(p.parent.name), reverse=True)
    return next((f for f in folders if (f / "initdb").is_file() and (f / "postgres").is_file()), None)


def own_postgres_problem() -> str | None:
    """Why a PostgreSQL server of one's own cannot be started here, or None."""
    if postgres_bindir() is None:
        return "PostgreSQL's server programs (initdb, postgres) are not installed"
    if os.geteuid() == 0:
        import pwd

        try:
            pwd.getpwnam("postgres")
        except KeyError:
            return "running as root, and there is no postgres user to run a PostgreSQL server as (it refuses root)"
    return None


class OwnPostgres:
    """A PostgreSQL server of one's own: initdb into a temporary folder, on a free loopback port,
    trust auth, no Unix socket; as the postgres user when this process is root (postgres refuses
    root). ``kill`` kills the whole server (postmaster and backends, as a killed container);
    ``start`` again on the same port and data folder recovers from its write-ahead log."""

    def __init__(self, log_path: Path) -> None:
        self.port = free_port()
        self.log_path = log_path
        self.bindir = postgres_bindir()
        self.user = "postgres" if os.geteuid() == 0 else None
        self.root: Path | None = None
        self.process: subprocess.Popen | None = None

    @property
    def data_dir(self) -> Path:
        return self.root / "data"

    def admin_url(self, database: str = "postgres") -> str:
        return f"postgresql://postgres@127.0.0.1:{self.port}/{database}"

    def database_url(self, database: str) -> str:
        """The URL the services get: compose's driver, loopback, this server's port."""
        compose_url = service_environment(load_compose({"FOLDWISE_API_TOKEN": "unused"})["services"]["migrate"])[
            "FOLDWISE_DATABASE_URL"
        ]
        scheme = compose_url.split("://", 1)[0]
        return f"{scheme}://postgres@127.0.0.1:{self.port}/{database}"

    def create_database(self, name: str) -> str:
        import psycopg
        from psycopg import sql

        with psycopg.connect(self.admin_url(), autocommit=True) as admin:
            admin.execute(sql.SQL("CREATE DATABASE {}").format(sql.Identifier(name)))
        return self.database_url(name)

    def _initdb(self) -> None:
        # Its own folder in the temporary directory, not under a caller's private one: the
        # postgres user must be able to reach it.
        self.root = Path(tempfile.mkdtemp(prefix="foldwise-postgres-"))
        if self.user:
            shutil.chown(self.root, self.user)
        command = [str(self.bindir / "initdb"), "-D", str(self.data_dir), "-U", "postgres", "--auth=trust"]
        command += ["--encoding=UTF8", "--locale=C", "--no-sync"]
        done = subprocess.run(command, user=self.user, capture_output=True, text=True, check=False)
        if done.returncode != 0:
            raise RuntimeError(f"initdb failed ({done.returncode}): {done.stderr.strip()[-2000:]}")

    def start(self) -> None:
        import psycopg

        if self.root is None:
            self._initdb()
        with self.log_path.open("ab") as log:
            self.process = subprocess.Popen(
                [str(self.bindir / "postgres"), "-D", str(self.data_dir), "-p", str(self.port)]
                + ["-c", "listen_addresses=127.0.0.1", "-c", "unix_socket_directories="],
                user=self.user,
                stdout=log,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        deadline = time.monotonic() + 60
        while True:
            try:
                with psycopg.connect(self.admin_url(), connect_timeout=2):
                    return
            except psycopg.OperationalError:
                if time.monotonic() > deadline or self.process.poll() is not None:
                    raise RuntimeError(f"PostgreSQL on port {self.port} did not start; see {self.log_path}") from None
                time.sleep(0.05)

    def kill(self) -> None:
        """SIGKILL to the server's whole process group, then wait until none of it is left."""
        group = self.process.pid
        try:
            os.killpg(group, signal.SIGKILL)
        except ProcessLookupError:
            pass
        self.process.wait(timeout=10)
        deadline = time.monotonic() + 10
        while _group_members(group) and time.monotonic() < deadline:
            time.sleep(0.02)
        left = _group_members(group)
        assert not left, f"PostgreSQL processes {left} outlived SIGKILL"

    def stop(self) -> None:
        """A fast shutdown (SIGINT to the postmaster), SIGKILL to what is left after 10 s."""
        if self.process is None or self.process.poll() is not None:
            return
        self.process.send_signal(signal.SIGINT)
        try:
            self.process.wait(timeout=10)
        except subprocess.TimeoutExpired:
            self.kill()

    def __enter__(self) -> OwnPostgres:
        try:
            self.start()
        except BaseException:
            self.__exit__()
            raise
        return self

    def __exit__(self, *_exc) -> None:
        try:
            self.stop()
        finally:
            if self.root is not None:
                shutil.rmtree(self.root, ignore_errors=True)


def _group_members(group: int) -> list[int]:
    """The live processes of process group ``group`` (zombies are dead)."""
    members = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            text = stat.read_text()
        except OSError:
            continue
        fields = text.rsplit(")", 1)[-1].split()  # after "pid (comm)": state, ppid, pgrp, ...
        if len(fields) > 2 and int(fields[2]) == group and fields[0] != "Z":
            members.append(int(stat.parent.name))
    return members


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


def process_tree(pid: int) -> list[int]:
    """``pid`` and every process below it (a worker's main process and its pool children)."""

    def descendants(parent: int) -> list[int]:
        children: list[int] = []
        for task in Path(f"/proc/{parent}/task").glob("*"):
            try:
                children += [int(c) for c in (task / "children").read_text().split()]
            except OSError:
                pass
        return children + [d for c in children for d in descendants(c)]

    return [pid, *descendants(pid)]


def kill_whole(process) -> None:
    """SIGKILL a worker's main process and every process below it, by PID, as a killed container."""
    victims = process_tree(process.pid)
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
    # Sent but not yet claimed, outside the queue the fault emptied: a message on its way from the
    # scheduler, or prefetched by a worker, may be lost with the broker or not, so each may be
    # sent once or twice.
    maybe_lost_thetas: frozenset[int] = frozenset()
    maybe_lost_models: frozenset[int] = frozenset()
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
    unclaimed_thetas, unclaimed_models = _sent_unclaimed(rows, experiment_id)
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
        maybe_lost_thetas=unclaimed_thetas - lost,
        maybe_lost_models=unclaimed_models - lost_models,
    )


def _sent_unclaimed(rows: Rows, experiment_id: int) -> tuple[frozenset[int], frozenset[int]]:
    """The θ and models sent and not yet claimed by a worker: waiting in the queue, on their way
    to it, or prefetched by a worker."""
    with rows() as session:
        thetas = session.scalars(
            select(ParameterSet.id).where(
                ParameterSet.experiment_id == experiment_id,
                ParameterSet.status == RenderStatus.queued,
                ParameterSet.task_id.is_(None),
            )
        ).all()
        models = session.scalars(
            select(Model.id).where(
                Model.experiment_id == experiment_id, Model.status == ModelStatus.queued, Model.task_id.is_(None)
            )
        ).all()
    return frozenset(thetas), frozenset(models)


def _second_increment_training(stack: Stack, rows: Rows, experiment_id: int) -> tuple[Model, Model]:
    """Waits for the experiment's first model to be evaluated (its checkpoint written, so the
    models folder is there) and the second to be training; returns both."""

    def second_training() -> tuple[Model, Model] | None:
        with rows() as session:
            models = session.scalars(
                select(Model).where(Model.experiment_id == experiment_id).order_by(Model.increment)
            ).all()
        if len(models) >= 2 and models[0].status == ModelStatus.evaluated and models[1].status == ModelStatus.training:
            return models[0], models[1]
        return None

    return stack.wait_for(
        "the first model evaluated and the second training", second_training, stack.experiment_timeout_s, 0.05
    )


def restart_postgres_mid_increment(
    stack: Stack,
    api,
    rows: Rows,
    own_postgres: OwnPostgres,
    recovery_timeout_s: float = RECOVERY_GOAL_S,
    iterations: int = 100,
) -> Recovery:
    experiment_id = post_smoke_experiment(
        stack, api, "fault-postgres", active_learning={"t": iterations, "max_increments": 2}
    )

    def training_alone() -> Model | None:
        """A model training while no θ is waiting or rendering: what the outage interrupts is
        the increment (and the scheduler's and API's reads), nothing else."""
        with rows() as session:
            model = session.scalar(
                select(Model).where(Model.experiment_id == experiment_id, Model.status == ModelStatus.training)
            )
            open_renders = session.scalar(
                select(func.count()).where(
                    ParameterSet.experiment_id == experiment_id,
                    ParameterSet.status.in_((RenderStatus.pending, RenderStatus.queued)),
                )
            )
        return model if model is not None and open_renders == 0 else None

    victim = stack.wait_for(
        "a model training with nothing rendering", training_alone, stack.experiment_timeout_s, interval_s=0.05
    )
    time.sleep(0.5)  # inside the increment
    before = _recorded(rows, experiment_id)
    killed_at = time.monotonic()
    own_postgres.kill()
    own_postgres.start()  # the same port and data folder: crash recovery from the WAL
    back_after = time.monotonic() - killed_at

    def writing_again() -> Model | None:
        """The delivery the outage interrupted writes again: its claim renewed (its heartbeat),
        its result recorded, or (had the outage cost it its claim) the model claimed again."""
        with rows() as session:
            model = session.get(Model, victim.id)
        renewed = model.claimed_at != victim.claimed_at
        return model if renewed or model.status == ModelStatus.evaluated or model.attempts >= 2 else None

    model = stack.wait_for("the interrupted increment to write again", writing_again, recovery_timeout_s, 0.05)
    seconds = time.monotonic() - killed_at
    after = _recorded(rows, experiment_id)
    lost = {
        kind: sorted(key for key, status in rows_before.items() if after[kind].get(key) is None)
        for kind, rows_before in before.items()
    }
    assert not any(lost.values()), f"rows committed before PostgreSQL was killed are gone: {lost}"

    def recorded() -> Model | None:
        with rows() as session:
            model = session.get(Model, victim.id)
        return model if model.status == ModelStatus.evaluated or model.attempts >= 2 else None

    done = stack.wait_for("the interrupted increment's result", recorded, stack.experiment_timeout_s, 0.1)
    again = done.attempts >= 2
    return Recovery(
        "postgres_restarted_mid_increment",
        experiment_id,
        seconds,
        "the increment training when PostgreSQL was killed writing again (its claim renewed or its result recorded)",
        # Sent again only if the outage cost the delivery its claim.
        lost_models=frozenset({victim.id}) if done.sends >= 2 else frozenset(),
        cut_off_models=frozenset({victim.id}) if again else frozenset(),
        notes={
            "database_back_s": round(back_after, 2),
            "first_write": "claim renewed" if model.claimed_at != victim.claimed_at else "result recorded",
            "increment_recorded_s": round(time.monotonic() - killed_at, 2),
            "increment": "claimed again" if again else "evaluated by the delivery the outage interrupted",
            "rows_before_kill": {kind: len(rows_before) for kind, rows_before in before.items()},
        },
    )


def _recorded(rows: Rows, experiment_id: int) -> dict[str, dict[int, str]]:
    """The experiment's rows as committed: θ, models and evaluations by id, with their status."""
    with rows() as session:
        thetas = session.execute(
            select(ParameterSet.id, ParameterSet.status).where(ParameterSet.experiment_id == experiment_id)
        ).all()
        models = session.execute(select(Model.id, Model.status).where(Model.experiment_id == experiment_id)).all()
        evaluations = session.scalars(
            select(Evaluation.model_id).join(Model).where(Model.experiment_id == experiment_id)
        ).all()
    return {
        "thetas": {i: status.value for i, status in thetas},
        "models": {i: status.value for i, status in models},
        "evaluations": {i: "evaluated" for i in evaluations},
    }


def _fsize_limits(pids: list[int], soft: int | None) -> dict[int, tuple[int, int]]:
    """Sets RLIMIT_FSIZE's soft limit of each live process in ``pids`` (None: no limit); returns
    the limits each had."""
    before = {}
    for pid in pids:
        try:
            current = resource.prlimit(pid, resource.RLIMIT_FSIZE)
            before[pid] = current
            resource.prlimit(pid, resource.RLIMIT_FSIZE, (resource.RLIM_INFINITY if soft is None else soft, current[1]))
        except ProcessLookupError:
            pass
    return before


def artifact_volume_full_at_checkpoint(
    stack: Stack, api, rows: Rows, recovery_timeout_s: float = RECOVERY_GOAL_S, iterations: int = 100
) -> Recovery:
    experiment_id = post_smoke_experiment(
        stack, api, "fault-disk-full", active_learning={"t": iterations, "max_increments": 2}
    )
    first, victim = _second_increment_training(stack, rows, experiment_id)
    checkpoint_bytes = (stack.data_dir / first.checkpoint_path).stat().st_size
    # Room for the worker's logs, not for a checkpoint: the write fails part way with EFBIG.
    limit = checkpoint_bytes // 2
    worker = stack.running("train-worker")
    _fsize_limits(process_tree(worker.pid), limit)
    try:

        def refused() -> str | None:
            with rows() as session:
                error = session.get(Model, victim.id).error
            return error if error and "no room" in error else None

        error = stack.wait_for("the checkpoint write to be refused", refused, stack.experiment_timeout_s, 0.02)
        refused_at = time.monotonic()
        checkpoint = stack.data_dir / store.checkpoint_path(experiment_id, victim.id)
        assert not checkpoint.exists(), f"{checkpoint} was written past the file size limit"
    finally:
        _fsize_limits(process_tree(worker.pid), None)  # room again
    room_after = time.monotonic() - refused_at
    stack.wait_for("the checkpoint written once there is room", checkpoint.exists, recovery_timeout_s, 0.02)
    return Recovery(
        "artifact_volume_full_at_checkpoint",
        experiment_id,
        time.monotonic() - refused_at,
        "the checkpoint the full volume refused written whole once there was room",
        notes={
            "error_recorded": error,
            "checkpoint_bytes": checkpoint_bytes,
            "file_size_limit_bytes": limit,
            "room_back_after_s": round(room_after, 2),
        },
    )


class DirectoryWatch:
    """inotify(7) on one folder, through libc: the names its files are written to, as they are."""

    IN_MODIFY = 0x00000002

    def __init__(self, folder: Path, mask: int = IN_MODIFY) -> None:
        libc = ctypes.CDLL(None, use_errno=True)
        self.fd = libc.inotify_init1(os.O_CLOEXEC)
        if self.fd < 0:
            raise OSError(ctypes.get_errno(), "inotify_init1")
        if libc.inotify_add_watch(self.fd, str(folder).encode(), mask) < 0:
            os.close(self.fd)
            raise OSError(ctypes.get_errno(), f"inotify_add_watch {folder}")

    def wait_for(self, wanted: Callable[[str], bool], timeout_s: float) -> str:
        """The first name an event comes for that ``wanted`` accepts; TimeoutError after ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while (left := deadline - time.monotonic()) > 0:
            ready, _, _ = select_module.select([self.fd], [], [], left)
            if not ready:
                break
            data = os.read(self.fd, 64 * 1024)
            offset = 0
            while offset < len(data):
                _wd, _mask, _cookie, length = struct.unpack_from("iIII", data, offset)
                name = data[offset + 16 : offset + 16 + length].rstrip(b"\0").decode()
                offset += 16 + length
                if name and wanted(name):
                    return name
        raise TimeoutError(f"no wanted event in {timeout_s:.0f} s")

    def __enter__(self) -> DirectoryWatch:
        return self

    def __exit__(self, *_exc) -> None:
        os.close(self.fd)


def kill_train_worker_mid_write(
    stack: Stack, api, rows: Rows, recovery_timeout_s: float = RECOVERY_GOAL_S, iterations: int = 100
) -> Recovery:
    experiment_id = post_smoke_experiment(
        stack, api, "fault-train-worker-mid-write", active_learning={"t": iterations, "max_increments": 2}
    )
    first, victim = _second_increment_training(stack, rows, experiment_id)
    folder = stack.data_dir / f"experiments/{experiment_id}/models"
    target = Path(store.checkpoint_path(experiment_id, victim.id)).name
    worker = stack.running("train-worker")
    victims = process_tree(worker.pid)  # read beforehand: the stop must land inside the write
    with DirectoryWatch(folder) as watch:
        # The first piece of the checkpoint written to its temporary file: stop the worker there.
        temporary = watch.wait_for(
            lambda name: store.unfinished_write_target(name) == target, stack.experiment_timeout_s
        )
        for pid in victims:
            os.kill(pid, signal.SIGSTOP)
    killed_at = time.monotonic()
    written = (folder / temporary).stat().st_size if (folder / temporary).exists() else None
    whole = (stack.data_dir / first.checkpoint_path).stat().st_size
    assert written is not None and not (folder / target).exists(), (
        f"the kill missed the write of {target}: temporary file {'gone' if written is None else 'there'}, "
        f"checkpoint {'there' if (folder / target).exists() else 'absent'}"
    )
    kill_whole(worker)  # SIGKILL to the stopped processes
    stack.restart(worker)

    def retaken() -> Model | None:
        with rows() as session:
            model = session.get(Model, victim.id)
            return model if model.attempts >= 2 else None

    taken = stack.wait_for("the killed increment to be claimed again", retaken, recovery_timeout_s, interval_s=0.1)
    return Recovery(
        "train_worker_killed_mid_write",
        experiment_id,
        time.monotonic() - killed_at,
        "the increment whose checkpoint write was killed started again by a live train worker",
        lost_models=frozenset({victim.id}),
        cut_off_models=frozenset({victim.id}),
        notes={
            "temporary_file": temporary,
            # All of it, at times: then the kill fell between the last piece and the rename.
            "bytes_written_at_kill": written,
            "previous_checkpoint_bytes": whole,
            "task_id_killed": victim.task_id,
            "task_id_again": taken.task_id,
        },
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


def _allowed_sends(item_id: int, lost: frozenset[int], maybe_lost: frozenset[int]) -> tuple[int, ...]:
    if item_id in lost:
        return (2,)
    return (1, 2) if item_id in maybe_lost else (1,)


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
    # An error recorded while the model waited (for room, say) is cleared once it is trained.
    stale_errors = [(m.id, m.error) for m in models if m.status == ModelStatus.evaluated and m.error]
    if stale_errors:
        problems.append(f"evaluated models still showing an error: {stale_errors}")
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
    problems += _checkpoint_problems(stack, experiment_id, models)
    theta_sends = {t.id: t.sends for t in thetas if t.status != RenderStatus.discarded}
    wrong_theta_sends = {
        i: n
        for i, n in theta_sends.items()
        if n not in _allowed_sends(i, recovery.lost_thetas, recovery.maybe_lost_thetas)
    }
    if wrong_theta_sends:
        problems.append(f"θ sent other than once (twice if lost): {wrong_theta_sends}")
    wrong_model_sends = {
        m.id: m.sends
        for m in models
        if m.sends not in _allowed_sends(m.id, recovery.lost_models, recovery.maybe_lost_models)
    }
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


def _checkpoint_problems(stack: Stack, experiment_id: int, models: list[Model]) -> list[str]:
    """Every checkpoint the record points at is its model's one file and loads whole; the models
    folder holds nothing else but the temporary files of killed writes whose checkpoint was then
    written whole."""
    from workers.train.checkpoint import CheckpointError, read_checkpoint

    problems = []
    trained = [m for m in models if m.checkpoint_path is not None]
    misplaced = [
        (m.id, m.checkpoint_path) for m in trained if m.checkpoint_path != store.checkpoint_path(experiment_id, m.id)
    ]
    if misplaced:
        problems.append(f"checkpoints elsewhere than their model's one file: {misplaced}")
    torn = []
    for model in trained:
        try:
            read_checkpoint(stack.data_dir / model.checkpoint_path)
        except CheckpointError as error:
            torn.append(f"model {model.id}: {error}")
    if torn:
        problems.append(f"checkpoints that do not load: {torn}")
    folder = stack.data_dir / f"experiments/{experiment_id}/models"
    on_disk = {p.name for p in folder.iterdir()} if folder.is_dir() else set()
    expected = {Path(m.checkpoint_path).name for m in trained}
    killed_writes = {name: store.unfinished_write_target(name) for name in on_disk}
    killed_writes = {name: target for name, target in killed_writes.items() if target is not None}
    orphaned = sorted(name for name, target in killed_writes.items() if target not in expected)
    if orphaned:
        problems.append(f"temporary checkpoint files of no trained model: {orphaned}")
    stray = sorted(on_disk - set(killed_writes) - expected)
    if stray:
        problems.append(f"checkpoints of no trained model: {stray}")
    return problems


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
