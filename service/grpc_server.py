"""The gRPC server (grpc.aio, on the service's event loop): RenderService, the standard
health service, bearer-token checks on the writing rpcs, and message size limits that fit
tiles and images. A WatchJob stream is a coroutine, not a thread, so open streams cannot
starve Health.Check or GetJob; NPRT_MAX_WATCHERS bounds them (RESOURCE_EXHAUSTED beyond)."""

from __future__ import annotations

import logging

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
