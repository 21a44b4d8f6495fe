"""The compose stack as local processes: every service started from its compose.yaml definition.

Real Redis (127.0.0.1:6379) and PostgreSQL (127.0.0.1:5432, trust auth, user postgres) stand
in for the `redis` and `postgres` containers; the session gets its own database
(``foldwise_it_<random>``, dropped at the end), Redis db 9 (flushed before and after) and a
temporary artifact store. Each service runs its compose command with its compose environment,
the compose hostnames mapped to loopback, the way compose would start it: `migrate` first
(it must exit 0), then `api` on a free port, `scheduler`, two `render-worker` replicas and
one `train-worker`. Output goes to one log file per process; every failure message carries
the logs' tails.
"""

from __future__ import annotations

import fcntl
import os
import secrets
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any, TypeVar
from urllib.parse import urlsplit, urlunsplit

import pytest

# The compose reader lives beside its own tests, in tests/test_compose.py (tests/ has no package).
sys.path.insert(0, str(Path(__file__).resolve().parent.parent))
from test_compose import (  # noqa: E402
    REPO,
    VENV_BIN,
    load_compose,
    service_command,
    service_environment,
    volume_mounts,
)

REDIS_ADDRESS = ("127.0.0.1", 6379)
POSTGRES_ADDRESS = ("127.0.0.1", 5432)
# A Redis database of its own, so the session never sees (or flushes) anyone else's queues.
REDIS_DB = 9
BROKER_URL = f"redis://{REDIS_ADDRESS[0]}:{REDIS_ADDRESS[1]}/{REDIS_DB}"
ADMIN_URL = f"postgresql://postgres@{POSTGRES_ADDRESS[0]}:{POSTGRES_ADDRESS[1]}/postgres"
# Compose service names that the containers use as hostnames, and where they live here.
HOSTS = {"postgres": POSTGRES_ADDRESS[0], "redis": REDIS_ADDRESS[0]}
# Every wait is bounded; a stuck stack fails with its logs instead of hanging the suite.
STARTUP_TIMEOUT_S = 90.0
EXPERIMENT_TIMEOUT_S = 240.0
STOP_TIMEOUT_S = 10.0
# How long a session waits for another one on this machine to release Redis db 9.
LOCK_TIMEOUT_S = 300.0
# What the tests' .env says: a fast scheduler, and a short lease, so that a killed worker's work
# is sent again within seconds (bench/faults.py runs with compose's defaults instead).
TEST_SETTINGS = {"FOLDWISE_SCHEDULER_POLL_S": "0.2", "FOLDWISE_LEASE_S": "3"}

T = TypeVar("T")


# --------------------------------------------------------------------------- reachability


def _unreachable(address: tuple[str, int], what: str) -> str | None:
    try:
        with socket.create_connection(address, timeout=1.0):
            return None
    except OSError as error:
        return f"{what} is not reachable on {address[0]}:{address[1]} ({error}); tests/integration needs it"


def redis_problem() -> str | None:
    problem = _unreachable(REDIS_ADDRESS, "Redis")
    if problem:
        return problem
    import redis

    try:
        redis.Redis.from_url(BROKER_URL, socket_timeout=2).ping()
    except redis.RedisError as error:
        return f"Redis on {REDIS_ADDRESS[0]}:{REDIS_ADDRESS[1]} does not answer PING: {error}"
    return None


def postgres_problem() -> str | None:
    problem = _unreachable(POSTGRES_ADDRESS, "PostgreSQL")
    if problem:
        return problem
    import psycopg

    try:
        with psycopg.connect(ADMIN_URL, connect_timeout=3):
            return None
    except psycopg.Error as error:
        return f"PostgreSQL refuses {ADMIN_URL} (trust auth for user postgres expected): {error}"


# --------------------------------------------------------------------------- processes


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def tail(path: Path, lines: int = 40) -> str:
    if not path.exists():
        return "(no log)"
    return "\n".join(path.read_text(errors="replace").splitlines()[-lines:])


@dataclass
class ServiceProcess:
    """One process of a compose service (a replica), its own session so its children die with it."""

    name: str
    argv: list[str]
    environment: dict[str, str]
    log_path: Path
    process: subprocess.Popen | None = field(default=None, repr=False)
    # Set when the test itself ends the process, so its exit is not reported as a crash.
    stopped_on_purpose: bool = False

    def start(self) -> ServiceProcess:
        with self.log_path.open("ab") as log:
            log.write(f"$ {' '.join(self.argv)}\n".encode())
            log.flush()
            self.process = subprocess.Popen(
                self.argv,
                env=self.environment,
                cwd=REPO,
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        return self

    @property
    def pid(self) -> int:
        return self.process.pid

    def alive(self) -> bool:
        return self.process is not None and self.process.poll() is None

    def kill_hard(self) -> None:
        """SIGKILL the service's main process only, like a crashed container's PID 1."""
        self.stopped_on_purpose = True
        self.process.send_signal(signal.SIGKILL)
        self.process.wait(timeout=STOP_TIMEOUT_S)

    def terminate(self) -> None:
        """SIGTERM to the whole process group, as compose's stop sends it to the container."""
        if self.process is None:
            return
        self.stopped_on_purpose = True
        try:
            os.killpg(self.process.pid, signal.SIGTERM)
        except ProcessLookupError:
            pass

    def kill_group(self) -> None:
        """SIGKILL whatever of the group is left: the main process, or prefork children it left behind."""
        if self.process is None:
            return
        try:
            os.killpg(self.process.pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
        try:
            self.process.wait(timeout=STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            pass

    def log(self) -> str:
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""


# --------------------------------------------------------------------------- the stack


def localize_url(url: str, *, database: str | None = None, user: str | None = None, path: str | None = None) -> str:
    """A compose URL (``scheme://user:pw@service:port/db``) pointed at the loopback stand-in."""
    parts = urlsplit(url)
    if parts.hostname not in HOSTS:
        raise ValueError(f"{url!r} does not name a compose service ({', '.join(HOSTS)})")
    credentials = user if user is not None else (parts.username or "")
    netloc = f"{credentials + '@' if credentials else ''}{HOSTS[parts.hostname]}:{parts.port}"
    new_path = path if path is not None else (f"/{database}" if database else parts.path)
    return urlunsplit((parts.scheme, netloc, new_path, parts.query, parts.fragment))


@dataclass
class Stack:
    compose: dict[str, Any]
    database_url: str
    data_dir: Path
    log_dir: Path
    token: str
    api_port: int
    celery_control: Any  # a bare Celery client on the test broker: broadcast ping and stats
    processes: list[ServiceProcess] = field(default_factory=list)
    experiment_timeout_s: float = EXPERIMENT_TIMEOUT_S
    # A broker of the test's own (tests/integration/test_faults.py); None: the compose URL on loopback, db 9.
    broker_url: str | None = None

    @property
    def api_url(self) -> str:
        return f"http://127.0.0.1:{self.api_port}"

    @property
    def auth_headers(self) -> dict[str, str]:
        return {"Authorization": f"Bearer {self.token}"}

    def replicas(self, name: str) -> list[ServiceProcess]:
        """The processes started for a service (replica labels are name, name-2, ...)."""
        return [p for p in self.processes if p.name == name or p.name.startswith(f"{name}-")]

    @staticmethod
    def worker_name(process: ServiceProcess) -> str:
        """The Celery node name `foldwise worker ROLE` gives itself: ROLE-<its pid>@<host>."""
        role = next(r for r in ("render", "train", "detect") if process.name.startswith(f"{r}-worker"))
        return f"{role}-{process.pid}@{socket.gethostname()}"

    def worker_replies(self, method: str, timeout_s: float = 1.0, expected: int | None = None) -> dict[str, Any]:
        """``celery inspect METHOD`` (ping, stats...) over every worker: node name -> reply.

        With ``expected`` replies it returns as soon as that many came, instead of after ``timeout_s``.
        """
        inspector = self.celery_control.control.inspect(timeout=timeout_s, limit=expected)
        return getattr(inspector, method)() or {}

    def service(self, name: str) -> dict[str, Any]:
        return self.compose["services"][name]

    def command(self, name: str) -> list[str]:
        """The service's compose command, run with the venv's console scripts."""
        argv = service_command(self.service(name))
        executable = VENV_BIN / argv[0]
        if not executable.exists():
            raise FileNotFoundError(f"{name}: {argv[0]} is not installed in {VENV_BIN}")
        if name == "api":
            # Loopback only, on a port of its own: several test sessions may share the machine.
            argv = _replace_option(argv, "--host", "127.0.0.1")
            argv = _replace_option(argv, "--port", str(self.api_port))
        return [str(executable), *argv[1:]]

    def environment(self, name: str) -> dict[str, str]:
        """os.environ (PATH, HOME...) without any FOLDWISE_*, plus the service's compose environment, localised."""
        service = self.service(name)
        compose_environment = service_environment(service)
        data_dir = compose_environment.get("FOLDWISE_DATA_DIR")
        if volume_mounts(service).get(data_dir) != "artifacts":
            raise AssertionError(f"{name}: FOLDWISE_DATA_DIR={data_dir} is not the shared artifacts volume")
        environment = {key: value for key, value in os.environ.items() if not key.startswith("FOLDWISE_")}
        environment.update(compose_environment)
        environment["FOLDWISE_DATABASE_URL"] = self.database_url
        environment["FOLDWISE_BROKER_URL"] = localize_url(
            compose_environment["FOLDWISE_BROKER_URL"], path=f"/{REDIS_DB}"
        )
        if self.broker_url is not None:
            environment["FOLDWISE_BROKER_URL"] = self.broker_url
        environment["FOLDWISE_DATA_DIR"] = str(self.data_dir)
        # Folders compose puts in the artifacts volume (the texture check's cache) go in the local store.
        cache_dir = compose_environment.get("FOLDWISE_CACHE_DIR")
        if cache_dir and PurePosixPath(cache_dir).is_relative_to(data_dir):
            environment["FOLDWISE_CACHE_DIR"] = str(self.data_dir / PurePosixPath(cache_dir).relative_to(data_dir))
        # The checkout under test, not the one the venv's editable install points to.
        environment["PYTHONPATH"] = os.pathsep.join(filter(None, [str(REPO), os.environ.get("PYTHONPATH")]))
        # Two cores for the whole suite: no process fans out over threads.
        environment.update(OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", PYTHONUNBUFFERED="1")
        return environment

    def start(self, name: str, replica: int = 1) -> ServiceProcess:
        label = name if replica == 1 else f"{name}-{replica}"
        runs = sum(1 for p in self.processes if p.name == label)
        log_path = self.log_dir / f"{label}{'' if runs == 0 else f'.run{runs + 1}'}.log"
        process = ServiceProcess(label, self.command(name), self.environment(name), log_path).start()
        self.processes.append(process)
        return process

    def run_once(self, name: str, timeout_s: float = 120.0) -> subprocess.CompletedProcess:
        log_path = self.log_dir / f"{name}.log"
        with log_path.open("wb") as log:
            return subprocess.run(
                self.command(name),
                env=self.environment(name),
                cwd=REPO,
                stdout=log,
                stderr=subprocess.STDOUT,
                timeout=timeout_s,
                check=False,
            )

    def restart(self, process: ServiceProcess) -> ServiceProcess:
        """The same service and replica in a new process, as `restart: unless-stopped` would."""
        for name in self.compose["services"]:
            suffix = process.name.removeprefix(name)
            if suffix == "" or (suffix.startswith("-") and suffix[1:].isdigit()):
                return self.start(name, replica=int(suffix[1:]) if suffix else 1)
        raise LookupError(f"{process.name} is no replica of a compose service")

    def running(self, label: str) -> ServiceProcess:
        matches = [p for p in self.processes if p.name == label and p.alive()]
        if not matches:
            raise LookupError(f"no running process of {label}")
        return matches[-1]

    def logs(self, lines: int = 30) -> str:
        paths = sorted(self.log_dir.glob("*.log"))
        return "\n".join(f"----- {path.name} (last {lines} lines) -----\n{tail(path, lines)}" for path in paths)

    def fail(self, message: str) -> None:
        """Fail the test; the services' log tails are added to the report (see pytest_runtest_makereport)."""
        pytest.fail(message, pytrace=False)

    def wait_for(
        self,
        what: str,
        probe: Callable[[], T | None],
        timeout_s: float,
        interval_s: float = 0.1,
        state: Callable[[], Any] | None = None,
    ) -> T:
        """Poll ``probe`` until it returns something truthy; fail after ``timeout_s``, saying ``state()``."""
        deadline = time.monotonic() + timeout_s
        last_error: Exception | None = None
        while time.monotonic() < deadline:
            try:
                result = probe()
                if result:
                    return result
            except Exception as error:  # a service still starting answers with errors
                last_error = error
            dead = [p.name for p in self.processes if not p.alive() and not p.stopped_on_purpose]
            if dead:
                self.fail(f"while waiting for {what}, these services exited: {', '.join(dead)}")
            time.sleep(interval_s)
        message = f"timed out after {timeout_s:.0f} s waiting for {what}"
        if last_error is not None:
            message += f" (last error: {last_error!r})"
        if state is not None:
            message += f"\nstate then: {state()}"
        self.fail(message)
        raise AssertionError("unreachable")

    def stop_all(self) -> None:
        """SIGTERM to every process at once, a shared grace period, then SIGKILL: always."""
        for process in self.processes:
            process.terminate()
        deadline = time.monotonic() + STOP_TIMEOUT_S
        for process in self.processes:
            try:
                process.process.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                pass
        for process in self.processes:
            process.kill_group()


def _replace_option(argv: list[str], option: str, value: str) -> list[str]:
    if option not in argv:
        raise ValueError(f"{option} is not in {argv}")
    index = argv.index(option) + 1
    return [*argv[:index], value, *argv[index + 1 :]]


# --------------------------------------------------------------------------- fixtures

# The stack of this session, once started: its logs go into the report of any failing test.
_running_stack: Stack | None = None


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    report = outcome.get_result()
    if report.failed and _running_stack is not None:
        report.sections.append(("service logs (tails)", _running_stack.logs()))


@pytest.fixture(scope="session")
def services_reachable() -> None:
    for problem in (redis_problem(), postgres_problem()):
        if problem:
            pytest.skip(problem)


@pytest.fixture(scope="session")
def database_url(services_reachable) -> Iterator[str]:
    """A PostgreSQL database of this session's own, dropped afterwards."""
    with scratch_database() as url:
        yield url


@contextmanager
def scratch_database() -> Iterator[str]:
    """A PostgreSQL database of its own, dropped afterwards."""
    import psycopg
    from psycopg import sql

    name = f"foldwise_it_{secrets.token_hex(6)}"
    with psycopg.connect(ADMIN_URL, autocommit=True) as admin:
        admin.execute(sql.SQL("CREATE DATABASE {}").format(sql.Identifier(name)))
    compose_url = service_environment(load_compose({"FOLDWISE_API_TOKEN": "unused"})["services"]["migrate"])[
        "FOLDWISE_DATABASE_URL"
    ]
    try:
        # The compose URL's driver and host, with loopback's trust-auth user instead of the container's.
        yield localize_url(compose_url, database=name, user="postgres")
    finally:
        with psycopg.connect(ADMIN_URL, autocommit=True) as admin:
            admin.execute(sql.SQL("DROP DATABASE IF EXISTS {} WITH (FORCE)").format(sql.Identifier(name)))


@pytest.fixture(scope="session")
def broker(services_reachable) -> Iterator[str]:
    """Redis db 9, empty, and this session's alone: a second session on the machine waits its turn
    (its FLUSHDB would empty our queues, and its workers would take our tasks)."""
    import redis

    lock_path = Path(tempfile.gettempdir()) / f"foldwise-integration-redis-db{REDIS_DB}.lock"
    with lock_path.open("w") as lock:
        deadline = time.monotonic() + LOCK_TIMEOUT_S
        while True:
            try:
                fcntl.flock(lock, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() > deadline:
                    pytest.fail(f"another integration session has held Redis db {REDIS_DB} for {LOCK_TIMEOUT_S:.0f} s")
                time.sleep(0.5)
        client = redis.Redis.from_url(BROKER_URL)
        client.flushdb()
        try:
            yield BROKER_URL
        finally:
            client.flushdb()
            client.close()
            fcntl.flock(lock, fcntl.LOCK_UN)


@pytest.fixture(scope="session")
def celery_control(broker):
    """A bare Celery client on the test broker, for broadcast ping and stats of the workers."""
    from celery import Celery

    client = Celery("foldwise-integration", broker=broker)
    client.conf.broker_transport_options = {"polling_interval": 0.05}
    yield client
    client.close()


@pytest.fixture(scope="session")
def stack(database_url, broker, celery_control, tmp_path_factory) -> Iterator[Stack]:
    """migrate, then api, scheduler, 2 × render-worker, train-worker, detect-worker, all from compose.yaml."""
    with running_stack(database_url, celery_control, tmp_path_factory.mktemp("stack")) as started:
        yield started


@contextmanager
def running_stack(
    database_url: str,
    celery_control: Any,
    root: Path,
    broker_url: str | None = None,
    settings: Mapping[str, str] = TEST_SETTINGS,
) -> Iterator[Stack]:
    """The compose services as processes on ``database_url`` (and ``broker_url``, else db 9 of the
    shared Redis), with ``settings`` as a user's .env would give them ({}: compose's defaults)."""
    token = secrets.token_urlsafe(16)
    compose = load_compose({**settings, "FOLDWISE_API_TOKEN": token})
    stack = Stack(
        compose=compose,
        database_url=database_url,
        data_dir=root / "data",
        log_dir=root / "logs",
        token=token,
        api_port=free_port(),
        celery_control=celery_control,
        broker_url=broker_url,
    )
    stack.data_dir.mkdir()
    stack.log_dir.mkdir()
    global _running_stack
    _running_stack = stack
    try:
        # As the image does at build time: the render kernels compiled (or loaded) here, into
        # the cache the workers then load from, so the workers do not each compile them.
        from workers.render.pipeline import compile_kernels

        compile_kernels()
        migrated = stack.run_once("migrate")
        if migrated.returncode != 0:
            stack.fail(f"migrate exited {migrated.returncode}")
        stack.start("train-worker")
        stack.start("detect-worker")
        stack.start("render-worker", replica=1)
        stack.start("render-worker", replica=2)
        stack.start("scheduler")
        stack.start("api")

        import httpx

        stack.wait_for(
            "GET /health to say ok",
            lambda: httpx.get(f"{stack.api_url}/health", timeout=2).json().get("status") == "ok",
            STARTUP_TIMEOUT_S,
            interval_s=0.3,
        )
        workers = [p for p in stack.processes if "worker" in p.name]
        expected = {stack.worker_name(p) for p in workers}
        stack.wait_for(
            f"workers {sorted(expected)} to answer a ping",
            lambda: expected <= set(stack.worker_replies("ping", timeout_s=0.5, expected=len(expected))),
            STARTUP_TIMEOUT_S,
            interval_s=0.2,
        )
        yield stack
    finally:
        stack.stop_all()
        _running_stack = None


@pytest.fixture(scope="session")
def api(stack) -> Iterator[Any]:
    import httpx

    with httpx.Client(base_url=stack.api_url, timeout=10) as client:
        yield client
