"""API workers that share one store: a job stored through one is seen, watched and
canceled through another; a burst past the queue depth is refused with Retry-After and
loses nothing it accepted."""

from __future__ import annotations

import threading
import uuid

import httpx

from nprt.service.client import Client
from nprt.service.scheduler import Scheduler
from tests.service.helpers import BLOCKER, TINY, LiveServer, settings_for, sse_events, wait_for

FAST = {**TINY, "width": 8, "height": 8, "spp": 1, "tile_size": 8, "spp_per_pass": 1}


def test_job_submitted_through_one_worker_is_seen_watched_and_canceled_through_another(
        tmp_path):
    settings = settings_for(tmp_path, max_concurrent_jobs=1)
    with LiveServer(settings) as a, LiveServer(settings, scheduler=False) as b, \
            httpx.Client(base_url=a.url, timeout=30.0) as ca, \
            httpx.Client(base_url=b.url, timeout=30.0) as cb:
        key = {"Idempotency-Key": uuid.uuid4().hex}
        body = {"scene": "forest:tiny", **BLOCKER}
        job = ca.post("/v1/jobs", json=body, headers=key).json()
        again = cb.post("/v1/jobs", json=body, headers=key)  # a retry landing on B
        assert again.status_code == 202 and again.json()["id"] == job["id"]
        assert again.headers["idempotent-replayed"] == "true"
        assert cb.get(f"/v1/jobs/{job['id']}").json()["scene"] == "forest:tiny"

        states, tiles = [], 0
        for event, data in sse_events(cb, f"/v1/jobs/{job['id']}/events"):
            if event == "state":
                states.append(data["state"])
            tiles += event == "tile"
            if tiles == 1:  # B streams the tiles the scheduler beside A renders
                assert cb.post(f"/v1/jobs/{job['id']}/cancel").status_code == 202
        assert states[-1] == "canceled" and "running" in states, states
        assert ca.get(f"/v1/jobs/{job['id']}").json()["state"] == "canceled"
        assert ca.get("/v1/jobs").json()["count"] == 1  # the retry made no second job


def test_burst_past_the_queue_depth_gets_429_with_retry_after_and_loses_none(tmp_path,
                                                                           capsys):
    depth, burst = 4, 12
    settings = settings_for(tmp_path, max_queued_jobs=depth, retry_after_s=1)
    # No scheduler yet: the queue does not drain, so exactly `depth` jobs fit.
    with LiveServer(settings, scheduler=False) as server, \
            httpx.Client(base_url=server.url, timeout=30.0) as client:
        answers: list[httpx.Response] = []

        def submit() -> None:
            answers.append(client.post("/v1/jobs", json={"scene": "forest:tiny", **FAST},
                                       headers={"Idempotency-Key": uuid.uuid4().hex}))

        threads = [threading.Thread(target=submit) for _ in range(burst)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        accepted = {r.json()["id"] for r in answers if r.status_code == 202}
        refused = [r for r in answers if r.status_code != 202]
        assert len(accepted) == depth and len(refused) == burst - depth
        assert all(r.status_code == 429 and r.headers["retry-after"] == "1" for r in refused)
        assert "NPRT_MAX_QUEUED_JOBS" in refused[0].json()["detail"]

        # The Python client waits Retry-After and retries with one key until there is room.
        waiting: list[dict] = []
        retry = threading.Thread(target=lambda: waiting.append(
            Client(server.url).submit("forest:tiny", FAST)))
        retry.start()
        err: list[str] = []
        wait_for(lambda: err.append(capsys.readouterr().err) or "retrying in 1 s" in "".join(
            err), 30, what="the client's first 429")
        scheduler = Scheduler(settings).start()  # drains the queue
        try:
            retry.join(60)
            assert waiting and waiting[0]["id"] not in accepted
            done = {j: wait_for(lambda j=j: (r := client.get(f"/v1/jobs/{j}").json())
                                ["state"] in ("succeeded", "failed") and r, 60,
                                what=f"job {j}") for j in (*accepted, waiting[0]["id"])}
        finally:
            scheduler.stop(timeout_s=None)
        assert {d["state"] for d in done.values()} == {"succeeded"}
        assert client.get("/v1/jobs").json()["count"] == depth + 1
