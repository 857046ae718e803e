"""The hot path of POST /v1/jobs: a valid job body is parsed by pydantic straight from its
bytes, stored on the writer thread and answered, without FastAPI's per-request dependency
and validation machinery (about half the CPU of an admission). Anything else (a body that
does not validate, a bad header, a refusal) goes on to the FastAPI route, which answers it
as documented; a refusal is a read, so asking twice changes nothing."""

from __future__ import annotations

from pydantic import ValidationError
from starlette.responses import Response
from starlette.types import ASGIApp, Receive, Scope, Send

from nprt.service.bodyguard import read_body, replayed
from nprt.service.errors import ServiceError
from nprt.service.schemas import JobCreate, JobPublic

MAX_KEY_CHARS = 200  # the route's Idempotency-Key limit


class FastAdmission:
    def __init__(self, app: ASGIApp):
        self.app = app

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if not (scope["type"] == "http" and scope["method"] == "POST"
                and scope["path"] == "/v1/jobs"):
            await self.app(scope, receive, send)
            return
        headers = dict(scope["headers"])
        if not headers.get(b"content-type", b"").startswith(b"application/json"):
            await self.app(scope, receive, send)
            return
        body = await read_body(receive)
        if body is None:  # the client went away
            return
        answer = await _admit(scope["app"].state.api, headers, body)
        if answer is not None:
            await answer(scope, receive, send)
            return
        await self.app(scope, replayed(body, receive), send)


async def _admit(api, headers: dict, body: bytes) -> Response | None:
    """The 202 answer of a clean admission, else None."""
    key = headers.get(b"idempotency-key")
    if key is not None:
        key = key.decode("latin-1")
        if not 1 <= len(key) <= MAX_KEY_CHARS:
            return None
    try:
        job = JobCreate.model_validate_json(body)
    except ValidationError:
        return None
    frames = None if job.frames is None else (job.frames.first, job.frames.last)
    try:
        rec, created = await api.submit_async(job.scene, job.render_settings(), key, frames)
    except ServiceError:
        return None
    out = {"location": f"/v1/jobs/{rec.id}"}
    if not created:
        out["idempotent-replayed"] = "true"
    return Response(JobPublic.from_record(rec).model_dump_json(), 202, out,
                    media_type="application/json")
