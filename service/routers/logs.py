"""/v1/jobs/{id}/logs: a job's job.log as text, or followed line by line over SSE."""

from __future__ import annotations

import asyncio
import time
from typing import Annotated

from fastapi import APIRouter, Header, Query, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import PlainTextResponse
from sse_starlette.sse import EventSourceResponse

from nprt.service.deps import ApiDep
from nprt.service.errors import NotFound
from nprt.service.joblog import LOG_NAME, LogTail, read_lines
from nprt.service.schemas import error_responses
from nprt.service.store import TERMINAL

router = APIRouter(prefix="/v1/jobs", tags=["jobs"])

LOG_POLL_S = 0.25  # how often a follower looks for new lines
SSE_PING_S = 15


@router.get("/{job_id}/logs", response_class=Response, responses={200: {
    "content": {"text/plain": {}, "text/event-stream": {}},
    "description": "text/plain: the log from `offset` (at most 1 MiB; header "
                   "X-Nprt-Log-Offset is where to read next). follow=1: SSE `log` events, one "
                   "line each, `id` the byte offset after it (reconnects resume there), then "
                   "`end` with the job's final state."}} | error_responses(404))
async def job_logs(job_id: str, api: ApiDep,
                   follow: bool = False,
                   offset: Annotated[int, Query(ge=0, description="byte offset")] = 0,
                   last_event_id: Annotated[str | None, Header()] = None):
    """The records the job's render thread logged (INFO and above), as written to job.log."""
    await run_in_threadpool(api.get, job_id)  # 404 before anything else
    path = api.job_dir(job_id) / LOG_NAME
    if not follow:
        lines = await run_in_threadpool(read_lines, path, offset)
        end = lines[-1][1] if lines else offset
        return PlainTextResponse("".join(f"{text}\n" for text, _ in lines),
                                 headers={"X-Nprt-Log-Offset": str(end),
                                          "Cache-Control": "no-store"})
    if last_event_id and last_event_id.isdigit():
        offset = int(last_event_id)
    return EventSourceResponse(_follow(api, job_id, LogTail(path, offset)),
                               ping=SSE_PING_S)


async def _follow(api, job_id: str, tail: LogTail):
    while True:
        try:
            rec = await run_in_threadpool(api.get, job_id)
        except NotFound:  # deleted while followed
            yield {"event": "end", "data": "deleted"}
            return
        lines, done = await run_in_threadpool(tail.poll, rec.state in TERMINAL,
                                              time.monotonic())
        for text, end in lines:
            yield {"event": "log", "id": str(end), "data": text}
        if done:
            yield {"event": "end", "data": rec.state}
            return
        if not lines:
            await asyncio.sleep(LOG_POLL_S)
