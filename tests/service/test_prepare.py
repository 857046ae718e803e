"""A Coordinator whose shards cannot start cleans up after itself (no placement group, no
live actor), and a shard that keeps dying in its constructor fails the start with the
reason after a bounded number of restarts instead of restarting for ever."""

from __future__ import annotations

import logging
import os

import pytest

ray = pytest.importorskip("ray")

import nprt.workers.runtime.coordinator as coordinator  # noqa: E402
import nprt.workers.runtime.pool as pool  # noqa: E402
from nprt.scene.demos import make_demo  # noqa: E402
from nprt.workers.runtime.remote import ShardActor  # noqa: E402
from nprt.workers.settings import RenderSettings  # noqa: E402

pytestmark = pytest.mark.slow
SETTINGS = RenderSettings(width=16, height=16, spp=1, bounces=1, shadow_rays=1, tile_size=16,
                          spp_per_pass=1, shards=2)


@pytest.fixture(scope="module")
def local_ray():
    started = not ray.is_initialized()
    if started:
        ray.init(address="local", num_cpus=2, include_dashboard=False, log_to_driver=False,
                 logging_level=logging.WARNING)
    yield
    if started:
        ray.shutdown()


def _actors(class_name: str) -> list[dict]:
    return [a for a in ray._private.state.actors().values()
            if a["ActorClassName"].endswith(class_name)]


def _assert_nothing_left(class_name: str) -> None:
    assert all(pg["state"] == "REMOVED" for pg in ray.util.placement_group_table().values())
    actors = _actors(class_name)
    assert actors and all(a["State"] == "DEAD" for a in actors), actors


def test_shard_raising_in_its_constructor_fails_the_start_and_leaves_nothing(
        local_ray, monkeypatch):
    class RaisingShard(ShardActor):
        def __init__(self, config, *args):
            if config.shard_id == 1:
                raise MemoryError("simulated: no memory for the mesh BVH")
            super().__init__(config, *args)

    monkeypatch.setattr(pool, "ShardActor", RaisingShard)
    with pytest.raises(pool.ShardStartError) as e:
        coordinator.Coordinator(make_demo("forest", "tiny"), SETTINGS)
    assert str(e.value).startswith("shard 1 did not start: ")
    assert "simulated: no memory for the mesh BVH" in str(e.value)
    _assert_nothing_left("RaisingShard")


def test_shard_dying_in_its_constructor_is_restarted_a_bounded_number_of_times(
        local_ray, monkeypatch):
    class DyingShard(ShardActor):
        def __init__(self, config, *args):
            if config.shard_id == 0:
                os._exit(1)  # as the kernel's OOM killer would
            super().__init__(config, *args)

    monkeypatch.setattr(pool, "ShardActor", DyingShard)
    with pytest.raises(pool.ShardStartError, match="shard 0 did not start: "):
        coordinator.Coordinator(make_demo("forest", "tiny"), SETTINGS)
    _assert_nothing_left("DyingShard")
    restarts = [a["NumRestarts"] for a in _actors("DyingShard")]
    assert sorted(restarts)[-1] == pool.MAX_SHARD_RESTARTS, restarts
