"""gRPC server reflection (grpcurl, Postman, evans) for RenderService and health."""

from __future__ import annotations

import grpc
from grpc_health.v1 import health_pb2
from grpc_reflection.v1alpha import reflection

from nprt.protos import nprt_pb2


def enable_reflection(server: grpc.Server) -> tuple[str, ...]:
    """Register the reflection service; returns the service names it lists."""
    names = (nprt_pb2.DESCRIPTOR.services_by_name["RenderService"].full_name,
             health_pb2.DESCRIPTOR.services_by_name["Health"].full_name,
             reflection.SERVICE_NAME)
    reflection.enable_server_reflection(names, server)
    return names
