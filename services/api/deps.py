"""What the routes depend on: the settings, a database session, the token, the probes, path ids.

Everything is read from ``request.app.state`` (set by :func:`services.api.app.create_app`), so
one process can serve several apps with different settings (the tests do) and a test can swap
any of them with ``app.dependency_overrides[get_session] = ...``.
"""

# No `from __future__ import annotations`: FastAPI resolves these annotations at runtime.
import secrets
from collections.abc import Iterator
from typing import Annotated

from fastapi import Depends, HTTPException, Path, Request, status
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from sqlalchemy.orm import Session

from db.session import get_sessionmaker
from foldwise.settings import Settings
from services.api.probes import BrokerProbe, SchemaCheck
from services.queries import MAX_ID

# Ids, stage orders and increments k are 32-bit INTEGER columns (MAX_ID, services.queries). An
# id outside 1..MAX_ID names nothing: the app answers 404 for it (services.api.app.id_out_of_range);
# a stage or k filter past it is a 422. Either way the database, which would raise, never sees it.
MAX_INT_COLUMN = MAX_ID

ExperimentId = Annotated[int, Path(ge=1, le=MAX_ID, description="experiment id")]
ModelId = Annotated[int, Path(ge=1, le=MAX_ID, description="model id (ω)")]


def get_app_settings(request: Request) -> Settings:
    """The settings this app was created with."""
    return request.app.state.settings


SettingsDep = Annotated[Settings, Depends(get_app_settings)]


def get_session(settings: SettingsDep) -> Iterator[Session]:
    """A session per request; uncommitted work (a request that failed half way) is rolled back on close."""
    session = get_sessionmaker(settings.resolved_database_url)()
    try:
        yield session
    finally:
        session.close()


SessionDep = Annotated[Session, Depends(get_session)]


def get_broker(request: Request) -> BrokerProbe:
    return request.app.state.broker


BrokerDep = Annotated[BrokerProbe, Depends(get_broker)]


def get_schema_check(request: Request) -> SchemaCheck:
    return request.app.state.schema_check


SchemaCheckDep = Annotated[SchemaCheck, Depends(get_schema_check)]


bearer = HTTPBearer(auto_error=False, description="FOLDWISE_API_TOKEN of the API server")


def require_token(
    request: Request,
    settings: SettingsDep,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)],
) -> None:
    """Writes need ``Authorization: Bearer <FOLDWISE_API_TOKEN>``; with no token configured they are off."""
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


TokenRequired = Depends(require_token)
