"""GET /health: can the API serve the record (database), and can work be sent (broker)?

Anyone may ask whether the service is up; only a caller with the token learns why not (the
database's revision and the broker's address are no one else's business)."""

import secrets
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Response, status
from fastapi.security import HTTPAuthorizationCredentials
from sqlalchemy.orm import Session

from services.api.deps import BrokerDep, SchemaCheckDep, SessionDep, SettingsDep, bearer, run_probe
from services.api.schemas import Health

router = APIRouter(tags=["status"])


@router.get(
    "/health",
    response_model=Health,
    response_model_exclude_unset=True,
    responses={503: {"model": Health, "description": "the database is unreachable or not migrated"}},
)
async def health(
    session: SessionDep,
    schema_check: SchemaCheckDep,
    broker: BrokerDep,
    response: Response,
    settings: SettingsDep,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)],
) -> dict[str, Any]:
    """Database and broker reachability: 200 while the database serves (the broker may be down), else 503.
    The state of each is shown to callers with the token; anyone else gets the status alone."""

    def probe(session: Session) -> tuple[dict[str, Any], dict[str, Any]]:
        database = schema_check.check(session)
        session.close()  # a silent broker keeps this thread for its timeout; not a database connection too
        return database, broker.check()

    database, broker_state = await run_probe(probe, session)  # both block: one probe thread for the two
    if database["status"] != "ok":
        overall = "error"
        response.status_code = status.HTTP_503_SERVICE_UNAVAILABLE
    elif broker_state["status"] == "error":
        overall = "degraded"
    else:
        overall = "ok"
    token = settings.api_token
    if token and credentials is not None and secrets.compare_digest(credentials.credentials.encode(), token.encode()):
        return {"status": overall, "database": database, "broker": broker_state}
    return {"status": overall}
