"""The API's CPU per request over real sockets, to the microsecond: `nprt serve --api-only`
(two HTTP workers, nothing rendering) takes bursts of concurrent POST /v1/jobs (each on a
new connection with its own Idempotency-Key, as bench_service sends them) and bursts of
GET /healthz (the floor: a connection, a parse and an answer), and the on-CPU time of every
thread of its processes (/proc/<pid>/task/*/schedstat, nanoseconds) is divided by the
requests. Unlike latency, the figure hardly depends on what else runs on the cores; the
500-burst's p99 is about this CPU times 500 over the cores the API gets.

    python -m bench.service.bench_burst_cpu [--versus before=<checkout>] [--smoke]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import re
import statistics
import sys
import tempfile
import time
import uuid
from pathlib import Path

from bench.common import RESULTS
from bench.service.harness import REPO, Rest, api_cpu_ns, percentiles, run_client, start_service

JOB = {"scene": "forest:tiny", "width": 32, "height": 32, "spp": 2, "bounces": 2,
       "shadow_rays": 1, "tile_size": 16, "spp_per_pass": 1}
KINDS = ("POST /v1/jobs", "GET /healthz")


async def burst(rest: Rest, n: int, kind: str) -> tuple[list[int], list[float]]:
    """n concurrent requests of `kind`, each on a new connection: (statuses, latencies s)."""
    method, path = kind.split()
    lat: list[float] = []

    async def one() -> int:
        conn = rest.connection()
        post = method == "POST"
        t0 = time.perf_counter()
        status, _, _ = await rest.call(conn, method, path, JOB if post else None,
                                       {"Idempotency-Key": uuid.uuid4().hex} if post else None)
        lat.append(time.perf_counter() - t0)
        conn.close()
        return status

    return await asyncio.gather(*(one() for _ in range(n))), lat


async def measure(port: int, pid: int, bursts: int, jobs: int) -> dict:
    """CPU us per request of each kind over `bursts` bursts of `jobs`, after a warm-up."""
    rest = Rest("127.0.0.1", port)
    for kind in KINDS:
        await burst(rest, min(jobs, 200), kind)
    out = {}
    for kind in KINDS:
        ns, lat = 0, []
        for _ in range(bursts):
            await asyncio.sleep(0.2)  # the previous burst's closes handled
            c0 = api_cpu_ns(pid)
            statuses, times = await burst(rest, jobs, kind)
            await asyncio.sleep(0.05)
            ns += api_cpu_ns(pid) - c0
            want = 202 if kind.startswith("POST") else 200
            if set(statuses) != {want}:
                raise RuntimeError(f"{kind}: statuses {sorted(set(statuses))}, want {want}")
            lat += times
        out[kind] = {"cpu_us": round(ns / (bursts * jobs) / 1e3, 1),
                     "p99_ms": percentiles(lat)["p99"]}
    return out


def run_round(root: Path, bursts: int, jobs: int) -> dict:
    with tempfile.TemporaryDirectory(prefix="nprt-burst-cpu-") as tmp:
        proc, _, port, _ = start_service(root, Path(tmp) / "data", 1, 2,
                                         {"NPRT_MAX_QUEUED_JOBS": "10000000"}, api_only=True)
        try:
            load0 = os.getloadavg()[0]
            one = run_client(measure(port, proc.pid, bursts, jobs))
            one["load_average"] = [load0, os.getloadavg()[0]]
            return one
        finally:
            os.killpg(proc.pid, 15)
            proc.wait(60)


def summary(rounds: list[dict]) -> dict:
    """Median CPU per request of each kind over the rounds, and each round's figures."""
    return {kind: statistics.median(r[kind]["cpu_us"] for r in rounds) for kind in KINDS} | {
        "rounds": rounds}


def markdown(results: dict, jobs: int, bursts: int) -> str:
    labels = list(results)
    lines = [f"CPU of the API processes per request, us (median of rounds; each round {bursts} "
             f"bursts of {jobs} concurrent requests, each on a new connection; `nprt serve "
             "--api-only`, 2 HTTP workers, on-CPU ns of every thread):", "",
             "| request | " + " | ".join(labels) + " |", "| --- |" + " ---: |" * len(labels)]
    for kind in KINDS:
        lines.append(f"| {kind} (burst) | " + " | ".join(
            str(results[k]["summary"][kind]) for k in labels) + " |")
    lines.append("| POST less the /healthz floor | " + " | ".join(
        f"{results[k]['summary'][KINDS[0]] - results[k]['summary'][KINDS[1]]:.1f}"
        for k in labels) + " |")
    lines.append("| each round's POST us (load average before) | " + " | ".join(", ".join(
        f"{r[KINDS[0]]['cpu_us']:.0f} ({r['load_average'][0]:.0f})"
        for r in results[k]["summary"]["rounds"]) for k in labels) + " |")
    lines.append("| commit | " + " | ".join(results[k]["commit"] for k in labels) + " |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--label", default="after")
    ap.add_argument("--service-root", type=Path, default=REPO,
                    help="checkout whose service runs (default: this one)")
    ap.add_argument("--commit", help="what that checkout holds, for the record")
    ap.add_argument("--versus", action="append", default=[], metavar="LABEL=ROOT[@COMMIT]",
                    help="also measure the service of checkout ROOT, rounds alternating")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--bursts", type=int, default=6, help="bursts of each kind a round")
    ap.add_argument("--jobs", type=int, default=500, help="requests in a burst")
    ap.add_argument("--smoke", action="store_true", help="one round of 2 bursts of 20")
    args = ap.parse_args(argv)
    if args.smoke:
        args.rounds, args.bursts, args.jobs = 1, 2, 20
    services = [(args.label, args.service_root, args.commit or str(args.service_root))]
    for spec in args.versus:
        label, _, rest = spec.partition("=")
        root, _, commit = rest.partition("@")
        services.append((label, Path(root), commit or root))
    rounds: dict[str, list] = {label: [] for label, _, _ in services}
    load = os.getloadavg()
    for _ in range(args.rounds):
        for label, root, _ in services:
            rounds[label].append(run_round(root, args.bursts, args.jobs))
            print(label, rounds[label][-1], flush=True)
    results = {label: {"commit": commit, "summary": summary(rounds[label])}
               for label, _, commit in services}
    table = markdown(results, args.jobs, args.bursts)
    print(table)
    if args.smoke:
        return 0
    out = RESULTS / "bench_burst_cpu.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    command = " ".join(re.sub(r"/\S*", "<checkout>", a) if "/" in a else a
                       for a in (argv if argv is not None else sys.argv[1:]))
    shown = {k: str(v) for k, v in vars(args).items() if k not in ("service_root", "versus")}
    out.write_text(json.dumps({"results": results, "args": shown, "command": command,
                               "load_average_before": load,
                               "load_average_after": os.getloadavg(), "cpus": os.cpu_count(),
                               "markdown": table}, indent=1))
    write_readme()
    return 0


def write_readme() -> None:
    """bench/README.md's section from the saved result."""
    from bench.common import publish

    out = RESULTS / "bench_burst_cpu.json"
    saved = json.loads(out.read_text())
    publish("bench_burst_cpu", "## API CPU per request over sockets "
            "(`bench/service/bench_burst_cpu.py`)\n\n" + saved["markdown"] + "\n\n"
            f"Load average {saved['load_average_before'][0]:.1f} before, "
            f"{saved['load_average_after'][0]:.1f} after ({saved['cpus']} cores, shared; under "
            f"the bench lock). Command: `python -m bench.service.bench_burst_cpu "
            f"{saved['command']}`. The /healthz row is the floor of any request on a new "
            "connection (uvicorn's protocol and the kernel's TCP work); POST less it is what "
            "the admission itself costs.", out)


if __name__ == "__main__":
    sys.exit(main())
