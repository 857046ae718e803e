"""bench_shard_threads reads threads by their OS names: the wavefront thread's own, Ray's
Python-running threads by the process title, the rest by theirs."""

from __future__ import annotations

import os
import sys
import threading

import pytest

from bench.render.bench_shard_threads import group, markdown, split, threads_cpu
from nprt.workers.runtime.remote import WAVEFRONT_THREAD, name_os_thread

pytestmark = pytest.mark.skipif(not sys.platform.startswith("linux"), reason="/proc and prctl")


def test_a_named_thread_shows_its_name_and_counts_as_the_wavefront():
    seen = {}

    def body():
        name_os_thread(WAVEFRONT_THREAD)
        tid = threading.get_native_id()
        seen["threads"] = threads_cpu(os.getpid())
        seen["tid"] = tid

    t = threading.Thread(target=body)
    t.start()
    t.join()
    names = {tid: name for tid, name in seen["threads"]}
    assert names[seen["tid"]] == WAVEFRONT_THREAD[:15]
    assert group(names[seen["tid"]]) == "wavefront"


def test_groups_of_ray_threads():
    assert group("ray::ShardActor") == "ray python threads"
    assert group("worker.io") == "worker.io"


def test_a_thread_born_between_readings_counts_from_zero():
    before = {(1, "worker.io"): 2.0}
    after = {(1, "worker.io"): 2.5, (2, "ray::ShardActor"): 0.25}
    assert split(before, after) == {"worker.io": 0.5, "ray python threads": 0.25}


def test_a_render_too_short_for_a_tick_still_makes_its_table():
    """/proc counts CPU in ticks (10 ms): the smoke run's tiny render shows none at all."""
    row = {"scene": "forest", "mode": "exact", "k": 2, "render_s": 0.1, "parcels": 5,
           "cpu_s": {"wavefront": 0.0, "ray python threads": 0.0}, "total_cpu_s": 0.0,
           "ray_ms_per_parcel": 0.0}
    table = markdown({"rows": [row]})
    assert table.splitlines()[-1].startswith("| forest | exact | 2 | 0.10 | 0.00 | 0.00 |")
