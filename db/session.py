"""Engines and sessions. SQLite (embedded default) or PostgreSQL through FOLDWISE_DATABASE_URL."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from sqlalchemy import Engine, create_engine, event
from sqlalchemy.orm import Session, sessionmaker

from foldwise.settings import get_settings


def make_engine(url: str) -> Engine:
    if url.startswith("sqlite"):
        path = url.split("///", 1)[-1]
        if path and path != ":memory:":
            Path(path).parent.mkdir(parents=True, exist_ok=True)
        engine = create_engine(url, connect_args={"check_same_thread": False, "timeout": 30})

        @event.listens_for(engine, "connect")
        def _sqlite_pragmas(dbapi_connection, _record):  # pragma: no cover - trivial
            cursor = dbapi_connection.cursor()
            cursor.execute("PRAGMA foreign_keys=ON")
            # WAL lets the API read while a worker writes.
            cursor.execute("PRAGMA journal_mode=WAL")
            cursor.close()

        return engine
    # connect_timeout: an unreachable host fails a health check instead of hanging it.
    connect_args = {"connect_timeout": 5} if url.startswith("postgresql") else {}
    return create_engine(url, pool_pre_ping=True, connect_args=connect_args)


_ENGINES: dict[str, Engine] = {}


def get_engine(url: str | None = None) -> Engine:
    """One engine per URL and process."""
    url = url or get_settings().resolved_database_url
    if url not in _ENGINES:
        _ENGINES[url] = make_engine(url)
    return _ENGINES[url]


# Each URL's session factory, beside the engine it was made for. Each sessionmaker defines a
# Session subclass of its own, and SQLAlchemy sets up that class's event dispatch on its first
# query: a factory made per session cost about as much again as the session's first read.
_SESSIONMAKERS: dict[str, tuple[Engine, sessionmaker[Session]]] = {}


def get_sessionmaker(url: str | None = None) -> sessionmaker[Session]:
    """One session factory per URL and engine (made again when reset_engines replaced the engine)."""
    url = url or get_settings().resolved_database_url
    engine = get_engine(url)
    made = _SESSIONMAKERS.get(url)
    if made is None or made[0] is not engine:
        made = _SESSIONMAKERS[url] = (engine, sessionmaker(engine, expire_on_commit=False))
    return made[1]


@contextmanager
def session_scope(url: str | None = None) -> Iterator[Session]:
    """A transaction: committed on success, rolled back on error."""
    session = get_sessionmaker(url)()
    try:
        yield session
        session.commit()
    except BaseException:
        session.rollback()
        raise
    finally:
        session.close()


def reset_engines() -> None:
    """Dispose of every engine (tests that switch databases, processes after a fork)."""
    _SESSIONMAKERS.clear()
    while _ENGINES:
        _, engine = _ENGINES.popitem()
        engine.dispose()
