"""Response shapes of the API, for its OpenAPI document and its clients.

They describe the dictionaries :mod:`services.queries` builds (the CLI and the report read the
same ones). Each model allows extra keys, so a field added to a query reaches clients before
it is documented here; a documented field that goes missing fails the request loudly.
Times are ISO 8601 strings as the queries write them; durations are seconds.
"""

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from db.models import ExperimentStatus, ModelStatus, StageEndReason, StageStatus


class _Shape(BaseModel):
    model_config = ConfigDict(extra="allow")


class ErrorDetail(BaseModel):
    detail: str = Field(description="what was wrong, naming the id, key or header at fault")


class InvalidInput(BaseModel):
    """A 422: one line from the route (a bad body), or FastAPI's list of the parameters at fault."""

    detail: str | list[dict[str, Any]] = Field(
        description="what was wrong: a message naming the key or file, or one entry per bad parameter"
    )


class ExperimentListItem(_Shape):
    id: int
    name: str
    study: str | None = Field(default=None, description="the study it was run in, side by side with others")
    status: ExperimentStatus
    created_at: str | None
    finished_at: str | None


class CurrentStage(_Shape):
    order: int = Field(description="position of (c, δ) in the curriculum, from 0")
    condition: str = Field(description="c")
    difficulty: str = Field(description="δ")
    k: int | None = Field(description="the latest increment of this stage (None before the first)")


class Counts(_Shape):
    parameter_sets: dict[str, dict[str, int]] = Field(description="θ per split (train/test) and render status")
    models: dict[str, int] = Field(description="ω per status")
    evaluations: int = Field(description="entries of P")
    stages: int


class BestModel(_Shape):
    map: float
    model_id: int


class ExperimentSummary(_Shape):
    id: int
    name: str
    study: str | None = Field(default=None, description="the study it was run in, if any")
    status: ExperimentStatus
    error: str | None
    seed: int
    classes: list[Any] | None = Field(description="the detector's classes (object names), fixed at the start")
    current_stage: CurrentStage | None
    counts: Counts
    failed_by_reason: dict[str, int] = Field(
        default_factory=dict, description="failed θ (images that could not be rendered) counted by reason"
    )
    best: BestModel | None = Field(description="the best score in P so far and its model")
    final_model_id: int | None
    created_at: str | None
    started_at: str | None
    finished_at: str | None
    elapsed_seconds: float | None = Field(description="since the start; up to now while it runs")


class StageSummary(_Shape):
    order: int
    condition: str = Field(
        description="c (canonical: the canonical baseline's one stage, or a learnability run's shared first stage)"
    )
    difficulty: str = Field(
        description="δ (canonical: the canonical baseline's one stage, or a learnability run's shared first stage)"
    )
    status: StageStatus
    end_reason: StageEndReason | None = Field(
        description="plateau (|P_M − P_N| ≤ τ) or cap (max increments); kappa: a learnability stage's κ increments; "
        "increments: the canonical baseline's (or a learnability run's canonical stage's) fixed increments"
    )
    increments: int = Field(description="evaluated increments k")
    init_model_id: int | None = Field(
        description="ω_in of the first increment: the previous stage's ω_be (learnability: the last ω_k of the "
        "condition's previous difficulty; at its first, none, or with learnability.start: canonical the "
        "canonical stage's last ω_k)"
    )
    best_model_id: int | None = Field(description="ω_be")
    best_map: float | None = Field(description="ω_be's mAP at the paper's confidence cut")
    loop_score: str = Field(
        default="map",
        description="the score P the stopping rule read (evaluation.loop_score): map or map_unthresholded",
    )
    start_p: float | None = Field(default=None, description="P of ω_in, the model the stage started from")
    best_p: float | None = Field(default=None, description="P of ω_be")
    failed_images: int = Field(default=0, description="θ of this stage that could not be rendered")
    started_at: str | None
    finished_at: str | None
    seconds: float | None


class HistoryEntry(_Shape):
    """One entry of P: the score of ω_k on the standard test set."""

    stage: int
    condition: str = Field(description="c")
    difficulty: str = Field(description="δ")
    k: int
    model_id: int
    parent_id: int | None = Field(description="ω_in")
    map: float | None = Field(description="mAP under the paper's protocol (confidence threshold); None if not finite")
    map_unthresholded: float | None
    render_seconds: float | None = Field(description="summed render time of this increment's training θ")
    train_seconds: float | None
    eval_seconds: float
    wall_seconds: float | None = Field(description="from the experiment's start to this score")
    evaluated_at: str | None


class StageRef(_Shape):
    order: int
    condition: str
    difficulty: str


class EvaluationDetail(_Shape):
    map: float | None
    map_unthresholded: float | None
    eval_seconds: float
    details: dict[str, Any] = Field(description="per condition and difficulty breakdown")


class ModelDetail(_Shape):
    id: int
    experiment_id: int
    stage: StageRef
    k: int
    parent_id: int | None = Field(description="ω_in")
    detector: str
    status: ModelStatus
    iterations: int = Field(description="t")
    checkpoint_path: str | None = Field(description="relative to the artifact store")
    train_seconds: float | None
    train_stats: dict[str, Any] | None
    attempts: int
    error: str | None
    evaluation: EvaluationDetail | None


class ComponentState(_Shape):
    status: Literal["ok", "error", "skipped"]
    detail: str | None = None


class Health(BaseModel):
    status: Literal["ok", "degraded", "error"] = Field(
        description="ok; degraded: the broker is down but the record can be read; error: the database is down"
    )
    database: ComponentState | None = Field(default=None, description="with the token only")
    broker: ComponentState | None = Field(default=None, description="with the token only")


class BrokerState(_Shape):
    status: Literal["ok", "error"]
    url: str | None = Field(default=None, description="the broker URL without its password; with the token only")


class QueueStatus(BaseModel):
    broker: BrokerState
    queues: dict[str, int] = Field(description="messages waiting in the render and train queues")
    unacked: int = Field(
        description="messages delivered to a worker and not yet acknowledged: running, or reserved by a worker"
    )
    workers: list[str] = Field(description="hostnames of the workers that answered a ping")
    ping_timeout_s: float


class BrokerDown(_Shape):
    detail: str
    broker: BrokerState | None = None


# Error responses shared by the routes, for the OpenAPI document.
NOT_FOUND: dict[int | str, dict[str, Any]] = {
    404: {"model": ErrorDetail, "description": "no experiment or model with this id"}
}
WRITE_ERRORS: dict[int | str, dict[str, Any]] = {
    401: {"model": ErrorDetail, "description": "missing or wrong token"},
    403: {"model": ErrorDetail, "description": "no token is configured on the server (FOLDWISE_API_TOKEN)"},
}
