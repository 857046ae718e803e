"""Service load benchmark: N concurrent job submissions while SSE watchers and gRPC
WatchJob streams are open on running jobs and clients poll; checks every job is accepted
once and completed, and reports latency percentiles of the REST calls and of gRPC health
during the burst. The client is aiohttp (httpx spent 4x the service's CPU per request,
and client and service share the machine).

    python bench/service/bench_service.py [--jobs 500] [--sse-watchers 100] [--grpc-streams 40]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import platform
import random
import socket
import subprocess
import sys
import tempfile
import time
import uuid
from collections import defaultdict
from pathlib import Path

import aiohttp
import grpc
import httpx
import numpy as np

REPO = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(REPO))  # run as a script: make protos and bench importable

from grpc_health.v1 import health_pb2, health_pb2_grpc  # noqa: E402

from nprt.protos import nprt_pb2 as pb  # noqa: E402
from nprt.protos import nprt_pb2_grpc  # noqa: E402

RESULTS = REPO / "bench" / "results"
TERMINAL = {"succeeded", "failed", "canceled"}
HEALTH_INTERVAL_S = 0.02


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_service(data_dir: Path, max_jobs: int) -> tuple[subprocess.Popen, str, str]:
    """The service in its own process, as deployed: the client's CPU time stays apart.
    Returns (process, REST url, gRPC target)."""
    port, grpc_port = _free_port(), _free_port()
    env = {**os.environ, "PYTHONPATH": str(REPO), "NPRT_MAX_CONCURRENT_JOBS": str(max_jobs)}
    env.pop("NPRT_API_TOKEN", None)
    proc = subprocess.Popen([sys.executable, "-m", "service", "serve", "--data-dir",
                             str(data_dir), "--port", str(port), "--grpc-port", str(grpc_port),
                             "--log-level", "warning"], cwd=REPO, env=env)
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            if httpx.get(f"{url}/healthz", timeout=1).status_code == 200:
                return proc, url, f"127.0.0.1:{grpc_port}"
        except httpx.TransportError:
            time.sleep(0.1)
    proc.kill()
    raise RuntimeError("service did not start within 60 s")


class Latency:
    def __init__(self):
        self.samples_s: dict[str, list[float]] = defaultdict(list)

    async def timed(self, kind: str, coro):
        t0 = time.perf_counter()
        out = await coro
        self.samples_s[kind].append(time.perf_counter() - t0)
        return out


async def sse_watch(session: aiohttp.ClientSession, job_id: str, counts: dict) -> None:
    """Follow one job's SSE stream to its `end` event, counting events."""
    async with session.get(f"/v1/jobs/{job_id}/events",
                           timeout=aiohttp.ClientTimeout(total=None, sock_read=600)) as r:
        counts["opened"] += r.status == 200
        async for line in r.content:
            if line.startswith(b"event:"):
                counts[line[6:].strip().decode()] += 1
    counts["closed"] += 1


async def grpc_watch(stub, job_id: str, counts: dict) -> None:
    counts["opened"] += 1
    async for ev in stub.WatchJob(pb.WatchJobRequest(job_id=job_id,
                                                     tile_format=pb.TILE_FORMAT_RGB_F32)):
        counts[ev.WhichOneof("event")] += 1
    counts["closed"] += 1


async def request(session: aiohttp.ClientSession, method: str, path: str,
                  retries: dict | None = None, **kw) -> tuple[int, dict]:
    """(status, JSON body). A pooled connection the server closed as idle is retried once
    on a fresh one (POSTs carry an Idempotency-Key, so a retry cannot duplicate a job)."""
    for attempt in range(2):
        try:
            async with session.request(method, path, **kw) as r:
                return r.status, await r.json()
        except aiohttp.ServerDisconnectedError:
            if attempt == 1:
                raise
            if retries is not None:
                retries[method] = retries.get(method, 0) + 1
    raise AssertionError("unreachable")


async def list_all(session: aiohttp.ClientSession) -> list[dict]:
    jobs, offset = [], 0
    while True:
        _, page = await request(session, "GET", "/v1/jobs",
                                params={"limit": 500, "offset": offset})
        jobs += page["data"]
        offset += len(page["data"])
        if not page["data"] or offset >= page["count"]:
            return jobs


def process_cpu_s(pid: int) -> float | None:
    """User + system CPU seconds of a process so far (Linux), else None."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


async def run(url: str, target: str, pid: int, args: argparse.Namespace, job: dict,
              watched_job: dict) -> dict:
    lat = Latency()
    stop = asyncio.Event()
    sse_counts: dict = defaultdict(int)
    grpc_counts: dict = defaultdict(int)
    connector = aiohttp.TCPConnector(limit=args.jobs + args.pollers + args.sse_watchers + 16)
    async with aiohttp.ClientSession(url, connector=connector,
                                     timeout=aiohttp.ClientTimeout(total=120)) as session, \
            grpc.aio.insecure_channel(target) as channel:
        stub = nprt_pb2_grpc.RenderServiceStub(channel)
        health = health_pb2_grpc.HealthStub(channel)

        retries: dict = {}

        def call(method: str, path: str, **kw):
            return request(session, method, path, retries, **kw)

        # Long jobs already rendering, watched by every stream, so the burst lands on a
        # busy service that fans tiles out; they are canceled after the burst.
        warm = [(await call("POST", "/v1/jobs", json=watched_job))[1]["id"]
                for _ in range(args.warm_jobs)]
        watchers = [asyncio.create_task(sse_watch(session, warm[i % len(warm)], sse_counts))
                    for i in range(args.sse_watchers)]
        watchers += [asyncio.create_task(grpc_watch(stub, warm[i % len(warm)], grpc_counts))
                     for i in range(args.grpc_streams)]
        # Steady state before the burst: every stream open, the long jobs past preparing
        # (loading the scene) and streaming tiles.
        while (sse_counts["opened"] + grpc_counts["opened"] < len(watchers)
               or sse_counts["tile"] < args.sse_watchers):
            await asyncio.sleep(0.05)
        ids: list[str] = list(warm)

        async def poller() -> None:
            while not stop.is_set():
                if random.random() < 0.8:
                    await lat.timed("GET /v1/jobs/{id}", call(
                        "GET", f"/v1/jobs/{random.choice(ids)}"))
                else:
                    await lat.timed("GET /v1/jobs", call("GET", "/v1/jobs",
                                                         params={"limit": 20}))
                await asyncio.sleep(0.005)

        async def health_loop() -> None:
            while not stop.is_set():
                reply = await lat.timed("gRPC Health.Check", health.Check(
                    health_pb2.HealthCheckRequest(service=""), timeout=30))
                assert reply.status == health_pb2.HealthCheckResponse.SERVING
                await asyncio.sleep(HEALTH_INTERVAL_S)

        async def submit() -> tuple[int, dict]:
            return await call("POST", "/v1/jobs", json=job,
                              headers={"Idempotency-Key": uuid.uuid4().hex})

        background = [asyncio.create_task(poller()) for _ in range(args.pollers)]
        background.append(asyncio.create_task(health_loop()))
        await asyncio.sleep(0.5)  # pollers and health running before the burst
        cpu0 = process_cpu_s(pid)
        t_burst = time.perf_counter()
        burst = await asyncio.gather(*(lat.timed("POST /v1/jobs", submit())
                                       for _ in range(args.jobs)))
        burst_s = time.perf_counter() - t_burst
        cpu1 = process_cpu_s(pid)
        open_after_burst = {"sse": sse_counts["opened"] - sse_counts["closed"],
                            "grpc": grpc_counts["opened"] - grpc_counts["closed"]}
        stop.set()
        await asyncio.gather(*background)
        for job_id in warm:
            await call("POST", f"/v1/jobs/{job_id}/cancel")
        statuses = [status for status, _ in burst]
        accepted = [body for status, body in burst if status == 202]
        ids += [j["id"] for j in accepted]

        t_drain = time.perf_counter()
        while True:
            jobs = await list_all(session)
            states = {j["id"]: j["state"] for j in jobs}
            if all(states.get(i) in TERMINAL for i in ids):
                break
            await asyncio.sleep(0.5)
        drain_s = time.perf_counter() - t_drain
        await asyncio.gather(*watchers)

    burst_ids = [j["id"] for j in accepted]
    return {
        "submitted": args.jobs, "accepted_202": statuses.count(202),
        "other_statuses": sorted(set(statuses) - {202}),
        "queued_on_accept": sum(j["state"] == "queued" for j in accepted),
        "lost": sum(i not in states for i in burst_ids),
        "duplicated": len(jobs) - len(set(ids)),
        "succeeded": sum(states.get(i) == "succeeded" for i in burst_ids),
        "burst_s": round(burst_s, 3), "drain_s": round(drain_s, 2),
        "service_cpu_s_during_burst": None if cpu0 is None else round(cpu1 - cpu0, 2),
        "streams_open_after_burst": open_after_burst,
        "client_retries_after_idle_disconnect": retries,
        "sse_events": dict(sse_counts), "grpc_events": dict(grpc_counts),
        "latency_ms": {k: _percentiles(v) for k, v in sorted(lat.samples_s.items())},
    }


def _percentiles(samples_s: list[float]) -> dict:
    ms = np.asarray(samples_s) * 1e3
    return {"n": int(len(ms)), "p50": round(float(np.percentile(ms, 50)), 2),
            "p99": round(float(np.percentile(ms, 99)), 2), "max": round(float(ms.max()), 2)}


def markdown(r: dict, args: argparse.Namespace) -> str:
    post_p99 = r["latency_ms"]["POST /v1/jobs"]["p99"]
    lines = [f"### {r['submitted']} concurrent submissions, {args.sse_watchers} SSE watchers, "
             f"{args.grpc_streams} gRPC WatchJob streams ({args.scene}, {args.width}x"
             f"{args.height}, {args.spp} spp, {args.max_jobs} job slots, {args.pollers} "
             "pollers)", "",
             "| check | value | target |", "| --- | --- | --- |",
             f"| accepted (202) | {r['accepted_202']} / {r['submitted']} | all |",
             f"| lost | {r['lost']} | 0 |",
             f"| duplicated | {r['duplicated']} | 0 |",
             f"| completed (succeeded) | {r['succeeded']} | all |",
             f"| POST /v1/jobs p99 | {post_p99} ms | < 200 ms: "
             f"{'met' if post_p99 < 200 else '**NOT met**'} |",
             f"| streams still open after the burst (SSE, gRPC) | "
             f"{r['streams_open_after_burst']['sse']}, "
             f"{r['streams_open_after_burst']['grpc']} | all |",
             f"| burst wall time | {r['burst_s']} s | |",
             f"| service CPU during the burst (renders included) | "
             f"{r['service_cpu_s_during_burst']} s | |",
             f"| drain time | {r['drain_s']} s | |", "",
             "| request (during the burst) | n | p50 ms | p99 ms | max ms |",
             "| --- | ---: | ---: | ---: | ---: |"]
    for kind, p in r["latency_ms"].items():
        lines.append(f"| {kind} | {p['n']} | {p['p50']} | {p['p99']} | {p['max']} |")
    lines += ["", f"All {r['submitted']} submissions arrive together and one event loop "
              "answers them in turn, so a POST's latency is mostly its wait in that line: the "
              f"p99 is close to the burst's wall time ({r['burst_s']} s), in which the service "
              f"process used {r['service_cpu_s_during_burst']} s of CPU, its renders and the "
              "tile fan-out to the streams included. A POST costs the service about 1.5-2 ms "
              "of CPU (measured in process, apart from this run), so a burst of 500 takes "
              "0.75 s or more on an idle core: the 200 ms p99 target needs more service "
              "processes or admission control, not a faster handler."]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=500, help="concurrent submissions")
    ap.add_argument("--sse-watchers", type=int, default=100)
    ap.add_argument("--grpc-streams", type=int, default=40)
    ap.add_argument("--max-jobs", type=int, default=2, help="job slots of the started service")
    ap.add_argument("--pollers", type=int, default=4, help="concurrent GET loops")
    ap.add_argument("--warm-jobs", type=int, default=2,
                    help="long jobs rendering during the burst, watched by the streams")
    ap.add_argument("--scene", default="forest:tiny")
    ap.add_argument("--width", type=int, default=32)
    ap.add_argument("--height", type=int, default=32)
    ap.add_argument("--spp", type=int, default=2)
    ap.add_argument("--out", type=Path, default=RESULTS / "bench_service.json")
    args = ap.parse_args(argv)
    job = {"scene": args.scene, "width": args.width, "height": args.height, "spp": args.spp,
           "bounces": 2, "shadow_rays": 1, "tile_size": 16, "spp_per_pass": 1}
    # Long enough to outlast the burst (canceled after it): 512 passes of 64x64 x 2 spp.
    watched_job = {**job, "width": 64, "height": 64, "spp": 1024, "tile_size": 64,
                   "spp_per_pass": 2}

    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="nprt-bench-") as tmp:
        proc, url, target = start_service(Path(tmp) / "data", args.max_jobs)
        try:
            result = asyncio.run(run(url, target, proc.pid, args, job, watched_job))
        finally:
            proc.terminate()
            proc.wait(30)
    table = markdown(result, args)
    print(table)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"result": result, "job": job, "watched_job": watched_job,
                                    "args": {k: str(v) for k, v in vars(args).items()},
                                    "host": {"cpus": os.cpu_count(),
                                             "python": platform.python_version(),
                                             "platform": platform.platform(),
                                             "load_average_before": load_before,
                                             "load_average_after": os.getloadavg()},
                                    "markdown": table}, indent=1))
    print(f"\nwrote {args.out}")
    if args.out.resolve() == (RESULTS / "bench_service.json").resolve():
        from bench.common import BENCH_README, replace_section

        replace_section(BENCH_README, "<!-- bench_service:begin -->",
                        "<!-- bench_service:end -->",
                        "## Service under load (`bench_service.py`)\n\n`python "
                        "bench/service/bench_service.py` (`results/bench_service.json`): "
                        "starts the "
                        "service (REST and gRPC) on loopback, starts long jobs and opens the "
                        "SSE and gRPC watchers on them, then fires the submissions at once "
                        "(each with its own Idempotency-Key) while pollers list and read jobs "
                        "and a gRPC client checks health; cancels the long jobs, waits for "
                        "every job, then audits the job list. The aiohttp client and the "
                        f"service share the machine's {os.cpu_count()} cores (load average "
                        f"{load_before[0]:.1f} before the run).\n\n{table}")
    ok = (result["succeeded"] == result["accepted_202"] == args.jobs and result["lost"] == 0
          and result["duplicated"] == 0)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
