"""Shared fixtures: an isolated artifact store and a migrated SQLite database per test."""

from __future__ import annotations

import pytest


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


@pytest.fixture
def database(tmp_path, monkeypatch):
    """A fresh SQLite database and data dir; yields the URL. Settings and engines are reset."""
    yield from _use_database(f"sqlite:///{tmp_path / 'foldwise.db'}", tmp_path, monkeypatch)


@pytest.fixture
def eager():
    from workers.app import app, use_eager

    previous = app.conf.task_always_eager
    use_eager(True)
    yield
    use_eager(previous)


POSTGRES_ADMIN_URL = "postgresql+psycopg://postgres@127.0.0.1:5432/postgres"


@pytest.fixture
def postgres_url():
    """A fresh, empty PostgreSQL database on loopback (dropped afterwards); skips, saying why,
    where no server answers. Override the server with FOLDWISE_TEST_POSTGRES_URL."""
    import os
    import uuid

    from sqlalchemy import create_engine, text

    admin_url = os.environ.get("FOLDWISE_TEST_POSTGRES_URL", POSTGRES_ADMIN_URL)
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
def postgres_database(postgres_url, tmp_path, monkeypatch):
    """Like ``database``, on a fresh migrated PostgreSQL database."""
    yield from _use_database(postgres_url, tmp_path, monkeypatch)
