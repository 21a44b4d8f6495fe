"""Migrations: upgrade, downgrade and upgrade again; the schema matches the models; data moves."""

import json

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


def test_postgresql(postgres_url):
    _assert_round_trip(postgres_url)


def test_rows_rendered_before_objects_per_image_get_their_one_target(tmp_path):
    url = f"sqlite:///{tmp_path / 'old.db'}"
    upgrade(url, revision="0001")
    engine = create_engine(url)
    theta = {"condition": "fb", "difficulty": "easy", "object": "coffee", "seed": 1}
    with engine.begin() as connection:
        connection.execute(
            text(
                "INSERT INTO experiments (id, name, config, seed, status, created_at) VALUES (1, 'old', '{}', 0, 'finished', '2026-01-01')"
            )
        )
        for row_id, box in ((1, "[1.0, 2.0, 30.0, 40.0]"), (2, "null")):
            connection.execute(
                text(
                    'INSERT INTO parameter_sets (id, experiment_id, key, split, "index", condition, difficulty, seed, theta, status, label, box, amodal_box, visible_fraction) '
                    f"VALUES ({row_id}, 1, 'test/fb/easy/{row_id}', 'test', {row_id}, 'fb', 'easy', 1, :theta, 'rendered', 1, '{box}', '{box}', 0.75)"
                ),
                {"theta": json.dumps(theta)},
            )
    upgrade(url)
    with engine.connect() as connection:
        rows = dict(connection.execute(text("SELECT id, objects FROM parameter_sets ORDER BY id")).all())
    engine.dispose()
    assert json.loads(rows[1]) == [
        {
            "object": "coffee",
            "label": 1,
            "box": [1.0, 2.0, 30.0, 40.0],
            "amodal_box": [1.0, 2.0, 30.0, 40.0],
            "visible_fraction": 0.75,
        }
    ]
    assert rows[2] is None or json.loads(rows[2]) is None


def _stage_end_reasons_added_since_the_first_migration_are_stored(url):
    """The end reasons added after 0001 (learnability's kappa, the canonical baseline's
    increments) and the canonical baseline's stage need no migration: the migrated columns are
    plain text (no CHECK constraint of 0001's reasons), on every backend."""
    from sqlalchemy.orm import Session

    from db.models import Experiment, Stage, StageEndReason

    upgrade(url)
    engine = create_engine(url)
    with Session(engine) as session:
        experiment = Experiment(name="b", config={}, seed=0)
        session.add(experiment)
        for order, reason in enumerate((StageEndReason.kappa, StageEndReason.increments)):
            session.add(
                Stage(
                    experiment=experiment, order=order, condition="canonical", difficulty="canonical", end_reason=reason
                )
            )
        session.commit()
    with Session(engine) as session:
        stored = [(s.condition, s.difficulty, s.end_reason) for s in session.query(Stage).order_by(Stage.order)]
    engine.dispose()
    assert stored == [
        ("canonical", "canonical", StageEndReason.kappa), ("canonical", "canonical", StageEndReason.increments)
    ]  # fmt: skip


def test_new_stage_end_reasons_need_no_migration_on_sqlite(tmp_path):
    _stage_end_reasons_added_since_the_first_migration_are_stored(f"sqlite:///{tmp_path / 'r.db'}")


def test_new_stage_end_reasons_need_no_migration_on_postgresql(postgres_url):
    _stage_end_reasons_added_since_the_first_migration_are_stored(postgres_url)
