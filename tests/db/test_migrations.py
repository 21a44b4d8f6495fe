"""Migrations: upgrade, downgrade and upgrade again; the schema matches the models; data moves."""

import json
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


def test_rows_rendered_before_objects_per_image_get_their_one_target(tmp_path):
    url = f"sqlite:///{tmp_path / 'old.db'}"
    upgrade(url, revision="0001")
    engine = create_engine(url)
    theta = {"condition": "fb", "difficulty": "easy", "object": "coffee", "seed": 1}
    with engine.begin() as connection:
        connection.execute(text(
            "INSERT INTO experiments (id, name, config, seed, status, created_at) VALUES (1, 'old', '{}', 0, 'finished', '2026-01-01')"
        ))
        for row_id, box in ((1, "[1.0, 2.0, 30.0, 40.0]"), (2, "null")):
            connection.execute(text(
                "INSERT INTO parameter_sets (id, experiment_id, key, split, \"index\", condition, difficulty, seed, theta, status, label, box, amodal_box, visible_fraction) "
                f"VALUES ({row_id}, 1, 'test/fb/easy/{row_id}', 'test', {row_id}, 'fb', 'easy', 1, :theta, 'rendered', 1, '{box}', '{box}', 0.75)"
            ), {"theta": json.dumps(theta)})
    upgrade(url)
    with engine.connect() as connection:
        rows = dict(connection.execute(text("SELECT id, objects FROM parameter_sets ORDER BY id")).all())
    engine.dispose()
    assert json.loads(rows[1]) == [
        {"object": "coffee", "label": 1, "box": [1.0, 2.0, 30.0, 40.0], "amodal_box": [1.0, 2.0, 30.0, 40.0], "visible_fraction": 0.75}
    ]
    assert rows[2] is None or json.loads(rows[2]) is None
