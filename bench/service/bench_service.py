"""Service load benchmark: a burst of concurrent job submissions while SSE watchers and
gRPC WatchJob streams follow running jobs (one of them a K = 2 render) and clients poll.
Checks every job is accepted once and completed, and reports p50 / p99 per route and for
gRPC health during the burst, plus the CPU of the API processes and of this load
generator. The REST client is bench.service.rawhttp: client and service share the
machine, and aiohttp spent more CPU per request than the service did; every client process
runs on uvloop (harness.run_client). The watchers, and the pollers with the health prober,
run in processes of their own (bench.service.clientroles).

    python -m bench.service.bench_service [--label after] [--jobs 500] [--smoke]
    python -m bench.service.bench_service --label before --service-root /tmp/before
    python -m bench.service.bench_service --repeat 3 --versus before=/tmp/before@abc1234

--service-root runs the service of another checkout (the commit before a change) with this
client, so "before" and "after" are measured the same way; --versus measures another
checkout in the same run, round for round in turn with this one. --profile DIR writes py-spy
stacks of every API process and of the client over the burst.
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
import uuid
from collections import defaultdict
from pathlib import Path

from bench.common import RESULTS
from bench.service.clientroles import Readers, Watchers
from bench.service.harness import (
    REPO,
    Latency,
    Rest,
    api_cpu_s,
    http_workers,
    niceness,
    percentiles,
    run_client,
    running_service,
    start_profilers,
    stop_profilers,
)
from bench.service.rawhttp import request_bytes
from nprt.protos import nprt_pb2 as pb

TERMINAL = {"succeeded", "failed", "canceled"}
HEALTH_INTERVAL_S = 0.02
POLL_PAUSE_S = 0.005
LABELS = ("before", "after", "after_2_workers")
_EVENT = re.compile(rb"event: (\w+)\r\n")


async def sse_watch(rest: Rest, job_id: str, counts: dict) -> None:
    """Follow one job's SSE stream to its `end` event, counting events by name."""
    conn = rest.connection()
    ended = asyncio.get_running_loop().create_future()
    tail = b""

    def on_chunk(data: bytes) -> None:
        nonlocal tail
        data = tail + data
        cut = data.rfind(b"\n") + 1  # whole lines only; the rest waits for the next chunk
        tail = data[cut:]
        for name in _EVENT.findall(data[:cut]):
            counts[name.decode()] += 1
            if name == b"end" and not ended.done():
                ended.set_result(None)

    head = await conn.stream(request_bytes("GET", f"/v1/jobs/{job_id}/events", rest.host),
                             on_chunk)
    counts["opened"] += head.status == 200
    await asyncio.wait([ended, asyncio.ensure_future(conn.closed())],
                       return_when=asyncio.FIRST_COMPLETED)
    conn.close()
    counts["closed"] += 1


async def grpc_watch(stub, job_id: str, counts: dict) -> None:
    counts["opened"] += 1
    async for ev in stub.WatchJob(pb.WatchJobRequest(job_id=job_id,
                                                     tile_format=pb.TILE_FORMAT_RGB_F32)):
        counts[ev.WhichOneof("event")] += 1
    counts["closed"] += 1


async def list_all(rest: Rest, conn) -> list[dict]:
    jobs, offset = [], 0
    while True:
        _, page, _ = await rest.call(conn, "GET", "/v1/jobs",
                                     params={"limit": 500, "offset": offset})
        jobs += page["data"]
        offset += len(page["data"])
        if not page["data"] or offset >= page["count"]:
            return jobs


async def run(host: str, port: int, target: str, pid: int, args: argparse.Namespace,
              job: dict, watched: list[dict]) -> dict:
    lat = Latency()
    refused: dict = defaultdict(int)
    rest = Rest(host, port)
    control = rest.connection()
    # Long jobs already rendering (one of them sharded), watched by every stream, so the
    # burst lands on a busy service that fans tiles out; canceled after the burst. The
    # watchers, and the pollers with the health prober, are clients of their own
    # (clientroles): processes beside this one, which only submits.
    warm = [(await rest.call(control, "POST", "/v1/jobs", w))[1]["id"] for w in watched]
    watchers = Watchers(host, port, target, warm, args.sse_watchers, args.grpc_streams)
    # Steady state: every stream open and every long job streaming tiles (the sharded
    # one once Ray and its shards are up).
    while True:
        running = [(await rest.call(control, "GET", f"/v1/jobs/{j}"))[1] for j in warm]
        sse_counts, grpc_counts = watchers.counts()
        if (sse_counts.get("opened", 0) + grpc_counts.get("opened", 0)
                == args.sse_watchers + args.grpc_streams
                and all(r["passes_done"] > 0 for r in running)):
            break
        await asyncio.sleep(0.2)
    ids: list[str] = list(warm)

    async def submit() -> tuple[int, dict]:
        """One submission on a connection of its own, honouring Retry-After; its
        latency is the first answer's."""
        conn = rest.connection()
        key = {"Idempotency-Key": uuid.uuid4().hex}
        t0 = time.perf_counter()
        status, body, after = await rest.call(conn, "POST", "/v1/jobs", job, key)
        lat.samples_s["POST /v1/jobs"].append(time.perf_counter() - t0)
        while status in (429, 503) and after is not None:
            refused[status] += 1
            await asyncio.sleep(after)
            status, body, after = await rest.call(conn, "POST", "/v1/jobs", job, key)
        conn.close()
        return status, body

    readers = Readers(host, port, target, ids, args.pollers, POLL_PAUSE_S, HEALTH_INTERVAL_S)
    await readers.start()
    profilers = [] if args.profile is None else start_profilers(pid, args.profile)
    await asyncio.sleep(0.5)  # pollers and health running before the burst
    cpu0, client0 = api_cpu_s(pid), time.process_time()
    t_burst = time.perf_counter()
    burst = await asyncio.gather(*(submit() for _ in range(args.jobs)))
    burst_s = time.perf_counter() - t_burst
    cpu1, client1 = api_cpu_s(pid), time.process_time()
    stop_profilers(profilers)
    sse_counts, grpc_counts = watchers.counts()
    open_after_burst = {"sse": sse_counts["opened"] - sse_counts["closed"],
                        "grpc": grpc_counts["opened"] - grpc_counts["closed"]}
    nice = niceness(pid)
    for kind, samples in (await readers.stop()).items():
        lat.samples_s[kind] += samples
    for job_id in warm:
        await rest.call(control, "POST", f"/v1/jobs/{job_id}/cancel")
    statuses = [status for status, _ in burst]
    accepted = [body for status, body in burst if status == 202]
    ids += [j["id"] for j in accepted]

    t_drain = time.perf_counter()
    while True:
        jobs = await list_all(rest, control)
        states = {j["id"]: j["state"] for j in jobs}
        if all(states.get(i) in TERMINAL for i in ids):
            break
        await asyncio.sleep(0.5)
    drain_s = time.perf_counter() - t_drain
    sse_counts, grpc_counts = await watchers.wait()
    post_cpu_ms = await sequential_post_cpu_ms(rest, control, pid, job, args.cpu_posts)
    control.close()

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
        "client_cpu_s_during_burst": round(client1 - client0, 2),
        "api_cpu_ms_per_sequential_post": post_cpu_ms,
        "streams_open_after_burst": open_after_burst,
        "client_retries_after_idle_disconnect": rest.retries,
        "nice_by_process": nice, "api_workers": http_workers(pid),
        "sse_events": dict(sse_counts), "grpc_events": dict(grpc_counts),
        "latency_ms": lat.summary(), "_samples_s": dict(lat.samples_s),
    }


async def sequential_post_cpu_ms(rest: Rest, conn, pid: int, job: dict, n: int) -> float:
    """The serving processes' CPU per POST /v1/jobs, one request at a time, each job
    canceled at once so nothing renders in between (the cancels are timed apart)."""
    posts = 0.0
    for _ in range(n):
        c0 = api_cpu_s(pid)
        _, body, _ = await rest.call(conn, "POST", "/v1/jobs", job)
        posts += api_cpu_s(pid) - c0
        await rest.call(conn, "POST", f"/v1/jobs/{body['id']}/cancel")
    return round(posts / n * 1e3, 3)


def pool(rounds: list[dict]) -> dict:
    """One result from several rounds (each on a fresh service): counts summed, latency
    percentiles over every round's samples, CPU and times as medians, and each round's
    p99s and load average kept."""
    import statistics

    out = {k: sum(r[k] for r in rounds) for k in ("submitted", "accepted_202", "lost",
                                                  "duplicated", "succeeded")}
    out["other_statuses"] = sorted({s for r in rounds for s in r["other_statuses"]})
    out["api_workers"] = max(r.get("api_workers", 1) for r in rounds)
    refused: dict = defaultdict(int)
    for r in rounds:
        for status, n in r["refused_then_retried"].items():
            refused[status] += n
    out["refused_then_retried"] = dict(refused)
    for k in ("burst_s", "drain_s", "api_cpu_s_during_burst", "client_cpu_s_during_burst",
              "api_cpu_ms_per_sequential_post"):
        out[k] = round(statistics.median(r[k] for r in rounds), 3)
    out["streams_open_after_burst"] = {k: min(r["streams_open_after_burst"][k]
                                              for r in rounds) for k in ("sse", "grpc")}
    samples: dict = defaultdict(list)
    for r in rounds:
        for kind, v in r.pop("_samples_s").items():
            samples[kind] += v
    out["latency_ms"] = {k: percentiles(v) for k, v in sorted(samples.items())}
    out["rounds"] = rounds
    return out


def _worst_p99(lat: dict, kinds: tuple[str, ...]) -> float:
    return max(lat[k]["p99"] for k in kinds if k in lat)


_GETS = ("GET /v1/jobs", "GET /v1/jobs/{id}")
_HEALTH = ("GET /healthz", "gRPC Health.Check")


def markdown(r: dict, label: str, args: dict) -> str:
    lat = r["latency_ms"]
    post = lat["POST /v1/jobs"]["p99"]
    gets = _worst_p99(lat, _GETS)
    health = _worst_p99(lat, _HEALTH)
    rounds = r.get("rounds", [])

    def verdict(ok: bool) -> str:
        return "met" if ok else "**NOT met**"

    per_round = r["submitted"] // max(1, len(rounds))
    workers = r.get("api_workers", args["api_workers"])
    lines = [f"### {label}: {per_round} concurrent submissions, {args['sse_watchers']} SSE"
             f" watchers, {args['grpc_streams']} gRPC WatchJob streams, a K = "
             f"{args['long_shards']} render running ({args['scene']}, {workers} "
             f"API worker(s)){f', {len(rounds)} rounds pooled' if len(rounds) > 1 else ''}",
             "",
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
             f"| submitting client CPU during the burst | "
             f"{r.get('client_cpu_s_during_burst', '-')} s | |",
             f"| API CPU per POST, one at a time | {r['api_cpu_ms_per_sequential_post']} ms "
             "| < 1 ms |",
             f"| drain time | {r['drain_s']} s | |", "",
             "| request (during the burst) | n | p50 ms | p99 ms | max ms |",
             "| --- | ---: | ---: | ---: | ---: |"]
    for kind, p in lat.items():
        lines.append(f"| {kind} | {p['n']} | {p['p50']} | {p['p99']} | {p['max']} |")
    if len(rounds) > 1:
        lines += ["", "Each round's p99 (POST / worst GET / worst health, ms) and load "
                  "average before, after: " + "; ".join(
                      f"{x['latency_ms']['POST /v1/jobs']['p99']:.0f} / "
                      f"{_worst_p99(x['latency_ms'], _GETS):.0f} / "
                      f"{_worst_p99(x['latency_ms'], _HEALTH):.0f} at load "
                      f"{x['load_average'][0]:.1f}, {x['load_average'][1]:.1f}"
                      for x in rounds) + "."]
    return "\n".join(lines)


def summary_table(runs: dict[str, dict]) -> str:
    """The saved runs side by side: the targets' figures and the CPU behind them."""
    rows = [("POST /v1/jobs p99 (target < 200 ms)",
             lambda r: r["latency_ms"]["POST /v1/jobs"]["p99"]),
            ("worst GET p99 (target < 100 ms)", lambda r: _worst_p99(r["latency_ms"], _GETS)),
            ("GET /healthz p99 (target < 50 ms)",
             lambda r: r["latency_ms"]["GET /healthz"]["p99"]),
            ("gRPC Health.Check p99 (target < 50 ms)",
             lambda r: r["latency_ms"]["gRPC Health.Check"]["p99"]),
            ("POST /v1/jobs p50", lambda r: r["latency_ms"]["POST /v1/jobs"]["p50"]),
            ("burst wall time, s", lambda r: r["burst_s"]),
            ("API processes' CPU during the burst, s", lambda r: r["api_cpu_s_during_burst"]),
            ("... over the burst's wall time, cores",
             lambda r: round(r["api_cpu_s_during_burst"] / r["burst_s"], 2)),
            ("submitting client's CPU during the burst, s",
             lambda r: r.get("client_cpu_s_during_burst", "-")),
            ("lost / duplicated", lambda r: f"{r['lost']} / {r['duplicated']}")]
    labels = list(runs)
    lines = ["| ms unless noted | " + " | ".join(labels) + " |",
             "| --- |" + " ---: |" * len(labels)]
    for name, get in rows:
        lines.append(f"| {name} | " + " | ".join(str(get(runs[k]["result"])) for k in labels)
                     + " |")
    lines.append("| load average before, after | " + " | ".join(
        f"{runs[k]['host']['load_average_before'][0]:.1f}, "
        f"{runs[k]['host']['load_average_after'][0]:.1f}" for k in labels) + " |")
    lines.append("| NPRT_* settings | " + " | ".join(", ".join(
        f"{n}={v}" for n, v in runs[k].get("env", {}).items()) or "defaults" for k in labels)
        + " |")
    lines.append("| commit of the service | " + " | ".join(runs[k]["commit"] for k in labels)
                 + " |")
    return "\n".join(lines)


def findings(runs: dict[str, dict]) -> str:
    """What the saved runs show, in words (figures read from them)."""
    if not {"before", "after"} <= runs.keys():
        return ""

    def post(r, q="p99"):
        return f"{r['latency_ms']['POST /v1/jobs'][q]:.0f}"

    def met(r) -> str:
        lat = r["latency_ms"]
        return ", ".join(name for name, ok in (
            ("POST p99 < 200 ms", lat["POST /v1/jobs"]["p99"] < 200),
            ("GET p99 < 100 ms", _worst_p99(lat, _GETS) < 100),
            ("health p99 < 50 ms", _worst_p99(lat, _HEALTH) < 50)) if ok) or "none"

    loads = [v for saved in runs.values() for x in saved["result"].get("rounds", [])
             for v in x["load_average"]]
    text = []
    for label, saved in runs.items():
        r = saved["result"]
        best = min(x["latency_ms"]["POST /v1/jobs"]["p99"] for x in r.get("rounds", [r]))
        text.append(f"{label} ({r.get('api_workers', 1)} API worker(s)): POST p99 {post(r)} ms "
                    f"(p50 {post(r, 'p50')}, best round {best:.0f}), worst GET p99 "
                    f"{_worst_p99(r['latency_ms'], _GETS):.0f} ms, worst health p99 "
                    f"{_worst_p99(r['latency_ms'], _HEALTH):.0f} ms, API CPU over the burst "
                    f"{r['api_cpu_s_during_burst']} s; targets met pooled: {met(r)}")
    return ("; ".join(text) + f". Load average {min(loads):.0f} to {max(loads):.0f} over the "
            "rounds (other work on the 2 cores). One event loop admits a burst's requests in "
            "turn, so the last waits for the CPU of all of them, and a health check or a "
            "read waits behind them; two HTTP workers (what `nprt serve` runs by default on "
            "a host with 2 or more cores) split the burst between two loops.")


SESSION8 = (
    "Issue 24, eighth session: the CPU of an admission cut, measured over sockets by "
    "`bench_burst_cpu` (section below; on-CPU ns of every API thread, 3,000 burst POSTs a "
    "round, under the bench lock, load 2-3.5): 221.5 -> 170.8 us an admission, of which "
    "the admission itself (less a GET /healthz on a new connection, the floor) 123.8 -> 81.7 "
    "us. The job body is validated once and its settings stored as the JSON text "
    "RenderSettings' serializer writes (no second model, no model_dump + json.dumps), the "
    "202 body is written from the stored row (equal byte for byte to JobPublic's, tested), "
    "the API workers collect young objects every 50,000 allocations instead of 700 (the "
    "requests in flight set off a collection every few admissions: 11-14 us of CPU each, "
    "in process), uvicorn no longer formats access lines that WARNING drops, and the gRPC "
    "child runs on uvloop (213-223 against 240 us of CPU per Health.Check). In the run of "
    "the tables above (21:30-21:35, load 2.3-4.0, this session's service against 5315b43's, "
    "rounds alternating) the API's CPU over the burst fell from 0.17 to 0.12 s and POST p99 "
    "from 216 to 127 ms (rounds 150 / 216 / 131 against 127 / 128 / 104). The tick-counted "
    "'API CPU per POST, one at a time' (100 POSTs, 10 ms ticks) read 0.3 before and 0.5 "
    "after in this run: too coarse to compare (0.2-1.0 between rounds of one service in the "
    "seventh session); in process one at a time costs 177-197 us after against 208-284 "
    "before (diagnostic, unlocked).")


WORKERS = (
    "One API worker against two, same code, the same client, one locked run with `before` "
    "(15:45-15:50, load 7-21; `--repeat 2 --set after:NPRT_API_WORKERS=1 --versus "
    "after_2_workers=<checkout> --set after_2_workers:NPRT_API_WORKERS=2`; JSON replaced by "
    "the run above): POST / worst GET / /healthz / gRPC health p99 with one worker 861 / "
    "105 / 347 / 74 ms (rounds' POST 366 and 861, the second at a load spike), with two "
    "240 / 30 / 35 / 33 ms (rounds 163 and 240), `before` 430 / 100 / 92 / 45 ms: why "
    "`nprt serve` runs two HTTP workers by default on 2 or more cores.")


SESSION7 = (
    "Issue 24, seventh session (commands and logs in the session's notes, every run under "
    "the bench lock). With every client process on uvloop the previous service (a7cf400) "
    "met all three latency targets in a run at load 4-13 (18:32-18:36, rounds alternating "
    "with a service that paced its admissions): POST / worst GET / worst health p99 178 / "
    "27 / 38 ms, POST rounds 178, 115 and 112 ms: the submitting client's own CPU had been "
    "part of the latency measured before. The service changed in three ways: each HTTP "
    "worker listens on a socket of its own (SO_REUSEPORT, `service/httpworkers.py`; with "
    "uvicorn's one shared socket one worker of two spent 58-69 % of the API's CPU in a "
    "burst), job ids come from a batch of random bytes (os.urandom let the GIL go on every "
    "id), and a job body's settings are not validated twice. Pacing the admissions over the "
    "event loop's turns, so that /healthz would not wait behind a burst's 15-30 ms turn, was "
    "measured and reverted: POST p99 346 ms against 178 for a7cf400 in that run, API CPU over "
    "the burst 0.27 s against 0.14 (paced admissions reached the store writer a few at a "
    "time: smaller commits). On a quiet machine (load 1.3-2.6, one round each, twice; no "
    "saved JSON) POST p99 was 137 and 122 ms for a7cf400 and 147 and 110 ms for the service "
    "without pacing, health p99 6-34 ms for both. The run in the tables above (load 3.4 to "
    "30) shows what other work on the 2 cores does to either: rounds during which the load "
    "reached 16-30 took "
    "195-467 ms; the changes' effect on POST latency is smaller than that spread.")


def write_readme() -> None:
    """The README section from the saved results of every label."""
    from bench.common import BENCH_README, replace_section

    parts, runs = [], {}
    for label in LABELS:
        path = RESULTS / f"bench_service_{label}.json"
        if path.exists():
            saved = runs[label] = json.loads(path.read_text())
            host = saved["host"]
            table = markdown(saved["result"], label, saved["args"])  # this script's layout
            parts.append(f"{table}\n\nRun: `{saved['command']}` (commit "
                         f"{saved['commit']}, {host['cpus']} cores shared with the client, "
                         f"load average {host['load_average_before'][0]:.1f} before, "
                         f"{host['load_average_after'][0]:.1f} after).")
    replace_section(BENCH_README, "<!-- bench_service:begin -->", "<!-- bench_service:end -->",
                    "## Service under load (`bench/service/bench_service.py`)\n\n"
                    "`python -m bench.service.bench_service --label after --repeat 3` "
                    "(`results/bench_service_after.json`; `--label before --service-root "
                    "<checkout>` measures another commit with the same client, `--versus "
                    "before=<checkout>` in the same run, rounds alternating): starts "
                    "`nprt serve` on loopback, starts two long jobs (one reference, one "
                    "K = 2) and opens the SSE and gRPC watchers on them, then fires the "
                    "submissions at once, each on a new connection with its own "
                    "Idempotency-Key, honouring Retry-After, while pollers list and read jobs "
                    "and a prober checks `/healthz` and gRPC health; cancels the long jobs, "
                    "waits for every job and audits the job list. Each round starts a fresh "
                    "service; the latencies of all rounds are pooled. API CPU counts the "
                    "serving processes, not the scheduler or its renders. The REST client is "
                    "`bench/service/rawhttp.py` (prebuilt HTTP/1.1 requests on asyncio "
                    "protocols): with aiohttp the load generator's event loop was busy 88 % "
                    "of the burst (py-spy, `--profile`), most of it opening connections, and "
                    "it delayed the requests more than the service did. The watchers, and "
                    "the pollers with the prober, are processes of their own beside the "
                    "submitting one (`bench/service/clientroles.py`), as a dashboard and a "
                    "health probe are in deployment: while they shared its event loop (up "
                    "to commit 4567def), a health check's answer waited behind hundreds of "
                    "POST answers and watcher tiles in the load generator, and that wait "
                    "counted as the service's latency; figures from before are not "
                    "comparable with these. Every client process runs on uvloop (since "
                    "issue 24's seventh session): on asyncio's own loop the submitting "
                    "client spent 0.10 s of CPU on a burst, on uvloop about 0.055 s, CPU "
                    "that the service, on the same 2 cores, lost to its client; the "
                    "service's costs are the same either way, and `before` and `after` "
                    "are measured with the same client.\n\n"
                    + summary_table(runs) + "\n\n" + findings(runs) + "\n\n" + SESSION8
                    + "\n\n" + SESSION7
                    + "\n\n" + WORKERS
                    + "\n\n"
                    + "\n\n".join(parts))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--label", choices=LABELS, default="after")
    ap.add_argument("--service-root", type=Path, default=REPO,
                    help="checkout whose service runs (default: this one)")
    ap.add_argument("--service-commit", help="the commit --service-root holds (for the "
                    "record; default: git rev-parse there)")
    ap.add_argument("--repeat", type=int, default=1,
                    help="rounds, each on a fresh service; latencies pooled")
    ap.add_argument("--versus", action="append", default=[], metavar="LABEL=ROOT[@COMMIT]",
                    help="also measure the service of checkout ROOT under LABEL, its rounds "
                         "alternating with this one's (before/after under the same load)")
    ap.add_argument("--set", action="append", default=[], metavar="LABEL:NAME=VALUE",
                    help="start LABEL's service with the environment variable NAME=VALUE "
                         "(an NPRT_* setting, e.g. NPRT_API_WORKERS=2)")
    ap.add_argument("--jobs", type=int, default=500, help="concurrent submissions")
    ap.add_argument("--sse-watchers", type=int, default=100)
    ap.add_argument("--grpc-streams", type=int, default=40)
    ap.add_argument("--max-jobs", type=int, default=2, help="job slots of the scheduler")
    ap.add_argument("--api-workers", type=int,
                    help="nprt serve --workers (default: the service's)")
    ap.add_argument("--pollers", type=int, default=4, help="concurrent GET loops")
    ap.add_argument("--cpu-posts", type=int, default=100,
                    help="sequential POSTs for the CPU-per-POST figure")
    ap.add_argument("--long-shards", type=int, default=2,
                    help="K of the long sharded render running during the burst")
    ap.add_argument("--scene", default="forest:tiny")
    ap.add_argument("--profile", type=Path, metavar="DIR",
                    help="py-spy each API worker over the burst (collapsed stacks in DIR)")
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

    # (label, service root, commit): this run's, then every --versus one; their rounds
    # alternate, so load from other work drifts over all of them alike.
    services = [(args.label, args.service_root, args.service_commit)]
    for spec in args.versus:
        label, _, rest = spec.partition("=")
        root, _, commit = rest.partition("@")
        if label not in LABELS or not root:
            ap.error(f"--versus {spec}: want LABEL=ROOT[@COMMIT], LABEL one of {LABELS}")
        services.append((label, Path(root), commit or None))
    envs: dict[str, dict[str, str]] = {label: {} for label, _, _ in services}
    for spec in args.set:
        label, _, setting = spec.partition(":")
        name, eq, value = setting.partition("=")
        if label not in envs or not eq or not name:
            ap.error(f"--set {spec}: want LABEL:NAME=VALUE, LABEL one of {list(envs)}")
        envs[label][name] = value
    load_before = os.getloadavg()
    rounds: dict[str, list] = {label: [] for label, _, _ in services}
    for _ in range(args.repeat):
        for label, root, _ in services:
            rounds[label].append(_round(root, envs[label], args, job, watched))
    shown = {k: v for k, v in vars(args).items()
             if k not in ("service_root", "profile", "versus", "set")}
    ok = True
    for label, root, commit in services:
        result = pool(rounds[label])
        table = markdown(result, label, shown)
        print(table)
        ok &= (result["succeeded"] == result["accepted_202"] == args.jobs * args.repeat
               and result["lost"] == 0 and result["duplicated"] == 0)
        if not args.smoke:
            _save(label, root, commit, result, table, job, watched, shown, load_before, argv,
                  envs[label])
    if not args.smoke:
        write_readme()
    return 0 if ok else 1


def _round(root: Path, env: dict, args: argparse.Namespace, job: dict, watched: list[dict]
           ) -> dict:
    """One round on a fresh service of the checkout at root, with NPRT_* settings env."""
    load0 = os.getloadavg()[0]
    with running_service(root, args.max_jobs, args.api_workers, env) as (proc, host, port,
                                                                         target):
        one = run_client(run(host, port, target, proc.pid, args, job, watched))
    one["load_average"] = [load0, os.getloadavg()[0]]
    return one


def _save(label: str, root: Path, commit: str | None, result: dict, table: str, job: dict,
          watched: list[dict], shown: dict, load_before: tuple, argv, env: dict) -> None:
    commit = commit or subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=root,
                                      capture_output=True, text=True).stdout.strip()
    out = RESULTS / f"bench_service_{label}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    command = "python -m bench.service.bench_service " + " ".join(
        a if "/" not in a else re.sub(r"/\S*", "<checkout>", a) for a in (argv or sys.argv[1:]))
    out.write_text(json.dumps({"result": result, "job": job, "watched_jobs": watched,
                               "args": {k: str(v) for k, v in shown.items()},
                               "commit": commit, "env": env, "command": command.strip(),
                               "host": {"cpus": os.cpu_count(),
                                        "python": platform.python_version(),
                                        "platform": platform.platform(),
                                        "load_average_before": load_before,
                                        "load_average_after": os.getloadavg()},
                               "markdown": table}, indent=1))
    print(f"\nwrote {out}")


if __name__ == "__main__":
    sys.exit(main())
