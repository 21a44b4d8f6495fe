"""Fault recovery benchmark (issues 10 and 41): seconds from each fault to the lost work running
again, with compose.yaml's default settings; the goal is at most 60 s for every kind of fault,
with no record or checkpoint lost or torn.

For each fault the compose services start afresh as local processes, the way
tests/integration starts them: every service with its compose command and environment, the
settings compose gives when no .env sets them (read from compose.yaml: scheduler poll, lease,
requeue-after), two render-worker replicas, one train worker. Only the broker and the database
are the bench's own: a redis-server it starts on a free port without persistence (so that it
can be killed and come back empty; compose's Redis keeps an append-only file and would come back
with its queues) and a scratch PostgreSQL database, dropped afterwards (for the ``postgres``
fault a PostgreSQL server of its own, initdb'd into a temporary folder and run on a free port,
so that it can be killed). A smoke-sized experiment is posted, the fault injected at its
moment, the killed service brought back at once (compose's ``restart: unless-stopped``), and
the clock runs from the SIGKILL until:

* ``render-worker``: a whole render worker (main process and pool child) killed mid-batch;
  until one of the θ the batch still owed is claimed by another delivery;
* ``train-worker``: a whole train worker killed mid-increment; until the increment's model
  starts again on a live train worker;
* ``scheduler``: the scheduler killed once the first model is evaluated (the next increment
  waits on it); until the restarted scheduler's first decision is sent and logged;
* ``redis``: Redis killed with batches waiting and restarted empty; until one of the lost θ is
  claimed again (or rendered);
* ``postgres``: the PostgreSQL server killed whole while a model trains (nothing rendering) and
  started again on its port and data folder; until that increment's progress is recorded (its
  model evaluated, or claimed again);
* ``disk-full``: no room for the second increment's checkpoint; the clock runs from the refused
  write (recorded on the model row), room is given back at once, until the checkpoint is
  written whole. Without root a volume cannot be filled on purpose, so the train worker's
  RLIMIT_FSIZE is lowered under the checkpoint's size: its write fails part way with EFBIG, as
  on a full volume it fails with ENOSPC, and the worker treats the two alike;
* ``train-worker-mid-write``: a whole train worker stopped and killed once the first piece of a
  checkpoint is in its temporary file; until the increment is claimed again by a live worker.

Then the experiment must finish, and an audit of its rows says how often work was sent again
(``resends``: the lost work, once each, is expected) and started more often than the fault
allows (``duplicates``: 0 expected; the θ or model a kill cut off may start once more); every
checkpoint the record points at must load whole. The faults themselves are
tests/integration/fault_harness.py, which the fault tests share.

    python bench/faults.py --out bench/results/faults.json
    python bench/faults.py --faults render-worker,redis

Needs PostgreSQL on 127.0.0.1:5432 (trust auth for user postgres) and redis-server installed;
without them it prints a JSON that says it skipped and why, and exits 0. The ``postgres`` fault
also needs PostgreSQL's server programs (initdb, postgres; run as the postgres user when the
bench runs as root); without them that fault alone reports why. Exits 1 when a fault missed the
goal or its audit found a problem.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import shutil
import sys
import tempfile
import time
import traceback
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

import pytest  # the stack harness fails the way a test does: pytest.fail (Stack.fail)

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(ROOT))

GOAL_S = 60.0
# The settings a user's .env may set that decide how fast lost work comes back.
RECOVERY_SETTINGS = ("FOLDWISE_SCHEDULER_POLL_S", "FOLDWISE_LEASE_S", "FOLDWISE_REQUEUE_AFTER_S")
# How long to wait for the recovery before calling it failed: past the goal, so a slow recovery
# is measured rather than cut off at 60 s.
RECOVERY_TIMEOUT_S = 300.0
# A whole experiment under a fault, with compose's 1 s scheduler poll, on a shared 2-core machine.
EXPERIMENT_TIMEOUT_S = 900.0

# What runs beside the settings (tests/integration/conftest.py's running_stack).
SETUP = {
    "services": "migrate, api, scheduler, 2 x render-worker, train-worker, detect-worker: compose commands as local processes",
    "broker": "a redis-server of the bench's own, without persistence (compose's keeps an append-only file)",
    "database": "a scratch database on the local PostgreSQL; for the postgres fault a PostgreSQL server of the bench's own (initdb into a temporary folder, a free port)",
    "restart": "a killed service is started again at once, as restart: unless-stopped does",
    "full volume": "the train worker's RLIMIT_FSIZE lowered under a checkpoint's size (EFBIG, which the worker treats as ENOSPC)",
}

# CLI name -> the harness function's name (the harness is imported only when a fault runs).
FAULTS = {
    "render-worker": "kill_render_worker_mid_batch",
    "train-worker": "kill_train_worker_mid_increment",
    "scheduler": "kill_scheduler",
    "redis": "restart_redis_empty",
    "postgres": "restart_postgres_mid_increment",
    "disk-full": "artifact_volume_full_at_checkpoint",
    "train-worker-mid-write": "kill_train_worker_mid_write",
}


def parse_faults(text: str) -> list[str]:
    """``render-worker,redis`` -> the faults in FAULTS order; an unknown name is an error."""
    names = [name.strip() for name in text.split(",") if name.strip()]
    unknown = [name for name in names if name not in FAULTS]
    if unknown or not names:
        raise argparse.ArgumentTypeError(
            f"unknown fault {', '.join(unknown) or '(none given)'}; choose from {', '.join(FAULTS)}"
        )
    return [name for name in FAULTS if name in names]


def compose_settings() -> dict[str, str]:
    """What compose.yaml gives every foldwise service for RECOVERY_SETTINGS when no .env sets them."""
    sys.path.insert(0, str(ROOT / "tests"))  # the compose reader lives beside its tests (tests/ has no package)
    from test_compose import load_compose, service_environment

    environment = service_environment(load_compose({"FOLDWISE_API_TOKEN": "unused"})["services"]["scheduler"])
    return {name: environment[name] for name in RECOVERY_SETTINGS}


def fault_result(
    seconds_to_recovery: float | None,
    *,
    recovered_when: str,
    finished: bool,
    resends: int | None,
    duplicates: int | None,
    problems: list[str],
    goal_s: float = GOAL_S,
    **details: Any,
) -> dict[str, Any]:
    """One fault's entry of the report; ``met`` only when it recovered within the goal."""
    return {
        "seconds_to_recovery": None if seconds_to_recovery is None else round(seconds_to_recovery, 2),
        "goal_s": goal_s,
        "met": seconds_to_recovery is not None and seconds_to_recovery <= goal_s,
        "recovered_when": recovered_when,
        "finished": finished,
        "resends": resends,
        "duplicates": duplicates,
        "problems": problems,
        **details,
    }


def report(
    results: Mapping[str, dict[str, Any]], settings: Mapping[str, str], machine: Mapping[str, Any]
) -> dict[str, Any]:
    """The whole report: every fault's entry, and whether each met the goal with a clean audit."""
    return {
        "benchmark": "faults",
        "goal_s": GOAL_S,
        "all_met": bool(results) and all(r["met"] and r["finished"] and not r["problems"] for r in results.values()),
        "settings": dict(settings),
        "setup": SETUP,
        "faults": dict(results),
        "machine": dict(machine),
    }


def skipped(reason: str) -> dict[str, Any]:
    return {"benchmark": "faults", "skipped": True, "reason": reason}


def missing_service() -> str | None:
    """Why the bench cannot run here, or None."""
    if shutil.which("redis-server") is None:
        return "redis-server is not installed: the bench starts (and kills) a Redis of its own"
    from tests.integration.conftest import postgres_problem

    return postgres_problem()


def machine_info() -> dict[str, Any]:
    """bench/report.py's record (CPU, cores, Python, date, commit), the cores this process may
    use and the load it started under (other work on the machine slows every recovery)."""
    from bench.report import machine

    return {**machine(), "cpus_allowed": len(os.sched_getaffinity(0)), "load_average_1min": os.getloadavg()[0]}


def run_fault(name: str, root: Path, echo: Callable[[str], None]) -> dict[str, Any]:
    """One fault on a fresh stack (compose's defaults, its own Redis, a scratch database)."""
    import httpx
    from sqlalchemy import create_engine
    from sqlalchemy.orm import sessionmaker

    from tests.integration import fault_harness
    from tests.integration.conftest import scratch_database
    from tests.integration.test_distributed import wait_until_finished

    inject = getattr(fault_harness, FAULTS[name])
    (root / "stack").mkdir(parents=True)  # running_stack makes its data and log folders inside
    started = time.monotonic()
    with contextlib.ExitStack() as servers:
        extra: dict[str, Any] = {}
        if name == "postgres":  # a server of its own, to kill
            problem = fault_harness.own_postgres_problem()
            if problem:
                raise RuntimeError(f"cannot start a PostgreSQL server of the bench's own: {problem}")
            own_postgres = servers.enter_context(fault_harness.OwnPostgres(root / "postgres.log"))
            database_url = own_postgres.create_database("foldwise")
            extra["own_postgres"] = own_postgres
        else:
            database_url = servers.enter_context(scratch_database())
        own_redis = servers.enter_context(fault_harness.OwnRedis(root / "redis.log"))
        if name == "redis":
            extra["own_redis"] = own_redis
        stack = servers.enter_context(
            fault_harness.stack_on_own_redis(database_url, own_redis, root / "stack", settings={})
        )
        api = servers.enter_context(httpx.Client(base_url=stack.api_url, timeout=10))
        stack.experiment_timeout_s = EXPERIMENT_TIMEOUT_S
        given = {key: stack.environment("scheduler")[key] for key in RECOVERY_SETTINGS}
        if given != compose_settings():
            raise RuntimeError(f"the stack runs with {given}, not compose's defaults {compose_settings()}")
        # pool_pre_ping: the bench's own reads outlive a database restart, as the services' do.
        engine = create_engine(database_url, pool_pre_ping=True)
        rows = sessionmaker(engine, expire_on_commit=False).begin
        try:
            recovery = inject(stack, api, rows, recovery_timeout_s=RECOVERY_TIMEOUT_S, **extra)
        except (AssertionError, pytest.fail.Exception) as error:
            engine.dispose()
            echo(f"{name}: no recovery: {error}\n{stack.logs(15)}")
            return fault_result(
                None, recovered_when="", finished=False, resends=None, duplicates=None, problems=[str(error)]
            )
        echo(
            f"{name}: lost work running again {recovery.seconds:.1f} s after the fault; waiting for the experiment to end"
        )
        try:
            wait_until_finished(stack, api, recovery.experiment_id)
        except pytest.fail.Exception as error:
            echo(f"{name}: {error}")
        audit = fault_harness.audit_done_once(stack, rows, recovery)
        engine.dispose()
        return fault_result(
            recovery.seconds,
            recovered_when=recovery.recovered_when,
            finished=audit.finished,
            resends=audit.resends,
            duplicates=audit.duplicates,
            problems=audit.problems,
            lost_thetas=len(recovery.lost_thetas),
            lost_models=len(recovery.lost_models),
            # In hand when killed: these may start a second time without counting as duplicates.
            cut_off_thetas=len(recovery.cut_off_thetas),
            cut_off_models=len(recovery.cut_off_models),
            notes=recovery.notes,
            wall_seconds=round(time.monotonic() - started, 1),
        )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument(
        "--faults",
        type=parse_faults,
        default=list(FAULTS),
        help=f"comma-separated, of {', '.join(FAULTS)} (default: all)",
    )
    parser.add_argument("--out", type=Path, help="also write the JSON here")
    args = parser.parse_args(argv)

    def emit(document: dict[str, Any]) -> None:
        text = json.dumps(document, indent=2, ensure_ascii=False)
        print(text)
        if args.out:
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_text(text + "\n")

    def echo(line: str) -> None:
        print(line, file=sys.stderr, flush=True)

    reason = missing_service()
    if reason:
        echo(f"skipped: {reason}")
        emit(skipped(reason))
        return 0
    machine = machine_info()
    results: dict[str, dict[str, Any]] = {}
    with tempfile.TemporaryDirectory(prefix="foldwise-bench-faults-") as scratch:
        for name in args.faults:
            try:
                results[name] = run_fault(name, Path(scratch) / name, echo)
            except (Exception, pytest.fail.Exception) as error:  # a stack that would not start: say so, go on
                echo(traceback.format_exc())
                results[name] = fault_result(
                    None,
                    recovered_when="",
                    finished=False,
                    resends=None,
                    duplicates=None,
                    problems=[f"{type(error).__name__}: {error}"],
                )
    machine = {**machine, "load_average_1min_after": os.getloadavg()[0]}
    document = report(results, compose_settings(), machine)
    emit(document)
    return 0 if document["all_met"] else 1


if __name__ == "__main__":
    sys.exit(main())
