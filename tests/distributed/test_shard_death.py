"""A shard that dies in the middle of a render is restarted by Ray (max_restarts=-1) and
the pass it was in is re-run: the image and the ray counts come out as if nothing happened."""

from __future__ import annotations

import logging
import time

import pytest
import ray

from tests.distributed.helpers import assert_matches, reference, settings
from workers.coordinator import Coordinator
from workers.render import render

SCENE = "city"
K = 4
KILL_PASS = 2  # of 6: 48x32 in 16-pixel tiles
# Ray fails calls that are in flight when the driver learns of a restart (ActorUnavailableError);
# let that news settle so the coordinator's next call reaches the new actor without an error.
RESTART_SETTLE_S = 1.0
COUNTED = ("rays", "transfers", "bytes", "hops_histogram", "counters")


@pytest.fixture(scope="module")
def s():
    return settings(K, tile_size=16)


@pytest.fixture(scope="module")
def uninterrupted(ray_local, scenes, s) -> dict:
    return render(scenes[SCENE], s).stats.to_dict()


@pytest.fixture(scope="module")
def ref_image(scenes, s):
    return reference(scenes[SCENE], s).film.image()


def _pid(actor) -> int:
    for _ in range(100):
        try:
            return ray.get(actor.ready.remote(), timeout=30)["pid"]
        except ray.exceptions.RayActorError:  # still restarting
            time.sleep(0.2)
    raise TimeoutError("shard did not come back")


def _retries(caplog) -> list[str]:
    return [r.getMessage() for r in caplog.records
            if r.name == "workers.coordinator" and "re-running" in r.getMessage()]


def _render_with_kill(scene, s, kill):
    """Render with `kill(coordinator, shard, method, pass_index, seen)` called before every
    actor call; seen maps shard -> manifest refs of its calls so far in the pass."""
    coord = Coordinator(scene, s)
    call, seen = coord._call, {}

    def spy(shard, method, p, *parcels):
        if not seen.get("_pass") == p.index:
            seen.clear()
            seen["_pass"] = p.index
        kill(coord, shard, method, p.index, seen)
        m_ref, out = call(shard, method, p, *parcels)
        seen.setdefault(shard, []).append(m_ref)
        return m_ref, out

    coord._call = spy
    try:
        pids = [i["pid"] for i in coord.shard_info]
        result = render(scene, s, renderer=coord)
        return result, pids, coord, [_pid(a) for a in coord.actors]
    finally:
        coord.close()


def _check(tmp_path, name, result, ref_image, uninterrupted):
    assert_matches(tmp_path, name, result.film.image(), ref_image)
    st = result.stats.to_dict()
    for key in COUNTED:  # nothing counted twice, nothing lost
        assert st[key] == uninterrupted[key], (key, st[key], uninterrupted[key])


def test_shard_killed_with_calls_in_flight_reruns_the_pass(scenes, s, uninterrupted, ref_image,
                                                           tmp_path, caplog):
    killed = []

    def kill(coord, shard, method, index, seen):
        # Kill the shard that is about to get work, right after earlier work of this pass,
        # so that calls to it are in flight or queued when it dies.
        if index == KILL_PASS and not killed and method == "process":
            killed.append(shard)
            ray.kill(coord.actors[shard], no_restart=False)

    caplog.set_level(logging.WARNING, logger="workers.coordinator")
    result, before, _, after = _render_with_kill(scenes[SCENE], s, kill)
    assert killed, "the kill never happened"
    assert after[killed[0]] != before[killed[0]], "the shard was not restarted"
    assert _retries(caplog), "no pass was re-run"
    _check(tmp_path, "killed_busy", result, ref_image, uninterrupted)


def test_shard_that_dies_idle_and_restarts_unseen_does_not_lose_its_film(
        scenes, s, uninterrupted, ref_image, tmp_path, caplog):
    killed = []

    def kill(coord, shard, method, index, seen):
        # A shard that already worked in this pass and has no call left in flight dies and is
        # back before the coordinator calls it again: no call of the coordinator ever fails.
        if index != KILL_PASS or killed:
            return
        idle = [v for v in seen if v not in ("_pass", shard)]
        if not idle:
            return
        victim = idle[0]
        ray.wait(seen[victim], num_returns=len(seen[victim]), fetch_local=False)
        killed.append(victim)
        ray.kill(coord.actors[victim], no_restart=False)
        _pid(coord.actors[victim])  # wait until it is back...
        time.sleep(RESTART_SETTLE_S)  # ...and the driver has heard that it restarted
        _pid(coord.actors[victim])

    caplog.set_level(logging.WARNING, logger="workers.coordinator")
    result, before, _, after = _render_with_kill(scenes[SCENE], s, kill)
    assert killed, "the kill never happened"
    assert after[killed[0]] != before[killed[0]], "the shard was not restarted"
    assert _retries(caplog), "the lost film went unnoticed: no pass was re-run"
    _check(tmp_path, "killed_idle", result, ref_image, uninterrupted)
