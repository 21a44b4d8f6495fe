"""ASGI middleware of the API: a body size limit enforced while the body streams in, and the
security headers of every response.

Checking ``Content-Length`` is not enough: a chunked body has none, and a route that reads it
whole before measuring it has already spent the memory (1000 MiB took the API to 2.2 GB). The
limit here counts bytes as the server hands them over and answers 413 the moment a body passes
it; the rest of the body is never read.
"""

from __future__ import annotations

import json
import re
from collections.abc import Sequence
from dataclasses import dataclass

from starlette.types import ASGIApp, Message, Receive, Scope, Send


@dataclass(frozen=True)
class BodyRule:
    """Bodies of requests whose path matches ``pattern`` may hold at most ``limit`` bytes."""

    pattern: re.Pattern[str]
    limit: int
    what: str  # "image", "config": names the body in the 413


class BodyTooLarge(Exception):
    """Raised into the app from ``receive`` once the body passes its limit."""


class BodyLimit:
    """413 for a body over its path's limit: at once for a ``Content-Length`` over it, else as
    soon as the bytes received pass it (whatever the app does with the exception it gets from
    ``receive``, the client gets the 413)."""

    def __init__(self, app: ASGIApp, rules: Sequence[BodyRule], default: BodyRule) -> None:
        self.app = app
        self.rules = tuple(rules)
        self.default = default

    def rule_for(self, path: str) -> BodyRule:
        return next((rule for rule in self.rules if rule.pattern.fullmatch(path)), self.default)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        rule = self.rule_for(scope["path"])
        declared = _header(scope, b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > rule.limit:
            await _refuse(send, rule)
            return
        received = 0
        refused = started = False

        async def limited_receive() -> Message:
            nonlocal received, refused
            if refused:
                raise BodyTooLarge
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > rule.limit:
                    refused = True
                    raise BodyTooLarge
            return message

        async def guarded_send(message: Message) -> None:
            nonlocal started
            if refused:
                return  # whatever the app answers to a body cut short, the answer is the 413
            if message["type"] == "http.response.start":
                started = True
            await send(message)

        try:
            await self.app(scope, limited_receive, guarded_send)
        except Exception:
            if not refused:
                raise
        if refused and not started:
            await _refuse(send, rule)


def _header(scope: Scope, name: bytes) -> str | None:
    for key, value in scope.get("headers", ()):
        if key.lower() == name:
            return value.decode("latin-1").strip()
    return None


async def _refuse(send: Send, rule: BodyRule) -> None:
    body = json.dumps({"detail": f"{rule.what} larger than {rule.limit} bytes"}).encode()
    await send(
        {
            "type": "http.response.start",
            "status": 413,
            "headers": [
                (b"content-type", b"application/json"),
                (b"content-length", str(len(body)).encode()),
                (b"connection", b"close"),  # the unread rest of the body makes the connection unusable
            ],
        }
    )
    await send({"type": "http.response.body", "body": body})


# The dashboard loads its script and stylesheet from this origin and sets inline style
# attributes from the script (stage colours); it embeds nothing and is embedded nowhere.
CONTENT_SECURITY_POLICY = (
    "default-src 'self'; script-src 'self'; style-src 'self' 'unsafe-inline'; img-src 'self' data:; "
    "connect-src 'self'; object-src 'none'; base-uri 'none'; form-action 'self'; frame-ancestors 'none'"
)
# FastAPI's /docs and /redoc pages load Swagger UI / ReDoc from a CDN and start them with an
# inline script.
DOCS_CONTENT_SECURITY_POLICY = (
    "default-src 'self'; script-src 'self' 'unsafe-inline' https://cdn.jsdelivr.net; "
    "style-src 'self' 'unsafe-inline' https://cdn.jsdelivr.net https://fonts.googleapis.com; "
    "font-src 'self' https://fonts.gstatic.com; img-src 'self' data: https://fastapi.tiangolo.com https://cdn.redoc.ly; "
    "worker-src 'self' blob:; connect-src 'self'; object-src 'none'; base-uri 'none'; frame-ancestors 'none'"
)
DOCS_PATHS = frozenset({"/docs", "/docs/oauth2-redirect", "/redoc"})
SECURITY_HEADERS = (
    (b"x-content-type-options", b"nosniff"),
    (b"x-frame-options", b"DENY"),
    (b"referrer-policy", b"no-referrer"),
)


class SecurityHeaders:
    """``nosniff``, ``DENY`` framing, no referrer and a Content-Security-Policy on every response."""

    def __init__(self, app: ASGIApp) -> None:
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        policy = DOCS_CONTENT_SECURITY_POLICY if scope["path"] in DOCS_PATHS else CONTENT_SECURITY_POLICY

        async def send_with_headers(message: Message) -> None:
            if message["type"] == "http.response.start":
                headers = list(message.get("headers", []))
                present = {key.lower() for key, _ in headers}
                extra = [*SECURITY_HEADERS, (b"content-security-policy", policy.encode())]
                headers += [(key, value) for key, value in extra if key not in present]
                message = {**message, "headers": headers}
            await send(message)

        await self.app(scope, receive, send_with_headers)
