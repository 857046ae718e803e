"""What the service benchmarks share: `nprt serve` of a checkout in its own process group,
the CPU of its API processes (not the scheduler's), py-spy profiles of them, a cheap REST
client over bench.service.rawhttp, and latency percentiles."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import random
import socket
import subprocess
import sys
import tempfile
import time
from collections import defaultdict
from pathlib import Path
from urllib.parse import urlencode

import numpy as np
from grpc_health.v1 import health_pb2

from bench.service.rawhttp import Connection, request_bytes

REPO = Path(__file__).resolve().parents[2]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _pythonpath(root: Path) -> str:
    """A checkout's folders importable as nprt.* ahead of the editable install of this one."""
    if root.resolve() == REPO:
        return str(REPO)
    shim = Path(tempfile.mkdtemp(prefix="nprt-shim-")) / "nprt"
    shim.mkdir()
    for name in ("scene", "workers", "proxies", "protos", "service"):
        (shim / name).symlink_to(root / name)
    return f"{shim.parent}{os.pathsep}{root}"


def start_service(root: Path, data_dir: Path, max_jobs: int, api_workers: int | None = None,
                  env: dict[str, str] | None = None, api_only: bool = False
                  ) -> tuple[subprocess.Popen, str, int, str]:
    """`nprt serve` of the checkout at root in a process group of its own, with
    `env` (NPRT_* settings) added to this environment; api_only: no scheduler, no gRPC.
    Returns (process, host, REST port, gRPC target)."""
    port, grpc_port = _free_port(), _free_port()
    env = {**os.environ, "PYTHONPATH": _pythonpath(root),
           "NPRT_MAX_CONCURRENT_JOBS": str(max_jobs), **(env or {})}
    env.pop("NPRT_API_TOKEN", None)
    cmd = [sys.executable, "-m", "service", "serve", "--data-dir", str(data_dir), "--port",
           str(port), "--grpc-port", "-1" if api_only else str(grpc_port), "--log-level",
           "warning", *(["--api-only"] if api_only else [])]
    if api_workers is not None:
        cmd += ["--workers", str(api_workers)]
    # A process group of its own (stopped as one), in this client's session: with
    # autogroups the kernel shares the CPU between sessions first, and a service in a
    # session of its own would compete with its client as a remote client does not, its
    # renders included.
    proc = subprocess.Popen(cmd, cwd=root, env=env, process_group=0)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=1) as s:
                s.sendall(b"GET /healthz HTTP/1.1\r\nHost: bench\r\n\r\n")
                if s.recv(64).startswith(b"HTTP/1.1 200"):
                    return proc, "127.0.0.1", port, f"127.0.0.1:{grpc_port}"
        except OSError:
            time.sleep(0.1)
    proc.kill()
    raise RuntimeError("service did not start within 60 s")


@contextlib.contextmanager
def running_service(root: Path, max_jobs: int, api_workers: int | None = None,
                    env: dict[str, str] | None = None):
    """start_service on a fresh data folder; yields (process, host, REST port, gRPC target)
    and stops the service's whole process group on the way out."""
    with tempfile.TemporaryDirectory(prefix="nprt-bench-") as tmp:
        proc, host, port, target = start_service(root, Path(tmp) / "data", max_jobs,
                                                 api_workers, env)
        try:
            yield proc, host, port, target
        finally:
            os.killpg(proc.pid, 15)
            proc.wait(60)


# ---------------------------------------------------------------- API process accounting

def _children(pid: int) -> list[int]:
    try:
        tasks = Path(f"/proc/{pid}/task").iterdir()
        return [int(c) for t in tasks for c in (t / "children").read_text().split()]
    except OSError:
        return []


def _cpu_s(pid: int) -> float:
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _is_scheduler(pid: int) -> bool:
    try:
        return b"scheduler" in Path(f"/proc/{pid}/cmdline").read_bytes()
    except OSError:
        return False


def api_pids(pid: int) -> list[int]:
    """The serving processes: `pid` and its descendants, except a scheduler process and
    everything under it (renders, Ray). Linux only."""
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        if not _is_scheduler(p):
            out.append(p)
            todo += _children(p)
    return out


def http_workers(pid: int) -> int:
    """How many HTTP API workers serve under pid: uvicorn's worker processes (spawned by
    multiprocessing), or pid itself when it has none."""
    def spawned(p: int) -> bool:
        try:
            return b"spawn_main" in Path(f"/proc/{p}/cmdline").read_bytes()
        except OSError:
            return False
    return sum(spawned(p) for p in api_pids(pid)) or 1


def api_cpu_s(pid: int) -> float:
    """CPU seconds of the serving processes so far."""
    return sum(_cpu_s(p) for p in api_pids(pid))


def api_cpu_ns(pid: int) -> int:
    """On-CPU nanoseconds so far of every thread of the serving processes (schedstat: not
    in clock ticks; a thread that has ended no longer counts). Linux only."""
    total = 0
    for p in api_pids(pid):
        try:
            tasks = list(Path(f"/proc/{p}/task").iterdir())
        except OSError:
            continue
        for task in tasks:
            try:
                total += int((task / "schedstat").read_text().split()[0])
            except OSError:
                pass
    return total


def render_cpu_s(pid: int) -> float:
    """CPU seconds so far of the scheduler process under pid and everything it started
    (renders, Ray)."""
    todo, inside = [(pid, False)], []
    while todo:
        p, under = todo.pop()
        under = under or _is_scheduler(p)
        if under:
            inside.append(p)
        todo += [(c, under) for c in _children(p)]
    return sum(_cpu_s(p) for p in inside)


def _tree_stat(pid: int, field: int, show) -> dict[str, list]:
    """show(field `field` of /proc/<p>/stat after the command name) for every process of
    pid's tree, by command name; sorted distinct values."""
    out: dict[str, set] = defaultdict(set)
    todo = [pid]
    while todo:
        p = todo.pop()
        try:
            fields = Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)
            name = fields[0].split("(", 1)[1]
            out[name].add(show(int(fields[1].split()[field])))
        except (OSError, IndexError):
            continue
        todo += _children(p)
    return {k: sorted(v) for k, v in sorted(out.items())}


def niceness(pid: int) -> dict[str, list[int]]:
    """Nice values of pid's process tree by command name, e.g. {"raylet": [10]}."""
    return _tree_stat(pid, 16, int)


POLICY_NAMES = {0: "normal", 1: "fifo", 2: "rr", 3: "batch", 5: "idle", 6: "deadline"}


def cpu_policies(pid: int) -> dict[str, list[str]]:
    """Scheduling policies of pid's process tree by command name, e.g. {"raylet": ["idle"]}
    (each process's main thread)."""
    return _tree_stat(pid, 38, lambda v: POLICY_NAMES.get(v, str(v)))


def start_profilers(pid: int, out_dir: Path) -> list[subprocess.Popen]:
    """py-spy sampling every serving process and this client until stopped (SIGINT writes
    the profile): collapsed stacks, one file per process, for `flamegraph.pl` or
    speedscope."""
    out_dir.mkdir(parents=True, exist_ok=True)
    spy = Path(sys.executable).with_name("py-spy")
    named = [(f"api-{p}", p) for p in api_pids(pid)] + [("client", os.getpid())]
    return [subprocess.Popen([str(spy), "record", "-p", str(p), "-r", "250", "-f", "raw",
                              "--nonblocking", "-o", str(out_dir / f"{name}.txt")],
                             stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
            for name, p in named]


def stop_profilers(procs: list[subprocess.Popen]) -> None:
    for proc in procs:
        proc.send_signal(2)
    for proc in procs:
        proc.wait(30)


# ---------------------------------------------------------------- REST client

class Rest:
    """JSON calls over keep-alive rawhttp connections: each concurrent caller uses a
    Connection of its own (`connection()`)."""

    def __init__(self, host: str, port: int):
        self.host, self.port = host, port
        self.retries: dict[str, int] = {}

    def connection(self) -> Connection:
        return Connection(self.host, self.port)

    async def call(self, conn: Connection, method: str, path: str, body: dict | None = None,
                   headers: dict | None = None, params: dict | None = None
                   ) -> tuple[int, dict, float | None]:
        """(status, JSON body, Retry-After s). A kept-alive connection the server closed
        as idle is retried on a fresh one, twice at most (POSTs carry an Idempotency-Key:
        no duplicate job)."""
        if params:
            path = f"{path}?{urlencode(params)}"
        data = request_bytes(method, path, self.host,
                             b"" if body is None else json.dumps(body).encode(), headers)
        for attempt in range(3):
            try:
                answer = await conn.request(data)
                break
            except ConnectionError:
                if attempt == 2:
                    raise
                self.retries[method] = self.retries.get(method, 0) + 1
        after = answer.headers.get("retry-after")
        return answer.status, answer.json(), None if after is None else float(after)


def run_client(coro):
    """Run a load generator's coroutine on uvloop (libuv's loop in C, as the service's
    HTTP workers run): with asyncio's own loop the submitting client spent 0.10 s of CPU on
    a burst of 500 connections, with uvloop about 0.055 s, CPU the service would otherwise
    lose on cores it shares with its client. The service's own costs are not touched."""
    import uvloop

    return uvloop.run(coro)


def percentiles(samples_s: list[float]) -> dict:
    ms = np.asarray(samples_s) * 1e3
    return {"n": int(len(ms)), "p50": round(float(np.percentile(ms, 50)), 2),
            "p99": round(float(np.percentile(ms, 99)), 2), "max": round(float(ms.max()), 2)}


class Latency:
    def __init__(self):
        self.samples_s: dict[str, list[float]] = defaultdict(list)

    async def timed(self, kind: str, coro):
        t0 = time.perf_counter()
        out = await coro
        self.samples_s[kind].append(time.perf_counter() - t0)
        return out

    def summary(self) -> dict:
        return {k: percentiles(v) for k, v in sorted(self.samples_s.items())}


async def poll(rest: Rest, lat: Latency, ids: list[str], stop: asyncio.Event,
               pause_s: float) -> None:
    """A dashboard until stop: reads a random job of `ids` (4 in 5) or the first page of
    the job list, pause_s apart, on one keep-alive connection."""
    conn = rest.connection()
    while not stop.is_set():
        if random.random() < 0.8:
            await lat.timed("GET /v1/jobs/{id}", rest.call(
                conn, "GET", f"/v1/jobs/{random.choice(ids)}"))
        else:
            await lat.timed("GET /v1/jobs", rest.call(conn, "GET", "/v1/jobs",
                                                      params={"limit": 20}))
        await asyncio.sleep(pause_s)
    conn.close()


async def check_health(rest: Rest, health, lat: Latency, stop: asyncio.Event,
                       interval_s: float) -> None:
    """gRPC Health.Check (health: a HealthStub), then GET /healthz, interval_s apart until
    stop; each must say serving."""
    conn = rest.connection()
    while not stop.is_set():
        reply = await lat.timed("gRPC Health.Check", health.Check(
            health_pb2.HealthCheckRequest(service=""), timeout=30))
        assert reply.status == health_pb2.HealthCheckResponse.SERVING
        status, _, _ = await lat.timed("GET /healthz", rest.call(conn, "GET", "/healthz"))
        assert status == 200
        await asyncio.sleep(interval_s)
    conn.close()
