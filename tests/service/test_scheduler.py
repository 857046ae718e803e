"""The job API and the scheduler without HTTP: cancel racing completion, retries after a
lost Ray node, renderers always closed, cancel while preparing, Ray start retries, stored
cancels."""

from __future__ import annotations

import random
import threading
import time

import numpy as np
import pytest

import nprt.workers.runtime.coordinator as coordinator
import nprt.workers.runtime.raysession as raysession
from nprt.service import raystart, runjob
from nprt.service.errors import Conflict
from nprt.service.jobapi import JobApi
from nprt.service.raystart import RayStarter, RayUnavailable
from nprt.service.scenes import SceneStore
from nprt.service.scheduler import Scheduler
from nprt.service.store import TERMINAL
from nprt.workers.passes import count_passes, iter_passes
from nprt.workers.render import render as real_render
from nprt.workers.settings import RenderSettings
from tests.service.helpers import settings_for, wait_for

FAST = {"width": 8, "height": 8, "spp": 1, "bounces": 1, "shadow_rays": 1, "tile_size": 8,
        "spp_per_pass": 1}
SHARDED = {**FAST, "width": 16, "height": 16, "spp": 2, "shards": 2}  # 8 passes


class _Service:
    """A JobApi and a Scheduler on one data directory: they share only the store."""

    def __init__(self, settings):
        self.api = JobApi(settings, SceneStore(settings)).start()
        self.scheduler = Scheduler(settings).start()

    def __getattr__(self, name):
        return getattr(self.api, name)

    def stop(self) -> None:
        self.scheduler.stop(timeout_s=None)
        self.api.stop()


def _manager(tmp_path, **overrides) -> _Service:
    return _Service(settings_for(tmp_path, **overrides))


@pytest.fixture
def manager(tmp_path):
    m = _manager(tmp_path)
    yield m
    m.stop()


def _done(m: _Service, job_id: str, timeout_s: float = 60.0):
    return wait_for(lambda: (r := m.get(job_id)).state in TERMINAL and r, timeout_s,
                    what=f"job {job_id} finished")


@pytest.mark.parametrize("w,h,spp,tile,chunk", [(1, 1, 1, 8, 1), (100, 40, 7, 32, 3),
                                                (64, 64, 16, 64, 4), (33, 65, 5, 16, 5)])
def test_count_passes_equals_the_length_of_the_plan(w, h, spp, tile, chunk):
    s = RenderSettings(width=w, height=h, spp=spp, tile_size=tile, spp_per_pass=chunk)
    assert count_passes(s) == len(list(iter_passes(s)))


def test_cancel_racing_completion_in_the_manager_never_leaves_a_terminal_state(manager):
    """One-pass jobs cancelled at random moments around their end: every watcher sees
    nothing after the first terminal state, and an accepted cancel ends canceled."""
    rng = random.Random(0)
    jobs = []
    for _ in range(30):
        rec, _ = manager.submit("forest:tiny", RenderSettings(**FAST))
        sub = manager.watch(rec.id, lambda: None)
        time.sleep(rng.uniform(0.0, 0.05))  # vary the moment; any outcome must be consistent
        try:
            manager.cancel(rec.id)
            accepted = True
        except Conflict as e:
            assert "already succeeded" in str(e)
            accepted = False
        jobs.append((rec.id, sub, accepted))
    outcomes = set()
    for job_id, sub, accepted in jobs:
        final = _done(manager, job_id)
        outcomes.add(final.state)
        assert final.state == ("canceled" if accepted else "succeeded"), final
        events = []
        # The feed hands the watcher the terminal state within a poll of the store.
        wait_for(lambda s=sub, ev=events: ev.extend(s.drain()) or any(
            e["type"] == "state" and e["job"].state in TERMINAL for e in ev), 10,
            what="the terminal state event")
        states = [e["job"].state for e in events if e["type"] == "state"]
        first_terminal = next(i for i, s in enumerate(states) if s in TERMINAL)
        assert states[first_terminal:] == [final.state] * (len(states) - first_terminal)
        assert manager.get(job_id).state == final.state
        sub.close()
    assert "canceled" in outcomes


class _FakeShards:
    """Stands in for a Coordinator: records that it was closed."""

    made: list[_FakeShards] = []

    def __init__(self, *args, **kwargs):
        self.closed = False
        _FakeShards.made.append(self)

    def close(self) -> None:
        self.closed = True


@pytest.fixture
def fake_shards(monkeypatch):
    _FakeShards.made = []
    monkeypatch.setattr(runjob, "make_renderer", _FakeShards)
    monkeypatch.setattr(RayStarter, "ensure", lambda self: None)
    return _FakeShards


def _losing_render(lose_times: int, calls: list):
    """render() that renders on one process, and the first `lose_times` times loses its
    shards after one more pass, as when a Ray node dies."""
    def fake(scene, settings, *, resume, cancel, renderer, on_pass):
        calls.append(resume.next_pass if resume else 0)
        local = RenderSettings(**{**settings.model_dump(), "shards": 0})
        attempt = len(calls)

        def on_pass_then_lose(p):
            on_pass(p)
            if attempt <= lose_times and p.index == calls[-1]:  # one pass per attempt
                raise coordinator.ShardsLost(f"shards did not come back while aborting "
                                             f"pass {p.index + 1}")

        return real_render(scene, local, resume=resume, cancel=cancel,
                           on_pass=on_pass_then_lose)
    return fake


def _sharded_job_losing_nodes(tmp_path, monkeypatch, lose_times: int):
    """(manager, final job record, resume points of each attempt) with 2 retries allowed."""
    calls = []
    monkeypatch.setattr(runjob, "render", _losing_render(lose_times, calls))
    m = _manager(tmp_path, max_job_retries=2)
    try:
        rec, _ = m.submit("forest:tiny", RenderSettings(**SHARDED))
        final = _done(m, rec.id)
    finally:
        m.stop()
    return m, final, calls


def test_job_that_loses_its_node_resumes_from_its_checkpoint(tmp_path, monkeypatch,
                                                             fake_shards):
    m, final, calls = _sharded_job_losing_nodes(tmp_path, monkeypatch, lose_times=1)
    assert final.state == "succeeded", final.error
    assert final.retries == 1 and calls == [0, 1]  # the retry resumed after pass 0
    assert final.pixel_samples == {"min": 2, "max": 2}
    assert all(r.closed for r in fake_shards.made) and len(fake_shards.made) == 2
    direct = real_render(m.scenes.load("forest:tiny"), RenderSettings(**{**SHARDED,
                                                                         "shards": 0}))
    sums = np.load(m.job_dir(final.id) / "sums.npy")
    np.testing.assert_array_equal(sums, direct.film.sums)


def test_job_that_keeps_losing_nodes_fails_after_the_retry_limit(tmp_path, monkeypatch,
                                                                 fake_shards):
    _, final, calls = _sharded_job_losing_nodes(tmp_path, monkeypatch, lose_times=99)
    assert final.state == "failed" and final.retries == 2 and calls == [0, 1, 2]
    assert final.error == "ShardsLost: shards did not come back while aborting pass 3"
    assert all(r.closed for r in fake_shards.made) and len(fake_shards.made) == 3


def test_renderer_that_fails_to_start_fails_the_job_with_the_reason(manager, monkeypatch):
    def broken(*args, **kwargs):
        raise coordinator.ShardStartError("shard 1 did not start: MemoryError in __init__")

    monkeypatch.setattr(runjob, "make_renderer", broken)
    monkeypatch.setattr(RayStarter, "ensure", lambda self: None)
    rec, _ = manager.submit("forest:tiny", RenderSettings(**SHARDED))
    final = _done(manager, rec.id)
    assert (final.state, final.retries) == ("failed", 0)
    assert final.error == "ShardStartError: shard 1 did not start: MemoryError in __init__"


def test_cancel_while_preparing_stops_before_rendering_and_closes_the_renderer(
        manager, monkeypatch):
    """The renderer is closed before the job shows as canceled: whoever sees the end sees
    its shards released (once the state was published first, and this test raced it)."""
    starting, release, made, state_at_close = threading.Event(), threading.Event(), [], []

    class SlowStart(_FakeShards):
        def __init__(self, *args, **kwargs):
            super().__init__()
            made.append(self)
            starting.set()
            release.wait(30)

        def close(self) -> None:
            state_at_close.append(manager.get(rec.id).state)
            super().close()

    def must_not_render(*args, **kwargs):
        raise AssertionError("rendered after a cancel")

    monkeypatch.setattr(runjob, "make_renderer", SlowStart)
    monkeypatch.setattr(runjob, "render", must_not_render)
    monkeypatch.setattr(RayStarter, "ensure", lambda self: None)
    rec, _ = manager.submit("forest:tiny", RenderSettings(**SHARDED))
    assert starting.wait(30)
    assert manager.get(rec.id).state == "preparing"
    canceled = manager.cancel(rec.id)
    assert canceled.state == "preparing" and canceled.cancel_requested
    release.set()
    final = _done(manager, rec.id)
    assert final.state == "canceled" and made[0].closed
    assert state_at_close == ["preparing"]


def test_ray_start_is_retried_then_fails_naming_the_address(tmp_path, monkeypatch):
    tries = []

    def flaky(address):
        tries.append(address)
        if len(tries) < 3:
            raise ConnectionError("GCS did not answer")
        return False

    monkeypatch.setattr(raysession, "ensure_ray", flaky)
    monkeypatch.setattr(raystart, "RAY_RETRY_S", 0.0)
    starter = RayStarter("10.255.0.1:6379", attempts=3)
    starter.ensure()
    assert tries == ["10.255.0.1:6379"] * 3

    def down(address):
        raise ConnectionError("GCS did not answer")

    monkeypatch.setattr(raysession, "ensure_ray", down)
    with pytest.raises(RayUnavailable) as e:
        starter.ensure()
    assert str(e.value) == ("could not join the Ray cluster at 10.255.0.1:6379 in 3 attempts: "
                            "ConnectionError: GCS did not answer")


def test_stored_cancel_of_a_running_job_is_honoured_on_restart(tmp_path):
    """As if the process died after storing the cancel and before the renderer saw it."""
    settings = settings_for(tmp_path)
    first = JobApi(settings, SceneStore(settings))  # no scheduler: nothing renders
    rec, _ = first.submit("forest:tiny", RenderSettings(**FAST))
    assert first.store.transition(rec.id, "running", ("queued",))
    assert first.store.request_cancel(rec.id)
    first.stop()
    second = _manager(tmp_path)
    try:
        final = second.get(rec.id)
        assert final.state == "canceled" and final.finished_at is not None
        assert second.list()[0][0].id == rec.id
    finally:
        second.stop()
