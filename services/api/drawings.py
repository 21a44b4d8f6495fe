"""Figures of the record (the report, the paper's figures) drawn once per content.

Each GET used to redraw with matplotlib and rewrite the files: 45 at once delayed every other
route by seconds. Now a GET first reads what the figure shows (a few queries) and hashes it;
a figure already drawn from the same content is served from its folder
(``<report dir>/drawn/<name>-<hash>/``). Otherwise it is drawn into a staging folder renamed
into place, so a reader never sees half a figure. Drawing waits for an asyncio lock, not a
thread: pyplot is not thread-safe, so one figure is drawn at a time, and the requests waiting
for it hold no thread meanwhile.
"""

from __future__ import annotations

import asyncio
import hashlib
import json
import shutil
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

from starlette.concurrency import run_in_threadpool

from foldwise import store

INDEX = "files.json"
# Folders of earlier contents kept beside the newest: a response may still be sending one.
KEEP_PREVIOUS = 1

_drawing_locks: dict[int, asyncio.Lock] = {}
_settled: set[str] = set()  # figures drawn once by this process, the heap settled after


def _drawing_lock() -> asyncio.Lock:
    """The lock of the running event loop (a test client may start a loop per request)."""
    loop = asyncio.get_running_loop()
    lock = _drawing_locks.get(id(loop))
    if lock is None or getattr(lock, "_foldwise_loop", None) is not loop:
        lock = asyncio.Lock()
        lock._foldwise_loop = loop  # type: ignore[attr-defined]
        _drawing_locks.clear()  # one loop serves an app at a time
        _drawing_locks[id(loop)] = lock
    return lock


def _digest(content: Any) -> str:
    return hashlib.sha256(json.dumps(content, sort_keys=True, default=str).encode()).hexdigest()[:20]


def report_content(experiment_id: int) -> str:
    """What ``foldwise report`` draws for one experiment, hashed (queries.NotFound if it does not exist).

    The report's rows (services.report.report_rows) are made of the history and the test set's
    render time: those are hashed, read in one session, rather than the rows themselves."""
    from db.session import session_scope
    from services import queries

    with session_scope() as session:
        experiment = queries.get_experiment(session, experiment_id)
        content = {
            "name": experiment.name,
            "status": str(experiment.status),
            "config": experiment.config,
            "history": queries.history(session, experiment_id),
            "test_set_render_seconds": queries.test_set_render_seconds(session, experiment_id),
        }
    return _digest(content)


def figure_content(experiment_id: int, name: str) -> str:
    """What figure ``name`` draws for one experiment, hashed (queries.NotFound if it does not exist).

    A figure draws services.figures.load_runs: the history and stages, and a label, cuts and
    kind that the experiment's name and stored config determine; those are hashed as stored,
    without validating the config per request."""
    from db.session import session_scope
    from services import queries

    with session_scope() as session:
        experiment = queries.get_experiment(session, experiment_id)
        content = {
            "figure": name,
            "name": experiment.name,
            "config": experiment.config,
            "history": queries.history(session, experiment_id),
            # A running stage's seconds grow with the clock; no figure draws them.
            "stages": [
                {key: value for key, value in stage.items() if key != "seconds"}
                for stage in queries.stages(session, experiment_id)
            ],
        }
    return _digest(content)


def _drawn_folder(experiment_id: int, name: str, digest: str) -> Path:
    return store.resolve(store.report_dir(experiment_id)) / "drawn" / f"{name}-{digest}"


def _index(folder: Path) -> dict[str, str] | None:
    try:
        return json.loads((folder / INDEX).read_text())
    except (OSError, ValueError):
        return None


def _draw_into(folder: Path, draw: Callable[[Path], dict[str, Path]]) -> dict[str, str]:
    """Run ``draw`` into a staging folder and rename it to ``folder``; the files by extension."""
    folder.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(dir=folder.parent, prefix=".drawing-"))
    try:
        files = {extension: path.name for extension, path in draw(staging).items()}
        (staging / INDEX).write_text(json.dumps(files))
        try:
            staging.rename(folder)
        except OSError:  # drawn meanwhile by another process serving the same store
            if _index(folder) is None:
                raise
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    prefix = folder.name.rsplit("-", 1)[0] + "-"
    older = sorted(
        (p for p in folder.parent.glob(f"{prefix}*") if p != folder and p.name.rsplit("-", 1)[0] + "-" == prefix),
        key=lambda p: p.stat().st_mtime,
    )
    for stale in older[: max(0, len(older) - KEEP_PREVIOUS)]:
        shutil.rmtree(stale, ignore_errors=True)
    return _index(folder) or files


# Digests being read, by event loop, experiment and figure.
_reading: dict[tuple[int, int, str], asyncio.Task] = {}


async def _content_digest(experiment_id: int, name: str, content: Callable[[], str]) -> str:
    """``content()`` read on a reader thread; requests for the same figure that arrive while it
    is being read share that read (a dashboard's crowd asks for the same few figures at once),
    and so see the record as it was a moment before they came."""
    from services.api.deps import run_read

    loop = asyncio.get_running_loop()
    key = (id(loop), experiment_id, name)
    reading = _reading.get(key)
    if reading is None or reading.get_loop() is not loop:
        reading = _reading[key] = loop.create_task(run_read(content))

        def done(task: asyncio.Task) -> None:
            if _reading.get(key) is task:
                del _reading[key]
            if not task.cancelled():
                task.exception()  # retrieved: each waiter gets it (a 404), or none is left

        reading.add_done_callback(done)
    return await asyncio.shield(reading)  # a client that hangs up leaves the read to the others


async def drawn(
    experiment_id: int,
    name: str,
    content: Callable[[], str],
    draw: Callable[[Path], dict[str, Path]],
) -> tuple[Path, dict[str, str]]:
    """The folder of figure ``name`` drawn from the record's present content, and its files by
    extension: drawn now if that content was never drawn, else as drawn before."""
    digest = await _content_digest(experiment_id, name, content)
    folder = _drawn_folder(experiment_id, name, digest)
    files = _index(folder)
    if files is None:
        async with _drawing_lock():
            files = _index(folder)  # drawn while this request waited
            if files is None:
                files = await run_in_threadpool(_draw_into, folder, draw)
                if name not in _settled:
                    # A figure's first drawing leaves matplotlib's modules and caches for the
                    # process's life: out of the collector's sight, as the API's own are. Later
                    # drawings leave little; a collection then would only hold the requests.
                    from services.api.app import settle_heap

                    settle_heap()
                    _settled.add(name)
    return folder, files
