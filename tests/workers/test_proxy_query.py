"""What `predict` makes of proxy answers along one ray: real Proxy objects whose ONNX nets
give a fixed visibility, so each case is set by hand. Two unit cubes of different meshes,
A at x = 5 and B at x = 10, on shards 1 and 2; the rays start at the origin along +x."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from nprt.proxies.inference import Proxy
from nprt.scene.model import Camera, Instance, Scene
from nprt.workers.routing.proxy_query import QueryKnobs, predict
from nprt.workers.wavefront.world import ShardWorld
from tests.workers.helpers import mesh_from_trimesh, trs

onnx = pytest.importorskip("onnx", reason="building the fixed nets needs onnx")
from tests.proxies.helpers import constant_net  # noqa: E402

BAND = 0.4


def _proxy(visibility: float) -> Proxy:
    """A proxy of the unit cube answering `visibility` everywhere; depth y = 0 puts the hit
    at the line's closest point to the box centre (half a unit in, along +x)."""
    box = [[-0.5, -0.5, -0.5], [0.5, 0.5, 0.5]]
    meta = {"box": box, "diag": 3 ** 0.5, "encoding": "line", "threshold": 0.5}
    return Proxy(meta, {"visibility": constant_net(visibility, 6), "depth": constant_net(0.0, 6)})


@pytest.fixture(scope="module")
def world():
    cube = trimesh.creation.box((1.0, 1.0, 1.0))
    meshes = (mesh_from_trimesh(cube, "a"), mesh_from_trimesh(cube, "b"))
    scene = Scene(meshes, (Instance(0, trs((5, 0, 0))), Instance(1, trs((10, 0, 0)))),
                  camera=Camera(eye=(0, 0, 0), target=(1, 0, 0), up=(0, 1, 0), fov_deg=40))
    return ShardWorld.build(scene, np.array([1, 2], np.int32))


def _knobs(margin: float = 0.0, band=(BAND, BAND)) -> QueryKnobs:
    return QueryKnobs(None, np.asarray(band, np.float64), margin)


def _ask(world, proxies: dict, visited: int | None = None, band=(BAND, BAND)):
    origin = np.zeros((1, 3), np.float32)
    direction = np.array([[1.0, 0.0, 0.0]], np.float32)
    tmax = np.full(1, np.inf, np.float32)
    seen = None if visited is None else np.array([visited], np.uint64)
    return predict(world, proxies, np.array([0, 1], np.int32), origin, direction, tmax,
                   _knobs(band=band), visited=seen)


def test_an_unsure_box_beyond_the_closest_confident_hit_does_not_matter(world):
    pred = _ask(world, {0: _proxy(0.99), 1: _proxy(0.5)})
    assert pred.inst[0] == 0 and not pred.uncertain[0]
    assert pred.t[0] == pytest.approx(5.0, abs=1e-4)


def test_an_unsure_box_before_the_confident_hit_sends_the_ray_to_exact(world):
    pred = _ask(world, {0: _proxy(0.5), 1: _proxy(0.99)})
    assert pred.uncertain[0] and pred.inst[0] == 1  # the hit is known; A may hide a nearer one
    assert pred.first_open[0] == 0  # the box to settle exactly first


def test_boxes_of_visited_shards_are_not_asked_about(world):
    """A's shard (1) was visited: its geometry was intersected exactly, so its unsure box no
    longer holds the ray back."""
    pred = _ask(world, {0: _proxy(0.5), 1: _proxy(0.99)}, visited=1 << 1)
    assert not pred.uncertain[0] and pred.inst[0] == 1 and pred.first_open[0] == -1
    pred = _ask(world, {0: _proxy(0.99), 1: _proxy(0.99)}, visited=(1 << 1) | (1 << 2))
    assert pred.inst[0] == -1 and not pred.uncertain[0]


def test_a_box_without_proxy_counts_only_before_the_confident_hit(world):
    assert not _ask(world, {0: _proxy(0.99)}).uncertain[0]
    pred = _ask(world, {1: _proxy(0.99)})
    assert pred.uncertain[0] and pred.inst[0] == 1


def test_confident_misses_leave_no_hit_and_no_doubt(world):
    pred = _ask(world, {0: _proxy(0.01), 1: _proxy(0.02)})
    assert pred.inst[0] == -1 and np.isinf(pred.t[0]) and not pred.uncertain[0]
    pred = _ask(world, {0: _proxy(0.01), 1: _proxy(0.6)})  # no hit, and B is unsure
    assert pred.inst[0] == -1 and pred.uncertain[0] and pred.first_open[0] == 1


def _ask_from(world, x: float, proxies: dict, margin: float):
    """One ray from (x, 0, 0) along +x, with the internal margin of secondary rays."""
    origin = np.array([[x, 0.0, 0.0]], np.float32)
    direction = np.array([[1.0, 0.0, 0.0]], np.float32)
    return predict(world, proxies, np.array([0, 1], np.int32), origin, direction,
                   np.full(1, np.inf, np.float32), _knobs(margin))


def test_an_internal_hit_within_the_depth_error_of_the_origin_is_settled_not_trusted(world):
    """Inside A the reversed query puts A's surface at x = 5 (A spans 4.5-5.5). With a p90
    depth error of 0.2 diagonals and margin 0.5, surfaces within 0.173 of the origin are
    on an unknown side of it: the ray must visit A's shard, which settles it exactly."""
    a = _proxy(0.99)
    a.meta["report"] = {"depth_err_rel_p90": 0.2}
    proxies = {0: a, 1: _proxy(0.01)}
    far = _ask_from(world, 4.6, proxies, 0.5)  # surface 0.4 ahead: a confident hit
    assert far.inst[0] == 0 and far.internal[0] and not far.uncertain[0]
    assert far.t[0] == pytest.approx(0.4, abs=1e-4)
    for x in (4.9, 5.1):  # 0.1 ahead, 0.1 behind
        near = _ask_from(world, x, proxies, 0.5)
        assert near.uncertain[0] and near.first_open[0] == 0 and near.inst[0] == -1
        paper = _ask_from(world, x, proxies, 0.0)  # the paper's rule trusts the depth net
        assert not paper.uncertain[0] and paper.inst[0] == (0 if x < 5 else -1)


def test_bands_are_per_mesh_and_every_asked_box_is_counted(world):
    """A at visibility 0.7 is trusted under A's band 0.1 and settled under 0.4, whatever B's
    band; both boxes the ray crosses are counted as asked, per mesh."""
    proxies = {0: _proxy(0.7), 1: _proxy(0.99)}
    narrow = _ask(world, proxies, band=(0.1, 0.4))
    assert narrow.inst[0] == 0 and not narrow.uncertain[0]
    wide = _ask(world, proxies, band=(0.4, 0.1))
    assert wide.uncertain[0] and wide.first_open[0] == 0 and wide.inst[0] == 1
    assert sorted(narrow.asked_mesh.tolist()) == [0, 1] and set(narrow.asked_ray) == {0}


def test_a_policys_proxy_constants_go_with_its_knobs(world):
    """predict keeps each knobs' per-mesh constants (and so its proxies) only while the
    knobs live, and a changed proxies dict is not answered from the old one's constants."""
    import gc

    from nprt.workers.routing import proxy_query

    knobs = QueryKnobs(None, np.zeros(2))
    first = proxy_query._bank({0: _proxy(0.7)}, knobs, 2)
    assert proxy_query._bank({0: first.proxy[0]}, knobs, 2) is first
    other = proxy_query._bank({0: first.proxy[0], 1: _proxy(0.2)}, knobs, 2)
    assert other is not first and other.has.tolist() == [True, True]
    held = id(knobs)
    del knobs
    gc.collect()
    assert held not in proxy_query._BANKS
