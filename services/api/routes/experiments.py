"""/experiments: list, create, read (summary, config, stages, history P) and cancel.

The scheduler picks up an experiment created here on its next pass, so the API never enqueues
work itself.
"""

import json
from typing import Annotated, Any

from fastapi import APIRouter, Depends, HTTPException, Query, Request, Response, status
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool

from db.models import ExperimentStatus
from foldwise.config import ConfigError, ExperimentConfig, parse_config, parse_config_text
from foldwise.documents import TOO_DEEP
from services import queries
from services.api.deps import ExperimentId, SessionDep, TokenRequired, read_with
from services.api.schemas import (
    NOT_FOUND,
    WRITE_ERRORS,
    ErrorDetail,
    ExperimentListItem,
    ExperimentSummary,
    HistoryEntry,
    InvalidInput,
    StageSummary,
)

# An experiment config is a few kilobytes of YAML; anything this large is a mistake.
MAX_CONFIG_BYTES = 1 << 20

JSON_TYPES = frozenset({"application/json"})
YAML_TYPES = frozenset({"application/yaml", "text/yaml", "application/x-yaml", "text/x-yaml"})
ACCEPTED_TYPES = "application/json, application/yaml or text/yaml"

LIVE_STATUSES = (ExperimentStatus.pending, ExperimentStatus.running)

# queries.STUDY_NAME, with the length apart so that the error says which rule failed: no C0 or
# C1 control, no bidirectional override or isolate (U+202A-U+202E, U+2066-U+2069).
STUDY_NAME = dict(min_length=1, max_length=200, pattern=r"^[^\x00-\x1f\x7f-\x9f\u202a-\u202e\u2066-\u2069]+$")

router = APIRouter(prefix="/experiments", tags=["experiments"])


# --------------------------------------------------------------------------- the config body


def _media_type(request: Request) -> str | None:
    header = request.headers.get("content-type")
    if not header:
        return None
    return header.split(";", 1)[0].strip().lower()


def _reject_constant(name: str) -> None:
    # Python's json accepts NaN and Infinity; JSON does not, and PostgreSQL's JSON columns refuse them.
    raise ValueError(f"{name} is not a JSON number")


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    # Python's json keeps the last of a key given twice; a config that says two things is refused,
    # as its YAML reading refuses it (foldwise.config).
    mapping: dict[str, Any] = {}
    for key, value in pairs:
        if key in mapping:
            raise ConfigError(f"invalid experiment config: duplicate key {key!r}")
        mapping[key] = value
    return mapping


async def read_config(request: Request) -> ExperimentConfig:
    """The request body as a validated experiment config (JSON or YAML).

    The body is read here, on the event loop (the app's BodyLimit stops it at MAX_CONFIG_BYTES
    as it streams in); parsing and validating are CPU work, done on a worker thread so that a
    slow document delays no other request."""
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
    body = bytearray()
    async for chunk in request.stream():
        body += chunk
        if len(body) > MAX_CONFIG_BYTES:
            raise HTTPException(status.HTTP_413_CONTENT_TOO_LARGE, f"config larger than {MAX_CONFIG_BYTES} bytes")
    return await run_in_threadpool(parse_config_body, bytes(body), is_json)


def parse_config_body(body: bytes, is_json: bool) -> ExperimentConfig:
    """A body's bytes as a validated config, or the 422 that names what is wrong."""
    if not body.strip():
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, "empty body: send an experiment config")
    try:
        document = body.decode("utf-8")
    except UnicodeDecodeError as error:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, f"the body is not UTF-8 text: {error}") from None
    try:
        if is_json:
            try:
                data = json.loads(document, parse_constant=_reject_constant, object_pairs_hook=_unique_keys)
            except RecursionError:  # the decoder recurses once per level; parse_config bounds the rest
                raise ConfigError(f"invalid experiment config: {TOO_DEEP}") from None
            except ConfigError:
                raise
            except (json.JSONDecodeError, ValueError) as error:
                raise ConfigError(f"invalid experiment config: not JSON: {error}") from None
            config = parse_config(data)
        else:
            config = parse_config_text(document)
        return config
    except ConfigError as error:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, str(error)) from None


ConfigBody = Annotated[ExperimentConfig, Depends(read_config)]

# The body is read by hand (JSON or YAML), so its schema is documented by hand; the app adds
# ExperimentConfig to the OpenAPI components (services.api.app.document_config_schema).
CONFIG_BODY_DOC = {
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


# --------------------------------------------------------------------------- routes


@router.get("", response_model=list[ExperimentListItem])
async def list_experiments(
    session: SessionDep,
    status_filter: Annotated[ExperimentStatus | None, Query(alias="status")] = None,
    study: Annotated[str | None, Query(**STUDY_NAME, description="keep one study's experiments")] = None,
) -> list[ExperimentListItem]:
    """Every experiment, oldest first; ``?status=running`` keeps one status, ``?study=`` one study."""
    experiments = await read_with(session, queries.list_experiments)
    if status_filter is not None:
        experiments = [e for e in experiments if e.status == status_filter]
    if study is not None:
        experiments = [e for e in experiments if e.study == study]
    return experiments


@router.post(
    "",
    status_code=status.HTTP_201_CREATED,
    response_model=ExperimentSummary,
    dependencies=[TokenRequired],
    openapi_extra=CONFIG_BODY_DOC,
    responses={
        **WRITE_ERRORS,
        413: {"model": ErrorDetail, "description": "the body is larger than 1 MiB"},
        415: {"model": ErrorDetail, "description": "not JSON or YAML"},
        422: {"model": InvalidInput, "description": "an invalid config; the message names the key"},
    },
)
def create_experiment(
    request: Request,
    response: Response,
    session: SessionDep,
    config: ConfigBody,
    study: Annotated[
        str | None,
        Query(**STUDY_NAME, description="group it with other experiments"),
    ] = None,
) -> dict[str, Any]:
    """Record a new experiment (status pending); the scheduler starts it on its next pass.
    ``?study=NAME`` groups it with others run side by side (one per detector, say)."""
    from foldwise.asset_check import AssetError, check_asset_roots, check_photographs, validate_assets  # Pillow only

    try:
        from foldwise import store

        check_asset_roots(
            config.assets, request.app.state.settings.asset_root_paths, uploads=store.uploaded_assets_root()
        )
        validate_assets(config.assets)  # asset folders on this server, checked once before anything is recorded
        check_photographs(config.test_set, request.app.state.settings.asset_root_paths)
    except AssetError as error:
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, str(error)) from None
    from foldwise.weights import missing_imagenet_weights  # no torch: file names only

    # Every service runs one image (compose.yaml), so the weights the train workers will read are
    # the ones this process sees: a run that lacks them is refused now, not at its first step.
    if config.detector.pretrained == "imagenet" and (problem := missing_imagenet_weights(config.detector.backbone)):
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, problem)
    experiment = queries.create_experiment(session, config, study=study)
    session.commit()
    response.headers["Location"] = request.scope.get("root_path", "") + request.app.url_path_for(
        "experiment_summary", experiment_id=experiment.id
    )
    return queries.summary(session, experiment.id)


@router.get("/{experiment_id}", name="experiment_summary", response_model=ExperimentSummary, responses=NOT_FOUND)
async def experiment_summary(experiment_id: ExperimentId, session: SessionDep) -> dict[str, Any]:
    """Status, current stage and k, counts of θ, ω and P, elapsed time, best model."""
    return await read_with(session, queries.summary, experiment_id)


@router.get("/{experiment_id}/config", responses=NOT_FOUND)
async def experiment_config(experiment_id: ExperimentId, session: SessionDep) -> dict[str, Any]:
    """The experiment's config as recorded, every default filled in."""
    return await read_with(session, _recorded_config, experiment_id)


def _recorded_config(session: Session, experiment_id: int) -> dict[str, Any]:
    return queries.get_experiment(session, experiment_id).config


@router.post(
    "/{experiment_id}/cancel",
    response_model=ExperimentSummary,
    dependencies=[TokenRequired],
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


@router.get("/{experiment_id}/stages", response_model=list[StageSummary], responses=NOT_FOUND)
async def experiment_stages(experiment_id: ExperimentId, session: SessionDep) -> list[dict[str, Any]]:
    """The curriculum's stages (c, δ) in order: status, increments, why each ended, best model."""
    return await read_with(session, queries.stages, experiment_id)


@router.get("/{experiment_id}/history", response_model=list[HistoryEntry], responses=NOT_FOUND)
async def experiment_history(experiment_id: ExperimentId, session: SessionDep) -> list[dict[str, Any]]:
    """P: one entry per evaluated model (c, δ, k, mAP, model id, wall time), in arrival order."""
    return await read_with(session, queries.history, experiment_id)
