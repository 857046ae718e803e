"""REST /v1/jobs end to end against a real uvicorn server."""

from __future__ import annotations

import asyncio
import json
import time

import httpx
import numpy as np
import pytest

from nprt.scene.io import load_any
from nprt.workers.film import read_exr, tonemap_srgb
from nprt.workers.render import render
from nprt.workers.settings import RenderSettings
from tests.service.helpers import TINY, HeldSlots, png_pixels, problem_detail, sse_events, wait_for


def _upload(client, path):
    r = client.post("/v1/scenes", content=path.read_bytes(), params={"filename": path.name},
                    headers={"Content-Type": "model/gltf-binary"})
    assert r.status_code in (200, 201), r.text
    return r.json()["id"]


def test_uploaded_gltf_job_streams_tiles_and_matches_direct_render(live, client, glb_path,
                                                                   tmp_path):
    scene_id = _upload(client, glb_path)
    held = HeldSlots(live.url, live.settings.max_concurrent_jobs)
    r = client.post("/v1/jobs", json={"scene": scene_id, **TINY})
    assert r.status_code == 202, r.text
    job = r.json()
    assert job["state"] == "queued" and job["passes_total"] == 8
    assert r.headers["location"] == f"/v1/jobs/{job['id']}"

    states, tiles = [], []
    for event, data in sse_events(client, f"/v1/jobs/{job['id']}/events"):
        if event == "state":
            states.append(data["state"])
        elif event == "tile":
            tiles.append(data)
        if len(states) == 1 and not held.client.is_closed:
            held.release()  # subscribed while queued: every pass will be seen
    assert states == ["queued", "preparing", "running", "succeeded"], states
    assert [t["pass_index"] for t in tiles] == list(range(8))
    assert [t["progress"] for t in tiles] == [(i + 1) / 8 for i in range(8)]
    assert tiles[0]["rect"] == [0, 0, 16, 16] and tiles[-1]["rect"] == [16, 16, 32, 32]
    assert (tiles[-1]["sample0"], tiles[-1]["sample1"]) == (2, 4)

    png = client.get(f"/v1/jobs/{job['id']}/image.png")
    assert png.status_code == 200 and png.headers["content-type"] == "image/png"
    assert png.headers["x-nprt-partial"] == "false"
    direct = render(load_any(str(glb_path)), RenderSettings(**TINY))
    expected = direct.film.image()
    np.testing.assert_array_equal(png_pixels(png.content), tonemap_srgb(expected))

    exr = client.get(f"/v1/jobs/{job['id']}/image.exr")
    assert exr.status_code == 200
    (tmp_path / "job.exr").write_bytes(exr.content)
    np.testing.assert_array_equal(read_exr(tmp_path / "job.exr"), expected)

    final = client.get(f"/v1/jobs/{job['id']}").json()
    assert final["progress"] == 1.0 and final["pixel_samples"] == {"min": 4, "max": 4}
    assert final["stats"]["rays"]["primary"] == 32 * 32 * 4


def test_create_job_rejects_zero_spp(client):
    r = client.post("/v1/jobs", json={"scene": "forest:tiny", "spp": 0})
    assert r.status_code == 422
    err = r.json()["errors"][0]
    assert err["loc"] == ["body", "spp"] and err["input"] == 0


@pytest.mark.parametrize("depth", [9, 10_000])
def test_job_body_nested_past_the_limit_is_422_before_parsing(client, depth):
    body = b'{"scene": "forest:tiny", "x": ' + b"[" * (depth - 1) + b"]" * (depth - 1) + b"}"
    r = client.post("/v1/jobs", content=body, headers={"Content-Type": "application/json"})
    assert r.status_code == 422 and problem_detail(r) == "the body nests deeper than 8 levels"


def test_create_job_rejects_unknown_field(client):
    r = client.post("/v1/jobs", json={"scene": "forest:tiny", "spp_typo": 3})
    assert r.status_code == 422
    assert r.json()["errors"][0]["loc"] == ["body", "spp_typo"]


def test_create_job_rejects_proxy_mode_without_shards(client):
    r = client.post("/v1/jobs", json={"scene": "forest:tiny", "mode": "proxy", "shards": 0})
    assert r.status_code == 422
    assert "shards" in r.json()["errors"][0]["msg"]


def test_create_job_rejects_image_over_pixel_limit(client, live):
    limit = live.settings.max_image_pixels
    r = client.post("/v1/jobs", json={"scene": "forest:tiny", "width": 16384, "height": 16384})
    assert r.status_code == 422
    detail = r.json()["errors"][0]
    assert detail["loc"] == ["body", "width"] and detail["msg"] == (
        f"16384x16384 = 268435456 pixels is over the service limit of {limit} "
        "(NPRT_MAX_IMAGE_PIXELS)")


@pytest.mark.parametrize("scene", ["moon:tiny", "forest:huge", "0" * 64])
def test_create_job_rejects_unknown_scene(client, scene):
    r = client.post("/v1/jobs", json={"scene": scene, **TINY})
    assert r.status_code == 422
    detail = r.json()["errors"][0]
    assert detail["loc"] == ["body", "scene"] and detail["msg"].startswith(
        f"unknown scene {scene!r}: not a stored scene id nor a demo name")


@pytest.mark.parametrize("method,path", [
    ("GET", "/v1/jobs/{}"), ("GET", "/v1/jobs/{}/image.png"), ("GET", "/v1/jobs/{}/image.exr"),
    ("GET", "/v1/jobs/{}/events"), ("POST", "/v1/jobs/{}/cancel")])
def test_unknown_job_is_404(client, method, path):
    r = client.request(method, path.format("0123abcd"))
    assert r.status_code == 404
    assert problem_detail(r) == "no job with id '0123abcd'"


def test_list_jobs_pages_newest_first(client):
    ids = [client.post("/v1/jobs", json={"scene": "forest:tiny", **TINY}).json()["id"]
           for _ in range(3)]
    page = client.get("/v1/jobs", params={"limit": 2})
    assert page.status_code == 200
    body = page.json()
    assert [j["id"] for j in body["data"]] == ids[::-1][:2]
    assert body["count"] >= 3 and body["limit"] == 2
    older = client.get("/v1/jobs", params={"limit": 2, "offset": 2}).json()
    assert older["data"][0]["id"] == ids[0]
    assert client.get("/v1/jobs", params={"limit": 0}).status_code == 422
    for job_id in ids:  # let the module's server drain before the next test
        wait_for(lambda j=job_id: client.get(f"/v1/jobs/{j}").json()["state"] == "succeeded",
                 60, what=f"job {job_id}")


def test_cancel_stops_running_and_queued_jobs_and_keeps_partial_image(client):
    # Both slots busy with long renders, so the third job is surely still queued.
    long = {**TINY, "width": 64, "height": 64, "spp": 512, "tile_size": 16, "spp_per_pass": 1}
    running = [client.post("/v1/jobs", json={"scene": "forest:tiny", **long}).json()["id"]
               for _ in range(2)]
    queued = client.post("/v1/jobs", json={"scene": "forest:tiny", **TINY}).json()["id"]
    r = client.post(f"/v1/jobs/{queued}/cancel")
    assert r.status_code == 202 and r.json()["state"] == "canceled"
    again = client.post(f"/v1/jobs/{queued}/cancel")
    assert again.status_code == 409 and "already canceled" in problem_detail(again)

    wait_for(lambda: client.get(f"/v1/jobs/{running[0]}").json()["passes_done"] >= 1, 30,
             what="a finished pass")
    partial = client.get(f"/v1/jobs/{running[0]}/image.png")
    assert partial.status_code == 200 and partial.headers["x-nprt-partial"] == "true"
    assert png_pixels(partial.content).shape == (64, 64, 3)
    for job_id in running:
        assert client.post(f"/v1/jobs/{job_id}/cancel").status_code == 202
    t0 = time.monotonic()
    for job_id in running:
        wait_for(lambda j=job_id: client.get(f"/v1/jobs/{j}").json()["state"] == "canceled",
                 30, what=f"job {job_id} canceled")
    assert time.monotonic() - t0 < 10
    assert client.get(f"/v1/jobs/{queued}/image.png").status_code == 404


def test_dashboard_and_openapi_are_served(client):
    page = client.get("/")
    assert page.status_code == 200 and "<title>nprt render service</title>" in page.text
    assert client.get("/static/app.js").status_code == 200
    assert client.get("/docs").status_code == 200
    paths = client.get("/openapi.json").json()["paths"]
    assert {"/v1/jobs", "/v1/jobs/{job_id}/events", "/v1/scenes"} <= set(paths)


@pytest.mark.parametrize("field,value", [
    ("spp", "NaN"), ("width", "Infinity"), ("seed", "-Infinity"),
    ("proxy.threshold", "NaN"), ("proxy.steps", "Infinity")])
def test_non_finite_numbers_are_422_naming_the_field(client, field, value):
    """Python's JSON reader takes NaN and Infinity; the 422 must still encode them."""
    head, _, sub = field.partition(".")
    literal = f'{{"{sub}": {value}}}' if sub else value
    body = f'{{"scene": "forest:tiny", "mode": "proxy", "shards": 2, "{head}": {literal}}}'
    r = client.post("/v1/jobs", content=body, headers={"Content-Type": "application/json"})
    assert r.status_code == 422, r.text
    err = r.json()["errors"][0]
    assert err["loc"] == ["body", *field.split(".")] and err["input"] == value


@pytest.mark.parametrize("offset", [2**31, 2**63, 10**30])
def test_out_of_range_paging_is_422(client, offset):
    r = client.get("/v1/jobs", params={"offset": offset})
    assert r.status_code == 422
    assert r.json()["errors"][0]["loc"] == ["query", "offset"]


def test_job_over_the_sample_cap_is_refused_at_once_naming_the_limit(client, live):
    """4096x4096 in 8-pixel tiles at 4096 spp: within every other limit, 1.07e9 passes and
    6.9e10 samples. Refused without building anything; the service keeps answering."""
    limit = live.settings.max_job_samples
    job = {"scene": "forest:tiny", "width": 4096, "height": 4096, "spp": 4096,
           "tile_size": 8, "spp_per_pass": 1}
    r = client.post("/v1/jobs", json=job)
    assert r.status_code == 422
    detail = r.json()["errors"][0]
    assert detail["loc"] == ["body", "spp"] and detail["msg"] == (
        f"4096x4096 x 4096 spp = {4096 ** 3} samples is over the service limit of {limit} "
        "(NPRT_MAX_JOB_SAMPLES)")
    assert client.get("/healthz").json() == {"status": "ok"}


def test_passes_total_is_counted_with_partial_tiles_and_chunks(client):
    job = {"scene": "forest:tiny", "width": 100, "height": 40, "spp": 7, "tile_size": 32,
           "spp_per_pass": 3}
    r = client.post("/v1/jobs", json=job)
    assert r.status_code == 202, r.text
    assert r.json()["passes_total"] == 3 * 2 * 4  # ceil(7/3) chunks x ceil(40/32) x ceil(100/32)
    assert client.post(f"/v1/jobs/{r.json()['id']}/cancel").status_code in (202, 409)


def test_same_idempotency_key_returns_the_same_job(client):
    job = {"scene": "forest:tiny", **TINY, "seed": 7}
    key = {"Idempotency-Key": "client-retry-42"}
    first = client.post("/v1/jobs", json=job, headers=key)
    again = client.post("/v1/jobs", json=job, headers=key)
    assert first.status_code == again.status_code == 202
    assert again.json()["id"] == first.json()["id"]
    assert again.headers["idempotent-replayed"] == "true"
    assert "idempotent-replayed" not in first.headers
    listed = client.get("/v1/jobs", params={"limit": 500}).json()["data"]
    assert sum(j["settings"]["seed"] == 7 for j in listed) == 1
    other = client.post("/v1/jobs", json={**job, "spp": 2}, headers=key)
    assert other.status_code == 409
    assert problem_detail(other) == (f"Idempotency-Key 'client-retry-42' was used for job "
                                     f"{first.json()['id']} with a different request")
    fresh = client.post("/v1/jobs", json=job, headers={"Idempotency-Key": "another"})
    assert fresh.status_code == 202 and fresh.json()["id"] != first.json()["id"]
    for job_id in (first.json()["id"], fresh.json()["id"]):
        client.post(f"/v1/jobs/{job_id}/cancel")


def test_cancel_of_a_running_job_is_stored_and_reported(client):
    long = {**TINY, "width": 64, "height": 64, "spp": 512, "tile_size": 16, "spp_per_pass": 1}
    job_id = client.post("/v1/jobs", json={"scene": "forest:tiny", **long}).json()["id"]
    wait_for(lambda: client.get(f"/v1/jobs/{job_id}").json()["state"] == "running", 60,
             what="job running")
    r = client.post(f"/v1/jobs/{job_id}/cancel")
    assert r.status_code == 202
    assert r.json()["cancel_requested"] is True
    assert r.json()["state"] in ("running", "canceled")
    final = wait_for(lambda: (j := client.get(f"/v1/jobs/{job_id}").json())["state"]
                     in ("succeeded", "failed", "canceled") and j, 30, what="job stopped")
    assert final["state"] == "canceled" and final["cancel_requested"]


def test_fast_reads_answer_what_the_routes_answer(client, live):
    """GET /healthz and GET /v1/jobs/{id} are answered before FastAPI routes them
    (nprt.service.fastreads): same status, body and media type as the routes."""
    from nprt.service.routers.jobs import get_job

    job_id = client.post("/v1/jobs", json={"scene": "forest:tiny", **TINY}).json()["id"]
    fast = client.get(f"/v1/jobs/{job_id}")
    routed = asyncio.run(get_job(job_id, live.app.state.api))
    assert (fast.status_code, fast.headers["content-type"]) == (200, routed.media_type)
    # The job may move on between the two reads; everything else is the same.
    moving = {"state", "progress", "passes_done", "started_at", "finished_at", "stats",
              "pixel_samples"}
    routed_body = json.loads(routed.body)
    assert {k: v for k, v in fast.json().items() if k not in moving} == \
        {k: v for k, v in routed_body.items() if k not in moving}
    health = client.get("/healthz")
    assert (health.status_code, health.json()) == (200, {"status": "ok"})
    assert health.headers["content-type"] == "application/json"
    missing = client.get("/v1/jobs/" + "0" * 32)  # falls through to the route's 404
    assert missing.status_code == 404 and "no job with id" in problem_detail(missing)


def test_fast_list_pages_like_the_route_and_leaves_refusals_to_it(tmp_path):
    """GET /v1/jobs with plain offset / limit / state is answered before routing
    (fastreads); the page is the route's, and a query the route refuses still gets its 422."""
    from nprt.service.routers.jobs import list_jobs
    from tests.service.helpers import LiveServer, settings_for, stored_queued_job

    with LiveServer(settings_for(tmp_path), scheduler=False) as server, \
            httpx.Client(base_url=server.url) as c:
        api = server.app.state.api
        ids = [stored_queued_job(server) for _ in range(5)]
        assert api.store.transition(ids[0], "running", ("queued",))
        for query in ({}, {"limit": 2}, {"limit": 2, "offset": 1}, {"offset": 4},
                      {"state": "queued", "limit": 3}, {"state": "running"},
                      {"limit": "007"}):
            fast = c.get("/v1/jobs", params=query)
            routed = asyncio.run(list_jobs(api, **{k: int(v) if k != "state" else v
                                                   for k, v in query.items()}))
            assert fast.status_code == 200 and fast.content == routed.body, query
            assert fast.headers["content-type"] == routed.media_type
        assert [j["id"] for j in c.get("/v1/jobs", params={"state": "running"}).json()
                ["data"]] == [ids[0]]
        for bad in ("limit=0", "limit=501", "offset=-1", "limit=x", "state=done",
                    f"offset={2**31}"):
            r = c.get(f"/v1/jobs?{bad}")
            assert r.status_code == 422 and problem_detail(r), bad
