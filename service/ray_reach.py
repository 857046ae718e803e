"""Fail fast on a Ray cluster address where no Ray answers: ray.init retries an unreachable
GCS for minutes, so the CLI first asks the address for its gRPC health, with a deadline.
A TCP connect alone is not enough: proxies and silent listeners accept connections."""

from __future__ import annotations

import os

import grpc

from nprt.service.preflight import CliError

PROBE_TIMEOUT_S = 10.0
LOCAL_ADDRESSES = ("", "auto", "local")  # ray.init finds or starts these itself
_HEALTH_CHECK = "/grpc.health.v1.Health/Check"  # the GCS (and any gRPC server) answers it
_HTTP_NOT_GRPC = "http2 header with status"  # grpc's words for a plain HTTP answer


def ray_endpoint(address: str | None) -> str | None:
    """HOST:PORT that `ray.init(address)` would connect to, or None when it starts or finds
    a local Ray. `address` None means RAY_ADDRESS, as for ray.init."""
    address = address if address is not None else os.environ.get("RAY_ADDRESS", "")
    if address.strip() in LOCAL_ADDRESSES:
        return None
    hostport = address.strip().removeprefix("ray://")  # Ray Client server
    host, colon, port = hostport.rpartition(":")
    if not colon or not host or not port.isdigit() or not 0 < int(port) < 65536:
        raise CliError("invalid option", f"--ray-address {address}",
                       "expected HOST:PORT (the head's GCS) or ray://HOST:PORT")
    return hostport


def check_ray_reachable(address: str | None, timeout_s: float = PROBE_TIMEOUT_S) -> None:
    """CliError naming the address unless a gRPC server (Ray's GCS) answers there within
    `timeout_s`."""
    endpoint = ray_endpoint(address)
    if endpoint is None:
        return
    where = f"--ray-address {address if address is not None else os.environ['RAY_ADDRESS']}"
    with grpc.insecure_channel(endpoint) as channel:
        check = channel.unary_unary(_HEALTH_CHECK, request_serializer=bytes,
                                    response_deserializer=bytes)
        try:
            check(b"", timeout=timeout_s)
            return
        except grpc.RpcError as e:
            code, details = e.code(), e.details() or ""
    if code == grpc.StatusCode.DEADLINE_EXCEEDED:
        why = f"no answer within {timeout_s:g} s"
    elif code == grpc.StatusCode.UNAVAILABLE:
        why = f"nothing answers there ({details.rsplit(': ', 1)[-1].strip(' ])')})"
    elif _HTTP_NOT_GRPC in details:
        why = "an HTTP server answers there, not Ray's GCS"
    else:
        return  # a gRPC server answered; ray.init says what else is wrong
    raise CliError("cannot reach Ray", where, why)
