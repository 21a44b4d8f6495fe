"""The REST API: the experiment record for everyone to read; creating and cancelling need a token.

Reads go through :mod:`services.queries` (the same helpers the CLI and the report use); the
scheduler picks up an experiment created here on its next pass, so the API never enqueues
work itself. Queue depth is read straight from Redis (``LLEN`` on the queue keys) and
workers are found with a Celery broadcast ping; every broker call has a short timeout so a
dead broker makes the API say so instead of hanging.

Serve with ``uvicorn services.api.app:app``. Imports neither torch nor bpy (the task modules
of the Celery app import them only inside task bodies, and are never imported here).
"""

# No `from __future__ import annotations`: FastAPI must resolve the dependency annotations
# declared inside create_app at runtime, and string annotations cannot see those locals.
import json
import secrets
import threading
from collections.abc import Iterator
from typing import Annotated, Any
from urllib.parse import urlsplit

from fastapi import Depends, FastAPI, HTTPException, Path, Query, Request, Response, status
from fastapi.responses import JSONResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from kombu.utils.url import maybe_sanitize_url
from sqlalchemy import text
from sqlalchemy.orm import Session

from db.models import ExperimentStatus
from db.session import get_sessionmaker
from foldwise.config import ConfigError, ExperimentConfig, parse_config, parse_config_text
from foldwise.settings import Settings, get_settings
from services import queries
from services.api.schemas import (
    BrokerDown,
    ErrorDetail,
    ExperimentListItem,
    ExperimentSummary,
    Health,
    HistoryEntry,
    ModelDetail,
    QueueStatus,
    StageSummary,
)

# Database ids are 64-bit; a larger number can name nothing (and SQLite would overflow on it).
MAX_ID = 2**63 - 1
# An experiment config is a few kilobytes of YAML; anything this large is a mistake.
MAX_CONFIG_BYTES = 1 << 20

JSON_TYPES = frozenset({"application/json"})
YAML_TYPES = frozenset({"application/yaml", "text/yaml", "application/x-yaml", "text/x-yaml"})
ACCEPTED_TYPES = "application/json, application/yaml or text/yaml"

LIVE_STATUSES = (ExperimentStatus.pending, ExperimentStatus.running)

NOT_FOUND: dict[int | str, dict[str, Any]] = {
    404: {"model": ErrorDetail, "description": "no experiment or model with this id"}
}
WRITE_ERRORS: dict[int | str, dict[str, Any]] = {
    401: {"model": ErrorDetail, "description": "missing or wrong token"},
    403: {"model": ErrorDetail, "description": "no token is configured on the server (FOLDWISE_API_TOKEN)"},
}

ExperimentId = Annotated[int, Path(ge=1, le=MAX_ID, description="experiment id")]
ModelId = Annotated[int, Path(ge=1, le=MAX_ID, description="model id (ω)")]


# --------------------------------------------------------------------------- broker


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
        import redis
        from redis.backoff import NoBackoff
        from redis.retry import Retry

        # No retries: one refused or timed-out connection is the answer.
        return redis.Redis.from_url(
            self.url,
            socket_connect_timeout=self.timeout_s,
            socket_timeout=self.timeout_s,
            retry=Retry(NoBackoff(), 0),
        )

    def check(self) -> dict[str, Any]:
        """``{"status": "ok" | "error" | "skipped", ...}``; a silent broker costs about twice ``timeout_s``."""
        reason = self.skipped_reason
        if reason:
            return {"status": "skipped", "detail": reason}
        try:
            if self.is_redis:
                client = self._redis()
                try:
                    client.ping()
                finally:
                    client.close()
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

        client = self._redis()
        try:
            with client.pipeline(transaction=False) as pipe:
                for queue in queues:
                    for step in Channel.priority_steps:
                        pipe.llen(f"{queue}{Channel.sep}{step}" if step else queue)
                pipe.hlen(Channel.unacked_key)
                lengths = pipe.execute()
        except Exception as error:
            raise BrokerUnavailable(f"broker {self.display_url} is unreachable: {_first_line(error)}") from error
        finally:
            client.close()
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


# --------------------------------------------------------------------------- database


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
        from alembic.runtime.migration import MigrationContext

        try:
            session.execute(text("SELECT 1"))
            revision = MigrationContext.configure(session.connection()).get_current_revision()
        except Exception as error:
            session.rollback()
            return {"status": "error", "detail": f"database unreachable: {_first_line(error)}"}
        if revision != self.head:
            return {
                "status": "error",
                "revision": revision,
                "head": self.head,
                "detail": f"database schema is at revision {revision}, the code expects {self.head}: "
                "run `foldwise db upgrade`",
            }
        return {"status": "ok", "revision": revision}


# --------------------------------------------------------------------------- request bodies


def _media_type(request: Request) -> str | None:
    header = request.headers.get("content-type")
    if not header:
        return None
    return header.split(";", 1)[0].strip().lower()


def _reject_constant(name: str) -> None:
    # Python's json accepts NaN and Infinity; JSON does not, and PostgreSQL's JSON columns refuse them.
    raise ValueError(f"{name} is not a JSON number")


async def read_config(request: Request) -> ExperimentConfig:
    """The request body as a validated experiment config (JSON or YAML)."""
    media_type = _media_type(request)
    is_json = media_type in JSON_TYPES or (media_type or "").endswith("+json")
    if not is_json and media_type not in YAML_TYPES:
        raise HTTPException(
            status.HTTP_415_UNSUPPORTED_MEDIA_TYPE,
            f"unsupported content type {media_type or '(none)'}: send the experiment config as {ACCEPTED_TYPES}",
        )
    declared = request.headers.get("content-length")
    if declared and declared.isdigit() and int(declared) > MAX_CONFIG_BYTES:
        raise HTTPException(status.HTTP_413_CONTENT_TOO_LARGE, f"config larger than {MAX_CONFIG_BYTES} bytes")
    body = await request.body()
    if len(body) > MAX_CONFIG_BYTES:
        raise HTTPException(status.HTTP_413_CONTENT_TOO_LARGE, f"config larger than {MAX_CONFIG_BYTES} bytes")
    if not body.strip():
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, "empty body: send an experiment config")
    try:
        document = body.decode("utf-8")
    except UnicodeDecodeError as error:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, f"the body is not UTF-8 text: {error}") from None
    try:
        if is_json:
            try:
                data = json.loads(document, parse_constant=_reject_constant)
            except (json.JSONDecodeError, ValueError) as error:
                raise ConfigError(f"invalid experiment config: not JSON: {error}") from None
            config = parse_config(data)
        else:
            config = parse_config_text(document)
        return config
    except ConfigError as error:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, str(error)) from None


_CONFIG_BODY_DOC = {
    "requestBody": {
        "required": True,
        "description": "An experiment config (the same document as `foldwise run CONFIG` reads).",
        "content": {
            "application/json": {"schema": {"$ref": "#/components/schemas/ExperimentConfig"}},
            "application/yaml": {"schema": {"type": "string", "description": "the same config as YAML"}},
            "text/yaml": {"schema": {"type": "string", "description": "the same config as YAML"}},
        },
    }
}


def _document_config_schema(app: FastAPI) -> None:
    """Add ExperimentConfig and its sections to the OpenAPI components (the body is read by hand)."""
    build_openapi = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            document = build_openapi()
            config_schema = ExperimentConfig.model_json_schema(ref_template="#/components/schemas/{model}")
            components = document.setdefault("components", {}).setdefault("schemas", {})
            components.update(config_schema.pop("$defs", {}))
            components["ExperimentConfig"] = config_schema
        return app.openapi_schema

    app.openapi = openapi


# --------------------------------------------------------------------------- the app


def create_app(
    settings: Settings | None = None,
    *,
    broker_timeout_s: float = 1.0,
    ping_timeout_s: float = 0.5,
) -> FastAPI:
    """The API for ``settings`` (default: the process settings from the environment).

    ``broker_timeout_s`` bounds each connection to the broker, ``ping_timeout_s`` how long
    ``GET /queues`` waits for workers to answer. Nothing is connected until a request needs it.
    """
    settings = settings or get_settings()
    database_url = settings.resolved_database_url
    broker = BrokerProbe(settings, timeout_s=broker_timeout_s, ping_timeout_s=ping_timeout_s)
    schema = SchemaCheck(database_url)

    app = FastAPI(
        title="foldwise",
        summary="Active learning of a detector for one deformable object, from rendered images.",
        version="0.1.0",
    )
    app.state.settings = settings
    app.state.broker = broker
    _document_config_schema(app)

    def get_session() -> Iterator[Session]:
        session = get_sessionmaker(database_url)()
        try:
            yield session
        finally:
            # Uncommitted work (a request that failed half way) is rolled back here.
            session.close()

    bearer = HTTPBearer(auto_error=False, description="FOLDWISE_API_TOKEN of the API server")

    def require_token(
        request: Request, credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)]
    ) -> None:
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

    SessionDep = Annotated[Session, Depends(get_session)]

    @app.exception_handler(queries.NotFound)
    async def _not_found(_request: Request, error: queries.NotFound) -> JSONResponse:
        return JSONResponse({"detail": str(error)}, status_code=status.HTTP_404_NOT_FOUND)

    @app.get(
        "/health",
        tags=["status"],
        response_model=Health,
        responses={503: {"model": Health, "description": "the database is unreachable or not migrated"}},
    )
    def health(session: SessionDep, response: Response) -> dict[str, Any]:
        """Database and broker reachability: 200 while the database serves (the broker may be down), else 503."""
        database = schema.check(session)
        broker_state = broker.check()
        if database["status"] != "ok":
            overall = "error"
            response.status_code = status.HTTP_503_SERVICE_UNAVAILABLE
        elif broker_state["status"] == "error":
            overall = "degraded"
        else:
            overall = "ok"
        return {"status": overall, "database": database, "broker": broker_state}

    @app.get("/experiments", tags=["experiments"], response_model=list[ExperimentListItem])
    def list_experiments(
        session: SessionDep,
        status_filter: Annotated[ExperimentStatus | None, Query(alias="status")] = None,
    ) -> list[dict[str, Any]]:
        """Every experiment, oldest first; ``?status=running`` keeps one status."""
        experiments = queries.list_experiments(session)
        if status_filter is not None:
            experiments = [e for e in experiments if e["status"] == status_filter.value]
        return experiments

    @app.post(
        "/experiments",
        tags=["experiments"],
        status_code=status.HTTP_201_CREATED,
        response_model=ExperimentSummary,
        dependencies=[Depends(require_token)],
        openapi_extra=_CONFIG_BODY_DOC,
        responses={
            **WRITE_ERRORS,
            413: {"model": ErrorDetail, "description": "the body is larger than 1 MiB"},
            415: {"model": ErrorDetail, "description": "not JSON or YAML"},
            422: {"model": ErrorDetail, "description": "an invalid config; the message names the key"},
        },
    )
    def create_experiment(
        request: Request,
        response: Response,
        session: SessionDep,
        config: Annotated[ExperimentConfig, Depends(read_config)],
    ) -> dict[str, Any]:
        """Record a new experiment (status pending); the scheduler starts it on its next pass."""
        experiment = queries.create_experiment(session, config)
        session.commit()
        response.headers["Location"] = request.scope.get("root_path", "") + app.url_path_for(
            "experiment_summary", experiment_id=experiment.id
        )
        return queries.summary(session, experiment.id)

    @app.get(
        "/experiments/{experiment_id}",
        tags=["experiments"],
        name="experiment_summary",
        response_model=ExperimentSummary,
        responses=NOT_FOUND,
    )
    def experiment_summary(experiment_id: ExperimentId, session: SessionDep) -> dict[str, Any]:
        """Status, current stage and k, counts of θ, ω and P, elapsed time, best model."""
        return queries.summary(session, experiment_id)

    @app.get("/experiments/{experiment_id}/config", tags=["experiments"], responses=NOT_FOUND)
    def experiment_config(experiment_id: ExperimentId, session: SessionDep) -> dict[str, Any]:
        """The experiment's config as recorded, every default filled in."""
        return queries.get_experiment(session, experiment_id).config

    @app.post(
        "/experiments/{experiment_id}/cancel",
        tags=["experiments"],
        response_model=ExperimentSummary,
        dependencies=[Depends(require_token)],
        responses={
            **WRITE_ERRORS,
            **NOT_FOUND,
            409: {"model": ErrorDetail, "description": "the experiment has already ended"},
        },
    )
    def cancel_experiment(experiment_id: ExperimentId, session: SessionDep) -> dict[str, Any]:
        """Cancel a pending or running experiment; 409 when it has already ended."""
        experiment = queries.get_experiment(session, experiment_id)
        if experiment.status not in LIVE_STATUSES:
            raise HTTPException(
                status.HTTP_409_CONFLICT,
                f"experiment {experiment_id} is already {experiment.status.value}: "
                "only pending or running experiments can be cancelled",
            )
        queries.cancel_experiment(session, experiment_id)
        session.commit()
        return queries.summary(session, experiment_id)

    @app.get(
        "/experiments/{experiment_id}/stages",
        tags=["experiments"],
        response_model=list[StageSummary],
        responses=NOT_FOUND,
    )
    def experiment_stages(experiment_id: ExperimentId, session: SessionDep) -> list[dict[str, Any]]:
        """The curriculum's stages (c, δ) in order: status, increments, why each ended, best model."""
        return queries.stages(session, experiment_id)

    @app.get(
        "/experiments/{experiment_id}/history",
        tags=["experiments"],
        response_model=list[HistoryEntry],
        responses=NOT_FOUND,
    )
    def experiment_history(experiment_id: ExperimentId, session: SessionDep) -> list[dict[str, Any]]:
        """P: one entry per evaluated model (c, δ, k, mAP, model id, wall time), in arrival order."""
        return queries.history(session, experiment_id)

    @app.get("/models/{model_id}", tags=["models"], response_model=ModelDetail, responses=NOT_FOUND)
    def model_detail(model_id: ModelId, session: SessionDep) -> dict[str, Any]:
        """One ω: its stage, k, parent ω_in, training and its evaluation."""
        return queries.model_detail(session, model_id)

    @app.get(
        "/queues",
        tags=["status"],
        response_model=QueueStatus,
        responses={
            501: {"model": ErrorDetail, "description": "the broker is not Redis"},
            503: {"model": BrokerDown, "description": "the broker is unreachable, or tasks run in-process"},
        },
    )
    def queue_status() -> Any:
        """Depth of the render and train queues and the workers that answer a ping; 503 when the broker is down."""
        from workers.app import RENDER_QUEUE, TRAIN_QUEUE

        reason = broker.skipped_reason
        if reason:
            return JSONResponse(
                {"detail": f"no queues to read: {reason}"}, status_code=status.HTTP_503_SERVICE_UNAVAILABLE
            )
        if not broker.is_redis:
            return JSONResponse(
                {"detail": f"queue depth is read from Redis; the broker is {broker.display_url}"},
                status_code=status.HTTP_501_NOT_IMPLEMENTED,
            )
        try:
            depths = broker.queue_depths((RENDER_QUEUE, TRAIN_QUEUE))
            workers = broker.ping_workers()
        except BrokerUnavailable as error:
            return JSONResponse(
                {"detail": str(error), "broker": {"status": "error", "url": broker.display_url}},
                status_code=status.HTTP_503_SERVICE_UNAVAILABLE,
            )
        return {
            "broker": {"status": "ok", "url": broker.display_url},
            **depths,
            "workers": workers,
            "ping_timeout_s": broker.ping_timeout_s,
        }

    return app


app = create_app()
