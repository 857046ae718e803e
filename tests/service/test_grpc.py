"""gRPC RenderService over a real channel: submit, watch to completion, images, health."""

from __future__ import annotations

import grpc
import httpx
import numpy as np
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc

from nprt.protos import nprt_pb2 as pb
from nprt.protos import nprt_pb2_grpc
from nprt.workers.film import read_exr, tonemap_srgb
from tests.service.helpers import (
    TINY,
    HeldSlots,
    LiveServer,
    png_pixels,
    problem_detail,
    settings_for,
    stored_queued_job,
)


@pytest.fixture(scope="module")
def channel(live):
    with grpc.insecure_channel(live.grpc_target) as ch:
        yield ch


@pytest.fixture(scope="module")
def stub(channel):
    return nprt_pb2_grpc.RenderServiceStub(channel)


def test_health_reports_serving(channel):
    health = health_pb2_grpc.HealthStub(channel)
    for service in ("", "nprt.v1.RenderService"):
        reply = health.Check(health_pb2.HealthCheckRequest(service=service), timeout=5)
        assert reply.status == health_pb2.HealthCheckResponse.SERVING


def test_watch_streams_tiles_to_completion_and_last_tiles_equal_final_image(live, stub, tmp_path):
    held = HeldSlots(live.url, live.settings.max_concurrent_jobs)
    job = stub.SubmitJob(pb.SubmitJobRequest(scene="forest:tiny",
                                             settings=pb.RenderSettings(**TINY)), timeout=10)
    assert job.state == pb.JOB_STATE_QUEUED and job.passes_total == 8
    assert job.settings.spp == 4 and job.settings.mode == "exact"  # defaults filled in

    events = []
    for ev in stub.WatchJob(pb.WatchJobRequest(job_id=job.id, tile_format=pb.TILE_FORMAT_RGB_F32),
                            timeout=60):
        events.append(ev)
        if len(events) == 1:
            held.release()  # the watcher is subscribed while the job is still queued
    kinds = [e.WhichOneof("event") for e in events]
    states = [e.job.state for e in events if e.HasField("job")]
    assert states == [pb.JOB_STATE_QUEUED, pb.JOB_STATE_PREPARING, pb.JOB_STATE_RUNNING,
                      pb.JOB_STATE_SUCCEEDED]
    assert kinds == ["job"] * 3 + ["tile"] * 8 + ["job"]
    assert events[-1].job.progress == 1.0 and events[-1].job.passes_done == 8
    tiles = [e.tile for e in events if e.HasField("tile")]
    assert [t.pass_index for t in tiles] == list(range(8))

    exr = stub.GetImage(pb.GetImageRequest(job_id=job.id, format=pb.IMAGE_FORMAT_EXR))
    assert not exr.partial and (exr.width, exr.height) == (32, 32)
    (tmp_path / "final.exr").write_bytes(exr.data)
    final = read_exr(tmp_path / "final.exr")
    # A tile's last pass carries all of its samples: its pixels are the final image there.
    for t in tiles[4:]:  # passes 4..7 hold samples 2..4 of the four tiles
        x0, y0, x1, y1 = t.rect.x0, t.rect.y0, t.rect.x1, t.rect.y1
        assert t.sample1 == 4 and len(t.pixels) == (x1 - x0) * (y1 - y0) * 3 * 4
        rgb = np.frombuffer(t.pixels, "<f4").reshape(y1 - y0, x1 - x0, 3)
        np.testing.assert_array_equal(rgb, final[y0:y1, x0:x1])

    png = stub.GetImage(pb.GetImageRequest(job_id=job.id, format=pb.IMAGE_FORMAT_PNG))
    np.testing.assert_array_equal(png_pixels(png.data), tonemap_srgb(final))
    listed = stub.ListJobs(pb.ListJobsRequest(limit=500))
    assert job.id in [j.id for j in listed.jobs] and listed.total >= 1


def test_watch_sends_png_tiles_of_the_tile_size(stub):
    job = stub.SubmitJob(pb.SubmitJobRequest(scene="forest:tiny",
                                             settings=pb.RenderSettings(**TINY)))
    tiles = [e.tile for e in stub.WatchJob(pb.WatchJobRequest(
        job_id=job.id, tile_format=pb.TILE_FORMAT_PNG), timeout=60) if e.HasField("tile")]
    for t in tiles:
        assert t.format == pb.TILE_FORMAT_PNG
        assert png_pixels(t.pixels).shape == (t.rect.y1 - t.rect.y0, t.rect.x1 - t.rect.x0, 3)


def test_submit_rejects_zero_spp_with_invalid_argument(stub):
    with pytest.raises(grpc.RpcError) as e:
        stub.SubmitJob(pb.SubmitJobRequest(scene="forest:tiny",
                                           settings=pb.RenderSettings(spp=0)))
    assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert e.value.details() == ("invalid settings: spp: Input should be greater than or "
                                 "equal to 1 (got 0)")


def test_submit_rejects_unknown_mode_and_scene_with_invalid_argument(stub):
    with pytest.raises(grpc.RpcError) as e:
        stub.SubmitJob(pb.SubmitJobRequest(scene="forest:tiny",
                                           settings=pb.RenderSettings(mode="fast")))
    assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "'fast'" in e.value.details()
    with pytest.raises(grpc.RpcError) as e:
        stub.SubmitJob(pb.SubmitJobRequest(scene="moon", settings=pb.RenderSettings(**TINY)))
    assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "'moon'" in e.value.details()


@pytest.mark.parametrize("rpc,request_type", [
    ("GetJob", pb.GetJobRequest), ("CancelJob", pb.CancelJobRequest),
    ("GetImage", pb.GetImageRequest), ("WatchJob", pb.WatchJobRequest)])
def test_unknown_job_is_not_found(stub, rpc, request_type):
    with pytest.raises(grpc.RpcError) as e:
        result = getattr(stub, rpc)(request_type(job_id="feedbeef"), timeout=10)
        list(result) if rpc == "WatchJob" else result
    assert e.value.code() == grpc.StatusCode.NOT_FOUND
    assert e.value.details() == "no job with id 'feedbeef'"


def test_tile_over_message_limit_is_sent_without_pixels():
    from nprt.service.grpc_convert import tile_to_pb

    ev = {"rect": (0, 0, 64, 32), "rgb": np.ones((32, 64, 3), np.float32), "pass_index": 0,
          "passes_total": 1, "sample0": 0, "sample1": 1, "progress": 1.0}
    fits = tile_to_pb(ev, pb.TILE_FORMAT_RGB_F32, max_bytes=1 << 20)
    assert fits.format == pb.TILE_FORMAT_RGB_F32 and len(fits.pixels) == 64 * 32 * 3 * 4
    dropped = tile_to_pb(ev, pb.TILE_FORMAT_RGB_F32, max_bytes=16 * 1024)
    assert dropped.format == pb.TILE_FORMAT_NONE and dropped.pixels == b""
    assert (dropped.rect.x1, dropped.rect.y1, dropped.progress) == (64, 32, 1.0)


STREAMS = 40
ANSWER_DEADLINE_S = 1.0


def test_open_watch_streams_do_not_starve_health_or_get_job(tmp_path):
    """Each WatchJob stream once held one of 32 server threads: 40 of them starved every
    other rpc. Now they wait on the event loop."""
    with LiveServer(settings_for(tmp_path), grpc=True, scheduler=False) as live, \
            grpc.insecure_channel(live.grpc_target) as channel:
        _watch_many(live, channel, nprt_pb2_grpc.RenderServiceStub(channel))


def _watch_many(live, channel, stub) -> None:
    job_id = stored_queued_job(live)
    streams = [stub.WatchJob(pb.WatchJobRequest(job_id=job_id), timeout=60)
               for _ in range(STREAMS)]
    firsts = [next(s) for s in streams]  # every stream is open and subscribed
    assert all(f.job.state == pb.JOB_STATE_QUEUED for f in firsts)
    health = health_pb2_grpc.HealthStub(channel)
    for _ in range(5):
        reply = health.Check(health_pb2.HealthCheckRequest(service=""),
                             timeout=ANSWER_DEADLINE_S)
        assert reply.status == health_pb2.HealthCheckResponse.SERVING
        assert stub.GetJob(pb.GetJobRequest(job_id=job_id),
                           timeout=ANSWER_DEADLINE_S).state == pb.JOB_STATE_QUEUED
    assert live.app.state.api.broker.subscribers(job_id) == STREAMS
    stub.CancelJob(pb.CancelJobRequest(job_id=job_id), timeout=10)
    for s in streams:  # each ends with the terminal state
        assert [e.job.state for e in s] == [pb.JOB_STATE_CANCELED]


def test_watch_streams_over_the_limit_get_resource_exhausted(tmp_path):
    with LiveServer(settings_for(tmp_path, max_watchers=2), grpc=True,
                    scheduler=False) as server, \
            grpc.insecure_channel(server.grpc_target) as ch:
        stub = nprt_pb2_grpc.RenderServiceStub(ch)
        job_id = stored_queued_job(server)
        streams = [stub.WatchJob(pb.WatchJobRequest(job_id=job_id), timeout=60)
                   for _ in range(2)]
        assert all(next(s).job.state == pb.JOB_STATE_QUEUED for s in streams)
        with pytest.raises(grpc.RpcError) as e:
            next(stub.WatchJob(pb.WatchJobRequest(job_id=job_id), timeout=10))
        assert e.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
        assert "NPRT_MAX_WATCHERS" in e.value.details()
        sse = httpx.get(f"{server.url}/v1/jobs/{job_id}/events", timeout=10)
        assert sse.status_code == 503 and "NPRT_MAX_WATCHERS" in problem_detail(sse)
        stub.CancelJob(pb.CancelJobRequest(job_id=job_id), timeout=10)
        for s in streams:
            assert [ev.job.state for ev in s] == [pb.JOB_STATE_CANCELED]
        assert server.app.state.api.broker.subscribers(job_id) == 0
