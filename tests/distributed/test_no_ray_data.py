"""The coordinator is off the ray path: it never reads a ray batch back. Checked by
recording every ray.get made in its module and looking into what each returned."""

from __future__ import annotations

import numpy as np
import pytest
import ray

import nprt.workers.runtime.coordinator as coordinator_module
from nprt.workers.render import render
from nprt.workers.runtime.coordinator import Coordinator
from nprt.workers.runtime.protocol import Parcel, PollReply
from nprt.workers.wavefront.batch import RayBatch, ShadowRayBatch
from tests.distributed.helpers import assert_matches, settings

RAY_DATA = (RayBatch, ShadowRayBatch, Parcel)


def _types(x, out: set) -> set:
    """Every type inside x, looking into tuples, lists, dicts and dataclass-like objects."""
    out.add(type(x))
    if isinstance(x, list | tuple):
        for v in x:
            _types(v, out)
    elif isinstance(x, dict):
        for v in x.values():
            _types(v, out)
    elif hasattr(x, "__dict__") and not isinstance(x, type):
        for v in vars(x).values():
            _types(v, out)
    return out


class RecordingRay:
    """Stands in for the `ray` module inside nprt.workers.runtime.coordinator; records what get
    returns."""

    def __init__(self):
        self.got: set[type] = set()
        self.calls = 0

    def get(self, refs, *args, **kwargs):
        out = ray.get(refs, *args, **kwargs)
        self.calls += 1
        _types(out, self.got)
        return out

    def __getattr__(self, name):
        return getattr(ray, name)


@pytest.fixture
def recorder(monkeypatch) -> RecordingRay:
    rec = RecordingRay()
    monkeypatch.setattr(coordinator_module, "ray", rec)
    return rec


def test_recorder_sees_a_parcel_read_back(ray_local, recorder):
    """The check below can fail: a Parcel fetched through the module's ray.get is caught."""
    parcel = Parcel(0, {}, RayBatch.empty(), ShadowRayBatch.empty())
    coordinator_module.ray.get(ray.put(parcel))
    assert {Parcel, RayBatch, ShadowRayBatch} <= recorder.got


@pytest.mark.parametrize("k", (2, 4), ids=lambda k: f"k{k}")
def test_coordinator_never_reads_ray_batches(ray_local, recorder, scenes, references, tmp_path,
                                             k):
    coord = Coordinator(scenes["forest"], settings(k, tile_size=32))
    try:
        result = render(scenes["forest"], coord.s, renderer=coord)
    finally:
        coord.close()
    # It did render, through the recorded module, and rays did move between shards.
    assert_matches(tmp_path, f"forest_k{k}", result.film.image(),
                   references["forest"].film.image())
    assert result.stats.to_dict()["total_transfers"] > 0
    assert recorder.calls > 0
    # What it read: poll replies (weights, totals) and collected films.
    assert PollReply in recorder.got and tuple in recorder.got, recorder.got
    # Everything any ray.get in the module returned, looked into: no ray data anywhere.
    leaked = {t for t in recorder.got if issubclass(t, RAY_DATA)}
    assert not leaked, f"the coordinator read back {sorted(t.__name__ for t in leaked)}"
    assert np.ndarray in recorder.got  # the film sums did come through the recorder
