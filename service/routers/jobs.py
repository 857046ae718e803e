"""/v1/jobs: submit, list, inspect, follow (SSE), fetch images, cancel."""

from __future__ import annotations

import asyncio
import base64
from typing import Annotated, Literal

from fastapi import APIRouter, HTTPException, Query, Response, status
from fastapi.concurrency import run_in_threadpool
from sse_starlette.sse import EventSourceResponse

from service import images
from service.deps import ManagerDep, TokenDep
from service.errors import InvalidJob
from service.schemas import JobCreate, JobPublic, JobsPublic, JobState, TileEvent
from service.store import TERMINAL

router = APIRouter(prefix="/v1/jobs", tags=["jobs"])

_MEDIA = {"png": "image/png", "exr": "image/x-exr"}
SSE_PING_S = 15


@router.post("", status_code=status.HTTP_202_ACCEPTED, dependencies=[TokenDep])
async def create_job(body: JobCreate, manager: ManagerDep, response: Response) -> JobPublic:
    """Store the job and queue it; rendering starts when a slot is free."""
    try:
        rec = await run_in_threadpool(manager.submit, body.scene, body.render_settings())
    except InvalidJob as e:
        # Same shape as FastAPI's own validation errors, so clients see the field.
        raise HTTPException(status.HTTP_422_UNPROCESSABLE_CONTENT, [
            {"type": "value_error", "loc": ["body", e.field], "msg": str(e),
             "input": getattr(body, e.field)}]) from None
    response.headers["Location"] = f"/v1/jobs/{rec.id}"
    return JobPublic.from_record(rec)


@router.get("")
async def list_jobs(manager: ManagerDep,
                    offset: Annotated[int, Query(ge=0)] = 0,
                    limit: Annotated[int, Query(ge=1, le=500)] = 50,
                    state: JobState | None = None) -> JobsPublic:
    """Jobs, newest first."""
    recs, count = await run_in_threadpool(manager.list, offset, limit, state)
    return JobsPublic(data=[JobPublic.from_record(r) for r in recs], count=count,
                      offset=offset, limit=limit)


@router.get("/{job_id}")
async def get_job(job_id: str, manager: ManagerDep) -> JobPublic:
    return JobPublic.from_record(await run_in_threadpool(manager.get, job_id))


@router.post("/{job_id}/cancel", status_code=status.HTTP_202_ACCEPTED, dependencies=[TokenDep])
async def cancel_job(job_id: str, manager: ManagerDep) -> JobPublic:
    """Queued jobs cancel at once; running ones stop at the next pass boundary (409 if the
    job already finished)."""
    return JobPublic.from_record(await run_in_threadpool(manager.cancel, job_id))


async def _image(manager, job_id: str, fmt: str) -> Response:
    data, partial = await run_in_threadpool(manager.image, job_id, fmt)
    return Response(data, media_type=_MEDIA[fmt],
                    headers={"X-Nprt-Partial": str(partial).lower(),
                             "Cache-Control": "no-store"})


@router.get("/{job_id}/image.png", response_class=Response,
            responses={200: {"content": {"image/png": {}},
                             "description": "sRGB PNG; partial while running "
                                            "(header X-Nprt-Partial)"}})
async def get_image_png(job_id: str, manager: ManagerDep) -> Response:
    return await _image(manager, job_id, "png")


@router.get("/{job_id}/image.exr", response_class=Response,
            responses={200: {"content": {"image/x-exr": {}},
                             "description": "linear float32 OpenEXR; partial while running"}})
async def get_image_exr(job_id: str, manager: ManagerDep) -> Response:
    return await _image(manager, job_id, "exr")


@router.get("/{job_id}/events", response_class=EventSourceResponse,
            responses={200: {"content": {"text/event-stream": {}}, "description":
                             "`state` events (JobPublic JSON) on connect and on every change, "
                             "`tile` events (TileEvent JSON) per finished pass, then `end`"}})
async def job_events(job_id: str, manager: ManagerDep,
                     pixels: Annotated[Literal["none", "f16"], Query(
                         description="f16: tile events carry the tile's pixels")] = "none"
                     ) -> EventSourceResponse:
    await run_in_threadpool(manager.get, job_id)  # 404 before the stream starts
    return EventSourceResponse(_events(manager, job_id, pixels == "f16"), ping=SSE_PING_S)


async def _events(manager, job_id: str, with_pixels: bool = False):
    loop = asyncio.get_running_loop()
    q: asyncio.Queue[dict] = asyncio.Queue()

    def deliver(event: dict) -> None:
        try:
            loop.call_soon_threadsafe(q.put_nowait, event)
        except RuntimeError:  # the loop closed under a late event
            pass

    # Subscribe before the snapshot so nothing falls between them (duplicates are harmless).
    unsubscribe = manager.subscribe(job_id, deliver)
    try:
        rec = await run_in_threadpool(manager.get, job_id)
        while True:
            if rec is not None:
                yield {"event": "state", "data": JobPublic.from_record(rec).model_dump_json()}
                if rec.state in TERMINAL:
                    yield {"event": "end", "data": rec.state}
                    return
            ev = await q.get()
            rec = None
            if ev["type"] == "tile":
                tile = TileEvent(**{k: ev[k] for k in TileEvent.model_fields if k in ev})
                if with_pixels:
                    tile.pixels = base64.b64encode(images.f16_bytes(ev["rgb"])).decode()
                yield {"event": "tile", "data": tile.model_dump_json()}
            else:
                rec = ev["job"]
    finally:
        unsubscribe()
