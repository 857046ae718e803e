"""CPU per admission: POST /v1/jobs through the ASGI app of one API worker, in process
(no HTTP parsing, no client in the figure), against GET /healthz as the floor of any
request. Process CPU includes the writer thread that stores the job and the event feed.

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
    scope = {"type": "http", "method": method, "path": path, "raw_path": path.encode(),
             "query_string": b"", "http_version": "1.1", "scheme": "http",
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
    app = create_app(ServiceSettings(data_dir=data, max_queued_jobs=n + WARMUP + 1,
                                     api_token=None))
    body = json.dumps(JOB).encode()
    out = {}
    async with app.router.lifespan_context(app):
        for _ in range(WARMUP):
            assert await _call(app, "POST", "/v1/jobs", body) == 202
        for name, method, path, payload, want in (
                ("GET /healthz", "GET", "/healthz", b"", 200),
                ("POST /v1/jobs", "POST", "/v1/jobs", body, 202)):
            c0, t0 = time.process_time(), time.perf_counter()
            for _ in range(n):
                assert await _call(app, method, path, payload) == want
            out[name] = {"cpu_ms": round((time.process_time() - c0) / n * 1e3, 4),
                         "wall_ms": round((time.perf_counter() - t0) / n * 1e3, 4)}
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
    from bench.common import BENCH_README, replace_section

    replace_section(BENCH_README, "<!-- bench_admission:begin -->",
                    "<!-- bench_admission:end -->",
                    f"{table}\n\nLoad average {load[0]:.1f} during the run (2 shared cores). "
                    "An admission parses the body with pydantic, stores the job on the "
                    "writer thread (an O(1) insert: the queue depth is a counter) and "
                    "answers; HTTP parsing by uvicorn adds to both rows alike.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
