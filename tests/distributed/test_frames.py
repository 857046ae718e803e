"""Animated scenes (issue 10, item 4): every frame of the distributed render equals the
reference; a moving instance changes the image where it is and nowhere else; across
frames the shard pool keeps its actors, geometry and proxies (nothing is retrained).
The distributed renders run on what `nprt render --shards K` and the service use: the
scene's metadata from the scene store (`open_scene`), the driver reading no mesh."""

from __future__ import annotations

import json

import numpy as np
import pytest
import ray
import trimesh

from nprt.proxies import cache as proxy_cache
from nprt.scene.demos import make_demo
from nprt.scene.io import load_scene
from nprt.scene.meta import SceneMeta
from nprt.scene.store import open_scene
from nprt.workers.frames import render_frames
from nprt.workers.render import render
from nprt.workers.runtime import placement
from nprt.workers.runtime.coordinator import Coordinator
from nprt.workers.runtime.pool import PoolRegistry
from nprt.workers.settings import ProxySettings
from tests.distributed.helpers import assert_matches, reference, refuse_mesh_reads, settings


@pytest.fixture(scope="module")
def windy(tmp_path_factory):
    """windy:small as the distributed path opens it: written once to a scene cache (its
    animation as keyframes) and read back as metadata, no mesh in this process."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("NPRT_SCENE_CACHE", str(tmp_path_factory.mktemp("scenes")))
        meta = open_scene("windy:small")
    assert isinstance(meta, SceneMeta) and meta.frames == 8
    return meta


def _images(scene, s, frames, **kw) -> dict:
    return {d.frame: d.result.film.image() for d in render_frames(scene, s, frames, **kw)}


def test_exact_equals_the_reference_on_every_frame(ray_local, windy, monkeypatch, tmp_path):
    """The reference renders the demo as built in memory; K = 3 renders its stored
    metadata, each frame's instance table and lights sent to the shards by the driver,
    which reads no mesh: equal on all 8 frames."""
    frames = range(windy.frames)
    ref = _images(make_demo("windy", "small"), settings(0), frames)
    refuse_mesh_reads(monkeypatch)
    got = _images(windy, settings(3), frames)
    for f in frames:
        assert_matches(tmp_path, f"windy_f{f}", got[f], ref[f])
    # The frames really differ (trees and the sun moved), so the check above can fail.
    assert all(not np.array_equal(ref[f], ref[f + 1]) for f in range(windy.frames - 1))


def test_proxy_frames_train_nothing_after_the_first(ray_local, windy, monkeypatch, tmp_path):
    """One pool, started once, for all 8 frames: its actors stay, the proxy plan is made
    once, and no proxy is looked up or trained again once frame 0 is done."""
    plans, lookups, trained = [], [], []

    def counting(name, calls):
        real = getattr(proxy_cache.ProxyCache, name)
        monkeypatch.setattr(proxy_cache.ProxyCache, name, lambda self, mesh, *a, **kw:
                            calls.append(mesh.content_hash) or real(self, mesh, *a, **kw))

    counting("get", lookups)
    counting("get_or_train", trained)
    real_plan = placement.make_plan
    monkeypatch.setattr(placement, "make_plan",
                        lambda *a, **kw: plans.append(1) or real_plan(*a, **kw))
    pools = PoolRegistry()
    seen, pids = [], []
    try:
        # A target its tree proxies meet: at the default (0.97) the plan copies every tree
        # but one to every shard, and every shard then holds that one's instances too, so
        # no proxy would be asked.
        s = settings(2, mode="proxy", proxy=ProxySettings(accuracy_target=0.9))
        for done in render_frames(windy, s, range(windy.frames), pools=pools,
                                  proxy_dir=tmp_path / "proxies"):
            seen.append((len(plans), len(lookups), len(trained)))
            pids.append([i["pid"] for i in done.result.info["shard_stats"]])
            counts = done.result.info["proxy_plan"]["counts"]
            stats = done.result.stats.to_dict()["counters"]
            assert stats["proxy_queries"] > 0, f"frame {done.frame} used no proxy"
    finally:
        pools.close()
    assert counts["proxy"] > 0 and lookups, "the plan uses proxies, so the check can fail"
    assert pools.started == 1
    # Planned before frame 0 was shown (twice: the plan copies light meshes, and the
    # partition is made again without them), never after.
    assert seen == [(len(plans), len(lookups), len(trained))] * windy.frames and plans
    assert all(p == pids[0] for p in pids)  # the same actors on every frame


# A red box over a grey ground quad, lit straight down (its shadow hides under it), seen
# from above: with one bounce (direct light only), a pixel changes only where the box is
# on one frame or the other.
BOX_X = (-4.0, 4.0)  # the box's x on frames 0 and 2


def _moving_box_scene(tmp_path):
    box = trimesh.creation.box((2.0, 2.0, 2.0))
    doc = {
        "materials": [{"name": "grey", "albedo": [0.5, 0.5, 0.5]},
                      {"name": "red", "albedo": [0.8, 0.1, 0.1]}],
        "meshes": [
            {"name": "ground", "vertices": [[-10, 0, -10], [10, 0, -10], [10, 0, 10],
                                            [-10, 0, 10]], "faces": [[0, 2, 1], [0, 3, 2]]},
            {"name": "box", "vertices": box.vertices.tolist(), "faces": box.faces.tolist(),
             "material": "red"}],
        "instances": [{"mesh": "ground"}, {"mesh": "box", "translate": [BOX_X[0], 1, 0]}],
        "lights": {"directionals": [{"direction": [0, -1, 0], "irradiance": [3, 3, 3]}]},
        "camera": {"eye": [0, 20, 10], "target": [0, 0, 0], "fov_deg": 50},
        "animation": {"frames": 3, "instances": {"1": [
            {"frame": 0, "translate": [BOX_X[0], 1, 0]},
            {"frame": 2, "translate": [BOX_X[1], 1, 0]}]}},
    }
    (tmp_path / "box.json").write_text(json.dumps(doc))
    return tmp_path / "box.json"


def _screen_box(cam, w: int, h: int, lo, hi, pad: int = 2) -> tuple[slice, slice]:
    """Rows and columns covering the projection of the world box [lo, hi] (3,), padded."""
    eye = np.asarray(cam.eye, float)
    fwd = np.asarray(cam.target, float) - eye
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, cam.up)
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    half_h = np.tan(np.radians(cam.fov_deg) / 2)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                        for z in (lo[2], hi[2])]) - eye
    depth = corners @ fwd
    col = ((corners @ right) / depth / (half_h * w / h) + 1) / 2 * w
    row = (1 - (corners @ up) / depth / half_h) / 2 * h
    return (slice(max(int(row.min()) - pad, 0), int(np.ceil(row.max())) + pad),
            slice(max(int(col.min()) - pad, 0), int(np.ceil(col.max())) + pad))


@pytest.mark.parametrize("k", [0, 2], ids=["reference", "k2"])
def test_moving_an_instance_changes_the_image_only_where_it_was_and_is(ray_local, tmp_path,
                                                                       k):
    path = _moving_box_scene(tmp_path)
    # The reference loads the scene whole; the shards get its metadata (linear keyframes
    # sampled from the file alone) and load the meshes themselves.
    scene = load_scene(path) if k == 0 else open_scene(path)
    s = settings(k, width=64, height=48, spp=2, bounces=1)
    img = _images(scene, s, [0, 2])
    changed = np.abs(img[0] - img[2]).max(axis=2) > 0  # (h, w)
    where = np.zeros_like(changed)
    for x in BOX_X:
        rows, cols = _screen_box(scene.camera, s.width, s.height, (x - 1, 0, -1), (x + 1, 2, 1))
        assert changed[rows, cols].mean() > 0.3, f"the box at x={x} did not show"
        where[rows, cols] = True
    assert changed.any() and not changed[~where].any(), \
        f"{int(changed[~where].sum())} pixels changed away from the box"


def test_a_shard_killed_on_a_later_frame_is_shown_that_frame_again(ray_local, windy,
                                                                   tmp_path):
    """Ray restarts a dead shard with its start-up (frame 0) world; the coordinator sends
    it the frame being rendered before re-running the lost passes."""
    s = settings(3, tile_size=16)
    at = windy.at_frame(5)
    ref = reference(at, s).film.image()  # loads the stored scene whole, on frame 5
    coord = Coordinator(windy, s)
    killed, order = [], coord._order

    def kill_then_order(shard, passes, epoch):
        order(shard, passes, epoch)
        if not killed and max(p.index for p in passes) >= 2:  # passes 0 and 1 are live
            killed.append(shard)
            ray.kill(coord.actors[shard], no_restart=False)

    coord._order = kill_then_order
    try:
        coord.set_frame(at)
        result = render(at, s, renderer=coord)
    finally:
        coord.close()
    assert killed, "the kill never happened"
    assert_matches(tmp_path, "killed_on_frame5", result.film.image(), ref)


def test_a_warm_pool_left_on_a_later_frame_renders_frame_0_for_the_next_job(ray_local, windy,
                                                                            tmp_path):
    s = settings(2)
    pools = PoolRegistry()
    try:
        last = list(render_frames(windy, s, [6, 7], pools=pools))[-1]
        assert last.frame == 7
        coord = Coordinator(windy, s, pools=pools)
        try:
            again = render(windy, s, renderer=coord)
            with pytest.raises(ValueError, match="not a frame of the pool's scene"):
                coord.set_frame(make_demo("city", "small"))
        finally:
            coord.close()
    finally:
        pools.close()
    assert pools.started == 1
    assert_matches(tmp_path, "warm_frame0", again.film.image(),
                   reference(windy, s).film.image())
