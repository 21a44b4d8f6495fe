"""What the API tests share besides fixtures: the token, free ports, database counts, and a raw
ASGI call that says how much of the body the app read."""

from __future__ import annotations

import asyncio
import shutil
import socket
import subprocess
import warnings
from collections.abc import Iterable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path

import pytest
from sqlalchemy import func, select

from db.models import Experiment
from db.session import get_sessionmaker
from foldwise.settings import get_settings
from services.api.app import create_app
from tests.waiting import poll

with warnings.catch_warnings():
    # Starlette's test client asks for the `httpx2` fork; plain httpx works and is what is installed.
    warnings.simplefilter("ignore")
    from fastapi.testclient import TestClient

TOKEN = "s3cret-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
REPO = Path(__file__).resolve().parents[3]
T0 = datetime(2026, 1, 1, 12, 0, tzinfo=UTC)


def closed_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def client_with(broker_timeout_s: float = 0.5, **overrides) -> TestClient:
    settings = get_settings().model_copy(update=overrides)
    return TestClient(create_app(settings, broker_timeout_s=broker_timeout_s, ping_timeout_s=0.3))


def experiment_count(url: str) -> int:
    with get_sessionmaker(url)() as session:
        return session.scalar(select(func.count()).select_from(Experiment))


def stored_experiment(url: str, experiment_id: int) -> Experiment:
    with get_sessionmaker(url)() as session:
        return session.get(Experiment, experiment_id)


@dataclass
class RawResponse:
    status: int
    headers: dict[str, str]
    body: bytes
    body_bytes_read: int = 0  # how much of the request body the app took from the server
    chunks_read: int = 0
    extra: dict = field(default_factory=dict)


def call_asgi(app, method: str, path: str, headers: dict[str, str], chunks: Iterable[bytes]) -> RawResponse:
    """One request straight into the ASGI app, its body given as ``chunks`` (a generator may be
    endless: only what the app asks for is made), as a server would stream a chunked body."""
    return asyncio.run(call_asgi_async(app, method, path, headers, chunks))


async def call_asgi_async(app, method: str, path: str, headers: dict[str, str], chunks: Iterable[bytes]) -> RawResponse:
    path, _, query = path.partition("?")
    scope = {
        "type": "http", "asgi": {"version": "3.0"}, "http_version": "1.1", "method": method,
        "scheme": "http", "path": path, "raw_path": path.encode(), "query_string": query.encode(),
        "root_path": "", "server": ("127.0.0.1", 8000), "client": ("127.0.0.1", 50000),
        "headers": [(k.lower().encode("latin-1"), v.encode("latin-1")) for k, v in headers.items()],
        "app": app,
    }  # fmt: skip
    source = iter(chunks)
    response = RawResponse(status=0, headers={}, body=b"")
    finished = False

    async def receive():
        nonlocal finished
        if finished:
            await asyncio.Event().wait()  # a connection that stays open: no disconnect before the reply
        chunk = next(source, None)
        if chunk is None:
            finished = True
            return {"type": "http.request", "body": b"", "more_body": False}
        response.body_bytes_read += len(chunk)
        response.chunks_read += 1
        return {"type": "http.request", "body": chunk, "more_body": True}

    async def send(message):
        if message["type"] == "http.response.start":
            response.status = message["status"]
            response.headers = {k.decode("latin-1"): v.decode("latin-1") for k, v in message.get("headers", [])}
        elif message["type"] == "http.response.body":
            response.body += message.get("body", b"")

    await app(scope, receive, send)
    return response


def png_claiming(width: int, height: int, data: bytes | None = None) -> bytes:
    """A well-formed PNG header (valid CRCs) that claims width x height over ``data`` (default:
    one compressed row of zeros): tens of bytes, gigabytes if decoded."""
    import struct
    import zlib

    def chunk(kind: bytes, payload: bytes) -> bytes:
        return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", zlib.crc32(kind + payload))

    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    data = zlib.compress(b"\x00" * 64) if data is None else data
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", data) + chunk(b"IEND", b"")


class OwnRedis:
    """A redis-server of the test's own on a free port (never the shared one), empty, without
    persistence; it can be stopped and started again on the same port."""

    def __init__(self) -> None:
        self.server = shutil.which("redis-server")
        if self.server is None:
            pytest.skip("redis-server is not installed: a live-broker test needs a Redis of its own")
        self.port = closed_port()
        self.url = f"redis://127.0.0.1:{self.port}/0"
        self.process: subprocess.Popen | None = None

    def start(self) -> None:
        import redis

        self.process = subprocess.Popen(
            [self.server, "--port", str(self.port), "--bind", "127.0.0.1", "--save", "", "--appendonly", "no"],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        client = redis.Redis(port=self.port)

        def answers() -> bool:
            try:
                return client.ping()
            except redis.ConnectionError:
                return False

        try:
            if not poll(answers, timeout=5, interval=0.025):
                pytest.skip("redis-server did not start")
        finally:
            client.close()

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.terminate()
            self.process.wait(timeout=10)

    def connections_received(self) -> int:
        """Connections the server has accepted, this question's own included."""
        import redis

        client = redis.Redis(port=self.port)
        try:
            return int(client.info("stats")["total_connections_received"])
        finally:
            client.close()
