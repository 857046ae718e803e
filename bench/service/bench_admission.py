"""CPU per request through the ASGI app of one API worker, in process (no HTTP parsing, no
client in the figure): POST /v1/jobs one at a time and as a burst of concurrent ones, the
polled reads, and GET /healthz as the floor of any request. Process CPU includes the
writer thread that stores the jobs and the event feed.

    python -m bench.service.bench_admission [--requests 2000] [--smoke]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import os
import tempfile
import time
from pathlib import Path

from bench.common import RESULTS
from nprt.service.app import create_app
from nprt.service.config import ServiceSettings

JOB = {"scene": "forest:tiny", "width": 32, "height": 32, "spp": 2}
WARMUP = 50


async def _call(app, method: str, path: str, body: bytes = b"") -> int:
    """One request straight into the ASGI app; returns the status code."""
    path, _, query = path.partition("?")
    scope = {"type": "http", "method": method, "path": path, "raw_path": path.encode(),
             "query_string": query.encode(), "http_version": "1.1", "scheme": "http",
             "headers": [(b"content-type", b"application/json"), (b"host", b"bench")],
             "server": ("bench", 80), "client": ("bench", 1), "root_path": ""}
    sent = False
    status = []

    async def receive():
        nonlocal sent
        if not sent:
            sent = True
            return {"type": "http.request", "body": body, "more_body": False}
        await asyncio.Event().wait()  # the app never reads past the body

    async def send(message):
        if message["type"] == "http.response.start":
            status.append(message["status"])

    await app(scope, receive, send)
    return status[0]


async def _measure(n: int) -> dict:
    data = Path(tempfile.mkdtemp(prefix="nprt-admission-"))
    app = create_app(ServiceSettings(data_dir=data, max_queued_jobs=3 * n + WARMUP + 500,
                                     api_token=None))
    body = json.dumps(JOB).encode()
    out = {}
    async with app.router.lifespan_context(app):
        for _ in range(WARMUP):
            assert await _call(app, "POST", "/v1/jobs", body) == 202
        job_id = app.state.api.list(0, 1)[0][0].id
        for name, method, path, payload, want in (
                ("GET /healthz", "GET", "/healthz", b"", 200),
                ("GET /v1/jobs/{id}", "GET", f"/v1/jobs/{job_id}", b"", 200),
                ("GET /v1/jobs?limit=20", "GET", "/v1/jobs?limit=20", b"", 200),
                ("POST /v1/jobs", "POST", "/v1/jobs", body, 202),
                ("POST /v1/jobs, a burst of 500", "POST", "/v1/jobs", body, 202)):
            burst = 500 if "burst" in name else 1
            c0, t0 = time.process_time(), time.perf_counter()
            for _ in range(max(1, n // burst)):
                codes = await asyncio.gather(*(_call(app, method, path, payload)
                                               for _ in range(burst)))
                assert set(codes) == {want}, codes
            done = max(1, n // burst) * burst
            out[name] = {"cpu_ms": round((time.process_time() - c0) / done * 1e3, 4),
                         "wall_ms": round((time.perf_counter() - t0) / done * 1e3, 4)}
    return out


def markdown(r: dict, n: int) -> str:
    lines = [f"CPU per request through one API worker's ASGI app, in process, {n} requests "
             "each (`python -m bench.service.bench_admission`):", "",
             "| request | CPU ms | wall ms |", "| --- | ---: | ---: |"]
    lines += [f"| {k} | {v['cpu_ms']} | {v['wall_ms']} |" for k, v in r.items()]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--requests", type=int, default=2000)
    ap.add_argument("--smoke", action="store_true", help="20 requests; writes nothing")
    args = ap.parse_args(argv)
    n = 20 if args.smoke else args.requests
    result = asyncio.run(_measure(n))
    table = markdown(result, n)
    print(table)
    if args.smoke:
        return 0
    load = os.getloadavg()
    RESULTS.mkdir(parents=True, exist_ok=True)
    (RESULTS / "bench_admission.json").write_text(json.dumps(
        {"result": result, "requests": n, "job": JOB, "load_average": load}, indent=1))
    write_readme()
    return 0


def write_readme() -> None:
    """The bench/README.md section from the saved result."""
    from bench.common import BENCH_README, replace_section

    saved = json.loads((RESULTS / "bench_admission.json").read_text())
    load = saved["load_average"]
    replace_section(BENCH_README, "<!-- bench_admission:begin -->",
                    "<!-- bench_admission:end -->",
                    f"{markdown(saved['result'], saved['requests'])}\n\nLoad average "
                    f"{load[0]:.1f} during the run (2 shared cores). "
                    "An admission parses the body with pydantic, stores the job on the "
                    "writer thread (an O(1) insert: the queue depth is a counter; a burst's "
                    "admissions share commits) and answers; the polled reads (one job, a "
                    "page of the list) and /healthz are answered before FastAPI's routing, "
                    "and a stored job's settings are validated once per distinct settings. "
                    "The worker freezes its start-up objects out of the garbage collector's "
                    "reach. HTTP parsing by uvicorn adds to every row alike.")


if __name__ == "__main__":
    raise SystemExit(main())
