"""The distributed system end to end: the compose services as real processes on Redis and PostgreSQL.

An experiment posted to the API runs through the scheduler, two render workers and a train
worker; a scheduler killed with SIGKILL in the middle of an experiment is restarted and the
experiment finishes as if nothing had happened: no θ rendered twice to different files, no
model trained twice, every P entry there.
"""

from __future__ import annotations

import time
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager
from pathlib import Path

import pytest
from sqlalchemy import create_engine, select
from sqlalchemy.orm import Session, sessionmaker

from db.models import Evaluation, Model, ParameterSet, RenderStatus, Split, Stage, StageStatus
from foldwise import store
from services.api.routes.detect import REPLY_TIMEOUT_S
from tests.integration.fault_harness import TERMINAL, summary, wait_until_finished
from workers.app import RENDER_TASK, TRAIN_TASK

pytestmark = pytest.mark.integration

SMOKE_CONFIG = Path(__file__).resolve().parents[2] / "configs" / "smoke.yaml"


@pytest.fixture(scope="session")
def records(database_url) -> Iterator[Callable[[], AbstractContextManager[Session]]]:
    """Sessions on the stack's database, to check what the services wrote."""
    engine = create_engine(database_url)
    yield sessionmaker(engine, expire_on_commit=False).begin
    engine.dispose()


def submit(api, stack) -> int:
    response = api.post(
        "/experiments",
        content=SMOKE_CONFIG.read_bytes(),
        headers={**stack.auth_headers, "Content-Type": "application/yaml"},
    )
    if response.status_code != 201:
        stack.fail(f"POST /experiments answered {response.status_code}: {response.text}")
    return response.json()["id"]


def check_history(api, experiment_id: int, models: list[Model]) -> list[dict]:
    """P through the API: one entry per evaluated model, with c, δ, k and mAP, k = 1, 2, … per stage."""
    history = api.get(f"/experiments/{experiment_id}/history").json()
    assert sorted(entry["model_id"] for entry in history) == sorted(m.id for m in models)
    for entry in history:
        assert entry["condition"] == "fb" and entry["difficulty"] in ("easy", "hard")
        assert entry["map"] is None or 0.0 <= entry["map"] <= 1.0
    increments: dict[int, list[int]] = {}
    for entry in history:
        increments.setdefault(entry["stage"], []).append(entry["k"])
    for stage, ks in increments.items():
        assert sorted(ks) == list(range(1, len(ks) + 1)), f"stage {stage} has increments {ks}"
    stages = api.get(f"/experiments/{experiment_id}/stages").json()
    assert [(s["condition"], s["difficulty"]) for s in stages] == [("fb", "easy"), ("fb", "hard")]
    assert all(s["status"] == "done" and s["increments"] == len(increments[s["order"]]) for s in stages)
    return history


def test_experiment_posted_to_the_api_runs_through_the_workers(stack, api, records):
    # The token compose hands the API is the one that guards writes.
    wrong = api.post(
        "/experiments",
        content=SMOKE_CONFIG.read_bytes(),
        headers={"Authorization": "Bearer not-the-token", "Content-Type": "application/yaml"},
    )
    assert wrong.status_code == 401

    experiment_id = submit(api, stack)
    wait_until_finished(stack, api, experiment_id)

    with records() as session:
        models = session.scalars(select(Model).where(Model.experiment_id == experiment_id)).all()
    history = check_history(api, experiment_id, models)
    # smoke.yaml: two stages, each at least M + N = 2 increments.
    assert len(history) >= 4

    render_workers = stack.replicas("render-worker")
    train_workers = stack.replicas("train-worker")
    every_worker = len(render_workers) + len(train_workers) + len(stack.replicas("detect-worker"))
    stats = stack.worker_replies("stats", timeout_s=5.0, expected=every_worker)
    for process in render_workers:
        totals = stats.get(stack.worker_name(process), {}).get("total", {})
        assert totals.get(RENDER_TASK, 0) >= 1, f"{process.name} rendered nothing: {totals}"
        assert TRAIN_TASK not in totals, f"{process.name} took training from the wrong queue"
        assert f"Task {RENDER_TASK}[" in process.log() and "succeeded" in process.log()
    (train_worker,) = train_workers
    totals = stats.get(stack.worker_name(train_worker), {}).get("total", {})
    assert totals.get(TRAIN_TASK, 0) >= len(models) and RENDER_TASK not in totals, totals

    # The API, started from the same compose environment, sees the same broker and workers.
    queues = api.get("/queues")
    assert queues.status_code == 200, queues.text
    assert {stack.worker_name(p) for p in render_workers + train_workers} <= set(queues.json()["workers"])

    # POST /models/{id}/detect: over the detect queue to detect-worker, and the reply back.
    final = summary(api, experiment_id)["final_model_id"]
    with records() as session:
        test_image = session.scalars(
            select(ParameterSet.image_path).where(
                ParameterSet.experiment_id == experiment_id, ParameterSet.split == Split.test
            )
        ).first()
    image = (stack.data_dir / test_image).read_bytes()
    headers = {**stack.auth_headers, "Content-Type": "image/png"}
    # The client waits as long as the route waits for a detect worker (a worker's first image loads
    # the model and its texture check, slower where the suite loads both cores beside it).
    found = api.post(
        f"/models/{final}/detect?threshold=0", content=image, headers=headers, timeout=REPLY_TIMEOUT_S + 10
    )
    assert found.status_code == 200, found.text
    assert (
        found.json()["image"] == {"width": 64, "height": 64}
        and found.json()["classes"] == summary(api, experiment_id)["classes"]
    )
    garbage = api.post(f"/models/{final}/detect", content=image[:8] + b"\0" * 64, headers=headers)
    assert garbage.status_code == 422 and "truncated or damaged image header" in garbage.json()["detail"]
    (detect_worker,) = stack.replicas("detect-worker")
    assert "foldwise.detect" in detect_worker.log()


def test_experiment_finishes_exactly_once_after_the_scheduler_is_killed(stack, api, records):
    experiment_id = submit(api, stack)

    def first_model_evaluated() -> dict | None:
        state = summary(api, experiment_id)
        if state["status"] in TERMINAL or state["counts"]["models"].get("evaluated", 0) >= 1:
            return state
        return None

    at_kill = stack.wait_for(
        "the first model to be evaluated",
        first_model_evaluated,
        stack.experiment_timeout_s,
        interval_s=0.05,
        state=lambda: summary(api, experiment_id),
    )
    assert at_kill["status"] == "running", f"experiment ended before the scheduler could be killed: {at_kill}"
    stack.running("scheduler").kill_hard()

    # Without a scheduler the workers finish what is queued, and nothing decides what comes next.
    time.sleep(1.0)
    assert summary(api, experiment_id)["status"] == "running"

    restarted = stack.start("scheduler")  # the same compose command, as `restart: unless-stopped` would
    final = wait_until_finished(stack, api, experiment_id)
    assert final["counts"]["evaluations"] > at_kill["counts"]["evaluations"]
    assert "Finish" in restarted.log(), "the restarted scheduler did not finish the experiment"

    with records() as session:
        thetas = session.scalars(
            select(ParameterSet).where(ParameterSet.experiment_id == experiment_id).order_by(ParameterSet.id)
        ).all()
        models = session.scalars(select(Model).where(Model.experiment_id == experiment_id)).all()
        evaluated = set(
            session.scalars(select(Evaluation.model_id).join(Model).where(Model.experiment_id == experiment_id))
        )
        stages = session.scalars(select(Stage).where(Stage.experiment_id == experiment_id)).all()

    # Every θ rendered, each to the one file its id names, and nothing else on disk (no second
    # copy, no temporary file left by a duplicate delivery); a θ rendered ahead for an increment
    # that never came is discarded when the experiment finishes (its image may exist or not).
    unrendered = [
        (t.id, t.status.value, t.error)
        for t in thetas
        if t.status not in (RenderStatus.rendered, RenderStatus.discarded)
    ]
    assert thetas and not unrendered, unrendered
    rendered = [t for t in thetas if t.status == RenderStatus.rendered]
    discarded = {f"{t.id}.png" for t in thetas if t.status == RenderStatus.discarded}
    assert all(t.split == Split.train for t in thetas if t.status == RenderStatus.discarded)
    paths = [t.image_path for t in rendered]
    assert paths == [store.image_path(experiment_id, t.id) for t in rendered]
    assert len(set(paths)) == len(paths)
    images = stack.data_dir / f"experiments/{experiment_id}/images"
    on_disk = {p.name for p in images.iterdir()}
    assert {f"{t.id}.png" for t in rendered} <= on_disk <= {f"{t.id}.png" for t in rendered} | discarded

    # Every model trained once, one per (stage, k), each with its checkpoint and its P entry.
    assert models and [m.id for m in models if m.attempts != 1] == [], [(m.id, m.attempts) for m in models]
    assert max(Counter((m.stage_id, m.increment) for m in models).values()) == 1
    assert evaluated == {m.id for m in models}
    for model in models:
        assert (stack.data_dir / model.checkpoint_path).is_file()
    assert all(s.status == StageStatus.done and s.best_model_id in evaluated for s in stages)
    check_history(api, experiment_id, models)
