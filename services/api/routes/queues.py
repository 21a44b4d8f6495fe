"""GET /queues: how much work waits in the render and train queues, and which workers answer.

Anyone may read the depths and the workers; only a caller with the token learns where the
broker is (its URL, without the password) and why it cannot be reached, as with /health."""

import secrets
from typing import Any

from fastapi import APIRouter, Request, status
from fastapi.responses import JSONResponse

from services.api.deps import BrokerDep, SettingsDep
from services.api.probes import BrokerUnavailable
from services.api.schemas import BrokerDown, ErrorDetail, QueueStatus

router = APIRouter(tags=["status"])


def _has_token(request: Request, token: str | None) -> bool:
    """``Authorization: Bearer <FOLDWISE_API_TOKEN>`` on the request (read here, not required:
    the route serves everyone, the broker's whereabouts only the token's holders)."""
    scheme, _, given = request.headers.get("authorization", "").partition(" ")
    return bool(token) and scheme.lower() == "bearer" and secrets.compare_digest(given.strip().encode(), token.encode())


@router.get(
    "/queues",
    response_model=QueueStatus,
    response_model_exclude_unset=True,
    responses={
        501: {"model": ErrorDetail, "description": "the broker is not Redis"},
        503: {"model": BrokerDown, "description": "the broker is unreachable, or tasks run in-process"},
    },
)
def queue_status(broker: BrokerDep, request: Request, settings: SettingsDep) -> Any:
    """Depth of the render and train queues and the workers that answer a ping; 503 when the broker is down.
    The broker's URL (without its password) and why it cannot be reached are shown to callers with
    the token (``Authorization: Bearer``) only."""
    from workers.app import RENDER_QUEUE, TRAIN_QUEUE

    reason = broker.skipped_reason
    if reason:  # eager mode or an in-memory broker: nothing to hide
        return JSONResponse({"detail": f"no queues to read: {reason}"}, status_code=status.HTTP_503_SERVICE_UNAVAILABLE)
    trusted = _has_token(request, settings.api_token)
    if not broker.is_redis:
        where = broker.display_url if trusted else "not Redis"
        return JSONResponse(
            {"detail": f"queue depth is read from Redis; the broker is {where}"},
            status_code=status.HTTP_501_NOT_IMPLEMENTED,
        )
    try:
        depths = broker.queue_depths((RENDER_QUEUE, TRAIN_QUEUE))
        workers = broker.ping_workers()
    except BrokerUnavailable as error:
        if trusted:
            body = {"detail": str(error), "broker": {"status": "error", "url": broker.display_url}}
        else:
            body = {"detail": "the broker is unreachable", "broker": {"status": "error"}}
        return JSONResponse(body, status_code=status.HTTP_503_SERVICE_UNAVAILABLE)
    return {
        "broker": {"status": "ok", "url": broker.display_url} if trusted else {"status": "ok"},
        **depths,
        "workers": workers,
        "ping_timeout_s": broker.ping_timeout_s,
    }
