"""Service load benchmark: N concurrent job submissions while jobs render and clients poll;
checks every job is accepted, queued and completed, and reports API latency percentiles.

    python bench/bench_service.py [--jobs 50] [--url http://host:port]
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
from collections import defaultdict
from pathlib import Path

import httpx
import numpy as np

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "bench" / "results"
TERMINAL = {"succeeded", "failed", "canceled"}


def start_service(data_dir: Path, max_jobs: int) -> tuple[subprocess.Popen, str]:
    """The service in its own process, as deployed: the client's CPU time stays apart."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    env = {**os.environ, "PYTHONPATH": str(REPO), "NPRT_MAX_CONCURRENT_JOBS": str(max_jobs)}
    env.pop("NPRT_API_TOKEN", None)
    proc = subprocess.Popen([sys.executable, "-m", "service", "serve", "--data-dir",
                             str(data_dir), "--port", str(port), "--grpc-port", "-1",
                             "--log-level", "warning"], cwd=REPO, env=env)
    url = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        try:
            if httpx.get(f"{url}/healthz", timeout=1).status_code == 200:
                return proc, url
        except httpx.TransportError:
            time.sleep(0.1)
    proc.kill()
    raise RuntimeError("service did not start within 60 s")


async def run(url: str, n_jobs: int, job: dict, n_pollers: int, warm_jobs: int) -> dict:
    latency_s: dict[str, list[float]] = defaultdict(list)
    limits = httpx.Limits(max_connections=n_jobs + n_pollers + 8)
    async with httpx.AsyncClient(base_url=url, timeout=60.0, limits=limits) as client:

        async def timed(kind: str, method: str, path: str, **kw) -> httpx.Response:
            t0 = time.perf_counter()
            r = await client.request(method, path, **kw)
            latency_s[kind].append(time.perf_counter() - t0)
            return r

        # Jobs already rendering, so the burst lands on a busy service.
        warm = [(await timed("warm-up POST", "POST", "/v1/jobs", json=job)).json()["id"]
                for _ in range(warm_jobs)]
        ids: list[str] = list(warm)
        stop = asyncio.Event()

        async def poller() -> None:
            while not stop.is_set():
                if ids and random.random() < 0.8:
                    await timed("GET /v1/jobs/{id}", "GET", f"/v1/jobs/{random.choice(ids)}")
                else:
                    await timed("GET /v1/jobs", "GET", "/v1/jobs", params={"limit": 20})
                await asyncio.sleep(0.005)

        pollers = [asyncio.create_task(poller()) for _ in range(n_pollers)]
        t_burst = time.perf_counter()
        burst = await asyncio.gather(*(timed("POST /v1/jobs", "POST", "/v1/jobs", json=job)
                                       for _ in range(n_jobs)))
        burst_s = time.perf_counter() - t_burst
        statuses = [r.status_code for r in burst]
        accepted = [r.json() for r in burst if r.status_code == 202]
        ids += [j["id"] for j in accepted]
        queued_on_accept = sum(j["state"] == "queued" for j in accepted)

        t_drain = time.perf_counter()
        while True:
            page = (await client.get("/v1/jobs", params={"limit": 500})).json()
            states = {j["id"]: j["state"] for j in page["data"]}
            if all(states.get(i) in TERMINAL for i in ids):
                break
            await asyncio.sleep(0.1)
        drain_s = time.perf_counter() - t_drain
        stop.set()
        await asyncio.gather(*pollers)

    burst_ids = [j["id"] for j in accepted]
    return {
        "submitted": n_jobs, "accepted_202": statuses.count(202),
        "other_statuses": sorted(set(statuses) - {202}),
        "queued_on_accept": queued_on_accept,
        "listed": sum(i in states for i in burst_ids),
        "succeeded": sum(states.get(i) == "succeeded" for i in burst_ids),
        "lost": sum(i not in states for i in burst_ids),
        "burst_s": round(burst_s, 4), "drain_s": round(drain_s, 3),
        "jobs_per_s": round(len(ids) / (burst_s + drain_s), 2),
        "latency_ms": {k: _percentiles(v) for k, v in sorted(latency_s.items())},
    }


def _percentiles(samples_s: list[float]) -> dict:
    ms = np.asarray(samples_s) * 1e3
    return {"n": int(len(ms)), "p50": round(float(np.percentile(ms, 50)), 2),
            "p99": round(float(np.percentile(ms, 99)), 2), "max": round(float(ms.max()), 2)}


def markdown(result: dict, args: argparse.Namespace) -> str:
    r = result
    lines = [f"### Service load: {r['submitted']} concurrent submissions "
             f"({args.scene}, {args.width}x{args.height}, {args.spp} spp, "
             f"{args.max_jobs} job slots, {args.pollers} pollers)", "",
             "| check | value |", "| --- | --- |",
             f"| accepted (202) | {r['accepted_202']} / {r['submitted']} |",
             f"| queued on accept | {r['queued_on_accept']} |",
             f"| listed afterwards | {r['listed']} |",
             f"| succeeded | {r['succeeded']} |",
             f"| lost | {r['lost']} |",
             f"| burst wall time | {r['burst_s'] * 1e3:.1f} ms |",
             f"| drain time | {r['drain_s']:.2f} s ({r['jobs_per_s']} jobs/s overall) |", "",
             "| request | n | p50 ms | p99 ms | max ms |", "| --- | ---: | ---: | ---: | ---: |"]
    for kind, p in r["latency_ms"].items():
        lines.append(f"| {kind} | {p['n']} | {p['p50']} | {p['p99']} | {p['max']} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=50, help="concurrent submissions")
    ap.add_argument("--url", help="benchmark a running service instead of starting one")
    ap.add_argument("--max-jobs", type=int, default=2, help="job slots of the started service")
    ap.add_argument("--pollers", type=int, default=4, help="concurrent GET loops")
    ap.add_argument("--warm-jobs", type=int, default=2, help="jobs started before the burst")
    ap.add_argument("--scene", default="forest:tiny")
    ap.add_argument("--width", type=int, default=32)
    ap.add_argument("--height", type=int, default=32)
    ap.add_argument("--spp", type=int, default=2)
    ap.add_argument("--out", type=Path, default=RESULTS / "bench_service.json")
    args = ap.parse_args(argv)
    job = {"scene": args.scene, "width": args.width, "height": args.height, "spp": args.spp,
           "bounces": 2, "shadow_rays": 1, "tile_size": 16, "spp_per_pass": 1}

    proc = None
    with tempfile.TemporaryDirectory(prefix="nprt-bench-") as tmp:
        url = args.url
        if url is None:
            proc, url = start_service(Path(tmp) / "data", args.max_jobs)
        try:
            result = asyncio.run(run(url, args.jobs, job, args.pollers, args.warm_jobs))
        finally:
            if proc is not None:
                proc.terminate()
                proc.wait(15)
    table = markdown(result, args)
    print(table)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"result": result, "job": job, "args": {
        k: str(v) for k, v in vars(args).items()}, "host": {
        "cpus": os.cpu_count(), "python": platform.python_version(),
        "platform": platform.platform()}, "markdown": table}, indent=1))
    print(f"\nwrote {args.out}")
    if args.out.resolve() == (RESULTS / "bench_service.json").resolve():
        sys.path.insert(0, str(REPO))  # run as a script: make bench.common importable
        from bench.common import BENCH_README, replace_section

        replace_section(BENCH_README, "<!-- bench_service:begin -->",
                        "<!-- bench_service:end -->",
                        "## Service under load (`bench_service.py`)\n\n`python "
                        "bench/bench_service.py` (`results/bench_service.json`): starts the "
                        "service on loopback, starts warm-up jobs, fires the submissions at "
                        "once while pollers list and read jobs, and waits for every job. "
                        f"{os.cpu_count()} cores.\n\n{table}")
    ok = result["succeeded"] == result["accepted_202"] == args.jobs and result["lost"] == 0
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
