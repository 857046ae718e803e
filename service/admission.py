"""The hot path of POST /v1/jobs: a valid job body is parsed by pydantic straight from its
bytes (once: its settings are neither validated nor dumped again), stored on the writer
thread and answered from the stored row, without FastAPI's per-request dependency and
validation machinery (about half the CPU of an admission). Anything else (a body that
does not validate, a bad header, a refusal) goes on to the FastAPI route, which answers it
as documented; a refusal is a read, so asking twice changes nothing."""

from __future__ import annotations

from pydantic import ValidationError
from starlette.responses import Response
from starlette.types import Scope

from nprt.service.bodyguard import BodyMiddleware
from nprt.service.errors import ServiceError
from nprt.service.schemas import JobCreate, JobPublic, queued_job_json

MAX_KEY_CHARS = 200  # the route's Idempotency-Key limit


class FastAdmission(BodyMiddleware):
    async def answer(self, scope: Scope, body: bytes) -> Response | None:
        headers = dict(scope["headers"])
        if not headers.get(b"content-type", b"").startswith(b"application/json"):
            return None
        return await _admit(scope["app"].state.api, headers, body)


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
        # The JobCreate is a RenderSettings: its settings fields are stored as they are.
        rec, created = await api.submit_async(job.scene, job, key, frames)
    except ServiceError:
        return None
    headers = {"location": f"/v1/jobs/{rec.id}"}
    if created:
        body = queued_job_json(rec, rec.settings_json)
    else:  # a replayed key's job has these settings too (a different request is a Conflict)
        headers["idempotent-replayed"] = "true"
        body = JobPublic.from_record(rec, job.render_settings()).model_dump_json()
    return Response(body, 202, headers, media_type="application/json")
