"""GET /queues: how much work waits in the render and train queues, and which workers answer."""

from typing import Any

from fastapi import APIRouter, status
from fastapi.responses import JSONResponse

from services.api.deps import BrokerDep
from services.api.probes import BrokerUnavailable
from services.api.schemas import BrokerDown, ErrorDetail, QueueStatus

router = APIRouter(tags=["status"])


@router.get(
    "/queues",
    response_model=QueueStatus,
    responses={
        501: {"model": ErrorDetail, "description": "the broker is not Redis"},
        503: {"model": BrokerDown, "description": "the broker is unreachable, or tasks run in-process"},
    },
)
def queue_status(broker: BrokerDep) -> Any:
    """Depth of the render and train queues and the workers that answer a ping; 503 when the broker is down."""
    from workers.app import RENDER_QUEUE, TRAIN_QUEUE

    reason = broker.skipped_reason
    if reason:
        return JSONResponse({"detail": f"no queues to read: {reason}"}, status_code=status.HTTP_503_SERVICE_UNAVAILABLE)
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
