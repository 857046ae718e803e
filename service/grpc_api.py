"""The RenderService servicer: a thin adapter from gRPC onto the JobManager."""

from __future__ import annotations

import queue

import grpc
from pydantic import ValidationError

from protos import nprt_pb2 as pb
from protos import nprt_pb2_grpc
from service.errors import Conflict, InvalidJob, InvalidScene, NotFound, ServiceError
from service.grpc_convert import job_to_pb, settings_from_pb, tile_to_pb
from service.grpc_logs import JobLogServicer
from service.manager import JobManager
from service.store import TERMINAL

DEFAULT_PAGE = 50
MAX_PAGE = 500
WATCH_POLL_S = 0.5  # how often a watcher notices its client went away

_CODES = {NotFound: grpc.StatusCode.NOT_FOUND, Conflict: grpc.StatusCode.FAILED_PRECONDITION,
          InvalidJob: grpc.StatusCode.INVALID_ARGUMENT,
          InvalidScene: grpc.StatusCode.INVALID_ARGUMENT}
_FORMATS = {pb.IMAGE_FORMAT_PNG: "png", pb.IMAGE_FORMAT_EXR: "exr"}


def _abort(context: grpc.ServicerContext, exc: ServiceError):
    code = next((c for t, c in _CODES.items() if isinstance(exc, t)),
                grpc.StatusCode.INVALID_ARGUMENT)
    context.abort(code, str(exc))


def _validation_message(e: ValidationError) -> str:
    return "; ".join(f"{'.'.join(map(str, err['loc'])) or 'settings'}: {err['msg']} "
                     f"(got {err.get('input')!r})" for err in e.errors())


class RenderServicer(JobLogServicer, nprt_pb2_grpc.RenderServiceServicer):
    def __init__(self, manager: JobManager, max_message_bytes: int):
        self.manager = manager
        self.max_message_bytes = max_message_bytes

    def SubmitJob(self, request, context):
        try:
            settings = settings_from_pb(request.settings)
        except ValidationError as e:
            context.abort(grpc.StatusCode.INVALID_ARGUMENT,
                          f"invalid settings: {_validation_message(e)}")
        if not request.scene:
            context.abort(grpc.StatusCode.INVALID_ARGUMENT, "scene is required (got '')")
        try:
            return job_to_pb(self.manager.submit(request.scene, settings))
        except ServiceError as e:
            _abort(context, e)

    def GetJob(self, request, context):
        try:
            return job_to_pb(self.manager.get(request.job_id))
        except ServiceError as e:
            _abort(context, e)

    def ListJobs(self, request, context):
        limit = request.limit or DEFAULT_PAGE
        if limit > MAX_PAGE:
            context.abort(grpc.StatusCode.INVALID_ARGUMENT,
                          f"limit must be at most {MAX_PAGE} (got {limit})")
        recs, total = self.manager.list(request.offset, limit)
        return pb.ListJobsResponse(jobs=[job_to_pb(r) for r in recs], total=total)

    def CancelJob(self, request, context):
        try:
            return job_to_pb(self.manager.cancel(request.job_id))
        except ServiceError as e:
            _abort(context, e)

    def GetImage(self, request, context):
        fmt = _FORMATS.get(request.format)
        if fmt is None:
            context.abort(grpc.StatusCode.INVALID_ARGUMENT,
                          f"unknown image format {request.format}")
        try:
            data, partial = self.manager.image(request.job_id, fmt)
            rec = self.manager.get(request.job_id)
        except ServiceError as e:
            _abort(context, e)
        if len(data) > self.max_message_bytes - 1024:
            context.abort(grpc.StatusCode.RESOURCE_EXHAUSTED,
                          f"the {fmt} image is {len(data)} bytes, over the gRPC message limit "
                          f"of {self.max_message_bytes}; fetch /v1/jobs/{rec.id}/image.{fmt}")
        return pb.Image(job_id=rec.id, format=request.format, data=data, partial=partial,
                        width=rec.settings["width"], height=rec.settings["height"])

    def WatchJob(self, request, context):
        events: queue.Queue[dict] = queue.Queue()
        # Subscribe before the snapshot so no event falls between them.
        unsubscribe = self.manager.subscribe(request.job_id, events.put)
        try:
            try:
                rec = self.manager.get(request.job_id)
            except ServiceError as e:
                _abort(context, e)
            yield pb.JobEvent(job=job_to_pb(rec))
            while rec.state not in TERMINAL and context.is_active():
                try:
                    ev = events.get(timeout=WATCH_POLL_S)
                except queue.Empty:
                    continue
                if ev["type"] == "tile":
                    yield pb.JobEvent(tile=tile_to_pb(ev, request.tile_format,
                                                          self.max_message_bytes))
                else:
                    rec = ev["job"]
                    yield pb.JobEvent(job=job_to_pb(rec))
        finally:
            unsubscribe()
