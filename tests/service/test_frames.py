"""Frames jobs (issue 10, item 4): a job over a frame range of an animated scene renders
each frame on one renderer and serves each frame's image over REST and gRPC; the CLI
writes one numbered file per frame."""

from __future__ import annotations

import grpc
import httpx
import numpy as np
import pytest

from nprt.protos import nprt_pb2 as pb
from nprt.protos import nprt_pb2_grpc
from nprt.scene.demos import make_demo
from nprt.scene.meta import SceneMeta
from nprt.service import images
from nprt.service.cli import main
from nprt.service.jobapi import JobApi
from nprt.service.scenes import SceneStore
from nprt.service.scheduler import Scheduler
from nprt.service.store import TERMINAL, JobStore
from nprt.workers.passes import count_passes
from nprt.workers.render import render
from nprt.workers.settings import RenderSettings
from tests.service.helpers import TINY, LiveServer, png_pixels, settings_for, wait_for

FRAMES = {"first": 2, "last": 4}


def _finished(client, job_id: str) -> dict:
    return wait_for(lambda: (j := client.get(f"/v1/jobs/{job_id}").json())["state"] in
                    ("succeeded", "failed", "canceled") and j, 120, 0.2, f"job {job_id}")


@pytest.fixture(scope="module")
def frames_job(live, client) -> dict:
    r = client.post("/v1/jobs", json={"scene": "windy:tiny", **TINY, "frames": FRAMES})
    assert r.status_code == 202, r.text
    assert r.json()["frames"] == FRAMES
    return _finished(client, r.json()["id"])


def test_a_frames_job_serves_each_frame_as_rendered_alone(frames_job, client):
    job = frames_job
    assert job["state"] == "succeeded", job["error"]
    per = count_passes(RenderSettings(**TINY))
    assert job["passes_total"] == job["passes_done"] == 3 * per
    scene = make_demo("windy", "tiny")
    got = {}
    for f in range(FRAMES["first"], FRAMES["last"] + 1):
        r = client.get(f"/v1/jobs/{job['id']}/frames/{f}.png")
        assert r.status_code == 200 and r.headers["content-type"] == "image/png"
        got[f] = png_pixels(r.content)
        alone = render(scene.at_frame(f), RenderSettings(**TINY)).film.image()
        np.testing.assert_array_equal(got[f], png_pixels(images.png_bytes(alone)))
    assert not np.array_equal(got[2], got[4])  # the frames differ: the check can fail
    exr = client.get(f"/v1/jobs/{job['id']}/frames/3.exr")
    assert exr.status_code == 200 and exr.headers["content-type"] == "image/x-exr"
    final = png_pixels(client.get(f"/v1/jobs/{job['id']}/image.png").content)
    np.testing.assert_array_equal(final, got[4])  # the job's image is its last frame


@pytest.mark.parametrize("frame, detail", [(5, "renders frames 2 to 4; no frame 5"),
                                           (0, "no frame 0")])
def test_a_frame_outside_the_job_is_404(frames_job, client, frame, detail):
    r = client.get(f"/v1/jobs/{frames_job['id']}/frames/{frame}.png")
    assert r.status_code == 404 and detail in r.json()["detail"]


def test_bad_frame_ranges_are_refused_or_fail_naming_the_frame(live, client):
    r = client.post("/v1/jobs", json={"scene": "windy:tiny", **TINY,
                                      "frames": {"first": 3, "last": 1}})
    assert r.status_code == 422 and "last (1) is before first (3)" in r.text
    r = client.post("/v1/jobs", json={"scene": "windy:tiny", **TINY,
                                      "frames": {"first": 7, "last": 8}})
    assert r.status_code == 202
    job = _finished(client, r.json()["id"])
    assert job["state"] == "failed" and "0 <= A <= B < 8" in job["error"]


def test_grpc_submits_a_frame_range_and_gets_frames(live, client):
    with grpc.insecure_channel(live.grpc_target) as ch:
        stub = nprt_pb2_grpc.RenderServiceStub(ch)
        job = stub.SubmitJob(pb.SubmitJobRequest(
            scene="windy:tiny", settings=pb.RenderSettings(**TINY),
            frames=pb.FrameRange(first=6, last=7)), timeout=10)
        assert job.HasField("frames") and (job.frames.first, job.frames.last) == (6, 7)
        assert _finished(client, job.id)["state"] == "succeeded"
        img = stub.GetFrame(pb.GetFrameRequest(job_id=job.id, frame=7,
                                               format=pb.IMAGE_FORMAT_PNG), timeout=10)
        assert not img.partial and (img.width, img.height) == (TINY["width"], TINY["height"])
        rest = client.get(f"/v1/jobs/{job.id}/frames/7.png").content
        np.testing.assert_array_equal(png_pixels(img.data), png_pixels(rest))
        with pytest.raises(grpc.RpcError) as e:
            stub.GetFrame(pb.GetFrameRequest(job_id=job.id, frame=2), timeout=10)
        assert e.value.code() == grpc.StatusCode.NOT_FOUND
        plain = stub.SubmitJob(pb.SubmitJobRequest(scene="forest:tiny",
                                                   settings=pb.RenderSettings(**TINY)))
        assert not plain.HasField("frames")


def test_cli_frames_write_one_numbered_file_each(tmp_path, capsys):
    out = tmp_path / "out" / "windy_####.png"
    rc = main(["render", "windy:tiny", "--frames", "1:3", "-o", str(out), "--width", "24",
               "--height", "16", "--spp", "2", "--bounces", "1", "--stats",
               str(tmp_path / "stats.json")])
    assert rc == 0
    written = sorted(p.name for p in out.parent.iterdir())
    assert written == ["windy_0001.png", "windy_0002.png", "windy_0003.png"]
    assert "frame 3: wrote" in capsys.readouterr().out
    imgs = [png_pixels((out.parent / n).read_bytes()) for n in written]
    assert imgs[0].shape == (16, 24, 3) and not np.array_equal(imgs[0], imgs[2])


def test_cli_frames_out_of_range_is_an_error(tmp_path, capsys):
    rc = main(["render", "windy:tiny", "--frames", "6:9", "-o", str(tmp_path / "o_##.png")])
    assert rc != 0 and "0 <= A <= B < 8" in capsys.readouterr().err


def test_a_frames_job_resumed_after_a_restart_skips_the_frames_it_stored(tmp_path):
    """A job left running by a dead process, with frame 1 of 1..3 already stored: the next
    start renders frames 2 and 3 only, and the job ends with frame 3 as its image."""
    settings = settings_for(tmp_path)
    store = JobStore(settings.db_path)
    s = RenderSettings(**TINY)
    store.insert("resumed", "windy:tiny", s.model_dump(mode="json"), 3 * count_passes(s),
                 frames=[1, 3])
    assert store.transition("resumed", "running", ("queued",))
    store.close()
    stored = settings.jobs_dir / "resumed" / "frames"
    stored.mkdir(parents=True)
    marker = b"frame 1, stored before the restart"
    (stored / "00001.png").write_bytes(marker)
    (stored / "00001.exr").write_bytes(marker)
    m = JobApi(settings, SceneStore(settings)).start()
    scheduler = Scheduler(settings).start()
    try:
        rec = wait_for(lambda: (r := m.get("resumed")).state in TERMINAL and r, 60,
                       what="the resumed job")
        assert rec.state == "succeeded", rec.error
        assert m.frame_image("resumed", 1, "png") == marker  # not rendered again
        last = m.frame_image("resumed", 3, "png")
        assert m.image("resumed", "png")[0] == last
        assert png_pixels(m.frame_image("resumed", 2, "png")).shape == (32, 32, 3)
        assert sorted(rec.stats["frames"]["frame_wall_s"]) == ["2", "3"]
    finally:
        scheduler.stop(timeout_s=None)
        m.stop()


def test_submit_frames_waits_and_writes_each_frame(live, client, tmp_path, capsys):
    out = tmp_path / "sub_##.png"
    rc = main(["submit", "windy:tiny", "--server", live.url, "--frames", "5:6", "--width",
               "24", "--height", "16", "--spp", "2", "--tile-size", "8", "-o", str(out)])
    assert rc == 0
    job_id = capsys.readouterr().out.strip().splitlines()[-1]
    assert client.get(f"/v1/jobs/{job_id}").json()["frames"] == {"first": 5, "last": 6}
    for f in (5, 6):
        served = client.get(f"/v1/jobs/{job_id}/frames/{f}.png").content
        np.testing.assert_array_equal(png_pixels((tmp_path / f"sub_0{f}.png").read_bytes()),
                                      png_pixels(served))
    with pytest.raises(SystemExit) as e:
        main(["submit", "windy:tiny", "--server", live.url, "--frames", "3:1"])
    assert e.value.code == 2 and "want 0 <= A <= B" in capsys.readouterr().err


def test_nprt_scenes_lists_the_animated_demo_with_its_frames(capsys):
    assert main(["scenes", "--sizes", "tiny"]) == 0
    rows = {line.split("|")[1].strip(): line for line in capsys.readouterr().out.splitlines()
            if line.startswith("| ")}
    assert rows["windy"].rstrip(" |").endswith("8") and rows["forest"].rstrip(" |").endswith("1")


@pytest.mark.slow
def test_a_sharded_frames_job_renders_the_stored_scene_on_one_pool(tmp_path):
    """The service opens windy:tiny as metadata (the scene store); a K = 2 exact frames
    job shows each frame to one pool of shards and matches the reference job frame by
    frame."""
    pytest.importorskip("ray")
    with LiveServer(settings_for(tmp_path, max_concurrent_jobs=1)) as server, \
            httpx.Client(base_url=server.url, timeout=30.0) as client:
        scheduler = server.scheduler
        assert isinstance(scheduler.scenes.load("windy:tiny"), SceneMeta)
        jobs = {k: client.post("/v1/jobs", json={"scene": "windy:tiny", **TINY, "shards": k,
                                                 "frames": {"first": 0, "last": 2}}
                               ).json()["id"] for k in (0, 2)}
        done = {k: _finished(client, j) for k, j in jobs.items()}
        assert [d["state"] for d in done.values()] == ["succeeded"] * 2, done
        assert done[2]["stats"]["renderer"] == "distributed"
        assert scheduler.pools.started == 1  # one pool for the three frames
        got = {}
        for f in range(3):
            ref, img = (png_pixels(client.get(f"/v1/jobs/{jobs[k]}/frames/{f}.png").content)
                        .astype(int) for k in (0, 2))
            # Float summation order differs between shards: allow one 8-bit step.
            assert np.abs(img - ref).max() <= 1, f"frame {f}: 2 shards differ"
            got[f] = img
        assert not np.array_equal(got[0], got[2])  # the frames differ: the check can fail
