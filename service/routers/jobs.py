"""/v1/jobs: submit, list, inspect, follow (SSE), fetch images, cancel."""

from __future__ import annotations

import base64
from typing import Annotated, Literal

from fastapi import APIRouter, Header, Query, Response, status
from fastapi.concurrency import run_in_threadpool
from fastapi.encoders import jsonable_encoder
from fastapi.exceptions import RequestValidationError
from sse_starlette.event import ServerSentEvent
from sse_starlette.sse import EventSourceResponse

from nprt.service import images
from nprt.service.deps import ApiDep, TokenDep
from nprt.service.errors import InvalidJob, TooManyWatchers
from nprt.service.events import AsyncWatch, encoded
from nprt.service.schemas import (
    JobCreate,
    JobPublic,
    JobsPublic,
    JobState,
    TileEvent,
    error_responses,
)
from nprt.service.store import TERMINAL

router = APIRouter(prefix="/v1/jobs", tags=["jobs"])

_MEDIA = {"png": "image/png", "exr": "image/x-exr"}
SSE_PING_S = 15
SSE_SEP = "\r\n"
# Reads are SQLite rows on the store's reading connection (WAL: a read never waits for a
# writer), well under a millisecond: they run on the event loop, where a thread hop would
# cost more. Writes (submit, cancel) can wait for another process's write, so they go to
# a thread; so does image encoding. No render runs in this process.
MAX_OFFSET = (1 << 31) - 1  # SQLite takes 64-bit offsets; nobody pages past 2^31 jobs
MAX_LIMIT = 500


@router.post("", status_code=status.HTTP_202_ACCEPTED, dependencies=[TokenDep],
             response_model=JobPublic, responses=error_responses(400, 401, 409, 413, 429, 503))
async def create_job(body: JobCreate, api: ApiDep,
                     idempotency_key: Annotated[str | None, Header(
                         min_length=1, max_length=200,
                         description="a retried request with the same key returns the job "
                                     "the first one created (header Idempotent-Replayed)")
                     ] = None) -> Response:
    """Store the job and queue it; rendering starts when a slot is free. Past
    NPRT_MAX_QUEUED_JOBS queued jobs: 429 with Retry-After (retry with the same
    Idempotency-Key)."""
    try:
        frames = None if body.frames is None else (body.frames.first, body.frames.last)
        rec, created = await api.submit_async(body.scene, body.render_settings(),
                                              idempotency_key, frames)
    except InvalidJob as e:
        # Same answer as FastAPI's own validation errors, so clients see the field.
        raise RequestValidationError([
            {"type": "value_error", "loc": ["body", e.field], "msg": str(e),
             "input": jsonable_encoder(getattr(body, e.field))}]) from None
    headers = {"Location": f"/v1/jobs/{rec.id}"}
    if not created:
        headers["Idempotent-Replayed"] = "true"
    # Serialized here, once: returning the model would have FastAPI validate it again.
    return Response(JobPublic.from_record(rec).model_dump_json(), status.HTTP_202_ACCEPTED,
                    headers, media_type="application/json")


@router.get("", response_model=JobsPublic)
async def list_jobs(api: ApiDep,
                    offset: Annotated[int, Query(ge=0, le=MAX_OFFSET)] = 0,
                    limit: Annotated[int, Query(ge=1, le=MAX_LIMIT)] = 50,
                    state: JobState | None = None) -> Response:
    """Jobs, newest first."""
    return Response(jobs_page(api, offset, limit, state), media_type="application/json")


def jobs_page(api, offset: int, limit: int, state: str | None) -> str:
    """The JSON of a JobsPublic page (also answered by nprt.service.fastreads)."""
    recs, count = api.list(offset, limit, state)
    return JobsPublic(data=[JobPublic.from_record(r) for r in recs], count=count,
                      offset=offset, limit=limit).model_dump_json()


@router.get("/{job_id}", response_model=JobPublic, responses=error_responses(404))
async def get_job(job_id: str, api: ApiDep) -> Response:
    return _json(JobPublic.from_record(api.get(job_id)))


def _json(model) -> Response:
    """The model serialized once: returning it would have FastAPI validate it again
    against the response model (half the CPU of a polled read)."""
    return Response(model.model_dump_json(), media_type="application/json")


@router.post("/{job_id}/cancel", status_code=status.HTTP_202_ACCEPTED, dependencies=[TokenDep],
             responses=error_responses(401, 404, 409))
async def cancel_job(job_id: str, api: ApiDep) -> JobPublic:
    """The cancel is stored first (it survives a restart): a queued job is canceled at
    once, a running one stops at its next pass boundary and ends canceled (409 if the job
    already finished)."""
    return JobPublic.from_record(await api.in_writer(api.cancel, job_id))


async def _image(api, job_id: str, fmt: str) -> Response:
    data, partial = await run_in_threadpool(api.image, job_id, fmt)
    return Response(data, media_type=_MEDIA[fmt],
                    headers={"X-Nprt-Partial": str(partial).lower(),
                             "Cache-Control": "no-store"})


@router.get("/{job_id}/image.png", response_class=Response,
            responses={200: {"content": {"image/png": {}},
                             "description": "sRGB PNG; partial while running "
                                            "(header X-Nprt-Partial)"}} | error_responses(404))
async def get_image_png(job_id: str, api: ApiDep) -> Response:
    return await _image(api, job_id, "png")


@router.get("/{job_id}/image.exr", response_class=Response,
            responses={200: {"content": {"image/x-exr": {}},
                             "description": "linear float32 OpenEXR; partial while running"}}
            | error_responses(404))
async def get_image_exr(job_id: str, api: ApiDep) -> Response:
    return await _image(api, job_id, "exr")


@router.get("/{job_id}/events", response_class=EventSourceResponse,
            responses={200: {"content": {"text/event-stream": {}}, "description":
                             "`state` events (JobPublic JSON) on connect and on every change, "
                             "`tile` events (TileEvent JSON) per finished pass, then `end`; "
                             "a slow reader gets the latest tile of each rectangle"}}
            | error_responses(404, 503))
async def job_events(job_id: str, api: ApiDep,
                     pixels: Annotated[Literal["none", "f16"], Query(
                         description="f16: tile events carry the tile's pixels")] = "none"
                     ) -> EventSourceResponse:
    api.get(job_id)  # 404 before the stream starts
    api.broker.check_capacity()  # 503 likewise
    return EventSourceResponse(_events(api, job_id, pixels == "f16"), ping=SSE_PING_S,
                               sep=SSE_SEP)


async def _events(api, job_id: str, with_pixels: bool = False):
    """The stream's chunks: every batch the feed hands over goes out as one write, each
    event encoded once for all this process's watchers (nprt.service.events.encoded)."""
    try:
        # Subscribe before the snapshot so nothing falls between them (duplicates are harmless).
        watch = AsyncWatch(lambda notify: api.watch(job_id, notify))
    except TooManyWatchers as e:  # the limit filled up since the check
        yield _sse("error", str(e))
        return
    async with watch:
        rec = api.get(job_id)
        yield _state(rec)
        while rec.state not in TERMINAL:
            chunk = []
            for ev in await watch.next_events():
                if ev["type"] == "tile":
                    chunk.append(encoded(ev, ("sse", with_pixels),
                                         lambda e: _tile(e, with_pixels)))
                else:
                    rec = ev["job"]
                    chunk.append(encoded(ev, "sse", lambda e: _state(e["job"])))
                    if rec.state in TERMINAL:
                        break
            yield b"".join(chunk)
        yield _sse("end", rec.state)


def _sse(event: str, data: str) -> bytes:
    return ServerSentEvent(data, event=event, sep=SSE_SEP).encode()


def _state(rec) -> bytes:
    return _sse("state", JobPublic.from_record(rec).model_dump_json())


def _tile(ev: dict, with_pixels: bool) -> bytes:
    tile = TileEvent(**{k: ev[k] for k in TileEvent.model_fields if k in ev})
    if with_pixels:
        tile.pixels = base64.b64encode(images.f16_bytes(ev["rgb"])).decode()
    return _sse("tile", tile.model_dump_json())
