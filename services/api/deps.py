"""What the routes depend on: the settings, a database session, the token, the probes, path ids.

Everything is read from ``request.app.state`` (set by :func:`services.api.app.create_app`), so
one process can serve several apps with different settings (the tests do) and a test can swap
any of them with ``app.dependency_overrides[get_session] = ...``.

The dependencies that do no I/O are ``async def``: FastAPI runs a plain ``def`` dependency on a
worker thread, and each such hand-over (a thread woken, the result handed back to the event
loop) costs more than the dependency itself. Under load those hand-overs queue behind every
other request's, so a read route pays for them in latency. What touches the database or the
broker stays on a thread: the route's reads, and closing the session; a read route hands both
to one thread with :func:`read_with`.
"""

# No `from __future__ import annotations`: FastAPI resolves these annotations at runtime.
import asyncio
import secrets
import threading
from collections.abc import AsyncIterator, Callable
from concurrent.futures import ThreadPoolExecutor
from typing import Annotated, Any, TypeVar

import anyio
from fastapi import Depends, HTTPException, Path, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session

from db.session import get_sessionmaker
from foldwise.settings import Settings
from services.api.probes import BrokerProbe, SchemaCheck
from services.queries import MAX_ID

# Ids, stage orders and increments k are 32-bit INTEGER columns (MAX_ID, services.queries). An
# id outside 1..MAX_ID names nothing: the app answers 404 for it (services.api.app.id_out_of_range);
# a stage or k filter past it is a 422. Either way the database, which would raise, never sees it.
MAX_INT_COLUMN = MAX_ID

T = TypeVar("T")

ExperimentId = Annotated[int, Path(ge=1, le=MAX_ID, description="experiment id")]
ModelId = Annotated[int, Path(ge=1, le=MAX_ID, description="model id (ω)")]


async def get_app_settings(request: Request) -> Settings:
    """The settings this app was created with."""
    return request.app.state.settings


SettingsDep = Annotated[Settings, Depends(get_app_settings)]


async def get_session(settings: SettingsDep) -> AsyncIterator[Session]:
    """A session per request; uncommitted work (a request that failed half way) is rolled back on close.

    Creating the session connects nothing (the first query takes a connection from the engine's
    pool, on the route's thread), so it is created on the event loop; closing it returns the
    connection and may talk to the database, so it runs on a thread. That thread is not one of
    the shared pool's (a limiter of its own): with every pooled thread waiting for a database
    connection, the close that returns one must not wait for a thread. It is shielded from
    cancellation (a client that hangs up), which would otherwise leave the connection out. A
    session that holds no transaction (never used, or closed by the route) has nothing to return
    and is closed here."""
    session = get_sessionmaker(settings.resolved_database_url)()
    try:
        yield session
    finally:
        if session.in_transaction():
            with anyio.CancelScope(shield=True):
                await anyio.to_thread.run_sync(session.close, limiter=anyio.CapacityLimiter(1))
        else:
            session.close()


SessionDep = Annotated[Session, Depends(get_session)]


# The threads that run the reads (read_with) and /health's probes (run_probe), started with
# the API (start_threads) and kept for its life. A crowd of requests on the shared pool made it
# start a thread for nearly each one, and every start waits for the new thread to take the GIL
# from the busy ones: the event loop, and every request, stalled for milliseconds per thread.
# The probes have threads of their own: a silent broker holds one for its timeout, which no
# status read should wait behind.
READ_THREADS = 8
PROBE_THREADS = 4
_readers = ThreadPoolExecutor(max_workers=READ_THREADS, thread_name_prefix="foldwise-read")
_probers = ThreadPoolExecutor(max_workers=PROBE_THREADS, thread_name_prefix="foldwise-probe")


async def start_threads() -> None:
    """Start every reader and probe thread now (each of the first requests would start one)."""

    async def start(pool: ThreadPoolExecutor, count: int) -> None:
        gate = threading.Barrier(count)

        def hold() -> None:
            try:
                gate.wait(timeout=5)  # held until all are running: each on a thread of its own
            except threading.BrokenBarrierError:
                pass

        loop = asyncio.get_running_loop()
        await asyncio.gather(*(loop.run_in_executor(pool, hold) for _ in range(count)))

    await start(_readers, READ_THREADS)
    await start(_probers, PROBE_THREADS)


async def run_probe(function: Callable[..., T], *args: Any) -> T:
    """``function(*args)`` on a probe thread (/health's database and broker checks)."""
    return await asyncio.get_running_loop().run_in_executor(_probers, function, *args)


async def read_with(session: Session, read: Callable[..., T], *args: Any) -> T:
    """``read(session, *args)`` on a reader thread, the session closed on that thread after it.

    A read route declared ``async def`` that reads through this hands over to a thread once:
    FastAPI runs a plain ``def`` route on a thread, then validates its answer on another hand-over,
    and :func:`get_session` would close the session on a third. ``read`` must return plain data
    (dicts, lists, schema models): the ORM objects it read are detached once it returns. A read
    that the client stops waiting for still runs to its end, and closes its session."""

    def run() -> T:
        try:
            return read(session, *args)
        finally:
            session.close()

    return await run_read(run)


async def run_read(function: Callable[..., T], *args: Any) -> T:
    """``function(*args)`` on a reader thread (a read that opens its own session)."""
    return await asyncio.get_running_loop().run_in_executor(_readers, function, *args)


async def get_broker(request: Request) -> BrokerProbe:
    return request.app.state.broker


BrokerDep = Annotated[BrokerProbe, Depends(get_broker)]


async def get_schema_check(request: Request) -> SchemaCheck:
    return request.app.state.schema_check


SchemaCheckDep = Annotated[SchemaCheck, Depends(get_schema_check)]


bearer = HTTPBearer(auto_error=False, description="FOLDWISE_API_TOKEN of the API server")


async def require_token(
    request: Request,
    settings: SettingsDep,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)],
) -> None:
    """Writes need ``Authorization: Bearer <FOLDWISE_API_TOKEN>``; with no token configured they are off."""
    if not settings.api_token:
        raise HTTPException(
            status.HTTP_403_FORBIDDEN,
            "writes are disabled: FOLDWISE_API_TOKEN is not set on the API server",
        )
    challenge = {"WWW-Authenticate": "Bearer"}
    if credentials is None:
        detail = (
            "the Authorization header must be 'Bearer <token>'"
            if request.headers.get("authorization")
            else "missing token: send 'Authorization: Bearer <token>'"
        )
        raise HTTPException(status.HTTP_401_UNAUTHORIZED, detail, headers=challenge)
    if not secrets.compare_digest(credentials.credentials.encode(), settings.api_token.encode()):
        raise HTTPException(status.HTTP_401_UNAUTHORIZED, "wrong token", headers=challenge)


TokenRequired = Depends(require_token)
