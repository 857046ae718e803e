"""A shard that dies in the middle of a render, with several passes in flight, is
restarted by Ray and the passes it held are re-run: the image and the ray counts come out
as if nothing happened."""

from __future__ import annotations

import logging
import time

import pytest
import ray

from nprt.workers.render import render
from nprt.workers.runtime.coordinator import Coordinator
from tests.distributed.helpers import assert_matches, reference, settings

SCENE = "city"
K = 4
KILL_PASS = 2  # of 6 (48x32 in 16-pixel tiles), all 6 in flight at once
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


def _retries(caplog, words: str = "re-running") -> list[str]:
    return [r.getMessage() for r in caplog.records
            if r.name == "nprt.workers.runtime.coordinator" and words in r.getMessage()]


def _render_with_kill(scene, s, kill):
    """Render with `kill(coordinator, shard, items, refs)` called before every work call;
    refs maps shard -> refs of its calls so far (work and collect)."""
    coord = Coordinator(scene, s)
    dispatch, collect, refs = coord._dispatch, coord._collect, {}

    def spy_dispatch(shard, items, parcels):
        kill(coord, shard, items, refs)
        m_ref, out = dispatch(shard, items, parcels)
        refs.setdefault(shard, []).append(m_ref)
        return m_ref, out

    def spy_collect(shard, tokens):
        ref = collect(shard, tokens)
        refs.setdefault(shard, []).append(ref)
        return ref

    coord._dispatch, coord._collect = spy_dispatch, spy_collect
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


def _passes_in_flight(items) -> set[int]:
    return {i.pass_.index for i in items}


def test_shard_killed_with_several_passes_in_flight_reruns_them(
        scenes, s, uninterrupted, ref_image, tmp_path, caplog):
    killed = []

    def kill(coord, shard, items, refs):
        # Kill the shard that is about to get parcels of a later pass, so that calls of
        # several passes are in flight or queued when it dies.
        if not killed and any(i.n_parcels for i in items) and \
                max(_passes_in_flight(items)) >= KILL_PASS:
            killed.append(shard)
            ray.kill(coord.actors[shard], no_restart=False)

    caplog.set_level(logging.WARNING, logger="nprt.workers.runtime.coordinator")
    result, before, _, after = _render_with_kill(scenes[SCENE], s, kill)
    assert killed, "the kill never happened"
    assert after[killed[0]] != before[killed[0]], "the shard was not restarted"
    assert _retries(caplog, "passes in flight"), "no pass was re-run"
    _check(tmp_path, "killed_busy", result, ref_image, uninterrupted)


def test_shard_that_dies_idle_and_restarts_unseen_does_not_lose_its_film(
        scenes, s, uninterrupted, ref_image, tmp_path, caplog):
    killed = []

    def kill(coord, shard, items, refs):
        # A shard that already worked and has no call left in flight dies and is back
        # before the coordinator calls it again: no call of the coordinator ever fails.
        if killed or not any(i.n_parcels for i in items):
            return
        idle = [v for v in refs if v != shard]
        if not idle:
            return
        victim = idle[0]
        ray.wait(refs[victim], num_returns=len(refs[victim]), fetch_local=False)
        killed.append(victim)
        ray.kill(coord.actors[victim], no_restart=False)
        _pid(coord.actors[victim])  # wait until it is back...
        time.sleep(RESTART_SETTLE_S)  # ...and the driver has heard that it restarted
        _pid(coord.actors[victim])

    caplog.set_level(logging.WARNING, logger="nprt.workers.runtime.coordinator")
    result, before, _, after = _render_with_kill(scenes[SCENE], s, kill)
    assert killed, "the kill never happened"
    assert after[killed[0]] != before[killed[0]], "the shard was not restarted"
    assert _retries(caplog, "fewer calls"), "the lost film went unnoticed: no pass was re-run"
    assert not _retries(caplog, "passes in flight"), "a call failed: the test missed its case"
    _check(tmp_path, "killed_idle", result, ref_image, uninterrupted)
