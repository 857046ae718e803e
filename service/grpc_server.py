"""The gRPC server: RenderService, the standard health service, bearer-token checks on the
writing rpcs, and message size limits that fit tiles and images."""

from __future__ import annotations

import hmac
import logging
from concurrent import futures

import grpc
from grpc_health.v1 import health, health_pb2, health_pb2_grpc

from protos import nprt_pb2, nprt_pb2_grpc
from service.config import ServiceSettings
from service.grpc_api import RenderServicer
from service.grpc_reflection import enable_reflection
from service.manager import JobManager

log = logging.getLogger(__name__)

SERVICE_NAME = nprt_pb2.DESCRIPTOR.services_by_name["RenderService"].full_name
WRITING_RPCS = frozenset(f"/{SERVICE_NAME}/{m}" for m in ("SubmitJob", "CancelJob"))
# Each WatchJob stream holds a thread for its lifetime.
MAX_WORKERS = 32


class TokenInterceptor(grpc.ServerInterceptor):
    """Writing rpcs need metadata `authorization: Bearer <token>`, like REST."""

    def __init__(self, token: str):
        self._expected = f"Bearer {token}".encode()

        def deny(_request, context):
            context.abort(grpc.StatusCode.UNAUTHENTICATED, "missing or wrong bearer token")

        self._deny = grpc.unary_unary_rpc_method_handler(deny)

    def intercept_service(self, continuation, details):
        if details.method in WRITING_RPCS:
            got = dict(details.invocation_metadata).get("authorization", "")
            got = got.encode() if isinstance(got, str) else got
            if not hmac.compare_digest(got, self._expected):
                return self._deny
        return continuation(details)


def start_grpc_server(manager: JobManager, settings: ServiceSettings, host: str,
                      port: int) -> tuple[grpc.Server, int]:
    """Start serving; returns the server and the bound port (port 0 picks a free one)."""
    limit = settings.grpc_max_message_bytes
    interceptors = [TokenInterceptor(settings.api_token)] if settings.api_token else []
    server = grpc.server(futures.ThreadPoolExecutor(max_workers=MAX_WORKERS,
                                                    thread_name_prefix="nprt-grpc"),
                         interceptors=interceptors,
                         options=[("grpc.max_send_message_length", limit),
                                  ("grpc.max_receive_message_length", limit)])
    nprt_pb2_grpc.add_RenderServiceServicer_to_server(RenderServicer(manager, limit), server)
    health_servicer = health.HealthServicer()
    health_pb2_grpc.add_HealthServicer_to_server(health_servicer, server)
    enable_reflection(server)
    bound = server.add_insecure_port(f"{host}:{port}")
    if bound == 0:
        raise OSError(f"gRPC could not bind {host}:{port}")
    server.start()
    for name in ("", SERVICE_NAME):
        health_servicer.set(name, health_pb2.HealthCheckResponse.SERVING)
    log.info("gRPC %s listening on %s:%d", SERVICE_NAME, host, bound)
    return server, bound
