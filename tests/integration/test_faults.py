"""Faults that heal, on the compose services as real processes (PostgreSQL on loopback, a Redis
this module starts itself on a free port, so it can kill it), with the tests' short lease (3 s):

- a whole train worker killed mid-increment (main process and pool child, SIGKILL): the
  increment is sent again once its lease lapses and trained by the next worker, once;
- a whole render worker killed mid-batch: the batch's claims lapse, the θ nobody holds any
  more are sent again once and rendered by another worker;
- the scheduler killed mid-run and started again (as compose's restart policy does): the new
  one goes on from the database, and nothing is sent or trained twice;
- Redis killed and restarted empty with batches waiting: the scheduler finds the messages that
  nobody holds (no queue has them, no live worker does) and sends each again, once;
- no room on the artifact volume for a checkpoint (the train worker's file size limit lowered
  under it): the refusal is recorded on the model, nothing torn is left, and the trained
  increment is written once there is room, not trained again;
- a whole train worker killed while it writes a checkpoint: no checkpoint the record points
  at is torn (each loads), and the increment is sent again once and trained by the next worker.

PostgreSQL restarted mid-increment needs a server of its own under a stack of its own, so it
runs in bench/faults.py only (tests/services/scheduler/test_service_outage.py tests the
scheduler's side of it). The faults themselves live in fault_harness.py, which bench/faults.py
times with compose's default settings. Each test prints the seconds from the fault to the lost
work running again (``-s`` shows them).
"""

from __future__ import annotations

import shutil
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager

import pytest
from sqlalchemy import create_engine, select
from sqlalchemy.orm import Session, sessionmaker

from db.models import Model
from tests.integration.conftest import scratch_database
from tests.integration.fault_harness import (
    OwnRedis,
    artifact_volume_full_at_checkpoint,
    audit_done_once,
    kill_render_worker_mid_batch,
    kill_scheduler,
    kill_train_worker_mid_increment,
    kill_train_worker_mid_write,
    restart_redis_empty,
    stack_on_own_redis,
    wait_until_finished,
)

pytestmark = pytest.mark.integration


@pytest.fixture(scope="module")
def own_redis(tmp_path_factory) -> Iterator[OwnRedis]:
    if shutil.which("redis-server") is None:
        pytest.skip("redis-server is not installed: the fault tests start (and kill) a Redis of their own")
    with OwnRedis(tmp_path_factory.mktemp("redis") / "redis.log") as server:
        yield server


@pytest.fixture(scope="module")
def fault_database(services_reachable) -> Iterator[str]:
    with scratch_database() as url:
        yield url


@pytest.fixture(scope="module")
def fault_stack(fault_database, own_redis, tmp_path_factory):
    with stack_on_own_redis(fault_database, own_redis, tmp_path_factory.mktemp("stack")) as stack:
        yield stack


@pytest.fixture(scope="module")
def fault_api(fault_stack):
    import httpx

    with httpx.Client(base_url=fault_stack.api_url, timeout=10) as client:
        yield client


@pytest.fixture(scope="module")
def rows(fault_database) -> Iterator[Callable[[], AbstractContextManager[Session]]]:
    engine = create_engine(fault_database)
    yield sessionmaker(engine, expire_on_commit=False).begin
    engine.dispose()


def check_done_once(stack, api, rows, recovery) -> None:
    """The experiment finishes; the lost work was sent once more, nothing ran twice."""
    wait_until_finished(stack, api, recovery.experiment_id)
    audit = audit_done_once(stack, rows, recovery)
    assert not audit.problems, audit.problems


# Training iterations per increment: the kill lands 0.5 s into the increment, and the model is
# built and its images read before the first iteration, so 30 (~3 s of training alone on an idle
# core) leave it well inside; bench/faults.py keeps the harness's 100 (~10 s). The killed
# increment and the one after it train in full, so each iteration here is paid twice.
TRAIN_ITERATIONS = 30


def test_a_train_worker_killed_mid_increment_is_replaced_and_nothing_trains_twice(fault_stack, fault_api, rows):
    recovery = kill_train_worker_mid_increment(fault_stack, fault_api, rows, iterations=TRAIN_ITERATIONS)
    # A message sent again, not the killed one redelivered.
    assert recovery.notes["task_id_again"] != recovery.notes["task_id_killed"]
    check_done_once(fault_stack, fault_api, rows, recovery)
    # The lease is 3 s here (60 s by default), and the harness waits RECOVERY_GOAL_S at most for
    # the claim: sent again within seconds of the loss, not after FOLDWISE_REQUEUE_AFTER_S (an
    # hour) or Redis's visibility timeout (6 h).
    print(f"\nkilled train worker: increment claimed again {recovery.seconds:.1f} s after the kill")
    assert "train" in fault_stack.running("train-worker").log()


def test_a_render_worker_killed_mid_batch_loses_nothing_and_renders_nothing_twice(fault_stack, fault_api, rows):
    recovery = kill_render_worker_mid_batch(fault_stack, fault_api, rows)
    check_done_once(fault_stack, fault_api, rows, recovery)
    # Only the θ that was rendering at the kill may start twice (the audit allows the cut-off ones).
    assert len(recovery.cut_off_thetas) <= 1, recovery.cut_off_thetas
    print(
        f"\nkilled render worker: {len(recovery.lost_thetas)} lost θ claimed again {recovery.seconds:.1f} s after the kill"
    )


def test_a_scheduler_killed_mid_run_is_restarted_and_nothing_runs_twice(fault_stack, fault_api, rows):
    recovery = kill_scheduler(fault_stack, fault_api, rows)
    # The scheduler holds no task: nothing was cut off, so the audit allows no second start.
    check_done_once(fault_stack, fault_api, rows, recovery)
    print(f"\nkilled scheduler: the restarted one decided {recovery.seconds:.1f} s after the kill")


def test_redis_restarted_empty_mid_run_loses_nothing(fault_stack, fault_api, rows, own_redis):
    recovery = restart_redis_empty(fault_stack, fault_api, rows, own_redis)
    # No process died: nothing was cut off, so the audit allows no θ a second start.
    check_done_once(fault_stack, fault_api, rows, recovery)
    print(
        f"\nRedis restarted empty: {len(recovery.lost_thetas)} lost θ rendering again {recovery.seconds:.1f} s after the"
        f" kill ({len(recovery.maybe_lost_thetas)} more were on their way or prefetched)"
    )


# The checkpoint faults strike at the second increment's write, not inside its training: a few
# iterations leave the harness (which watches from the moment the model is claimed) ample time.
WRITE_FAULT_ITERATIONS = 10


def test_a_full_artifact_volume_at_a_checkpoint_is_waited_out_and_nothing_trains_twice(fault_stack, fault_api, rows):
    recovery = artifact_volume_full_at_checkpoint(fault_stack, fault_api, rows, iterations=WRITE_FAULT_ITERATIONS)
    assert "no room on the volume" in recovery.notes["error_recorded"]
    assert "File too large" in recovery.notes["error_recorded"]  # EFBIG, from the file size limit
    # Nobody was killed: nothing was cut off or sent again; every checkpoint loads (the audit).
    check_done_once(fault_stack, fault_api, rows, recovery)
    with rows() as session:
        waited = session.scalars(
            select(Model).where(Model.experiment_id == recovery.experiment_id).order_by(Model.increment)
        ).all()[1]
    assert waited.attempts == 1 and waited.error is None
    assert waited.train_stats["checkpoint_writes_refused"]["refused"] >= 1
    print(f"\nfull volume: the checkpoint written {recovery.seconds:.1f} s after the refused write")


def test_a_train_worker_killed_mid_checkpoint_write_leaves_nothing_torn(fault_stack, fault_api, rows):
    recovery = kill_train_worker_mid_write(fault_stack, fault_api, rows, iterations=WRITE_FAULT_ITERATIONS)
    assert recovery.notes["bytes_written_at_kill"] > 0  # inside the write: begun, never renamed
    # The audit loads every checkpoint the record points at; the killed write's temporary file
    # may stay, as its checkpoint was then written whole by the next delivery.
    check_done_once(fault_stack, fault_api, rows, recovery)
    print(f"\ntrain worker killed mid-write: increment claimed again {recovery.seconds:.1f} s after the kill")
