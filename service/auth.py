"""The bearer token of writing requests, for REST and gRPC alike: the scheme is
case-insensitive (RFC 7235), the token compared in constant time."""

from __future__ import annotations

import hmac

from starlette.types import ASGIApp, Receive, Scope, Send

WRITING_METHODS = frozenset({"POST", "PUT", "PATCH", "DELETE"})


def bearer_error(authorization: str | bytes | None, token: str) -> str | None:
    """None when the Authorization value carries `token`, else why not (for the 401)."""
    if isinstance(authorization, bytes):
        authorization = authorization.decode("latin-1")
    scheme, _, credentials = (authorization or "").strip().partition(" ")
    credentials = credentials.strip()
    if scheme.lower() != "bearer" or not credentials:
        return "missing bearer token"
    if not hmac.compare_digest(credentials.encode("utf-8", "surrogateescape"),
                               token.encode()):
        return "wrong bearer token"
    return None


class TokenMiddleware:
    """Refuse writing /v1 requests without the token before anything reads their body:
    a client without the token learns nothing from how its body would have parsed."""

    def __init__(self, app: ASGIApp, token: str | None):
        self.app = app
        self.token = token

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if (self.token is not None and scope["type"] == "http"
                and scope["method"] in WRITING_METHODS and scope["path"].startswith("/v1/")):
            headers = dict(scope["headers"])
            why = bearer_error(headers.get(b"authorization"), self.token)
            if why is not None:
                from nprt.service.problems import problem_response

                response = problem_response(401, why, instance=scope["path"],
                                            headers={"WWW-Authenticate": "Bearer"})
                await response(scope, receive, send)
                return
        await self.app(scope, receive, send)
