"""Does a render move the API's latency? Pollers read jobs and a client checks /healthz
and gRPC health, first with nothing rendering, then while a K = 8 sharded render runs
(the scheduler and Ray at their lower priority), then idle again after it is canceled;
p50 / p99 per request side by side, the same client and service throughout.

    python -m bench.service.bench_render_effect [--shards 8] [--phase-s 20] [--smoke]
    python -m bench.service.bench_render_effect --repeat 2 --versus before=/tmp/b@abc1234

--versus measures the service of another checkout under another label in the same run,
rounds alternating (each round a fresh service), so load from other work falls on both;
--set LABEL:NAME=VALUE starts that label's service with an NPRT_* setting (e.g. another
NPRT_SCHEDULER_CPU). Each label's results go to results/bench_render_effect_<label>.json;
the README section is rebuilt from every saved label.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import platform
import re
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
    cpu_policies,
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
        nice, policies = niceness(pid), cpu_policies(pid)
        await rest.call(control, "POST", f"/v1/jobs/{render}/cancel")
        while (await rest.call(control, "GET", f"/v1/jobs/{render}"))[1]["state"] != "canceled":
            await asyncio.sleep(0.5)
        phases["idle, after"] = await measure_phase(rest, health, ids, args.pollers,
                                                    args.phase_s, pid)
        control.close()
    return {"phases": phases, "render_start_s": round(start_s, 1),
            "render_passes_per_s": round((done1 - done0) / phases[
                f"K = {args.shards} rendering"]["wall_s"], 2),
            "nice_by_process": nice, "policy_by_process": policies}


def summarize(raws: list[dict], shards: int) -> dict:
    """Per request: p50 / p99 idle (both idle phases of every round pooled) and rendering
    (every round pooled), and the p99 difference; cores per phase averaged over rounds."""
    from bench.service.harness import percentiles

    busy_name = f"K = {shards} rendering"
    rows = {}
    for kind in sorted({k for r in raws for k in r["phases"][busy_name]["samples_s"]}):
        idle = [s for r in raws for name in ("idle, before", "idle, after")
                for s in r["phases"][name]["samples_s"].get(kind, [])]
        a = percentiles(idle)
        b = percentiles([s for r in raws for s in r["phases"][busy_name]["samples_s"][kind]])
        rows[kind] = {"idle": a, "rendering": b, "p99_moved_ms": round(b["p99"] - a["p99"], 2)}

    def mean(values):
        return round(sum(values) / len(values), 3)

    return {"requests": rows, "rounds": len(raws),
            "cores": {name: {"api": mean([r["phases"][name]["api_cores"] for r in raws]),
                             "render": mean([r["phases"][name]["render_cores"] for r in raws])}
                      for name in raws[0]["phases"]},
            "render_start_s": [r["render_start_s"] for r in raws],
            "render_passes_per_s": [r["render_passes_per_s"] for r in raws],
            "load_average": [r["load_average"] for r in raws],
            "nice_by_process": raws[-1]["nice_by_process"],
            "policy_by_process": raws[-1].get("policy_by_process", {})}


def worst_moved(r: dict) -> float:
    return max(v["p99_moved_ms"] for v in r["requests"].values())


def markdown(r: dict, label: str, args: dict) -> str:
    k = args["shards"]
    worst = worst_moved(r)
    ok = "met" if worst <= TARGET_MS else "**NOT met**"
    lines = [f"### {label}: a K = {k} render running vs idle ({r['rounds']} round(s), "
             f"{args['pollers']} pollers, health checks every {HEALTH_INTERVAL_S * 1e3:.0f} ms, "
             f"{args['phase_s']} s per phase)",
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
              + ". The render ran " + " / ".join(str(v) for v in r["render_passes_per_s"])
              + " passes/s once started (" + " / ".join(str(v) for v in r["render_start_s"])
              + " s to its first pass); load average per round " + ", ".join(
                  f"{a:.1f} -> {b:.1f}" for a, b in r["load_average"])
              + "; nice values: " + ", ".join(
                  f"{n} {v}" for n, v in r["nice_by_process"].items())
              + "; CPU policies: " + (", ".join(
                  f"{n} {v}" for n, v in r["policy_by_process"].items()) or "not recorded")
              + "."]
    return "\n".join(lines)


def summary_table(runs: dict[str, dict]) -> str:
    labels = list(runs)
    kinds = sorted({k for saved in runs.values() for k in saved["result"]["requests"]})
    lines = ["| p99 moved by the render, ms | " + " | ".join(labels) + " |",
             "| --- |" + " ---: |" * len(labels)]
    for kind in kinds:
        lines.append(f"| {kind} | " + " | ".join(
            f"{runs[la]['result']['requests'][kind]['p99_moved_ms']:+.1f}"
            if kind in runs[la]["result"]["requests"] else "" for la in labels) + " |")
    busy = [n for n in next(iter(runs.values()))["result"]["cores"] if "rendering" in n][0]
    lines.append("| **worst** | " + " | ".join(
        f"**{worst_moved(runs[la]['result']):+.1f}**" for la in labels) + " |")
    lines.append("| cores while rendering, API / render | " + " | ".join(
        f"{runs[la]['result']['cores'][busy]['api']:.2f} / "
        f"{runs[la]['result']['cores'][busy]['render']:.2f}" for la in labels) + " |")
    lines.append("| render passes/s | " + " | ".join(" / ".join(
        str(v) for v in runs[la]["result"]["render_passes_per_s"]) for la in labels) + " |")
    lines.append("| NPRT_* settings | " + " | ".join(
        ", ".join(f"{k}={v}" for k, v in runs[la].get("env", {}).items()) or "defaults"
        for la in labels) + " |")
    lines.append("| commit of the service | " + " | ".join(runs[la]["commit"] for la in labels)
                 + " |")
    return "\n".join(lines)


INTRO = ("## A render's effect on the API (`bench/service/bench_render_effect.py`)\n\n"
         "`python -m bench.service.bench_render_effect --shards 8 --repeat 2 --versus "
         "before=<checkout>`: 4 pollers and a health checker (REST and gRPC) for 20 s idle, "
         "20 s while a K = 8 render runs (started first, measured once it has a pass), 20 s "
         "idle after it is canceled; the same client throughout, a fresh service each round, "
         "the rounds of every label alternating. API cores count the serving processes; "
         "render cores the scheduler and everything under it (Ray, the shard workers).")

HISTORY = (
    "Earlier runs (sessions 2 and 3, saved JSON replaced): nice 10 with SCHED_BATCH moved "
    "the p99s by +160..614 ms (commit f65621d, load 4.5-6.7) and +1116..1352 ms (load 4-22), "
    "the render taking 1.7-1.8 cores and the API 0.03-0.10: with autogroups (enabled here) "
    "the kernel shares the CPU between sessions before nice orders the processes inside "
    "one, and a SCHED_BATCH task is preempted only by the cross-session fairness, not at "
    "once. The scheduler session's autogroup at nice 10 cut it to +29..79 ms but, with "
    "other sessions busy, Ray needed 255 s to start the render (one try timed out).")


def saved_runs() -> dict[str, dict]:
    """Every saved label, before and after first."""
    paths = sorted(RESULTS.glob("bench_render_effect_*.json"))
    order = {"before": 0, "after": 1}
    runs = {p.stem.removeprefix("bench_render_effect_"): json.loads(p.read_text())
            for p in paths}
    return dict(sorted(runs.items(), key=lambda kv: (order.get(kv[0], 2), kv[0])))


def findings(runs: dict[str, dict]) -> str:
    parts = []
    for label, saved in runs.items():
        r = saved["result"]
        parts.append(f"{label} {worst_moved(r):+.1f} ms")
    met = [la for la, saved in runs.items() if worst_moved(saved["result"]) <= TARGET_MS]
    return ("Worst p99 moved: " + ", ".join(parts) + f" (target <= {TARGET_MS:.0f} ms: "
            + (f"met by {', '.join(met)}" if met else "not met") + ").")


def write_readme() -> None:
    from bench.common import BENCH_README, replace_section

    runs = saved_runs()
    parts = []
    for label, saved in runs.items():
        host = saved["host"]
        table = markdown(saved["result"], label, saved["args"])
        parts.append(f"{table}\n\nRun: `{saved['command']}` (commit {saved['commit']}, "
                     f"{host['cpus']} cores shared with the client, load average "
                     f"{host['load_average_before'][0]:.1f} before, "
                     f"{host['load_average_after'][0]:.1f} after).")
    replace_section(BENCH_README, "<!-- bench_render_effect:begin -->",
                    "<!-- bench_render_effect:end -->",
                    INTRO + "\n\n" + summary_table(runs) + "\n\n" + findings(runs) + "\n\n"
                    + NOTES + "\n\n" + "\n\n".join(parts) + "\n\n" + HISTORY)


NOTES = (
    "The scheduler and everything it starts (Ray's GCS, raylet, agents and shard workers) run "
    "as SCHED_IDLE at nice 10 in the session of `nprt serve`, the API workers' "
    "(`NPRT_SCHEDULER_CPU=idle`, the default; service/priority.py): in one autogroup the "
    "kernel preempts an idle-policy task at once for a normal one that wakes and gives it "
    "the smallest weight. Across autogroups it does neither: it shares the CPU between "
    "sessions before any policy inside them counts, and a session's group is not idle "
    "however idle its tasks are. The service runs in the benchmark client's session "
    "(`harness.start_service`), as a remote client would not compete with it for CPU at "
    "all; `before` (nice 10, SCHED_BATCH, the scheduler in a session of its own) ran under "
    "the same harness. `render passes/s` is what the render got beside the API and the "
    "other work on the machine: SCHED_IDLE renders get no CPU a normal task of their "
    "session wants.")

HISTORY = (
    "Earlier runs (JSON not kept here): nice 10 with SCHED_BATCH in a session of its own "
    "moved the p99s by +160..614 ms (commit f65621d, load 4.5-6.7) and +1116..1352 ms (load "
    "4-22), the render taking 1.7-1.8 cores and the API 0.03-0.10. The scheduler session's "
    "autogroup at nice 10 cut it to +29..79 ms but, with other sessions busy, Ray needed "
    "255 s to start the render (one try timed out). In this session, before the service ran "
    "in the client's session (service and client in sessions of their own, 15:08-15:30, "
    "load 4-23, `--repeat 2`, rounds alternating): SCHED_IDLE in a session of its own "
    "+550 ms (first run) and +312 ms (`NPRT_SCHEDULER_OWN_SESSION=true`, second run), "
    "SCHED_IDLE in the API's session +143 ms, SCHED_BATCH +1089 and +980 ms: the render "
    "in the API's session no longer took the API's CPU (the API processes got 0.10 cores, "
    "not 0.03-0.05) but still took the client's, in a session of its own.")


def _round(root: Path, env: dict, args: argparse.Namespace, small: dict, long: dict) -> dict:
    load0 = os.getloadavg()[0]
    with running_service(root, 1, args.api_workers, env) as (proc, host, port, target):
        raw = asyncio.run(run(host, port, target, proc.pid, args, small, long))
    raw["load_average"] = [load0, os.getloadavg()[0]]
    return raw


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shards", type=int, default=8, help="K of the render")
    ap.add_argument("--phase-s", type=float, default=20.0, help="seconds per phase")
    ap.add_argument("--pollers", type=int, default=4, help="concurrent GET loops")
    ap.add_argument("--jobs", type=int, default=20, help="finished jobs the pollers read")
    ap.add_argument("--scene", default="forest:tiny")
    ap.add_argument("--api-workers", type=int,
                    help="nprt serve --workers (default: the service's)")
    ap.add_argument("--label", default="after", help="name of this run's results")
    ap.add_argument("--service-root", type=Path, default=REPO,
                    help="checkout whose service runs (default: this one)")
    ap.add_argument("--service-commit", help="the commit --service-root holds (for the "
                    "record; default: git rev-parse there)")
    ap.add_argument("--versus", action="append", default=[], metavar="LABEL=ROOT[@COMMIT]",
                    help="also measure the service of checkout ROOT under LABEL, rounds "
                         "alternating with this one's")
    ap.add_argument("--set", action="append", default=[], metavar="LABEL:NAME=VALUE",
                    help="start LABEL's service with the environment variable NAME=VALUE")
    ap.add_argument("--repeat", type=int, default=1, help="rounds per label")
    ap.add_argument("--smoke", action="store_true",
                    help="K = 2, 1 s phases, 2 jobs; writes nothing under bench/results")
    args = ap.parse_args(argv)
    if args.smoke:
        args.shards, args.phase_s, args.jobs, args.pollers = 2, 1.0, 2, 1
    services = {args.label: (args.service_root, args.service_commit, {})}
    for spec in args.versus:
        label, _, rest = spec.partition("=")
        root, _, commit = rest.partition("@")
        if not re.fullmatch(r"[a-z0-9_]+", label) or not root or label in services:
            ap.error(f"--versus {spec}: want LABEL=ROOT[@COMMIT], a new LABEL of [a-z0-9_]")
        services[label] = (Path(root), commit or None, {})
    for spec in args.set:
        label, _, setting = spec.partition(":")
        name, eq, value = setting.partition("=")
        if label not in services or not eq or not name:
            ap.error(f"--set {spec}: want LABEL:NAME=VALUE, LABEL one of {list(services)}")
        services[label][2][name] = value
    small = {"scene": args.scene, "width": 16, "height": 16, "spp": 1, "bounces": 1}
    # Outlasts the phase (canceled after it): 128x128 in 4 tiles, 2 spp a pass.
    long = {"scene": args.scene, "width": 128, "height": 128, "spp": 16384, "tile_size": 64,
            "spp_per_pass": 2, "bounces": 2, "shards": args.shards}
    load_before = os.getloadavg()
    rounds: dict[str, list] = {label: [] for label in services}
    for _ in range(args.repeat):
        for label, (root, _, env) in services.items():
            rounds[label].append(_round(root, env, args, small, long))
    shown = {k: v for k, v in vars(args).items()
             if k not in ("service_root", "service_commit", "versus", "set")}
    command = "python -m bench.service.bench_render_effect " + " ".join(
        a if "/" not in a else re.sub(r"/\S*", "<checkout>", a) for a in (argv or sys.argv[1:]))
    for label, (root, commit, env) in services.items():
        result = summarize(rounds[label], args.shards)
        table = markdown(result, label, shown)
        print(table)
        if args.smoke:
            continue
        commit = commit or subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root,
                                          capture_output=True, text=True).stdout.strip()
        out = RESULTS / f"bench_render_effect_{label}.json"
        out.parent.mkdir(parents=True, exist_ok=True)
        out.write_text(json.dumps({"result": result, "args": shown, "env": env,
                                   "commit": commit, "command": command.strip(),
                                   "host": {"cpus": os.cpu_count(),
                                            "python": platform.python_version(),
                                            "load_average_before": load_before,
                                            "load_average_after": os.getloadavg()},
                                   "markdown": table}, indent=1))
        print(f"\nwrote {out}")
    if not args.smoke:
        write_readme()
    return 0


if __name__ == "__main__":
    sys.exit(main())
