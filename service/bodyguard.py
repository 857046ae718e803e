"""Refuse a job body that is too large or nested too deep before it is parsed into objects:
Python's JSON parser recurses once per level, so a body nested 10,000 levels deep would
otherwise end in a RecursionError (a 500) after costing the CPU to get there."""

from __future__ import annotations

import re

from starlette.types import ASGIApp, Message, Receive, Scope, Send

MAX_JSON_DEPTH = 8  # a job body nests 2 levels (proxy, frames); leave room for clients
MAX_JSON_BYTES = 64 << 10  # a job body is a few hundred bytes
GUARDED_PATHS = frozenset({"/v1/jobs"})
_STRING = re.compile(rb'"(?:[^"\\]|\\.)*"')
_NOT_BRACKETS = bytes(c for c in range(256) if c not in b"[]{}")


def json_depth(body: bytes) -> int:
    """The deepest nesting of arrays and objects in a JSON text (strings ignored); a
    malformed text gets some count and fails in the parser later."""
    brackets = _STRING.sub(b"", body).translate(None, _NOT_BRACKETS)
    depth = deepest = 0
    for b in brackets:
        depth += 1 if b in b"[{" else -1
        deepest = max(deepest, depth)
    return deepest


async def read_body(receive: Receive, max_bytes: int | None = None) -> bytes | None:
    """The request body (reading stops once it is over max_bytes), or None if the client
    went away first."""
    body, more = b"", True
    while more and (max_bytes is None or len(body) <= max_bytes):
        message = await receive()
        if message["type"] != "http.request":
            return None
        body += message.get("body", b"")
        more = message.get("more_body", False)
    return body


def replayed(body: bytes, receive: Receive) -> Receive:
    """A receive() that hands the app `body` (read already) first, then the real one."""
    sent = False

    async def replay() -> Message:
        nonlocal sent
        if sent:
            return await receive()
        sent = True
        return {"type": "http.request", "body": body, "more_body": False}

    return replay


class JsonGuard:
    """ASGI middleware for POSTs to GUARDED_PATHS: 413 over max_bytes, 422 past max_depth,
    else the body is passed on unchanged. Runs after the token check."""

    def __init__(self, app: ASGIApp, max_depth: int = MAX_JSON_DEPTH,
                 max_bytes: int = MAX_JSON_BYTES):
        self.app, self.max_depth, self.max_bytes = app, max_depth, max_bytes

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if not (scope["type"] == "http" and scope["method"] == "POST"
                and scope["path"] in GUARDED_PATHS):
            await self.app(scope, receive, send)
            return
        body = await read_body(receive, self.max_bytes)
        if body is None:  # the client went away
            return
        if len(body) > self.max_bytes:
            await self._refuse(scope, receive, send, 413, f"a job body is at most "
                               f"{self.max_bytes} bytes (got more)")
            return
        if json_depth(body) > self.max_depth:
            await self._refuse(scope, receive, send, 422, f"the body nests deeper than "
                               f"{self.max_depth} levels")
            return
        await self.app(scope, replayed(body, receive), send)

    @staticmethod
    async def _refuse(scope: Scope, receive: Receive, send: Send, status: int,
                      detail: str) -> None:
        from nprt.service.problems import problem_response

        await problem_response(status, detail, instance=scope["path"])(scope, receive, send)
