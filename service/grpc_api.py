"""The RenderService servicer (grpc.aio): a thin adapter from gRPC onto the JobApi.
Reading a job record takes well under a millisecond, so reads run on the event loop (as in
the REST routers); writes (submit, cancel), which may wait for another process's write,
and image encoding go to a thread. A WatchJob stream waits on the event loop and holds no
thread."""

from __future__ import annotations

import asyncio
import inspect

import grpc
from pydantic import ValidationError

from nprt.protos import nprt_pb2 as pb
from nprt.protos import nprt_pb2_grpc
from nprt.service.errors import ServiceError, TooManyWatchers
from nprt.service.events import AsyncWatch, encoded
from nprt.service.grpc_convert import job_to_pb, settings_from_pb, tile_to_pb
from nprt.service.grpc_logs import JobLogServicer
from nprt.service.jobapi import JobApi
from nprt.service.store import TERMINAL

DEFAULT_PAGE = 50
MAX_PAGE = 500

_FORMATS = {pb.IMAGE_FORMAT_PNG: "png", pb.IMAGE_FORMAT_EXR: "exr"}


async def _call(context: grpc.aio.ServicerContext, fn, *args, thread: bool = False):
    """fn(*args), on a worker thread if `thread`, awaited if it is a coroutine; a
    ServiceError ends the rpc with its status code."""
    try:
        if thread:
            return await asyncio.to_thread(fn, *args)
        out = fn(*args)
        return await out if inspect.isawaitable(out) else out
    except ServiceError as e:
        await context.abort(grpc.StatusCode[e.grpc_code], str(e))


def _validation_message(e: ValidationError) -> str:
    return "; ".join(f"{'.'.join(map(str, err['loc'])) or 'settings'}: {err['msg']} "
                     f"(got {err.get('input')!r})" for err in e.errors())


class RenderServicer(JobLogServicer, nprt_pb2_grpc.RenderServiceServicer):
    def __init__(self, api: JobApi, max_message_bytes: int):
        self.api = api
        self.max_message_bytes = max_message_bytes

    async def SubmitJob(self, request, context):
        try:
            settings = settings_from_pb(request.settings)
        except ValidationError as e:
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT,
                                f"invalid settings: {_validation_message(e)}")
        if not request.scene:
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, "scene is required (got '')")
        frames = (request.frames.first, request.frames.last) \
            if request.HasField("frames") else None
        rec, _ = await _call(context, self.api.submit_async, request.scene, settings, None,
                             frames)
        return job_to_pb(rec)

    async def GetJob(self, request, context):
        return job_to_pb(await _call(context, self.api.get, request.job_id))

    async def ListJobs(self, request, context):
        limit = request.limit or DEFAULT_PAGE
        if limit > MAX_PAGE:
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT,
                                f"limit must be at most {MAX_PAGE} (got {limit})")
        recs, total = await _call(context, self.api.list, request.offset, limit)
        return pb.ListJobsResponse(jobs=[job_to_pb(r) for r in recs], total=total)

    async def CancelJob(self, request, context):
        return job_to_pb(await _call(context, self.api.in_writer, self.api.cancel,
                                     request.job_id))

    async def GetImage(self, request, context):
        fmt = await self._format(request, context)
        data, partial = await _call(context, self.api.image, request.job_id, fmt,
                                    thread=True)
        return await self._image(request, context, data, partial, f"image.{fmt}")

    async def GetFrame(self, request, context):
        fmt = await self._format(request, context)
        data = await _call(context, self.api.frame_image, request.job_id, request.frame,
                           fmt, thread=True)
        return await self._image(request, context, data, False,
                                 f"frames/{request.frame}.{fmt}")

    async def _format(self, request, context) -> str:
        fmt = _FORMATS.get(request.format)
        if fmt is None:
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT,
                                f"unknown image format {request.format}")
        return fmt

    async def _image(self, request, context, data: bytes, partial: bool, route: str):
        rec = await _call(context, self.api.get, request.job_id)
        if len(data) > self.max_message_bytes - 1024:
            await context.abort(
                grpc.StatusCode.RESOURCE_EXHAUSTED,
                f"the image is {len(data)} bytes, over the gRPC message limit of "
                f"{self.max_message_bytes}; fetch /v1/jobs/{rec.id}/{route}")
        return pb.Image(job_id=rec.id, format=request.format, data=data, partial=partial,
                        width=rec.settings["width"], height=rec.settings["height"])

    async def WatchJob(self, request, context):
        job_id = request.job_id
        try:
            # Subscribe before the snapshot so no event falls between them.
            watch = AsyncWatch(lambda notify: self.api.watch(job_id, notify))
        except TooManyWatchers as e:
            await context.abort(grpc.StatusCode.RESOURCE_EXHAUSTED, str(e))
        async with watch:
            rec = await _call(context, self.api.get, job_id)
            yield pb.JobEvent(job=job_to_pb(rec))
            while rec.state not in TERMINAL:
                for ev in await watch.next_events():
                    if ev["type"] == "tile":
                        yield await self._tile_event(ev, request.tile_format)
                    else:
                        rec = ev["job"]
                        # One message per event for every stream of this process.
                        yield encoded(ev, "grpc", lambda e: pb.JobEvent(job=job_to_pb(e["job"])))
                        if rec.state in TERMINAL:
                            break

    async def _tile_event(self, ev: dict, fmt: int) -> pb.JobEvent:
        """The event's message in `fmt`, built once for every stream of this process (PNG
        encoding on a thread)."""
        cache = ev.setdefault("_encoded", {})
        key = ("grpc", fmt)
        if key not in cache:
            args = (ev, fmt, self.max_message_bytes)
            tile = (await asyncio.to_thread(tile_to_pb, *args) if fmt == pb.TILE_FORMAT_PNG
                    else tile_to_pb(*args))
            cache[key] = pb.JobEvent(tile=tile)
        return cache[key]
