"""RenderService.StreamJobLog: a job's job.log over gRPC (a mixin of the servicer, which
provides self.api)."""

from __future__ import annotations

import asyncio
import time

import grpc

from nprt.protos import nprt_pb2 as pb
from nprt.service.errors import NotFound
from nprt.service.joblog import LOG_NAME, LogTail, read_lines
from nprt.service.store import TERMINAL

LOG_POLL_S = 0.25  # how often a follower looks for new lines


class JobLogServicer:
    async def StreamJobLog(self, request, context):
        """An async generator on the service's event loop (grpc.aio): no thread per
        follower."""
        try:
            self.api.get(request.job_id)
        except NotFound as e:
            await context.abort(grpc.StatusCode.NOT_FOUND, str(e))
        path = self.api.job_dir(request.job_id) / LOG_NAME
        if not request.follow:
            for text, end in read_lines(path, request.offset):
                yield pb.LogLine(text=text, end_offset=end)
            return
        tail = LogTail(path, request.offset)
        while not context.done():
            try:
                rec = self.api.get(request.job_id)
            except NotFound:  # deleted while followed
                return
            lines, done = tail.poll(rec.state in TERMINAL, time.monotonic())
            for text, end in lines:
                yield pb.LogLine(text=text, end_offset=end)
            if done:
                return
            if not lines:
                await asyncio.sleep(LOG_POLL_S)
