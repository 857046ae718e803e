"""Stopping the service ends what it started: its threads (the next test in the same process
checks for them), and a Ray it started with every process of it, agents included."""

from __future__ import annotations

import logging
import os
import threading
from pathlib import Path

import grpc
import httpx
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc

from nprt.service.jobapi import JobApi
from nprt.service.scenes import SceneStore
from nprt.service.scheduler import Scheduler
from nprt.service.store import TERMINAL
from nprt.workers.settings import RenderSettings
from tests.service.helpers import TINY, LiveServer, settings_for, wait_for


def _service_threads() -> list[str]:
    return sorted(t.name for t in threading.enumerate() if t.name.startswith("nprt-"))


class _Errors(logging.Handler):
    def __init__(self):
        super().__init__(logging.ERROR)
        self.messages: list[str] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.messages.append(record.getMessage())


def test_stopped_service_leaves_no_thread_and_its_shutdown_succeeds(tmp_path):
    """Five starts and stops in a row: the gRPC thread's stop raced its own loop's end
    about half the time, failing the lifespan before the store writer and event feed
    were stopped."""
    before = _service_threads()
    errors = _Errors()  # uvicorn's records do not reach the root logger (caplog)
    logging.getLogger("uvicorn.error").addHandler(errors)
    try:
        for i in range(5):
            with LiveServer(settings_for(tmp_path / str(i)), grpc=True) as server:
                assert httpx.get(f"{server.url}/healthz").json() == {"status": "ok"}
                with grpc.insecure_channel(server.grpc_target) as channel:
                    answer = health_pb2_grpc.HealthStub(channel).Check(
                        health_pb2.HealthCheckRequest())
                assert answer.status == health_pb2.HealthCheckResponse.SERVING
                running = _service_threads()
                assert {"nprt-grpc", "nprt-store-writer", "nprt-event-feed",
                        "nprt-scheduler-poll"} <= set(running), running
            assert _service_threads() == before, f"after stop {i + 1}"
    finally:
        logging.getLogger("uvicorn.error").removeHandler(errors)
    assert errors.messages == []  # e.g. "Application shutdown failed. Exiting."


def _children() -> dict[int, str]:
    """Every live process below this one: pid -> its command name."""
    parent, names = {}, {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:  # ended while we looked
            continue
        name, rest = stat[stat.index("(") + 1:stat.rindex(")")], stat[stat.rindex(")") + 2:]
        state, ppid = rest.split()[:2]
        try:  # named by its command line: agents rename themselves
            cmd = (entry / "cmdline").read_bytes().split(b"\0")[0].decode(errors="replace")
        except OSError:
            continue
        if state != "Z":
            parent[int(entry.name)] = int(ppid)
            names[int(entry.name)] = os.path.basename(cmd.split()[0]) if cmd.strip() else name
    below, todo = {}, [os.getpid()]
    while todo:
        pid = todo.pop()
        for child, ppid in parent.items():
            if ppid == pid and child not in below:
                below[child] = names[child]
                todo.append(child)
    return below


def _alive(pids) -> list[int]:
    out = []
    for pid in pids:
        try:
            if Path(f"/proc/{pid}/stat").read_text().split(") ")[1][0] != "Z":
                out.append(pid)
        except OSError:
            pass
    return out


@pytest.mark.slow
def test_stopped_scheduler_ends_the_ray_it_started_agents_included(tmp_path):
    ray = pytest.importorskip("ray")
    if ray.is_initialized():  # a Ray of earlier tests would be joined, not started
        ray.shutdown()
    settings = settings_for(tmp_path, max_concurrent_jobs=1)
    before = set(_children())
    api = JobApi(settings, SceneStore(settings)).start()
    scheduler = Scheduler(settings).start()
    try:
        rec, _ = api.submit("forest:tiny", RenderSettings(**TINY, shards=2))
        done = wait_for(lambda: (r := api.get(rec.id)).state in TERMINAL and r, 300,
                        interval_s=0.1, what="the sharded job")
        assert done.state == "succeeded", done.error
        started = {pid: name for pid, name in _children().items() if pid not in before}
        assert "raylet" in started.values() and "gcs_server" in started.values(), started
        # The raylet's agents: a raylet killed rather than stopped left these behind.
        assert {"ray::DashboardAgent", "ray::RuntimeEnvAgent"} & set(started.values()), started
        assert "nprt-ray" in _service_threads()
    finally:
        scheduler.stop(timeout_s=None)
        api.stop()
    assert not ray.is_initialized()
    left = _alive(started)
    assert not left, {pid: started[pid] for pid in left}
    assert "nprt-ray" not in _service_threads()
