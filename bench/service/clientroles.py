"""The load generator's other clients, each in a process of its own: the dashboards and the
health prober (`readers`), and the SSE and gRPC watchers (`watchers`). In one process with
the burst, a health check's answer waited for the load generator's own event loop to get
through hundreds of POST answers and the watchers' tiles, and was counted as the service's
latency; a prober, a dashboard and a submission script are separate clients in deployment.
"""

from __future__ import annotations

import asyncio
import multiprocessing as mp
import queue
from collections import defaultdict

import grpc
from grpc_health.v1 import health_pb2_grpc

from bench.service.harness import Latency, Rest, check_health, poll, run_client

_CTX = mp.get_context("spawn")  # the parent runs grpc: forking it is unsafe


async def _until(flag, seconds: float = 0.02) -> None:
    while not flag.is_set():
        await asyncio.sleep(seconds)


def _readers(host: str, port: int, target: str, ids: list[str], pollers: int,
             poll_pause_s: float, health_interval_s: float, started, stop, out) -> None:
    async def main() -> None:
        rest, lat, done = Rest(host, port), Latency(), asyncio.Event()
        async with grpc.aio.insecure_channel(target) as channel:
            health = health_pb2_grpc.HealthStub(channel)
            tasks = [asyncio.create_task(poll(rest, lat, ids, done, poll_pause_s))
                     for _ in range(pollers)]
            tasks.append(asyncio.create_task(check_health(rest, health, lat, done,
                                                          health_interval_s)))
            started.set()
            await _until(stop)
            done.set()
            await asyncio.gather(*tasks)
        out.put(dict(lat.samples_s))

    run_client(main())


class Readers:
    """`pollers` dashboards reading jobs of `ids` and a health prober (REST and gRPC), in a
    process of their own from start() until stop(), which returns their latency samples
    ({request kind: [seconds]})."""

    def __init__(self, host: str, port: int, target: str, ids: list[str], pollers: int,
                 poll_pause_s: float, health_interval_s: float):
        self._started, self._stop, self._out = _CTX.Event(), _CTX.Event(), _CTX.Queue()
        self._proc = _CTX.Process(target=_readers, name="bench-readers", daemon=True, args=(
            host, port, target, ids, pollers, poll_pause_s, health_interval_s,
            self._started, self._stop, self._out))

    async def start(self) -> None:
        self._proc.start()
        await _until(self._started, 0.05)

    async def stop(self) -> dict[str, list[float]]:
        self._stop.set()
        samples = await asyncio.to_thread(self._out.get, True, 120)
        await asyncio.to_thread(self._proc.join, 30)
        return samples


def _watchers(host: str, port: int, target: str, jobs: list[str], sse: int, streams: int,
              out) -> None:
    from bench.service.bench_service import grpc_watch, sse_watch
    from nprt.protos import nprt_pb2_grpc

    async def main() -> None:
        rest = Rest(host, port)
        sse_counts: dict = defaultdict(int)
        grpc_counts: dict = defaultdict(int)
        async with grpc.aio.insecure_channel(target) as channel:
            stub = nprt_pb2_grpc.RenderServiceStub(channel)
            tasks = [asyncio.create_task(sse_watch(rest, jobs[i % len(jobs)], sse_counts))
                     for i in range(sse)]
            tasks += [asyncio.create_task(grpc_watch(stub, jobs[i % len(jobs)], grpc_counts))
                      for i in range(streams)]
            every = asyncio.gather(*tasks)
            while not every.done():
                out.put((dict(sse_counts), dict(grpc_counts), False))
                await asyncio.wait([every], timeout=0.1)
            every.result()
        out.put((dict(sse_counts), dict(grpc_counts), True))

    run_client(main())


class Watchers:
    """`sse` SSE watchers and `streams` gRPC WatchJob streams on `jobs` (spread evenly), in
    a process of their own until every stream has ended; counts() are their latest event
    counts by name (SSE, gRPC), with "opened" and "closed"."""

    def __init__(self, host: str, port: int, target: str, jobs: list[str], sse: int,
                 streams: int):
        self._out = _CTX.Queue()
        self._latest: tuple[dict, dict] = ({}, {})
        self._ended = False
        self._proc = _CTX.Process(target=_watchers, name="bench-watchers", daemon=True,
                                  args=(host, port, target, jobs, sse, streams, self._out))
        self._proc.start()

    def counts(self) -> tuple[dict, dict]:
        while True:
            try:
                sse, grpc_, self._ended = self._out.get_nowait()
            except queue.Empty:
                return self._latest
            self._latest = (defaultdict(int, sse), defaultdict(int, grpc_))

    async def wait(self) -> tuple[dict, dict]:
        """The final counts, once every stream has ended."""
        while not self._ended:
            if not self._proc.is_alive() and self._out.empty():
                raise RuntimeError(f"the watchers' process exited ({self._proc.exitcode})")
            self.counts()
            await asyncio.sleep(0.1)
        await asyncio.to_thread(self._proc.join, 30)
        return self._latest
