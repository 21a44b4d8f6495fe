"""Fixtures of the API tests: a migrated SQLite database per test, a client, a seeded record."""

from __future__ import annotations

import shutil
from datetime import timedelta

import pytest

from db.models import (
    Evaluation,
    Experiment,
    ExperimentStatus,
    Model,
    ModelStatus,
    ParameterSet,
    RenderStatus,
    Split,
    Stage,
    StageEndReason,
    StageStatus,
)
from db.session import get_sessionmaker, reset_engines
from foldwise.config import ExperimentConfig
from foldwise.settings import get_settings
from services.api.app import create_app
from tests.services.api.helpers import T0, TOKEN, OwnRedis, TestClient, closed_port


@pytest.fixture
def database_url(tmp_path, monkeypatch, migrated_sqlite_template) -> str:
    path = tmp_path / "api.db"
    shutil.copy(migrated_sqlite_template, path)
    url = f"sqlite:///{path}"
    monkeypatch.setenv("FOLDWISE_DATA_DIR", str(tmp_path))
    monkeypatch.setenv("FOLDWISE_DATABASE_URL", url)
    monkeypatch.setenv("FOLDWISE_BROKER_URL", f"redis://127.0.0.1:{closed_port()}/0")
    monkeypatch.setenv("FOLDWISE_API_TOKEN", TOKEN)
    monkeypatch.delenv("FOLDWISE_EAGER", raising=False)
    get_settings.cache_clear()
    reset_engines()
    yield url
    reset_engines()
    get_settings.cache_clear()


@pytest.fixture
def client(database_url) -> TestClient:
    return TestClient(create_app(broker_timeout_s=0.5, ping_timeout_s=0.3))


@pytest.fixture
def seeded(database_url) -> dict:
    """A running experiment: stage 0 (fb, easy) ended on a plateau, stage 1 (fb, medium) at k = 2."""
    curriculum = {"conditions": ["fb"], "difficulties": ["easy", "medium"]}
    config = ExperimentConfig(name="seeded", seed=7, curriculum=curriculum)
    with get_sessionmaker(database_url)() as session:
        experiment = Experiment(
            name="seeded",
            config=config.model_dump(mode="json"),
            seed=7,
            classes=["astronaut", "coffee"],
            status=ExperimentStatus.running,
            started_at=T0,
        )
        finished = Experiment(
            name="done",
            config=config.model_dump(mode="json"),
            seed=1,
            status=ExperimentStatus.finished,
            started_at=T0,
            finished_at=T0 + timedelta(hours=1),
        )
        session.add_all([experiment, finished])
        session.flush()
        easy = Stage(
            experiment_id=experiment.id,
            order=0,
            condition="fb",
            difficulty="easy",
            status=StageStatus.done,
            end_reason=StageEndReason.plateau,
            started_at=T0,
            finished_at=T0 + timedelta(seconds=35),
        )
        medium = Stage(
            experiment_id=experiment.id,
            order=1,
            condition="fb",
            difficulty="medium",
            status=StageStatus.running,
            started_at=T0 + timedelta(seconds=35),
        )
        session.add_all([easy, medium])
        session.flush()

        models = []
        parent = None
        # (stage, k, mAP or None when not yet evaluated); scores arrive 10 s apart.
        plan = [(easy, 1, 0.40), (easy, 2, 0.70), (easy, 3, 0.60), (medium, 1, 0.65), (medium, 2, None)]
        for arrival, (stage, k, score) in enumerate(plan, start=1):
            model = Model(
                experiment_id=experiment.id,
                stage_id=stage.id,
                increment=k,
                parent_id=parent,
                detector="faster_rcnn",
                status=ModelStatus.evaluated if score is not None else ModelStatus.training,
                iterations=100,
                checkpoint_path=f"checkpoints/{stage.order}/{k}.pt" if score is not None else None,
                train_seconds=5.0 * k if score is not None else None,
                attempts=1,
            )
            session.add(model)
            session.flush()
            if score is not None:
                session.add(
                    Evaluation(
                        model_id=model.id,
                        map=score,
                        map_unthresholded=score + 0.05,
                        details={"fb": {"easy": score}},
                        eval_seconds=1.5,
                        created_at=T0 + timedelta(seconds=10 * arrival),
                    )
                )
            models.append(model)
            parent = model.id
        easy.best_model_id = models[1].id
        medium.init_model_id = models[1].id

        # Two rendered training θ for (stage 0, k = 1) and one test θ still queued.
        for index, seconds in enumerate([1.5, 2.5]):
            session.add(
                ParameterSet(
                    experiment_id=experiment.id,
                    key=f"train/0/1/{index}",
                    split=Split.train,
                    stage_id=easy.id,
                    increment=1,
                    index=index,
                    condition="fb",
                    difficulty="easy",
                    seed=index,
                    theta={"fb": 0.5},
                    status=RenderStatus.rendered,
                    render_seconds=seconds,
                    image_path=f"images/{index}.png",
                    box=[1, 2, 30, 40],
                    label=0,
                )
            )
        session.add(
            ParameterSet(
                experiment_id=experiment.id,
                key="test/fb/easy/0",
                split=Split.test,
                index=0,
                condition="fb",
                difficulty="easy",
                seed=99,
                theta={"fb": 0.6},
                status=RenderStatus.queued,
            )
        )
        session.commit()
        return {
            "experiment": experiment.id,
            "finished": finished.id,
            "models": [m.id for m in models],
            "stages": [easy.id, medium.id],
        }


@pytest.fixture
def redis_url():
    """A Redis server of the test's own on a free port (never the shared one), empty."""
    server = OwnRedis()
    try:
        server.start()
        yield server.url
    finally:
        server.stop()
