"""The gRPC server (grpc.aio): RenderService, the standard health service, bearer-token
checks on the writing rpcs, and message size limits that fit tiles and images. In an API
worker it runs on a thread of its own with its own asyncio loop (GrpcThread): a burst of
HTTP requests queued on uvicorn's loop does not hold a health check back, and uvicorn can
use uvloop, on which grpc.aio answers several times slower. A WatchJob stream is a
coroutine, not a thread, so open streams cannot starve Health.Check or GetJob;
NPRT_MAX_WATCHERS bounds them (RESOURCE_EXHAUSTED beyond)."""

from __future__ import annotations

import asyncio
import logging
import threading

import grpc
from grpc_health.v1 import health, health_pb2, health_pb2_grpc

from nprt.protos import nprt_pb2, nprt_pb2_grpc
from nprt.service.auth import bearer_error
from nprt.service.config import ServiceSettings
from nprt.service.grpc_api import RenderServicer
from nprt.service.grpc_reflection import enable_reflection
from nprt.service.jobapi import JobApi

log = logging.getLogger(__name__)

SERVICE_NAME = nprt_pb2.DESCRIPTOR.services_by_name["RenderService"].full_name
WRITING_RPCS = frozenset(f"/{SERVICE_NAME}/{m}" for m in ("SubmitJob", "CancelJob"))


class TokenInterceptor(grpc.aio.ServerInterceptor):
    """Writing rpcs need metadata `authorization: Bearer <token>`, like REST."""

    def __init__(self, token: str):
        self._token = token

        async def deny(_request, context):
            await context.abort(grpc.StatusCode.UNAUTHENTICATED, "missing or wrong bearer token")

        self._deny = grpc.unary_unary_rpc_method_handler(deny)

    async def intercept_service(self, continuation, details):
        if details.method in WRITING_RPCS:
            got = dict(details.invocation_metadata or ()).get("authorization")
            if bearer_error(got, self._token) is not None:
                return self._deny
        return await continuation(details)


async def start_grpc_server(api: JobApi, settings: ServiceSettings, host: str,
                            port: int) -> tuple[grpc.aio.Server, int]:
    """Start serving on the running loop; returns the server and the bound port (port 0
    picks a free one). Stop it with `await server.stop(grace_s)`."""
    limit = settings.grpc_max_message_bytes
    interceptors = [TokenInterceptor(settings.api_token)] if settings.api_token else []
    server = grpc.aio.server(interceptors=interceptors,
                             options=[("grpc.max_send_message_length", limit),
                                      ("grpc.max_receive_message_length", limit)])
    nprt_pb2_grpc.add_RenderServiceServicer_to_server(RenderServicer(api, limit), server)
    health_servicer = health.aio.HealthServicer()
    health_pb2_grpc.add_HealthServicer_to_server(health_servicer, server)
    enable_reflection(server)
    bound = server.add_insecure_port(f"{host}:{port}")
    if bound == 0:
        raise OSError(f"gRPC could not bind {host}:{port}")
    await server.start()
    for name in ("", SERVICE_NAME):
        await health_servicer.set(name, health_pb2.HealthCheckResponse.SERVING)
    log.info("gRPC %s listening on %s:%d", SERVICE_NAME, host, bound)
    return server, bound


class GrpcThread:
    """start_grpc_server on a daemon thread running its own asyncio loop until stop().

    The server is stopped by the coroutine that started it, on its loop, and the thread
    ends once that stop has finished: stopping it from outside while the thread tore its
    loop down canceled the stop half-way (stop() then raised CancelledError, and the
    lifespan that called it failed)."""

    def __init__(self, api: JobApi, settings: ServiceSettings, host: str, port: int):
        self._args = (api, settings, host, port)
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._release: asyncio.Future | None = None  # its result: the grace in seconds
        self.port: int | None = None
        self._thread = threading.Thread(target=self._run, name="nprt-grpc", daemon=True)

    def start(self) -> int:
        """Serve; returns the bound port once it is bound (or raises why not)."""
        self._thread.start()
        self._ready.wait()
        if self._error is not None:
            raise self._error
        return self.port

    def _run(self) -> None:
        loop = self._loop = asyncio.new_event_loop()
        try:
            loop.run_until_complete(self._serve())
        except BaseException as e:  # handed to start(), or logged once serving
            if self._ready.is_set():
                log.exception("the gRPC server failed")
            self._error = e
        finally:
            self._ready.set()
            left = asyncio.all_tasks(loop)  # handlers the server's stop left behind
            for task in left:
                task.cancel()
            if left:
                loop.run_until_complete(asyncio.gather(*left, return_exceptions=True))
            loop.run_until_complete(loop.shutdown_default_executor())
            loop.close()

    async def _serve(self) -> None:
        self._release = asyncio.get_running_loop().create_future()
        server, self.port = await start_grpc_server(*self._args)
        self._ready.set()
        try:
            grace_s = await self._release
        finally:
            await server.stop(grace_s if self._release.done() else None)

    def stop(self, grace_s: float = 1.0) -> None:
        """Stop serving (streams are canceled after grace_s), then join the thread."""
        if not self._thread.is_alive():
            return
        try:
            self._loop.call_soon_threadsafe(_resolve, self._release, grace_s)
        except RuntimeError:  # the loop closed meanwhile: the thread is ending
            pass
        self._thread.join()


def _resolve(future: asyncio.Future, value) -> None:
    if not future.done():
        future.set_result(value)
