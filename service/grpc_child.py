"""gRPC in a process of its own (`nprt serve` starts it beside the HTTP workers), on uvloop:
its tile fan-out to WatchJob streams and its health checks no longer take turns for one
interpreter lock with a burst of HTTP requests, and neither waits for the other. Like any
API worker it stores and reads jobs in the store and follows its events; it renders
nothing."""

from __future__ import annotations

import asyncio
import gc
import logging
import signal
import socket
import time

import uvloop

from nprt.service.config import ServiceSettings
from nprt.service.ports import connect_target

log = logging.getLogger(__name__)

READY_TIMEOUT_S = 60.0  # a cold start imports grpc, pydantic, numpy: seconds on a busy host


def run_grpc(settings: ServiceSettings, host: str, port: int) -> int:
    """Serve gRPC on host:port until SIGTERM or SIGINT, then stop (streams get 1 s)."""
    from nprt.service.grpc_server import start_grpc_server
    from nprt.service.jobapi import JobApi
    from nprt.service.scenes import SceneStore

    api = JobApi(settings, SceneStore(settings)).start()

    async def serve() -> None:
        server, bound = await start_grpc_server(api, settings, host, port)
        done = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, done.set)
        gc.collect()  # what lives now lives as long as the process (nprt.service.app)
        gc.freeze()
        await done.wait()
        await server.stop(1.0)

    try:
        # uvloop (a dependency, as under the HTTP workers): the process's CPU per
        # Health.Check 213-223 us against 240 on asyncio's loop, per GetJob 306-326 against
        # 359-375 (2,000 calls each, 8 at a time, loaded host; issue 24, session 8).
        uvloop.run(serve())
    finally:
        api.stop()
    return 0


def wait_listening(proc, host: str, port: int, timeout_s: float = READY_TIMEOUT_S) -> None:
    """Return once host:port accepts connections; RuntimeError if `proc` exits first or
    timeout_s passes (HTTP should not answer before gRPC can)."""
    deadline = time.monotonic() + timeout_s
    target = connect_target(host)
    while True:
        if proc.poll() is not None:
            raise RuntimeError(f"the gRPC process exited with {proc.returncode} on start")
        try:
            with socket.create_connection((target, port), timeout=1.0):
                return
        except OSError:
            if time.monotonic() > deadline:
                raise RuntimeError(f"gRPC did not listen on {host}:{port} within "
                                   f"{timeout_s:.0f} s") from None
            time.sleep(0.05)
