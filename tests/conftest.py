"""Shared fixtures: an isolated artifact store and a migrated SQLite database per test."""

from __future__ import annotations

import os
import shutil
import sqlite3
import sys
import tempfile
from contextlib import contextmanager

import pytest
from sqlalchemy import event
from sqlalchemy.engine import Engine


def pytest_configure(config):
    """What the code under test caches (FOLDWISE_CACHE_DIR: the texture check's keypoints) goes to
    a folder of this run (each xdist worker its own), never the user's ~/.cache."""
    folder = tempfile.mkdtemp(prefix="foldwise-test-cache-")
    config._foldwise_cache_dir = folder
    os.environ["FOLDWISE_CACHE_DIR"] = folder
    _keep_bytecode(config)


def _keep_bytecode(config):
    """Where PYTHONDONTWRITEBYTECODE forbids writing bytecode beside the sources, the suite's
    processes (xdist's workers and the hundred-odd Python processes the tests start, all of which
    inherit this environment) write and share it under pytest's cache folder instead. Without it
    every process compiles the source of all it imports again: torch, torchvision and the rest,
    about 5 s of CPU a process. The packages are installed without their bytecode (Makefile)."""
    if not sys.dont_write_bytecode:
        return  # written already: beside the sources, or where PYTHONPYCACHEPREFIX says
    cache = getattr(config, "cache", None)
    if sys.pycache_prefix is not None:
        prefix = sys.pycache_prefix
    elif cache is not None:
        prefix = str(cache.mkdir("bytecode"))  # kept for the next run, as pytest keeps its cache
    else:  # -p no:cacheprovider: a folder of this run
        prefix = config._foldwise_bytecode_dir = tempfile.mkdtemp(prefix="foldwise-test-bytecode-")
    os.environ.pop("PYTHONDONTWRITEBYTECODE", None)
    os.environ["PYTHONPYCACHEPREFIX"] = prefix
    sys.dont_write_bytecode = False
    sys.pycache_prefix = prefix


def pytest_unconfigure(config):
    for folder in (getattr(config, "_foldwise_cache_dir", None), getattr(config, "_foldwise_bytecode_dir", None)):
        if folder:
            shutil.rmtree(folder, ignore_errors=True)


@event.listens_for(Engine, "connect")
def _no_fsync_per_commit(dbapi_connection, _record):
    """SQLite in this process commits without an fsync each time (``synchronous=NORMAL``, which
    with the WAL journal every foldwise engine sets syncs at checkpoints only). A crashed
    *machine* could lose the last commits, which no test checks; a killed process loses none.
    The suite commits thousands of times, and an fsync on this shared disk costs milliseconds to
    tens of them: test_flow.py and test_study.py took 21-40 s with it, 9 s without."""
    if isinstance(dbapi_connection, sqlite3.Connection):
        dbapi_connection.execute("PRAGMA synchronous=NORMAL")


def _use_database(url: str, tmp_path, monkeypatch):
    """Point settings at ``url`` (migrated) and a data dir under ``tmp_path``; reset afterwards."""
    from db.migrate import upgrade
    from db.session import reset_engines
    from foldwise.settings import get_settings

    monkeypatch.setenv("FOLDWISE_DATA_DIR", str(tmp_path / "data"))
    monkeypatch.setenv("FOLDWISE_DATABASE_URL", url)
    get_settings.cache_clear()
    reset_engines()
    upgrade(url)
    yield url
    reset_engines()
    get_settings.cache_clear()


@pytest.fixture(scope="session")
def migrated_sqlite_template(tmp_path_factory):
    """One SQLite file migrated to head, copied for each test: a copy costs milliseconds, a
    migration from scratch ~0.15 s (more on a loaded machine). Tests still run ``upgrade`` on
    their copy, which finds it at head."""
    from db.migrate import upgrade
    from db.session import reset_engines

    path = tmp_path_factory.mktemp("sqlite-template") / "foldwise.db"
    upgrade(f"sqlite:///{path}")
    reset_engines()  # closes every connection, so SQLite folds its WAL back into the file
    return path


@pytest.fixture
def database(tmp_path, monkeypatch, migrated_sqlite_template):
    """A fresh SQLite database and data dir; yields the URL. Settings and engines are reset."""
    shutil.copy(migrated_sqlite_template, tmp_path / "foldwise.db")
    yield from _use_database(f"sqlite:///{tmp_path / 'foldwise.db'}", tmp_path, monkeypatch)


@pytest.fixture
def eager():
    from workers.app import app, use_eager

    previous = app.conf.task_always_eager
    use_eager(True)
    yield
    use_eager(previous)


POSTGRES_ADMIN_URL = "postgresql+psycopg://postgres@127.0.0.1:5432/postgres"


def _postgres_admin_url() -> str:
    import os

    return os.environ.get("FOLDWISE_TEST_POSTGRES_URL", POSTGRES_ADMIN_URL)


@contextmanager
def _scratch_postgres():
    """An empty PostgreSQL database of its own, dropped afterwards; skips, saying why, where no
    server answers."""
    import uuid

    from sqlalchemy import create_engine, text

    admin_url = _postgres_admin_url()
    admin = create_engine(admin_url, isolation_level="AUTOCOMMIT")
    try:
        connection = admin.connect()
    except Exception as error:  # no server on this machine
        admin.dispose()
        pytest.skip(f"PostgreSQL not reachable at {admin_url}: {type(error).__name__}")
    name = f"foldwise_test_{uuid.uuid4().hex[:8]}"
    connection.execute(text(f'CREATE DATABASE "{name}"'))
    try:
        yield admin_url.rsplit("/", 1)[0] + f"/{name}"
    finally:
        connection.execute(text(f'DROP DATABASE "{name}" WITH (FORCE)'))
        connection.close()
        admin.dispose()


@pytest.fixture
def postgres_url():
    """A fresh, empty PostgreSQL database on loopback (dropped afterwards); skips, saying why,
    where no server answers. Override the server with FOLDWISE_TEST_POSTGRES_URL."""
    with _scratch_postgres() as url:
        yield url


# The table of the schema's version: the one a migration to head leaves rows in.
SCHEMA_VERSION_TABLE = "alembic_version"


def _postgres_tables(connection) -> list[str]:
    from sqlalchemy import text

    query = "SELECT tablename FROM pg_tables WHERE schemaname = current_schema() AND tablename <> :version ORDER BY 1"
    return list(connection.scalars(text(query), {"version": SCHEMA_VERSION_TABLE}))


@pytest.fixture(scope="session")
def migrated_postgres_run_url():
    """One PostgreSQL database migrated to head for the whole test run (``migrated_postgres_url``
    empties it for each test); dropped when the run ends."""
    from sqlalchemy import create_engine, func, select, table

    from db.migrate import upgrade
    from db.session import reset_engines

    with _scratch_postgres() as url:
        upgrade(url)
        reset_engines()
        engine = create_engine(url)
        with engine.connect() as connection:
            filled = [
                name
                for name in _postgres_tables(connection)
                if connection.scalar(select(func.count()).select_from(table(name)))
            ]
        engine.dispose()
        # Emptying a table stands for a fresh copy only where a migration leaves it empty.
        assert not filled, f"migrating to head fills {filled}: emptying them would not give a fresh database"
        yield url


@pytest.fixture
def migrated_postgres_url(migrated_postgres_run_url):
    """A PostgreSQL database at head holding no rows, as a fresh one would: the run's, any
    connection an earlier test left open ended (as DROP DATABASE … WITH (FORCE) ends them), every
    table but the schema version's emptied and its ids restarted at 1: some 0.02 s a test, where
    copying a migrated template and dropping the copy costs 0.4-1 s."""
    from sqlalchemy import create_engine, text

    url = migrated_postgres_run_url
    admin = create_engine(_postgres_admin_url(), isolation_level="AUTOCOMMIT")
    with admin.connect() as connection:
        connection.execute(
            text(
                "SELECT pg_terminate_backend(pid) FROM pg_stat_activity WHERE datname = :name AND pid <> pg_backend_pid()"
            ),
            {"name": url.rsplit("/", 1)[1]},
        )
    admin.dispose()
    engine = create_engine(url)
    with engine.begin() as connection:
        tables = ", ".join(f'"{name}"' for name in _postgres_tables(connection))
        connection.execute(text(f"TRUNCATE {tables} RESTART IDENTITY CASCADE"))
    engine.dispose()
    yield url


@pytest.fixture
def postgres_database(migrated_postgres_url, tmp_path, monkeypatch):
    """Like ``database``, on a fresh migrated PostgreSQL database."""
    yield from _use_database(migrated_postgres_url, tmp_path, monkeypatch)


@pytest.hookimpl(optionalhook=True)  # a hook of pytest-xdist, which `make test` runs under (-n 2)
def pytest_xdist_make_scheduler(config, log):
    """Tests go to xdist's workers a module at a time (its module fixtures, a trained detector or a
    rendered set, built once), and tests/integration as one unit: its modules share one compose
    stack per session, and a session holds Redis db 9 until it ends (a second worker would wait
    for it, then fail). xdist's own ``xdist_group`` marks would say this, but pytest 9.2 drops
    them silently (pytest-dev/pytest-xdist#1386).

    The heaviest units go first (``unit_weight``), so that the run does not end on one worker
    still busy with a benchmark's end-to-end test while the other has nothing left."""
    from xdist.scheduler import LoadScopeScheduling

    class ModuleScheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            return xdist_unit(nodeid)

        def _assign_work_unit(self, node) -> None:
            heaviest = max(self.workqueue, key=lambda unit: unit_weight(unit, len(self.workqueue[unit])))
            self.workqueue.move_to_end(heaviest, last=False)  # the unit xdist hands out next
            super()._assign_work_unit(node)

    return ModuleScheduling(config, log)


def unit_weight(unit: str, tests: int) -> tuple[bool, int]:
    """How early a unit goes to a worker: tests/integration and the benchmarks' modules
    (tests/test_bench_*.py: each runs a whole service stack or benchmark, in a few tests of tens
    of seconds) before the rest, and within each, units of more tests first (xdist's own order)."""
    whole_runs = unit == "tests/integration" or unit.startswith("tests/test_bench_")
    return whole_runs, tests


def xdist_unit(nodeid: str) -> str:
    """The unit of tests one xdist worker runs together: the test's module, or tests/integration."""
    module = nodeid.split("::", 1)[0]
    return "tests/integration" if module.startswith("tests/integration/") else module
