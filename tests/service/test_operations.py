"""Operating the service: job logs (REST, SSE follow, gRPC), /metrics, DELETE, the linear
pixels the dashboard draws, and gRPC server reflection."""

from __future__ import annotations

import base64
import tempfile
from pathlib import Path

import grpc
import numpy as np
import pytest
from prometheus_client.parser import text_string_to_metric_families

from nprt.protos import nprt_pb2 as pb
from nprt.protos import nprt_pb2_grpc
from nprt.workers.film import read_exr
from tests.service.helpers import TINY, HeldSlots, problem_detail, sse_events, wait_for

TERMINAL = ("succeeded", "failed", "canceled")


def _run_job(client, **overrides) -> dict:
    job = client.post("/v1/jobs", json={"scene": "forest:tiny", **TINY, **overrides}).json()
    return wait_for(lambda: (j := client.get(f"/v1/jobs/{job['id']}").json())["state"]
                    in TERMINAL and j, 120, what=f"job {job['id']} ends")


@pytest.fixture(scope="module")
def done_job(client):
    job = _run_job(client)
    assert job["state"] == "succeeded", job
    return job


def _exr(client, job_id: str) -> np.ndarray:
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "final.exr"
        path.write_bytes(client.get(f"/v1/jobs/{job_id}/image.exr").content)
        return read_exr(path)


def test_job_log_holds_the_render_threads_records_only(client, done_job):
    r = client.get(f"/v1/jobs/{done_job['id']}/logs")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain")
    assert f"job {done_job['id']}: preparing scene 'forest:tiny'" in r.text
    assert "nprt.scene.demos" in r.text or "nprt.service.runjob" in r.text
    assert "uvicorn" not in r.text and "GET /v1" not in r.text  # no access log lines
    assert int(r.headers["x-nprt-log-offset"]) == len(r.content)
    rest = client.get(f"/v1/jobs/{done_job['id']}/logs",
                      params={"offset": r.headers["x-nprt-log-offset"]})
    assert rest.status_code == 200 and rest.text == ""


def test_log_follow_streams_every_line_with_resume_offsets_then_ends(client, done_job):
    whole = client.get(f"/v1/jobs/{done_job['id']}/logs").text.splitlines()
    events = list(sse_events(client, f"/v1/jobs/{done_job['id']}/logs?follow=1"))
    assert [d for e, d in events if e == "log"] == whole
    assert events[-1] == ("end", "succeeded")


def test_logs_of_unknown_job_are_404(client):
    assert client.get("/v1/jobs/feedbeef/logs").status_code == 404
    assert client.get("/v1/jobs/feedbeef/logs", params={"follow": 1}).status_code == 404


def test_grpc_job_log_equals_rest_log(live, client, done_job):
    whole = client.get(f"/v1/jobs/{done_job['id']}/logs").text.splitlines()
    with grpc.insecure_channel(live.grpc_target) as ch:
        stub = nprt_pb2_grpc.RenderServiceStub(ch)
        lines = list(stub.StreamJobLog(pb.StreamJobLogRequest(job_id=done_job["id"]),
                                       timeout=30))
        followed = list(stub.StreamJobLog(pb.StreamJobLogRequest(
            job_id=done_job["id"], offset=lines[1].end_offset, follow=True), timeout=30))
        with pytest.raises(grpc.RpcError) as e:
            list(stub.StreamJobLog(pb.StreamJobLogRequest(job_id="feedbeef"), timeout=10))
    assert [x.text for x in lines] == whole
    assert [x.text for x in followed] == whole[2:]
    assert e.value.code() == grpc.StatusCode.NOT_FOUND


def test_pixels_are_the_exr_in_float16(client, done_job):
    r = client.get(f"/v1/jobs/{done_job['id']}/pixels")
    assert r.status_code == 200 and r.headers["x-nprt-partial"] == "false"
    w, h = int(r.headers["x-nprt-width"]), int(r.headers["x-nprt-height"])
    px = np.frombuffer(r.content, "<f2").reshape(h, w, 3)
    np.testing.assert_array_equal(px, _exr(client, done_job["id"]).astype(np.float16))


def test_pixels_before_the_first_pass_are_404_and_tile_events_carry_pixels(live, client):
    held = HeldSlots(live.url, live.settings.max_concurrent_jobs)
    job = client.post("/v1/jobs", json={"scene": "forest:tiny", **TINY}).json()
    assert client.get(f"/v1/jobs/{job['id']}/pixels").status_code == 404  # queued
    tiles = []
    for event, data in sse_events(client, f"/v1/jobs/{job['id']}/events?pixels=f16"):
        if event == "tile":
            tiles.append(data)
        if not held.client.is_closed:
            held.release()
    final = _exr(client, job["id"])
    for t in tiles[4:]:  # the last pass of each tile holds all of its samples
        x0, y0, x1, y1 = t["rect"]
        px = np.frombuffer(base64.b64decode(t["pixels"]), "<f2").reshape(y1 - y0, x1 - x0, 3)
        np.testing.assert_array_equal(px, final[y0:y1, x0:x1].astype(np.float16))
    assert len(tiles) == 8


def test_delete_refuses_a_live_job_and_forgets_a_finished_one(live, client):
    held = HeldSlots(live.url, live.settings.max_concurrent_jobs)
    job_id = held.ids[0]
    # Running, so it has its folder (the previous test's job may still hold the slot).
    wait_for(lambda: client.get(f"/v1/jobs/{job_id}").json()["state"] == "running", 60,
             what=f"blocker {job_id} running")
    r = client.delete(f"/v1/jobs/{job_id}")
    assert r.status_code == 409 and "cancel it before deleting" in problem_detail(r)
    held.release()
    job_dir = live.settings.jobs_dir / job_id
    assert job_dir.exists()
    assert client.delete(f"/v1/jobs/{job_id}").status_code == 204
    assert client.get(f"/v1/jobs/{job_id}").status_code == 404
    assert not job_dir.exists()
    assert client.delete(f"/v1/jobs/{job_id}").status_code == 404


def _metrics(client) -> dict:
    r = client.get("/metrics")
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain")
    return {(s.name, tuple(sorted(s.labels.items()))): s.value
            for f in text_string_to_metric_families(r.text) for s in f.samples}


def test_metrics_count_jobs_by_state_and_the_rays_they_traced(client, done_job):
    wait_for(lambda: all(j["state"] in TERMINAL for j in
                         client.get("/v1/jobs", params={"limit": 500}).json()["data"]),
             120, what="every job of the module ends")
    jobs = client.get("/v1/jobs", params={"limit": 500}).json()["data"]
    m = _metrics(client)
    for state in ("queued", "running", "succeeded", "canceled"):
        assert m[("nprt_jobs", (("state", state),))] == sum(j["state"] == state for j in jobs)
    assert m[("nprt_queue_length", ())] == 0
    # Deleted jobs stay counted, so counters are at least what the remaining jobs traced.
    for kind in ("primary", "shadow"):
        traced = sum((j["stats"] or {}).get("rays", {}).get(kind, 0) for j in jobs)
        assert traced > 0 and m[("nprt_rays_total", (("kind", kind),))] >= traced
    assert m[("nprt_rays_per_second", ())] == 0.0  # nothing running
    assert ("nprt_shard_busy_fraction_count", ()) in m
    assert ("process_resident_memory_bytes", ()) in m


def test_reflection_lists_and_describes_the_services(live):
    from google.protobuf.descriptor_pool import DescriptorPool
    from grpc_reflection.v1alpha.proto_reflection_descriptor_database import (
        ProtoReflectionDescriptorDatabase,
    )

    with grpc.insecure_channel(live.grpc_target) as ch:
        db = ProtoReflectionDescriptorDatabase(ch)
        services = set(db.get_services())
        pool = DescriptorPool(db)
        render = pool.FindServiceByName("nprt.v1.RenderService")
        log_rpc = render.FindMethodByName("StreamJobLog")
        assert log_rpc.output_type.full_name == "nprt.v1.LogLine"
    assert {"nprt.v1.RenderService", "grpc.health.v1.Health",
            "grpc.reflection.v1alpha.ServerReflection"} <= services
    assert {m.name for m in render.methods} >= {"SubmitJob", "WatchJob", "GetImage"}
