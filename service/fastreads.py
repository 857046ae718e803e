"""The hot reads of a polling dashboard or script, answered before FastAPI's routing and
dependency machinery (which cost more than the read itself): GET /healthz, and GET
/v1/jobs/{id} of a stored job. Anything else, an unknown job included, goes on to the
FastAPI routes, which answer it as documented."""

from __future__ import annotations

from starlette.responses import Response
from starlette.types import ASGIApp, Receive, Scope, Send

from nprt.service.schemas import JobPublic

HEALTHY = b'{"status":"ok"}'
_JOB_PREFIX = "/v1/jobs/"


class FastReads:
    def __init__(self, app: ASGIApp):
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http" and scope["method"] == "GET":
            answer = _answer(scope)
            if answer is not None:
                await answer(scope, receive, send)
                return
        await self.app(scope, receive, send)


def _answer(scope: Scope) -> Response | None:
    path = scope["path"]
    if path == "/healthz":
        return Response(HEALTHY, media_type="application/json")
    if path.startswith(_JOB_PREFIX) and "/" not in path[len(_JOB_PREFIX):]:
        rec = scope["app"].state.api.store.get(path[len(_JOB_PREFIX):])
        if rec is not None:
            return Response(JobPublic.from_record(rec).model_dump_json(),
                            media_type="application/json")
    return None
