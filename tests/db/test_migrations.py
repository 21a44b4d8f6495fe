"""Migrations: upgrade, downgrade and upgrade again; the schema matches the models."""

import os
import uuid

import pytest
from alembic.autogenerate import compare_metadata
from alembic.migration import MigrationContext
from sqlalchemy import create_engine, text

from db.migrate import downgrade, upgrade
from db.models import Base


def _assert_round_trip(url):
    upgrade(url)
    downgrade(url)
    upgrade(url)
    engine = create_engine(url)
    with engine.connect() as connection:
        assert compare_metadata(MigrationContext.configure(connection), Base.metadata) == []
    engine.dispose()


def test_sqlite(tmp_path):
    _assert_round_trip(f"sqlite:///{tmp_path / 'm.db'}")


def _postgres_admin_url():
    return os.environ.get("FOLDWISE_TEST_POSTGRES_URL", "postgresql+psycopg://postgres@127.0.0.1:5432/postgres")


def test_postgresql():
    admin = create_engine(_postgres_admin_url(), isolation_level="AUTOCOMMIT")
    try:
        connection = admin.connect()
    except Exception as error:  # no server on this machine
        pytest.skip(f"PostgreSQL not reachable at {_postgres_admin_url()}: {type(error).__name__}")
    name = f"foldwise_mig_{uuid.uuid4().hex[:8]}"
    connection.execute(text(f'CREATE DATABASE "{name}"'))
    try:
        _assert_round_trip(_postgres_admin_url().rsplit("/", 1)[0] + f"/{name}")
    finally:
        connection.execute(text(f'DROP DATABASE "{name}" WITH (FORCE)'))
        connection.close()
        admin.dispose()
