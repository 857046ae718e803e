"""Shared test helpers: a real uvicorn server on a loopback port with a scheduler beside it,
scene files, SSE parsing."""

from __future__ import annotations

import io
import json
import re
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import trimesh
import uvicorn
from PIL import Image

from nprt.service.app import create_app
from nprt.service.config import ServiceSettings
from nprt.service.scheduler import Scheduler

REPO = Path(__file__).resolve().parents[2]
TINY = {"width": 32, "height": 32, "spp": 4, "bounces": 2, "shadow_rays": 1,
        "tile_size": 16, "spp_per_pass": 2}
START_TIMEOUT_S = 20.0
STOP_TIMEOUT_S = 120.0


class LiveServer:
    """The app under uvicorn in a thread, on a socket bound here (no free-port race), and
    (unless scheduler=False) a Scheduler on the same data directory. They share nothing
    but the store and the job folders, as the API and scheduler processes of `nprt
    serve` do; tests/service/test_processes.py runs them as separate processes."""

    def __init__(self, settings: ServiceSettings, grpc: bool = False, scheduler: bool = True):
        self.settings = settings
        self.app = create_app(settings, grpc_port=0 if grpc else None)
        self.scheduler = Scheduler(settings) if scheduler else None
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.sock.bind(("127.0.0.1", 0))
        self.url = f"http://127.0.0.1:{self.sock.getsockname()[1]}"
        config = uvicorn.Config(self.app, log_level="warning", timeout_graceful_shutdown=1)
        self.server = uvicorn.Server(config)
        self.thread = threading.Thread(target=self.server.run, kwargs={"sockets": [self.sock]},
                                       daemon=True)

    @property
    def grpc_target(self) -> str:
        return f"127.0.0.1:{self.app.state.grpc_port}"

    def __enter__(self) -> LiveServer:
        if self.scheduler is not None:
            self.scheduler.start()
        self.thread.start()
        deadline = time.monotonic() + START_TIMEOUT_S
        while not self.server.started:
            if not self.thread.is_alive() or time.monotonic() > deadline:
                raise RuntimeError(f"uvicorn did not start within {START_TIMEOUT_S} s")
            time.sleep(0.02)
        return self

    def __exit__(self, *exc) -> None:
        self.server.should_exit = True
        self.thread.join(STOP_TIMEOUT_S)
        self.sock.close()
        # Stops a Ray the scheduler started: one still stopping behind the next test
        # would pull Ray from under it.
        if self.scheduler is not None:
            self.scheduler.stop(timeout_s=None)
        if self.thread.is_alive():
            raise RuntimeError(f"the service did not stop within {STOP_TIMEOUT_S} s")


def settings_for(tmp: Path, **overrides) -> ServiceSettings:
    # Explicit values, so NPRT_* variables in the environment do not change the tests.
    base = {"data_dir": tmp / "data", "max_concurrent_jobs": 2, "api_token": None,
            "ray_address": None}
    return ServiceSettings(**(base | overrides))


def two_box_glb(path: Path) -> Path:
    """One box mesh placed by two glTF nodes: one base mesh, two instances."""
    box = trimesh.creation.box((1.0, 1.0, 1.0))
    scene = trimesh.Scene()
    scene.add_geometry(box, geom_name="box", node_name="left",
                       transform=trimesh.transformations.translation_matrix([-0.8, 0, 0]))
    right = trimesh.transformations.translation_matrix([0.8, 0.3, -0.5])
    scene.graph.update(frame_to="right", frame_from=scene.graph.base_frame, matrix=right,
                       geometry="box")
    path.write_bytes(scene.export(file_type="glb"))
    return path


def sse_events(client: httpx.Client, url: str, timeout_s: float = 60.0):
    """(event, parsed data) pairs until the server closes the stream."""
    with client.stream("GET", url, timeout=httpx.Timeout(5.0, read=timeout_s)) as r:
        assert r.status_code == 200, r.read()
        event, data = "message", []
        for line in r.iter_lines():
            if line.startswith("event:"):
                event = line[6:].strip()
            elif line.startswith("data:"):
                data.append(line[5:].strip())
            elif not line and data:
                text = "\n".join(data)
                yield event, (json.loads(text) if text.startswith("{") else text)
                event, data = "message", []


def png_pixels(data: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(data)).convert("RGB"))


def wait_for(predicate, timeout_s: float, interval_s: float = 0.05, what: str = "condition"):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(interval_s)
    raise AssertionError(f"timed out after {timeout_s} s waiting for {what}")


def wait_serving(proc, url: str, log_path: Path, timeout_s: float = 60.0) -> None:
    """Wait until the service process `proc` answers GET url/healthz; fails with its log
    if it exits first."""
    def ready() -> bool:
        assert proc.poll() is None, log_path.read_text()
        try:
            return httpx.get(f"{url}/healthz", timeout=1).status_code == 200
        except httpx.TransportError:
            return False

    wait_for(ready, timeout_s, what=f"{url}/healthz")


def logged(proc, log_path: Path, start: int, pattern: bytes, timeout_s: float) -> str:
    """The first group of `pattern` in what `proc` wrote to log_path after byte `start`;
    fails with the log if it exits first."""
    def found() -> str | None:
        assert proc.poll() is None, log_path.read_text()
        with log_path.open("rb") as f:
            f.seek(start)
            m = re.search(pattern, f.read())
        return m and m[1].decode()

    return wait_for(found, timeout_s, what=f"{pattern!r} in {log_path}")


def start_serve(args: list[str], log_path: Path, env: dict[str, str],
                timeout_s: float = 60.0) -> tuple[subprocess.Popen, str]:
    """`nprt serve --port 0 *args` of this checkout, its output appended to log_path;
    returns (process, REST URL) once it answers. Port 0: the service binds one the kernel
    picks and logs it, where a port picked here and bound there later could be handed to
    another test's service meanwhile (and SO_REUSEPORT would let both serve it)."""
    start = log_path.stat().st_size if log_path.exists() else 0
    with log_path.open("ab") as log:
        proc = subprocess.Popen([sys.executable, "-m", "service", "serve", "--port", "0",
                                 *args], cwd=REPO, env=env, stdout=log,
                                stderr=subprocess.STDOUT)
    url = logged(proc, log_path, start, rb"REST on (http://\S+:\d+)", timeout_s)
    wait_serving(proc, url, log_path, timeout_s)
    return proc, url


BLOCKER = {**TINY, "width": 64, "height": 64, "spp": 1024, "spp_per_pass": 1}


class HeldSlots:
    """Fill every job slot with a long render so the next job stays queued until release():
    a watcher can then subscribe before that job's first pass."""

    def __init__(self, base_url: str, slots: int, token: str | None = None):
        headers = {"Authorization": f"Bearer {token}"} if token else {}
        self.client = httpx.Client(base_url=base_url, timeout=30.0, headers=headers)
        self.ids = [self.client.post("/v1/jobs", json={"scene": "forest:tiny", **BLOCKER}
                                     ).json()["id"] for _ in range(slots)]

    def release(self) -> None:
        for job_id in self.ids:
            self.client.post(f"/v1/jobs/{job_id}/cancel")
        for job_id in self.ids:
            wait_for(lambda j=job_id: self.client.get(f"/v1/jobs/{j}").json()["state"]
                     == "canceled", 30, what=f"blocker {job_id} canceled")
        self.client.close()


def stored_queued_job(server: LiveServer, settings: dict | None = None) -> str:
    """A job stored as queued on a server without a scheduler: it stays queued, and
    watchers stay open on it, until the test cancels it. Costs no rendering."""
    import uuid

    assert server.scheduler is None, "a scheduler would render the job"
    job_id = uuid.uuid4().hex
    server.app.state.api.store.insert(job_id, "forest:tiny", {**TINY, **(settings or {})},
                                      passes_total=8)
    return job_id


def problem_detail(r: httpx.Response) -> str:
    """The `detail` of an error answer, after checking it is RFC 9457 problem details."""
    assert r.headers["content-type"] == "application/problem+json", r.headers
    body = r.json()
    assert body["status"] == r.status_code and body["title"] and body["type"], body
    return body["detail"]
