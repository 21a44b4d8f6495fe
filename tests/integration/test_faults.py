"""Faults that heal, on the compose services as real processes (Redis and PostgreSQL on loopback):
a whole train worker killed mid-increment (main process and pool child, SIGKILL) loses nothing,
the increment is sent again once its lease lapses and trained by the next worker, once."""

from __future__ import annotations

import time

import pytest
import yaml
from sqlalchemy import select

from db.models import Model, ModelStatus
from tests.integration.test_distributed import SMOKE_CONFIG, records, summary, wait_until_finished  # noqa: F401

pytestmark = pytest.mark.integration


def test_a_train_worker_killed_mid_increment_is_replaced_and_nothing_trains_twice(stack, api, records):  # noqa: F811
    config = yaml.safe_load(SMOKE_CONFIG.read_text())
    config["name"] = "fault-train-worker"
    config["curriculum"]["difficulties"] = ["easy"]
    # Increments long enough (~10 s) to be killed inside; two of them.
    config["active_learning"] = {**config["active_learning"], "t": 100, "max_increments": 2}
    response = api.post("/experiments", json=config, headers=stack.auth_headers)
    assert response.status_code == 201, response.text
    experiment_id = response.json()["id"]

    def training() -> Model | None:
        with records() as session:
            return session.scalar(select(Model).where(Model.experiment_id == experiment_id, Model.status == ModelStatus.training))

    victim = stack.wait_for("a model to be training", training, stack.experiment_timeout_s, interval_s=0.1)
    time.sleep(0.5)  # inside the increment
    worker = stack.running("train-worker")
    killed_at = time.monotonic()
    worker.stopped_on_purpose = True
    worker.kill_group()  # the whole container: main process and its pool child
    assert not worker.alive()

    replacement = stack.start("train-worker")  # as `restart: unless-stopped` would
    def retaken() -> Model | None:
        with records() as session:
            model = session.get(Model, victim.id)
            return model if model.attempts >= 2 else None

    taken = stack.wait_for("the killed increment to be claimed again", retaken, 120, interval_s=0.2)
    recovered_s = time.monotonic() - killed_at
    final = wait_until_finished(stack, api, experiment_id)
    assert final["status"] == "finished"
    with records() as session:
        models = session.scalars(select(Model).where(Model.experiment_id == experiment_id)).all()
    attempts = {m.id: m.attempts for m in models}
    assert attempts[victim.id] == 2 and all(n == 1 for model_id, n in attempts.items() if model_id != victim.id), attempts
    assert all(m.status == ModelStatus.evaluated for m in models)
    assert taken.task_id != victim.task_id
    # The lease is 3 s here (60 s by default): re-sent and claimed again within seconds of the
    # loss, not after FOLDWISE_REQUEUE_AFTER_S (an hour) or Redis's visibility timeout (6 h).
    assert recovered_s < 60, recovered_s
    print(f"killed train worker: increment claimed again {recovered_s:.1f} s after the kill")
    assert "train" in replacement.log()
