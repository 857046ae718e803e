"""The hot reads of a polling dashboard or script, answered before FastAPI's routing and
dependency machinery (which cost more than the read itself): GET /healthz, GET
/v1/jobs/{id} of a stored job, and GET /v1/jobs with plain offset / limit / state. Anything
else (an unknown job, a query the route would refuse or parse otherwise) goes on to the
FastAPI routes, which answer it as documented."""

from __future__ import annotations

from typing import get_args

from starlette.responses import Response
from starlette.types import ASGIApp, Receive, Scope, Send

from nprt.service.routers.jobs import MAX_LIMIT, MAX_OFFSET, jobs_page
from nprt.service.schemas import JobPublic, JobState

HEALTHY = b'{"status":"ok"}'
_JOB_PREFIX = "/v1/jobs/"
_LIST = "/v1/jobs"
_STATES = frozenset(get_args(JobState))


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
    if path == _LIST:
        page = _list_query(scope["query_string"])
        if page is None:
            return None
        return Response(jobs_page(scope["app"].state.api, *page),
                        media_type="application/json")
    if path.startswith(_JOB_PREFIX) and "/" not in path[len(_JOB_PREFIX):]:
        rec = scope["app"].state.api.store.get(path[len(_JOB_PREFIX):])
        if rec is not None:
            return Response(JobPublic.from_record(rec).model_dump_json(),
                            media_type="application/json")
    return None


def _list_query(query: bytes) -> tuple[int, int, str | None] | None:
    """(offset, limit, state) of a list query the route would take as is: each name at
    most once, digits in range, a known state; None for anything else."""
    got: dict[bytes, bytes] = {}
    for part in query.split(b"&") if query else ():
        name, eq, value = part.partition(b"=")
        if not eq or name in got or name not in (b"offset", b"limit", b"state"):
            return None
        got[name] = value
    offset, limit = got.get(b"offset", b"0"), got.get(b"limit", b"50")
    if not (offset.isdigit() and limit.isdigit() and len(offset) <= 10 and len(limit) <= 3):
        return None
    state = got.get(b"state")
    state = None if state is None else state.decode("latin-1")
    if state is not None and state not in _STATES:
        return None
    offset, limit = int(offset), int(limit)
    if offset > MAX_OFFSET or not 1 <= limit <= MAX_LIMIT:
        return None
    return offset, limit, state
