"""A checkpoint write that fails or is killed leaves no torn checkpoint: the one written before
stays whole (or there is none), a write refused for want of room says so and succeeds once
there is room, and the train worker waits for room instead of losing the trained increment
(train_detector's side of it: tests/workers/train/test_training.py)."""

from __future__ import annotations

import errno
import os
import resource
import signal
import subprocess
import sys
import textwrap

import pytest
import torch
from torch import nn

from foldwise import store
from workers.train import checkpoint as checkpoint_module
from workers.train.checkpoint import WRITE_CHUNK_BYTES, NoRoomError, read_checkpoint, save_checkpoint

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))


def network(value: float) -> nn.Module:
    """A network whose checkpoint is several write pieces long (about 4 MB), every weight ``value``."""
    model = nn.Linear(1000, 1000)
    with torch.no_grad():
        model.weight.fill_(value)
        model.bias.fill_(value)
    return model


def weight(path) -> float:
    return float(read_checkpoint(path)["state_dict"]["weight"][0, 0])


@pytest.fixture
def written(tmp_path):
    """A checkpoint already there (weights 1.0), as the previous increment's or delivery's."""
    path = tmp_path / "7.pt"
    save_checkpoint(network(1.0), {"iterations": 1}, path)
    assert path.stat().st_size > 3 * WRITE_CHUNK_BYTES
    return path


def run_python(code: str, *args: str) -> subprocess.CompletedProcess:
    environment = {**os.environ, "PYTHONPATH": REPO, "OMP_NUM_THREADS": "1"}
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code), *args],
        capture_output=True,
        text=True,
        timeout=120,
        env=environment,
        check=False,
    )


def test_a_write_past_the_file_size_limit_is_a_no_room_error_that_keeps_the_old_checkpoint(written):
    """A real refusal: RLIMIT_FSIZE under the checkpoint's size makes the kernel refuse the write
    part way (EFBIG; Python ignores SIGXFSZ), as a full volume refuses it with ENOSPC."""
    limit = written.stat().st_size // 2
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, hard))
    try:
        with pytest.raises(NoRoomError) as refused:
            save_checkpoint(network(2.0), {"iterations": 2}, written)
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
    assert refused.value.errno == errno.EFBIG
    message = str(refused.value)
    assert f"no room on the volume for {written} (4.0 MB): File too large" in message and "as it was" in message
    assert weight(written) == 1.0
    assert sorted(p.name for p in written.parent.iterdir()) == ["7.pt"]  # its temporary file removed


def test_a_full_volume_keeps_the_old_checkpoint_and_the_write_succeeds_once_there_is_room(written, monkeypatch):
    real_write = os.write
    pieces = []

    def volume_full_after_two_pieces(descriptor, data):
        pieces.append(len(data))
        if len(pieces) > 2:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        return real_write(descriptor, data)

    monkeypatch.setattr(checkpoint_module.os, "write", volume_full_after_two_pieces)
    with pytest.raises(NoRoomError, match="No space left on device") as refused:
        save_checkpoint(network(2.0), {"iterations": 2}, written)
    assert refused.value.errno == errno.ENOSPC and isinstance(refused.value, OSError)
    assert weight(written) == 1.0
    assert sorted(p.name for p in written.parent.iterdir()) == ["7.pt"]

    monkeypatch.setattr(checkpoint_module.os, "write", real_write)  # room again
    save_checkpoint(network(2.0), {"iterations": 2}, written)
    assert weight(written) == 2.0


def test_other_write_errors_are_not_called_a_lack_of_room(written, monkeypatch):
    def broken(descriptor, data):
        raise OSError(errno.EIO, os.strerror(errno.EIO))

    monkeypatch.setattr(checkpoint_module.os, "write", broken)
    with pytest.raises(OSError) as failed:
        save_checkpoint(network(3.0), {}, written)
    assert not isinstance(failed.value, NoRoomError) and failed.value.errno == errno.EIO
    assert weight(written) == 1.0


def test_a_writer_killed_mid_write_leaves_the_old_checkpoint_whole_and_only_its_temporary_file(written):
    """SIGKILL after the second piece of the new checkpoint: the file at the path is the old one,
    whole; beside it only the temporary file, half written, which the store names as a killed
    write of that checkpoint; the next write (the increment run again) replaces the old one."""
    done = run_python(
        """
        import os, signal, sys
        from pathlib import Path
        from torch import nn
        from workers.train import checkpoint

        real_write, pieces = os.write, []

        def killed_after_two_pieces(descriptor, data):
            if len(pieces) == 2:
                os.kill(os.getpid(), signal.SIGKILL)
            pieces.append(len(data))
            return real_write(descriptor, data)

        checkpoint.os.write = killed_after_two_pieces
        checkpoint.save_checkpoint(nn.Linear(1000, 1000), {"iterations": 2}, Path(sys.argv[1]))
        """,
        str(written),
    )
    assert done.returncode == -signal.SIGKILL, done.stderr
    names = sorted(p.name for p in written.parent.iterdir())
    assert len(names) == 2 and "7.pt" in names
    (temporary,) = [name for name in names if name != "7.pt"]
    assert store.unfinished_write_target(temporary) == "7.pt"
    assert (written.parent / temporary).stat().st_size == 2 * WRITE_CHUNK_BYTES  # torn, never renamed
    assert weight(written) == 1.0

    save_checkpoint(network(4.0), {"iterations": 2}, written)
    assert weight(written) == 4.0


def test_the_train_worker_records_a_refused_write_on_the_model_and_gives_up_when_it_must(database, monkeypatch):
    from sqlalchemy import select

    from db.models import Model, ModelStatus
    from db.session import session_scope
    from services.embedded import start_experiment
    from services.scheduler import reconcile
    from tests.services.flow_helpers import config, in_flight
    from workers.train.tasks import WaitForRoom, _claim

    monkeypatch.setattr(reconcile, "_send", lambda send: None)  # no worker: the model waits, claimed below
    experiment_id = start_experiment(config())
    in_flight(experiment_id)
    with session_scope() as session:
        model_id = session.scalar(select(Model.id).where(Model.experiment_id == experiment_id))
    assert _claim(model_id, "delivery-1")
    slept = []
    wait = WaitForRoom(model_id, "delivery-1", retry_s=5.0, give_up_s=60.0, sleep=slept.append)
    refused = NoRoomError(errno.ENOSPC, "no room on the volume for 7.pt (4.0 MB): No space left on device")
    wait(refused)
    wait(refused)
    assert slept == [5.0, 5.0] and wait.record() == {"refused": 2, "last_error": str(refused)}
    with session_scope() as session:
        model = session.get(Model, model_id)
        assert model.status == ModelStatus.training
        assert "waiting for room to write the checkpoint" in model.error and "No space left" in model.error

    # Another delivery took the model over: this one gives up, and says nothing on its row.
    with session_scope() as session:
        session.get(Model, model_id).task_id = "delivery-2"
    with pytest.raises(NoRoomError):
        wait(refused)
    assert len(slept) == 2

    # Past its patience: given up, saying how long it waited.
    with session_scope() as session:
        session.get(Model, model_id).task_id = "delivery-1"
    patient = WaitForRoom(model_id, "delivery-1", retry_s=5.0, give_up_s=0.0, sleep=slept.append)
    with pytest.raises(NoRoomError, match="1 writes refused over 0 s, given up") as given_up:
        patient(refused)
    assert given_up.value.errno == errno.ENOSPC and len(slept) == 2
