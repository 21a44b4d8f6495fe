"""The REST API: the experiment record for everyone to read; creating and cancelling need a token.

The app is assembled here from one router per resource (``services/api/routes/``); what the
routes depend on (settings, session, token, probes) is in :mod:`services.api.deps`, the
response shapes in :mod:`services.api.schemas`. Reads go through :mod:`services.queries` (the
same helpers the CLI and the report use).

Serve with ``uvicorn services.api.app:app``. Imports neither torch nor bpy (the task modules
of the Celery app import them only inside task bodies, and are never imported here).
"""

import gc
import re
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

from fastapi import FastAPI, Request, status
from fastapi.exception_handlers import request_validation_exception_handler
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from starlette.concurrency import run_in_threadpool

from foldwise.config import ExperimentConfig
from foldwise.settings import Settings, get_settings
from services import queries
from services.api.deps import start_threads
from services.api.middleware import BodyLimit, BodyRule, SecurityHeaders
from services.api.probes import BrokerProbe, SchemaCheck
from services.api.routes import artifacts, assets, dashboard, detect, experiments, health, models, queues

ROUTERS = (
    health.router, experiments.router, models.router, detect.router, detect.study_router, artifacts.router,
    assets.router, queues.router,
    dashboard.router,
)  # fmt: skip


# Every body is counted as it streams in (services.api.middleware.BodyLimit); these paths take
# more than the default. An upload's multipart framing adds a little to its files' bytes.
BODY_RULES = (
    BodyRule(re.compile(r"/experiments"), experiments.MAX_CONFIG_BYTES, "config"),
    BodyRule(re.compile(r"/(models|studies)/[^/]+/detect"), detect.MAX_IMAGE_BYTES, "image"),
    BodyRule(re.compile(r"/assets/[^/]+"), assets.MAX_UPLOAD_BYTES + (1 << 20), "upload"),
)
DEFAULT_BODY_RULE = BodyRule(re.compile(".*"), 1 << 20, "request body")


def document_config_schema(app: FastAPI) -> None:
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


async def not_found(_request: Request, error: queries.NotFound) -> JSONResponse:
    return JSONResponse({"detail": str(error)}, status_code=status.HTTP_404_NOT_FOUND)


ID_RANGE_ERRORS = frozenset({"greater_than_equal", "less_than_equal"})


async def id_out_of_range(request: Request, error: RequestValidationError) -> JSONResponse:
    """A path id that is a whole number outside the ids' range names no row: 404, like any
    other id that does not exist. Every other validation error keeps FastAPI's 422."""
    errors = error.errors()
    if errors and all(item["loc"][0] == "path" and item["type"] in ID_RANGE_ERRORS for item in errors):
        names = ", ".join(f"{item['loc'][-1]} {item['input']}" for item in errors)
        return JSONResponse({"detail": f"{names} does not exist"}, status_code=status.HTTP_404_NOT_FOUND)
    return await request_validation_exception_handler(request, error)


def prepare_reads(app: FastAPI) -> None:
    """Run the status reads once, on the newest experiment, before serving.

    SQLAlchemy compiles each statement on its first run and caches it for the process; the
    crowd that polls an API which has just started (every dashboard reconnecting) would
    otherwise compile each one once per request of the crowd, all at once. Best effort: a
    database that cannot answer yet is /health's to report."""
    from sqlalchemy import func, select

    from db.models import Experiment
    from db.session import get_sessionmaker

    try:
        with get_sessionmaker(app.state.settings.resolved_database_url)() as session:
            app.state.schema_check.check(session)
            newest = session.scalar(select(func.max(Experiment.id)))
            if newest is not None:
                queries.summary(session, newest)
                queries.stages(session, newest)
                queries.history(session, newest)
    except Exception:
        pass


@asynccontextmanager
async def lifespan(app: FastAPI) -> AsyncIterator[None]:
    """Before the first request: what the first requests would otherwise each do while others wait."""
    await start_threads()
    await detect.prepare_broker()
    await run_in_threadpool(prepare_reads, app)
    settle_heap()
    yield


def settle_heap() -> None:
    """Move every object alive now out of the garbage collector's sight, garbage collected first.

    The API's heap is mostly what stays for the process's life (modules, the ORM's and
    pydantic's classes, matplotlib once a figure is drawn); each full collection walked all of
    it, holding the GIL and every request for over 100 ms every few seconds under load. Frozen,
    it is not walked again; the objects of requests still are."""
    gc.collect()
    gc.freeze()


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
    app = FastAPI(
        title="foldwise",
        summary="Active learning of a detector for one deformable object, from rendered images.",
        version="0.1.0",
        lifespan=lifespan,
    )
    app.state.settings = settings
    app.state.broker = BrokerProbe(settings, timeout_s=broker_timeout_s, ping_timeout_s=ping_timeout_s)
    app.state.schema_check = SchemaCheck(settings.resolved_database_url)
    app.add_exception_handler(queries.NotFound, not_found)
    app.add_exception_handler(RequestValidationError, id_out_of_range)
    for router in ROUTERS:
        app.include_router(router)
    app.add_middleware(BodyLimit, rules=BODY_RULES, default=DEFAULT_BODY_RULE)
    app.add_middleware(SecurityHeaders)  # added last: outermost, so the 413s above carry the headers too
    document_config_schema(app)
    return app


app = create_app()
