"""A shard that dies in the middle of a render, with several passes in flight and parcels
moving shard to shard, is restarted by Ray and the passes in flight are re-run: the film
sums (bit for bit) and the ray counts come out as if nothing happened."""

from __future__ import annotations

import logging
import time

import numpy as np
import pytest
import ray

from nprt.workers.render import render
from nprt.workers.runtime import coordinator
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
def uninterrupted(ray_local, scenes, s):
    result = render(scenes[SCENE], s)
    return result.stats.to_dict(), result.film.sums.copy()


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
            if r.name == "nprt.workers.runtime.coordinator" and "re-running" in r.getMessage()]


def _render(scene, s, wrap):
    """Render with the coordinator's seams (_order, _poll) wrapped by `wrap(coord)`."""
    coord = Coordinator(scene, s)
    wrap(coord)
    try:
        pids = [i["pid"] for i in coord.shard_info]
        result = render(scene, s, renderer=coord)
        return result, pids, coord, [_pid(a) for a in coord.actors]
    finally:
        coord.close()


def _check(tmp_path, name, result, ref_image, uninterrupted):
    stats, sums = uninterrupted
    assert_matches(tmp_path, name, result.film.image(), ref_image)
    assert np.array_equal(result.film.sums, sums), "the film sums differ from an unfaulted run"
    st = result.stats.to_dict()
    for key in COUNTED:  # nothing counted twice, nothing lost
        assert st[key] == stats[key], (key, st[key], stats[key])


def test_shard_killed_with_several_passes_in_flight_reruns_them(
        scenes, s, uninterrupted, ref_image, tmp_path, caplog):
    killed = []

    def wrap(coord):
        order = coord._order

        def kill_after_order(shard, passes, epoch):
            # Passes 0 .. KILL_PASS are live and their rays are moving shard to shard.
            order(shard, passes, epoch)
            if not killed and max(p.index for p in passes) >= KILL_PASS:
                killed.append(shard)
                ray.kill(coord.actors[(shard + 1) % K], no_restart=False)

        coord._order = kill_after_order

    caplog.set_level(logging.WARNING, logger="nprt.workers.runtime.coordinator")
    result, before, coord, after = _render(scenes[SCENE], s, wrap)
    victim = (killed[0] + 1) % K
    assert killed, "the kill never happened"
    assert after[victim] != before[victim], "the shard was not restarted"
    assert _retries(caplog) and coord.reruns >= 1, "no pass was re-run"
    _check(tmp_path, "killed_busy", result, ref_image, uninterrupted)


def test_shard_that_dies_between_polls_and_restarts_unseen_is_caught(
        scenes, s, uninterrupted, ref_image, tmp_path, caplog, monkeypatch):
    # films ride on polls at this K too (shipped from K = 8): a poll that carries films
    # reaches the restarted shard, and the sums still equal the unfaulted run's
    monkeypatch.setattr(coordinator, "COLLECT_ON_POLL_FROM_K", 1)
    killed = []

    def wrap(coord):
        poll = coord._poll

        def kill_then_poll(shard, epoch, collect=None):
            # After its first reply, the shard dies and is back before the coordinator
            # polls it again: no call of the coordinator fails, only the incarnation tells.
            if not killed and coord.totals[shard] is not None and coord.totals[shard].steps:
                killed.append(shard)
                ray.kill(coord.actors[shard], no_restart=False)
                _pid(coord.actors[shard])  # wait until it is back...
                time.sleep(RESTART_SETTLE_S)  # ...and the driver has heard that it restarted
                _pid(coord.actors[shard])
            return poll(shard, epoch, collect)

        coord._poll = kill_then_poll

    caplog.set_level(logging.WARNING, logger="nprt.workers.runtime.coordinator")
    result, before, coord, after = _render(scenes[SCENE], s, wrap)
    assert killed, "the kill never happened"
    assert after[killed[0]] != before[killed[0]], "the shard was not restarted"
    assert any("_Restarted" in m for m in _retries(caplog)), _retries(caplog)
    _check(tmp_path, "killed_idle", result, ref_image, uninterrupted)
