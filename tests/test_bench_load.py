"""bench/load.py's HTTP client (Connection): answers with a length or in chunks, one connection
kept for many requests, a request sent again when the server had closed the kept-alive
connection, and an answer cut short raised, never sent again."""

from __future__ import annotations

import asyncio
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from bench.load import Connection  # noqa: E402


async def _serve(handle):
    """A server on a free loopback port that answers with ``handle(request_head, body, count)``
    (bytes to write, and whether to close after); (server, port, connections accepted)."""
    accepted = []

    async def client(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        accepted.append(writer)
        count = 0
        try:
            while True:
                head = await reader.readuntil(b"\r\n\r\n")
                length = next(
                    (
                        int(line.split(b":")[1])
                        for line in head.split(b"\r\n")
                        if line.lower().startswith(b"content-length")
                    ),
                    0,
                )
                body = await reader.readexactly(length)
                count += 1
                answer, close = handle(head, body, count)
                writer.write(answer)
                await writer.drain()
                if close:
                    break
        except (asyncio.IncompleteReadError, ConnectionError):
            pass
        finally:
            writer.close()

    server = await asyncio.start_server(client, "127.0.0.1", 0)
    return server, server.sockets[0].getsockname()[1], accepted


def _answer(status: int, body: bytes, *headers: str) -> bytes:
    lines = [f"HTTP/1.1 {status} X", f"content-length: {len(body)}", *headers]
    return ("\r\n".join(lines) + "\r\n\r\n").encode() + body


def test_lengths_chunks_and_one_connection_for_many_requests():
    def handle(head, body, count):
        if head.startswith(b"POST"):
            return _answer(503, b"busy: " + body, "Retry-After: 5"), False
        chunked = b"HTTP/1.1 200 OK\r\ntransfer-encoding: chunked\r\n\r\n3\r\nabc\r\n2;x=y\r\nde\r\n0\r\n\r\n"
        return (chunked if b"/chunks" in head else _answer(200, b'{"status":"ok"}')), False

    async def scenario():
        server, port, accepted = await _serve(handle)
        async with server:
            connection = Connection("127.0.0.1", port)
            try:
                answers = [
                    await connection.request("GET", "/health"),
                    await connection.request("GET", "/chunks"),
                    await connection.request("POST", "/detect", b"image", {"Content-Type": "image/png"}),
                ]
            finally:
                connection.close()
            return answers, len(accepted)

    answers, connections = asyncio.run(scenario())
    assert [(code, body) for code, _, body in answers] == [
        (200, b'{"status":"ok"}'),
        (200, b"abcde"),
        (503, b"busy: image"),
    ]
    assert answers[2][1]["retry-after"] == "5"  # names lower-cased
    assert connections == 1


def test_a_kept_alive_connection_the_server_closed_is_opened_again():
    def handle(head, body, count):
        # Each connection answers once and closes without saying so, as an idle keep-alive
        # connection is closed by the server between two requests.
        return _answer(200, b"%d" % count), True

    async def scenario():
        server, port, accepted = await _serve(handle)
        async with server:
            connection = Connection("127.0.0.1", port)
            try:
                first = await connection.request("GET", "/a")
                # At once: the close is on its way, and the request goes out on the closed connection
                # (the server answers nothing) or, once the close has arrived, on a new one.
                second = await connection.request("GET", "/b")
                await asyncio.sleep(0.1)
                third = await connection.request("GET", "/c")
            finally:
                connection.close()
            return first, second, third, len(accepted)

    first, second, third, connections = asyncio.run(scenario())
    assert first[0] == second[0] == third[0] == 200 and connections == 3


def test_an_answer_cut_short_is_an_error_not_a_request_sent_twice():
    requests = []

    def handle(head, body, count):
        requests.append(head)
        return b"HTTP/1.1 200 OK\r\ncontent-length: 100\r\n\r\nonly part", True

    async def scenario():
        server, port, _ = await _serve(handle)
        async with server:
            connection = Connection("127.0.0.1", port)
            try:
                await connection.request("POST", "/models/1/detect", b"image")
            finally:
                connection.close()

    with pytest.raises(asyncio.IncompleteReadError):
        asyncio.run(scenario())
    assert len(requests) == 1
