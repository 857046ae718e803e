"""A minimal HTTP/1.1 client for the load generator: one asyncio Protocol per connection,
requests written as prebuilt bytes, answers parsed by Content-Length. It spends a few
percent of aiohttp's CPU per request, so on a machine shared with the service the figures
measure the service rather than the client (as a C load generator such as wrk would).
Not a general client: no chunked answers except a streamed body read as it comes, no
redirects, no TLS."""

from __future__ import annotations

import asyncio
import json


def request_bytes(method: str, path: str, host: str, body: bytes = b"",
                  headers: dict[str, str] | None = None) -> bytes:
    lines = [f"{method} {path} HTTP/1.1", f"Host: {host}"]
    if body or method in ("POST", "PUT", "PATCH"):
        lines += ["Content-Type: application/json", f"Content-Length: {len(body)}"]
    lines += [f"{k}: {v}" for k, v in (headers or {}).items()]
    return ("\r\n".join(lines) + "\r\n\r\n").encode("latin-1") + body


class Answer:
    """status : int, headers : dict (lower-case names), body : bytes."""

    __slots__ = ("status", "headers", "body")

    def __init__(self, status: int, headers: dict[str, str], body: bytes):
        self.status, self.headers, self.body = status, headers, body

    def json(self):
        return json.loads(self.body)


class _Protocol(asyncio.Protocol):
    def __init__(self):
        self.transport: asyncio.Transport | None = None
        self._buf = bytearray()
        self._waiter: asyncio.Future | None = None
        self._head: tuple[int, dict, int] | None = None  # status, headers, body length
        self.on_chunk = None  # streaming: called with each body chunk instead
        self.closed = asyncio.get_running_loop().create_future()

    def connection_made(self, transport) -> None:
        self.transport = transport

    def connection_lost(self, exc) -> None:
        if self._waiter is not None and not self._waiter.done():
            self._waiter.set_exception(ConnectionError("the server closed the connection"))
        if not self.closed.done():
            self.closed.set_result(None)

    def data_received(self, data: bytes) -> None:
        if self.on_chunk is not None and self._head is not None:
            self.on_chunk(data)
            return
        self._buf += data
        if self._head is None:
            end = self._buf.find(b"\r\n\r\n")
            if end < 0:
                return
            lines = bytes(self._buf[:end]).decode("latin-1").split("\r\n")
            headers = {}
            for line in lines[1:]:
                name, _, value = line.partition(":")
                headers[name.strip().lower()] = value.strip()
            self._head = (int(lines[0].split()[1]), headers,
                          int(headers.get("content-length", -1)))
            del self._buf[:end + 4]
            if self.on_chunk is not None:  # a stream: the head is the answer
                self._waiter.set_result(Answer(self._head[0], self._head[1], b""))
                if self._buf:
                    self.on_chunk(bytes(self._buf))
                return
        status, headers, length = self._head
        if 0 <= length <= len(self._buf):
            body, self._buf = bytes(self._buf[:length]), self._buf[length:]
            self._head = None
            if self._waiter is not None and not self._waiter.done():
                self._waiter.set_result(Answer(status, headers, body))

    def send(self, data: bytes) -> asyncio.Future:
        self._waiter = asyncio.get_running_loop().create_future()
        self.transport.write(data)
        return self._waiter


class Connection:
    """One keep-alive connection, used by one coroutine at a time; reconnects when the
    server closed it (an idle timeout) before a request is written."""

    def __init__(self, host: str, port: int):
        self.host, self.port = host, port
        self._proto: _Protocol | None = None

    async def _open(self) -> _Protocol:
        if self._proto is None or self._proto.transport.is_closing():
            _, self._proto = await asyncio.get_running_loop().create_connection(
                _Protocol, self.host, self.port)
        return self._proto

    async def request(self, data: bytes) -> Answer:
        """Send one prebuilt request (request_bytes) and wait for its whole answer."""
        return await (await self._open()).send(data)

    async def stream(self, data: bytes, on_chunk) -> Answer:
        """Send a request whose answer streams (SSE): returns the head, then hands every
        body chunk to on_chunk(bytes) until the server closes; await closed() for that."""
        proto = await self._open()
        proto.on_chunk = on_chunk
        return await proto.send(data)

    async def closed(self) -> None:
        await self._proto.closed

    def close(self) -> None:
        if self._proto is not None:
            self._proto.transport.close()
