"""Service load benchmark: a burst of concurrent job submissions while SSE watchers and
gRPC WatchJob streams follow running jobs (one of them a K = 2 render) and clients poll.
Checks every job is accepted once and completed, and reports p50 / p99 per route and for
gRPC health during the burst, plus the API processes' CPU. The client is aiohttp (httpx
spent 4x the service's CPU per request, and client and service share the machine).

    python -m bench.service.bench_service [--label after] [--jobs 500] [--smoke]
    python -m bench.service.bench_service --label before --service-root /tmp/before

--service-root runs the service of another checkout (the commit before a change) with this
client, so "before" and "after" are measured the same way.
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
from grpc_health.v1 import health_pb2, health_pb2_grpc

from nprt.protos import nprt_pb2 as pb
from nprt.protos import nprt_pb2_grpc

REPO = Path(__file__).resolve().parents[2]
RESULTS = REPO / "bench" / "results"
TERMINAL = {"succeeded", "failed", "canceled"}
HEALTH_INTERVAL_S = 0.02
LABELS = ("before", "after", "after_2_workers")


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


def start_service(root: Path, data_dir: Path, args) -> tuple[subprocess.Popen, str, str]:
    """`nprt serve` of the checkout at root in its own process group, as deployed. Returns
    (process, REST url, gRPC target)."""
    port, grpc_port = _free_port(), _free_port()
    env = {**os.environ, "PYTHONPATH": _pythonpath(root),
           "NPRT_MAX_CONCURRENT_JOBS": str(args.max_jobs)}
    env.pop("NPRT_API_TOKEN", None)
    cmd = [sys.executable, "-m", "service", "serve", "--data-dir", str(data_dir), "--port",
           str(port), "--grpc-port", str(grpc_port), "--log-level", "warning"]
    if args.api_workers > 1:
        cmd += ["--workers", str(args.api_workers)]
    proc = subprocess.Popen(cmd, cwd=root, env=env, start_new_session=True)
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


def api_cpu_s(pid: int) -> float:
    """CPU seconds of the serving processes so far: `pid` and its descendants, except a
    scheduler process and everything under it (renders, Ray). Linux only."""
    total, todo = 0.0, [pid]
    while todo:
        p = todo.pop()
        if _is_scheduler(p):
            continue
        total += _cpu_s(p)
        todo += _children(p)
    return total


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
                  retries: dict | None = None, **kw) -> tuple[int, dict, float | None]:
    """(status, JSON body, Retry-After s). A pooled connection the server closed as idle is
    retried on a fresh one, twice at most (POSTs carry an Idempotency-Key: no duplicate
    job)."""
    for attempt in range(3):
        try:
            async with session.request(method, path, **kw) as r:
                after = r.headers.get("Retry-After")
                return r.status, await r.json(), None if after is None else float(after)
        except (aiohttp.ServerDisconnectedError, aiohttp.ClientOSError):
            if attempt == 2:
                raise
            if retries is not None:
                retries[method] = retries.get(method, 0) + 1
    raise AssertionError("unreachable")


async def list_all(session: aiohttp.ClientSession) -> list[dict]:
    jobs, offset = [], 0
    while True:
        _, page, _ = await request(session, "GET", "/v1/jobs",
                                   params={"limit": 500, "offset": offset})
        jobs += page["data"]
        offset += len(page["data"])
        if not page["data"] or offset >= page["count"]:
            return jobs


async def run(url: str, target: str, pid: int, args: argparse.Namespace, job: dict,
              watched: list[dict]) -> dict:
    lat = Latency()
    stop = asyncio.Event()
    sse_counts: dict = defaultdict(int)
    grpc_counts: dict = defaultdict(int)
    refused: dict = defaultdict(int)
    # Idle connections are dropped before uvicorn's 5 s keep-alive closes them under us.
    connector = aiohttp.TCPConnector(limit=args.jobs + args.pollers + args.sse_watchers + 16,
                                     keepalive_timeout=2.0)
    async with aiohttp.ClientSession(url, connector=connector,
                                     timeout=aiohttp.ClientTimeout(total=120)) as session, \
            grpc.aio.insecure_channel(target) as channel:
        stub = nprt_pb2_grpc.RenderServiceStub(channel)
        health = health_pb2_grpc.HealthStub(channel)
        retries: dict = {}

        def call(method: str, path: str, **kw):
            return request(session, method, path, retries, **kw)

        # Long jobs already rendering (one of them sharded), watched by every stream, so the
        # burst lands on a busy service that fans tiles out; canceled after the burst.
        warm = [(await call("POST", "/v1/jobs", json=w))[1]["id"] for w in watched]
        watchers = [asyncio.create_task(sse_watch(session, warm[i % len(warm)], sse_counts))
                    for i in range(args.sse_watchers)]
        watchers += [asyncio.create_task(grpc_watch(stub, warm[i % len(warm)], grpc_counts))
                     for i in range(args.grpc_streams)]
        # Steady state: every stream open and every long job streaming tiles (the sharded
        # one once Ray and its shards are up).
        while True:
            running = [(await call("GET", f"/v1/jobs/{j}"))[1] for j in warm]
            if (sse_counts["opened"] + grpc_counts["opened"] == len(watchers)
                    and all(r["passes_done"] > 0 for r in running)):
                break
            await asyncio.sleep(0.2)
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
                await lat.timed("GET /healthz", call("GET", "/healthz"))
                await asyncio.sleep(HEALTH_INTERVAL_S)

        async def submit() -> tuple[int, dict]:
            """One submission, honouring Retry-After; its latency is the first answer's."""
            key = uuid.uuid4().hex
            t0 = time.perf_counter()
            status, body, after = await call("POST", "/v1/jobs", json=job,
                                             headers={"Idempotency-Key": key})
            lat.samples_s["POST /v1/jobs"].append(time.perf_counter() - t0)
            while status in (429, 503) and after is not None:
                refused[status] += 1
                await asyncio.sleep(after)
                status, body, after = await call("POST", "/v1/jobs", json=job,
                                                 headers={"Idempotency-Key": key})
            return status, body

        background = [asyncio.create_task(poller()) for _ in range(args.pollers)]
        background.append(asyncio.create_task(health_loop()))
        await asyncio.sleep(0.5)  # pollers and health running before the burst
        cpu0 = api_cpu_s(pid)
        t_burst = time.perf_counter()
        burst = await asyncio.gather(*(submit() for _ in range(args.jobs)))
        burst_s = time.perf_counter() - t_burst
        cpu1 = api_cpu_s(pid)
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
        post_cpu_ms = await sequential_post_cpu_ms(call, pid, job, args.cpu_posts)

    burst_ids = [j["id"] for j in accepted]
    return {
        "submitted": args.jobs, "accepted_202": statuses.count(202),
        "other_statuses": sorted(set(statuses) - {202}),
        "refused_then_retried": dict(refused),
        "lost": sum(i not in states for i in burst_ids),
        "duplicated": len(jobs) - len(set(j["id"] for j in jobs)),
        "succeeded": sum(states.get(i) == "succeeded" for i in burst_ids),
        "burst_s": round(burst_s, 3), "drain_s": round(drain_s, 2),
        "api_cpu_s_during_burst": round(cpu1 - cpu0, 2),
        "api_cpu_ms_per_sequential_post": post_cpu_ms,
        "streams_open_after_burst": open_after_burst,
        "client_retries_after_idle_disconnect": retries,
        "sse_events": dict(sse_counts), "grpc_events": dict(grpc_counts),
        "latency_ms": {k: _percentiles(v) for k, v in sorted(lat.samples_s.items())},
    }


async def sequential_post_cpu_ms(call, pid: int, job: dict, n: int) -> float:
    """The serving processes' CPU per POST /v1/jobs, one request at a time, each job
    canceled at once so nothing renders in between (the cancels are timed apart)."""
    posts = cancels = 0.0
    for _ in range(n):
        c0 = api_cpu_s(pid)
        _, body, _ = await call("POST", "/v1/jobs", json=job)
        c1 = api_cpu_s(pid)
        await call("POST", f"/v1/jobs/{body['id']}/cancel")
        posts += c1 - c0
        cancels += api_cpu_s(pid) - c1
    return round(posts / n * 1e3, 3)


def _percentiles(samples_s: list[float]) -> dict:
    ms = np.asarray(samples_s) * 1e3
    return {"n": int(len(ms)), "p50": round(float(np.percentile(ms, 50)), 2),
            "p99": round(float(np.percentile(ms, 99)), 2), "max": round(float(ms.max()), 2)}


def markdown(r: dict, label: str, args: dict) -> str:
    lat = r["latency_ms"]
    post = lat["POST /v1/jobs"]["p99"]
    gets = max(lat[k]["p99"] for k in ("GET /v1/jobs", "GET /v1/jobs/{id}") if k in lat)
    health = max(lat[k]["p99"] for k in ("GET /healthz", "gRPC Health.Check") if k in lat)

    def verdict(ok: bool) -> str:
        return "met" if ok else "**NOT met**"

    lines = [f"### {label}: {r['submitted']} concurrent submissions, {args['sse_watchers']} SSE"
             f" watchers, {args['grpc_streams']} gRPC WatchJob streams, a K = "
             f"{args['long_shards']} render running ({args['scene']}, {args['api_workers']} "
             "API worker(s))", "",
             "| check | value | target |", "| --- | --- | --- |",
             f"| accepted (202) | {r['accepted_202']} / {r['submitted']} | all |",
             f"| refused with Retry-After, then retried | {r['refused_then_retried'] or 0} "
             "| none at the default depth |",
             f"| lost / duplicated | {r['lost']} / {r['duplicated']} | 0 / 0 |",
             f"| completed (succeeded) | {r['succeeded']} | all |",
             f"| POST /v1/jobs p99 | {post} ms | < 200 ms: {verdict(post < 200)} |",
             f"| GET p99 (worst route) | {gets} ms | < 100 ms: {verdict(gets < 100)} |",
             f"| /healthz, gRPC health p99 (worst) | {health} ms | < 50 ms: "
             f"{verdict(health < 50)} |",
             f"| streams still open after the burst (SSE, gRPC) | "
             f"{r['streams_open_after_burst']['sse']}, "
             f"{r['streams_open_after_burst']['grpc']} | all |",
             f"| burst wall time | {r['burst_s']} s | |",
             f"| API process CPU during the burst | {r['api_cpu_s_during_burst']} s | |",
             f"| API CPU per POST, one at a time | {r['api_cpu_ms_per_sequential_post']} ms "
             "| < 1 ms |",
             f"| drain time | {r['drain_s']} s | |", "",
             "| request (during the burst) | n | p50 ms | p99 ms | max ms |",
             "| --- | ---: | ---: | ---: | ---: |"]
    for kind, p in lat.items():
        lines.append(f"| {kind} | {p['n']} | {p['p50']} | {p['p99']} | {p['max']} |")
    return "\n".join(lines)


def write_readme() -> None:
    """The README section from the saved before / after results."""
    from bench.common import BENCH_README, replace_section

    parts, runs = [], {}
    for label in LABELS:
        path = RESULTS / f"bench_service_{label}.json"
        if path.exists():
            saved = runs[label] = json.loads(path.read_text())
            host = saved["host"]
            parts.append(f"{saved['markdown']}\n\nRun: `{saved['command']}` (commit "
                         f"{saved['commit']}, {host['cpus']} cores shared with the client, "
                         f"load average {host['load_average_before'][0]:.1f} before, "
                         f"{host['load_average_after'][0]:.1f} after).")
    if {"before", "after"} <= runs.keys():
        b, a = (runs[k]["result"] for k in ("before", "after"))
        parts.append(
            "What changed: renders, Ray and the tile fan-out left the API process, so during "
            f"the burst it used {a['api_cpu_s_during_burst']} s of CPU instead of "
            f"{b['api_cpu_s_during_burst']} s, and POST p99 fell from "
            f"{b['latency_ms']['POST /v1/jobs']['p99']:.0f} to "
            f"{a['latency_ms']['POST /v1/jobs']['p99']:.0f} ms. The targets (POST p99 < 200 "
            "ms, GET < 100 ms, health < 50 ms) are still not met here, and this machine "
            "cannot tell whether they would be: its 2 cores ran at a load average of 13 to "
            "40 from other work during these runs, the 500-connection aiohttp client shares "
            "them, and the API process got about a quarter of a core during the burst "
            "(its CPU over the burst's wall time). At the in-process cost of an admission "
            "(`bench_admission` below) 500 POSTs need about 0.16 s of one core, so one "
            "event loop answering them in turn would put the last near 0.2 s on an idle "
            "core, and two workers half that. More API workers do not help on 2 loaded "
            "cores (the 2-worker run). \"API CPU per POST, one at a time\" before counts "
            "the renders that shared the process.")
    replace_section(BENCH_README, "<!-- bench_service:begin -->", "<!-- bench_service:end -->",
                    "## Service under load (`bench/service/bench_service.py`)\n\n"
                    "`python -m bench.service.bench_service --label after` "
                    "(`results/bench_service_after.json`; `--label before --service-root "
                    "<checkout>` measures another commit with the same client): starts "
                    "`nprt serve` on loopback, starts two long jobs (one reference, one "
                    "K = 2) and opens the SSE and gRPC watchers on them, then fires the "
                    "submissions at once (each with its own Idempotency-Key, honouring "
                    "Retry-After) while pollers list and read jobs and a client checks "
                    "`/healthz` and gRPC health; cancels the long jobs, waits for every job "
                    "and audits the job list. API CPU counts the serving processes, not the "
                    "scheduler or its renders.\n\n" + "\n\n".join(parts))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--label", choices=LABELS, default="after")
    ap.add_argument("--service-root", type=Path, default=REPO,
                    help="checkout whose service runs (default: this one)")
    ap.add_argument("--jobs", type=int, default=500, help="concurrent submissions")
    ap.add_argument("--sse-watchers", type=int, default=100)
    ap.add_argument("--grpc-streams", type=int, default=40)
    ap.add_argument("--max-jobs", type=int, default=2, help="job slots of the scheduler")
    ap.add_argument("--api-workers", type=int, default=1, help="nprt serve --workers")
    ap.add_argument("--pollers", type=int, default=4, help="concurrent GET loops")
    ap.add_argument("--cpu-posts", type=int, default=100,
                    help="sequential POSTs for the CPU-per-POST figure")
    ap.add_argument("--long-shards", type=int, default=2,
                    help="K of the long sharded render running during the burst")
    ap.add_argument("--scene", default="forest:tiny")
    ap.add_argument("--smoke", action="store_true",
                    help="a few jobs and watchers; writes nothing under bench/results")
    args = ap.parse_args(argv)
    if args.smoke:
        args.jobs, args.sse_watchers, args.grpc_streams, args.pollers = 4, 2, 2, 1
        args.cpu_posts = 2
    job = {"scene": args.scene, "width": 32, "height": 32, "spp": 2, "bounces": 2,
           "shadow_rays": 1, "tile_size": 16, "spp_per_pass": 1}
    # Long enough to outlast Ray's start and the burst (canceled after it): 8192 passes of
    # 64x64 x 2 spp.
    long = {**job, "width": 64, "height": 64, "spp": 16384, "tile_size": 64, "spp_per_pass": 2}
    watched = [long] if args.smoke else [long, {**long, "shards": args.long_shards}]

    load_before = os.getloadavg()
    with tempfile.TemporaryDirectory(prefix="nprt-bench-") as tmp:
        proc, url, target = start_service(args.service_root, Path(tmp) / "data", args)
        try:
            result = asyncio.run(run(url, target, proc.pid, args, job, watched))
        finally:
            os.killpg(proc.pid, 15)
            proc.wait(60)
    shown = {k: v for k, v in vars(args).items() if k != "service_root"}
    table = markdown(result, args.label, shown)
    print(table)
    ok = (result["succeeded"] == result["accepted_202"] == args.jobs and result["lost"] == 0
          and result["duplicated"] == 0)
    if args.smoke:
        return 0 if ok else 1
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=args.service_root,
                            capture_output=True, text=True).stdout.strip()
    out = RESULTS / f"bench_service_{args.label}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    command = "python -m bench.service.bench_service " + " ".join(
        a if not a.startswith("/") else "<checkout>" for a in (argv or sys.argv[1:]))
    out.write_text(json.dumps({"result": result, "job": job, "watched_jobs": watched,
                               "args": {k: str(v) for k, v in shown.items()},
                               "commit": commit, "command": command.strip(),
                               "host": {"cpus": os.cpu_count(),
                                        "python": platform.python_version(),
                                        "platform": platform.platform(),
                                        "load_average_before": load_before,
                                        "load_average_after": os.getloadavg()},
                               "markdown": table}, indent=1))
    print(f"\nwrote {out}")
    write_readme()
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
