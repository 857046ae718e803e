"""Does a render move the API's latency? Pollers read jobs and a client checks /healthz
and gRPC health, first with nothing rendering, then while a K = 8 sharded render runs
(the scheduler and Ray at their lower priority), then idle again after it is canceled;
p50 / p99 per request side by side, the same client and service throughout.

    python -m bench.service.bench_render_effect [--shards 8] [--phase-s 20] [--smoke]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import grpc
from grpc_health.v1 import health_pb2_grpc

from bench.common import RESULTS
from bench.service.harness import (
    REPO,
    Latency,
    Rest,
    api_cpu_s,
    check_health,
    niceness,
    poll,
    render_cpu_s,
    running_service,
)

TARGET_MS = 20.0  # the bound on how far a render may move the API's p99
POLL_PAUSE_S = 0.01
HEALTH_INTERVAL_S = 0.02


async def measure_phase(rest: Rest, health, ids: list[str], pollers: int, seconds: float,
                        pid: int) -> dict:
    """Latency of polled reads and health checks over `seconds`, and the CPU the API
    processes and the renders used meanwhile (in cores)."""
    lat = Latency()
    stop = asyncio.Event()

    api0, render0, t0 = api_cpu_s(pid), render_cpu_s(pid), time.perf_counter()
    tasks = [asyncio.create_task(poll(rest, lat, ids, stop, POLL_PAUSE_S))
             for _ in range(pollers)]
    tasks.append(asyncio.create_task(check_health(rest, health, lat, stop, HEALTH_INTERVAL_S)))
    await asyncio.sleep(seconds)
    stop.set()
    await asyncio.gather(*tasks)
    wall = time.perf_counter() - t0
    return {"wall_s": round(wall, 2), "samples_s": dict(lat.samples_s),
            "api_cores": round((api_cpu_s(pid) - api0) / wall, 3),
            "render_cores": round((render_cpu_s(pid) - render0) / wall, 3)}


async def run(host: str, port: int, target: str, pid: int, args: argparse.Namespace,
              small: dict, long: dict) -> dict:
    rest = Rest(host, port)
    control = rest.connection()
    async with grpc.aio.insecure_channel(target) as channel:
        health = health_pb2_grpc.HealthStub(channel)
        # A few finished jobs for the pollers to read.
        ids = [(await rest.call(control, "POST", "/v1/jobs", small))[1]["id"]
               for _ in range(args.jobs)]
        for j in ids:
            while (await rest.call(control, "GET", f"/v1/jobs/{j}"))[1]["state"] != "succeeded":
                await asyncio.sleep(0.5)
        phases = {"idle, before": await measure_phase(rest, health, ids, args.pollers,
                                                      args.phase_s, pid)}
        render = (await rest.call(control, "POST", "/v1/jobs", long))[1]["id"]
        t_start = time.perf_counter()
        while (job := (await rest.call(control, "GET", f"/v1/jobs/{render}"))[1]
               )["passes_done"] < 1:
            if job["state"] in ("failed", "canceled"):
                raise RuntimeError(f"the K = {args.shards} render {job['state']}: "
                                   f"{job['error']}")
            await asyncio.sleep(0.5)
        start_s = time.perf_counter() - t_start
        done0 = (await rest.call(control, "GET", f"/v1/jobs/{render}"))[1]["passes_done"]
        phases[f"K = {args.shards} rendering"] = await measure_phase(
            rest, health, ids, args.pollers, args.phase_s, pid)
        done1 = (await rest.call(control, "GET", f"/v1/jobs/{render}"))[1]["passes_done"]
        nice = niceness(pid)
        await rest.call(control, "POST", f"/v1/jobs/{render}/cancel")
        while (await rest.call(control, "GET", f"/v1/jobs/{render}"))[1]["state"] != "canceled":
            await asyncio.sleep(0.5)
        phases["idle, after"] = await measure_phase(rest, health, ids, args.pollers,
                                                    args.phase_s, pid)
        control.close()
    return {"phases": phases, "render_start_s": round(start_s, 1),
            "render_passes_per_s": round((done1 - done0) / phases[
                f"K = {args.shards} rendering"]["wall_s"], 2),
            "nice_by_process": nice}


def summarize(raw: dict, shards: int) -> dict:
    """Per request: p50 / p99 idle (both idle phases pooled) and rendering, and the p99
    difference."""
    from bench.service.harness import percentiles

    idle = [raw["phases"]["idle, before"], raw["phases"]["idle, after"]]
    busy = raw["phases"][f"K = {shards} rendering"]
    rows = {}
    for kind in sorted(busy["samples_s"]):
        a = percentiles([s for p in idle for s in p["samples_s"].get(kind, [])])
        b = percentiles(busy["samples_s"][kind])
        rows[kind] = {"idle": a, "rendering": b, "p99_moved_ms": round(b["p99"] - a["p99"], 2)}
    return {"requests": rows,
            "cores": {name: {"api": p["api_cores"], "render": p["render_cores"]}
                      for name, p in raw["phases"].items()},
            **{k: v for k, v in raw.items() if k != "phases"}}


def markdown(r: dict, args: dict) -> str:
    k = args["shards"]
    worst = max(v["p99_moved_ms"] for v in r["requests"].values())
    ok = "met" if worst <= TARGET_MS else "**NOT met**"
    lines = [f"### A K = {k} render running vs idle ({args['pollers']} pollers, health "
             f"checks every {HEALTH_INTERVAL_S * 1e3:.0f} ms, {args['phase_s']} s per phase)",
             "", "| request | n idle | p50 idle | p99 idle | n rendering | p50 rendering | "
             "p99 rendering | p99 moved |", "| --- | ---: | ---: | ---: | ---: | ---: | ---: "
             "| ---: |"]
    for kind, v in r["requests"].items():
        a, b = v["idle"], v["rendering"]
        lines.append(f"| {kind} | {a['n']} | {a['p50']} | {a['p99']} | {b['n']} | {b['p50']} "
                     f"| {b['p99']} | {v['p99_moved_ms']:+.2f} |")
    lines += ["", f"Worst p99 moved: {worst:+.2f} ms (target <= {TARGET_MS:.0f} ms: {ok}). "
              "Cores used per phase (API processes / scheduler and Ray): " + ", ".join(
                  f"{name} {c['api']:.2f} / {c['render']:.2f}" for name, c in r["cores"].items())
              + f". The render ran {r['render_passes_per_s']} passes/s once started "
              f"({r['render_start_s']} s to its first pass); nice values: "
              + ", ".join(f"{n} {v}" for n, v in r["nice_by_process"].items()) + "."]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shards", type=int, default=8, help="K of the render")
    ap.add_argument("--phase-s", type=float, default=20.0, help="seconds per phase")
    ap.add_argument("--pollers", type=int, default=4, help="concurrent GET loops")
    ap.add_argument("--jobs", type=int, default=20, help="finished jobs the pollers read")
    ap.add_argument("--scene", default="forest:tiny")
    ap.add_argument("--api-workers", type=int, default=1, help="nprt serve --workers")
    ap.add_argument("--service-root", type=Path, default=REPO,
                    help="checkout whose service runs (default: this one)")
    ap.add_argument("--smoke", action="store_true",
                    help="K = 2, 1 s phases, 2 jobs; writes nothing under bench/results")
    args = ap.parse_args(argv)
    if args.smoke:
        args.shards, args.phase_s, args.jobs, args.pollers = 2, 1.0, 2, 1
    small = {"scene": args.scene, "width": 16, "height": 16, "spp": 1, "bounces": 1}
    # Outlasts the phase (canceled after it): 128x128 in 4 tiles, 2 spp a pass.
    long = {"scene": args.scene, "width": 128, "height": 128, "spp": 16384, "tile_size": 64,
            "spp_per_pass": 2, "bounces": 2, "shards": args.shards}
    load_before = os.getloadavg()
    with running_service(args.service_root, 1, args.api_workers) as (proc, host, port, target):
        raw = asyncio.run(run(host, port, target, proc.pid, args, small, long))
    result = summarize(raw, args.shards)
    table = markdown(result, vars(args))
    args.service_root = str(args.service_root)
    print(table)
    if args.smoke:
        return 0
    commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=REPO,
                            capture_output=True, text=True).stdout.strip()
    command = "python -m bench.service.bench_render_effect " + " ".join(argv or sys.argv[1:])
    load_after = os.getloadavg()
    out = RESULTS / "bench_render_effect.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"result": result, "args": vars(args), "commit": commit,
                               "command": command.strip(),
                               "host": {"cpus": os.cpu_count(),
                                        "python": platform.python_version(),
                                        "load_average_before": load_before,
                                        "load_average_after": load_after},
                               "markdown": table}, indent=1))
    print(f"\nwrote {out}")
    from bench.common import BENCH_README, replace_section

    replace_section(BENCH_README, "<!-- bench_render_effect:begin -->",
                    "<!-- bench_render_effect:end -->",
                    f"{table}\n\nRun: `{command.strip()}` (commit {commit}, {os.cpu_count()} "
                    f"cores shared with the client, load average {load_before[0]:.1f} before, "
                    f"{load_after[0]:.1f} after).")
    return 0


if __name__ == "__main__":
    sys.exit(main())
