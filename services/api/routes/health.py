"""GET /health: can the API serve the record (database), and can work be sent (broker)?"""

from typing import Any

from fastapi import APIRouter, Response, status

from services.api.deps import BrokerDep, SchemaCheckDep, SessionDep
from services.api.schemas import Health

router = APIRouter(tags=["status"])


@router.get(
    "/health",
    response_model=Health,
    responses={503: {"model": Health, "description": "the database is unreachable or not migrated"}},
)
def health(session: SessionDep, schema_check: SchemaCheckDep, broker: BrokerDep, response: Response) -> dict[str, Any]:
    """Database and broker reachability: 200 while the database serves (the broker may be down), else 503."""
    database = schema_check.check(session)
    broker_state = broker.check()
    if database["status"] != "ok":
        overall = "error"
        response.status_code = status.HTTP_503_SERVICE_UNAVAILABLE
    elif broker_state["status"] == "error":
        overall = "degraded"
    else:
        overall = "ok"
    return {"status": overall, "database": database, "broker": broker_state}
