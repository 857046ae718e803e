"""`nprt serve`'s HTTP API worker processes, each with a listening socket of its own on the
one port (SO_REUSEPORT), so the kernel spreads new connections over them evenly. With one
socket shared by every worker (uvicorn --workers), the worker whose loop looked first
accepted what had arrived: in bursts of 500 submissions one of two workers spent 58-69 % of
the API's CPU, 80-90 % when its loop came back to its socket sooner (bench/README.md,
"Service under load")."""

from __future__ import annotations

import logging
import multiprocessing as mp
import os
import socket
import time
from multiprocessing.connection import wait

from uvicorn.config import STARTUP_FAILURE

from nprt.service.ports import reuseport_socket

log = logging.getLogger(__name__)

_CTX = mp.get_context("spawn")  # a fresh interpreter: the parent may hold threads
APP = "nprt.service.app:app_from_env"
RESTART_PAUSE_S = 1.0


def _worker(host: str, port: int, options: dict, parent: int) -> None:
    """One worker process: its own listening socket, then uvicorn on it (logging set up as
    uvicorn sets up its own workers'). It dies with a killed parent."""
    import os

    import uvicorn

    from nprt.service.processes import _die_with_parent

    _die_with_parent()
    if os.getppid() != parent:  # the parent died before that took hold
        return
    sock = reuseport_socket(host, port)
    sock.listen(options.get("backlog", 2048))
    config = uvicorn.Config(APP, factory=True, **options)
    try:
        uvicorn.Server(config).run(sockets=[sock])
    except KeyboardInterrupt:
        pass


class HttpWorkers:
    """n worker processes serving APP on host:port until this process is told to stop
    (SIGTERM/SIGINT end run() through the caller's handlers); a worker that dies is
    started again. The port is held here, bound but not listening (nprt.service.ports), so
    nothing else takes it between restarts."""

    def __init__(self, n: int, host: str, held: socket.socket, options: dict):
        """held: the port, bound and not listening (nprt.service.ports.hold_port)."""
        if n < 1:
            raise ValueError(f"HTTP workers must be >= 1, got {n}")
        self.n, self.host, self.options = n, host, options
        self._held = held
        self.port = held.getsockname()[1]  # port 0: the one the kernel picked
        self._procs: list = []

    def run(self) -> None:
        try:
            self._procs = [self._start() for _ in range(self.n)]
            while True:
                dead = wait([p.sentinel for p in self._procs])
                for i, proc in enumerate(self._procs):
                    if proc.sentinel not in dead:
                        continue
                    proc.join()
                    if proc.exitcode == STARTUP_FAILURE:  # would fail again: give up
                        raise SystemExit(f"HTTP worker {proc.pid} could not start")
                    log.error("HTTP worker %d exited with %s; starting another in %.0f s",
                              proc.pid, proc.exitcode, RESTART_PAUSE_S)
                    time.sleep(RESTART_PAUSE_S)
                    self._procs[i] = self._start()
        finally:
            self.stop()

    def stop(self) -> None:
        """SIGTERM to every worker (uvicorn shuts down gracefully), then wait for them."""
        for proc in self._procs:
            if proc.is_alive():
                proc.terminate()
        grace = self.options.get("timeout_graceful_shutdown") or 3
        for proc in self._procs:
            proc.join(grace + 5)
            if proc.is_alive():
                proc.kill()
                proc.join()
        self._procs = []
        self._held.close()

    def _start(self):
        proc = _CTX.Process(target=_worker, name="nprt-http-worker",
                            args=(self.host, self.port, self.options, os.getpid()))
        proc.start()
        return proc
