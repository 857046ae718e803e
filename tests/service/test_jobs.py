"""REST /v1/jobs end to end against a real uvicorn server."""

from __future__ import annotations

import time

import numpy as np
import pytest

from scene.io import load_any
from tests.service.helpers import TINY, HeldSlots, png_pixels, sse_events, wait_for
from workers.film import read_exr, tonemap_srgb
from workers.render import render
from workers.settings import RenderSettings


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
    err = r.json()["detail"][0]
    assert err["loc"] == ["body", "spp"] and err["input"] == 0


def test_create_job_rejects_unknown_field(client):
    r = client.post("/v1/jobs", json={"scene": "forest:tiny", "spp_typo": 3})
    assert r.status_code == 422
    assert r.json()["detail"][0]["loc"] == ["body", "spp_typo"]


def test_create_job_rejects_proxy_mode_without_shards(client):
    r = client.post("/v1/jobs", json={"scene": "forest:tiny", "mode": "proxy", "shards": 0})
    assert r.status_code == 422
    assert "shards" in r.json()["detail"][0]["msg"]


def test_create_job_rejects_image_over_pixel_limit(client, live):
    limit = live.settings.max_image_pixels
    r = client.post("/v1/jobs", json={"scene": "forest:tiny", "width": 16384, "height": 16384})
    assert r.status_code == 422
    detail = r.json()["detail"][0]
    assert detail["loc"] == ["body", "width"] and detail["msg"] == (
        f"16384x16384 = 268435456 pixels is over the service limit of {limit} "
        "(NPRT_MAX_IMAGE_PIXELS)")


@pytest.mark.parametrize("scene", ["moon:tiny", "forest:huge", "0" * 64])
def test_create_job_rejects_unknown_scene(client, scene):
    r = client.post("/v1/jobs", json={"scene": scene, **TINY})
    assert r.status_code == 422
    detail = r.json()["detail"][0]
    assert detail["loc"] == ["body", "scene"] and detail["msg"].startswith(
        f"unknown scene {scene!r}: not a stored scene id nor a demo name")


@pytest.mark.parametrize("method,path", [
    ("GET", "/v1/jobs/{}"), ("GET", "/v1/jobs/{}/image.png"), ("GET", "/v1/jobs/{}/image.exr"),
    ("GET", "/v1/jobs/{}/events"), ("POST", "/v1/jobs/{}/cancel")])
def test_unknown_job_is_404(client, method, path):
    r = client.request(method, path.format("0123abcd"))
    assert r.status_code == 404
    assert r.json() == {"detail": "no job with id '0123abcd'"}


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
    assert again.status_code == 409 and "already canceled" in again.json()["detail"]

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
