"""Refuse a job body that is too large or nested too deep before it is parsed into objects:
Python's JSON parser recurses once per level, so a body nested 10,000 levels deep would
otherwise end in a RecursionError (a 500) after costing the CPU to get there."""

from __future__ import annotations

import re

from starlette.responses import Response
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


class BodyMiddleware:
    """Base of the ASGI middlewares that read the body of a POST to GUARDED_PATHS (at most
    max_bytes + a chunk): answer() returns the response, or None to pass the request on
    with its body replayed."""

    max_bytes: int | None = None

    def __init__(self, app: ASGIApp):
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if not (scope["type"] == "http" and scope["method"] == "POST"
                and scope["path"] in GUARDED_PATHS):
            await self.app(scope, receive, send)
            return
        body = await read_body(receive, self.max_bytes)
        if body is None:  # the client went away
            return
        answer = await self.answer(scope, body)
        if answer is not None:
            await answer(scope, receive, send)
            return
        await self.app(scope, replayed(body, receive), send)

    async def answer(self, scope: Scope, body: bytes) -> Response | None:
        raise NotImplementedError


class JsonGuard(BodyMiddleware):
    """413 over max_bytes, 422 past max_depth, else the body is passed on unchanged. Runs
    after the token check."""

    def __init__(self, app: ASGIApp, max_depth: int = MAX_JSON_DEPTH,
                 max_bytes: int = MAX_JSON_BYTES):
        super().__init__(app)
        self.max_depth, self.max_bytes = max_depth, max_bytes

    async def answer(self, scope: Scope, body: bytes) -> Response | None:
        from nprt.service.problems import problem_response

        if len(body) > self.max_bytes:
            return problem_response(413, f"a job body is at most {self.max_bytes} bytes "
                                    "(got more)", instance=scope["path"])
        if json_depth(body) > self.max_depth:
            return problem_response(422, f"the body nests deeper than {self.max_depth} "
                                    "levels", instance=scope["path"])
        return None
