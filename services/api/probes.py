"""What the API asks of the services beside it: the broker and the database schema.

Every broker call has a short timeout so that a dead broker makes the API say so instead of
hanging. Queue depth is read straight from Redis (``LLEN`` on the queue keys) and workers are
found with a Celery broadcast ping. Nothing connects until a request needs it.

Both probes answer ``GET /health``, which load balancers and dashboards call often, so each
check is one round trip on a connection kept open: the Redis client is the probe's own, with a
pool (a new client per call opened a connection and ran redis-py's handshake, several times
the cost of the PING itself); the schema check reads ``alembic_version`` with one query, and
asks Alembic only when that row is not the head it expects.
"""

import threading
from typing import Any
from urllib.parse import urlsplit

from kombu.utils.url import maybe_sanitize_url
from sqlalchemy.orm import Session

from foldwise.settings import Settings


class BrokerUnavailable(RuntimeError):
    """The broker did not answer within the timeout."""


def _first_line(error: BaseException, limit: int = 300) -> str:
    message = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
    return message[:limit]


class BrokerProbe:
    """Short-timeout questions to the broker: is it up, how deep are the queues, which workers answer."""

    def __init__(self, settings: Settings, timeout_s: float, ping_timeout_s: float) -> None:
        self.url = settings.broker_url
        self.eager = settings.eager
        self.timeout_s = timeout_s
        self.ping_timeout_s = ping_timeout_s
        self.scheme = urlsplit(self.url).scheme.lower()
        self._settings = settings
        self._celery = None
        self._celery_lock = threading.Lock()
        self._client = None
        self._client_lock = threading.Lock()

    @property
    def display_url(self) -> str:
        """The broker URL without its password, safe to show."""
        return maybe_sanitize_url(self.url)

    @property
    def skipped_reason(self) -> str | None:
        # Embedded mode runs tasks in-process: there is no broker to ask.
        if self.eager:
            return "tasks run in-process (FOLDWISE_EAGER is set): no broker is used"
        if self.scheme == "memory":
            return "in-memory broker: nothing to reach"
        return None

    @property
    def is_redis(self) -> bool:
        return self.scheme in ("redis", "rediss")

    def _redis(self):
        """The probe's Redis client, made on first use; its pool keeps the connection between calls
        (redis-py's pool is thread-safe and opens a new one in a forked process)."""
        with self._client_lock:
            if self._client is None:
                import redis
                from redis.backoff import NoBackoff
                from redis.retry import Retry

                # One retry, on a connection error only: a pooled connection the broker closed
                # (it restarted) is replaced at once instead of failing one check. A refused
                # connection fails again at once; a timeout is not retried, so a silent broker
                # costs one timeout.
                self._client = redis.Redis.from_url(
                    self.url,
                    socket_connect_timeout=self.timeout_s,
                    socket_timeout=self.timeout_s,
                    retry=Retry(NoBackoff(), 1, supported_errors=(redis.ConnectionError,)),
                )
            return self._client

    def _drop_connections(self) -> None:
        """After a failed call: the next one starts on a new connection."""
        client = self._client
        if client is not None:
            try:
                client.connection_pool.disconnect()
            except Exception:  # nothing to answer for: the connections are being dropped
                pass

    def check(self) -> dict[str, Any]:
        """``{"status": "ok" | "error" | "skipped", ...}``; a silent broker costs about twice ``timeout_s``."""
        reason = self.skipped_reason
        if reason:
            return {"status": "skipped", "detail": reason}
        try:
            if self.is_redis:
                try:
                    self._redis().ping()
                except Exception:
                    self._drop_connections()
                    raise
            else:
                from kombu import Connection

                with Connection(self.url, connect_timeout=self.timeout_s) as connection:
                    self._connect_once(connection)
        except Exception as error:  # any failure to talk to the broker is the answer, not a 500
            return {"status": "error", "url": self.display_url, "detail": _first_line(error)}
        return {"status": "ok", "url": self.display_url}

    def _connect_once(self, connection) -> None:
        # Kombu would otherwise retry a lost broker for minutes.
        connection.ensure_connection(max_retries=1, interval_start=0, interval_step=0, timeout=self.timeout_s)

    def queue_depths(self, queues: tuple[str, ...]) -> dict[str, Any]:
        """Messages waiting per queue, and those delivered to a worker but not yet acknowledged.

        Kombu's Redis transport keeps a queue as one list per priority step (the plain queue
        name for priority 0); its depth is the sum of their lengths, as kombu itself counts it.
        """
        from kombu.transport.redis import Channel

        try:
            with self._redis().pipeline(transaction=False) as pipe:
                for queue in queues:
                    for step in Channel.priority_steps:
                        pipe.llen(f"{queue}{Channel.sep}{step}" if step else queue)
                pipe.hlen(Channel.unacked_key)
                lengths = pipe.execute()
        except Exception as error:
            self._drop_connections()
            raise BrokerUnavailable(f"broker {self.display_url} is unreachable: {_first_line(error)}") from error
        steps = len(Channel.priority_steps)
        depths = {queue: sum(lengths[i * steps : (i + 1) * steps]) for i, queue in enumerate(queues)}
        return {"queues": depths, "unacked": lengths[-1]}

    def _celery_app(self):
        with self._celery_lock:
            if self._celery is None:
                from workers.app import create_app as create_celery_app

                celery = create_celery_app(self._settings)
                # Closing a Redis channel waits out its pending BRPOP (1 s by default); a short
                # poll makes a ping take about ping_timeout_s instead of twice that.
                celery.conf.broker_transport_options = {
                    **celery.conf.broker_transport_options,
                    "polling_interval": 0.05,
                }
                self._celery = celery
            return self._celery

    def ping_workers(self) -> list[str]:
        """Hostnames of the workers that answer a broadcast ping within ``ping_timeout_s``."""
        celery = self._celery_app()
        try:
            with celery.connection_for_write() as connection:
                self._connect_once(connection)
                replies = celery.control.ping(timeout=self.ping_timeout_s, connection=connection) or []
        except Exception as error:
            raise BrokerUnavailable(f"broker {self.display_url} is unreachable: {_first_line(error)}") from error
        return sorted(hostname for reply in replies for hostname in reply)


# Alembic's version table under its default name (db/migrations/env.py keeps it): one row, the
# revision the database is at.
VERSION_QUERY = "SELECT version_num FROM alembic_version"


class SchemaCheck:
    """The migration head the code expects, read once from the migration scripts."""

    def __init__(self, url: str) -> None:
        self.url = url
        self._head: str | None = None

    @property
    def head(self) -> str | None:
        if self._head is None:
            from alembic.script import ScriptDirectory

            from db.migrate import alembic_config

            self._head = ScriptDirectory.from_config(alembic_config(self.url)).get_current_head()
        return self._head

    def check(self, session: Session) -> dict[str, Any]:
        """``{"status": "ok", "revision": ...}`` when the database answers at the head revision; else
        ``{"status": "error", ...}`` saying whether it is unreachable or at another revision."""
        try:
            connection = session.connection()  # connects: an unreachable database fails here
        except Exception as error:
            session.rollback()
            return {"status": "error", "detail": f"database unreachable: {_first_line(error)}"}
        try:
            recorded = connection.exec_driver_sql(VERSION_QUERY).scalars().all()
        except Exception:  # no version table yet (an empty database): Alembic says what it finds
            session.rollback()
            recorded = []
        if len(recorded) == 1:
            revision = recorded[0]
        else:
            revision = self._revision_by_alembic(session)
            if isinstance(revision, dict):
                return revision
        if revision != self.head:
            return {
                "status": "error",
                "revision": revision,
                "head": self.head,
                "detail": f"database schema is at revision {revision}, the code expects {self.head}: "
                "run `foldwise db upgrade`",
            }
        return {"status": "ok", "revision": revision}

    def _revision_by_alembic(self, session: Session) -> str | None | dict[str, Any]:
        """The revision as Alembic reads it (no version table: None), or the error to answer."""
        from alembic.runtime.migration import MigrationContext

        try:
            return MigrationContext.configure(session.connection()).get_current_revision()
        except Exception as error:
            session.rollback()
            return {"status": "error", "detail": f"database unreachable: {_first_line(error)}"}
