"""A step that sends what is leaving before it ends (`Shard.step`, emit; on Ray
`remote.EMIT_RAYS`) only cuts its parcels into more pieces: every pass's weight still comes
back exactly once, and the film and every statistic are those of a step that sends only at
its end."""

from __future__ import annotations

import functools
from fractions import Fraction

import pytest

from nprt.scene.store import open_scene
from nprt.workers.passes import iter_passes
from nprt.workers.settings import RenderSettings
from nprt.workers.wavefront.inprocess import shards_in_process
from tests.workers.pass_totals import deliver, pass_totals


def _render(shards, s: RenderSettings, emit_rays: int | None):
    """Each pass alone over the shards in process, its parcels (those emitted during a
    step too, with emit_rays set) delivered round by round. Returns per pass the film
    sums' bytes and the statistics summed over shards, and the parcels sent early."""
    films, stats, early = [], [], [0]
    for p in iter_passes(s):
        inbox = {p.index % len(shards): ([p], [], {p.index: Fraction(1)})}
        back = Fraction(0)
        while inbox:
            arrived, inbox = inbox, {}
            emit = None
            if emit_rays is not None:
                emit = functools.partial(_deliver, inbox, early)
            for sid, (orders, parcels, credits) in sorted(arrived.items()):
                res = shards[sid].step(orders, parcels, credits, emit, emit_rays or 0)
                back += sum(res.returned.values(), Fraction(0))
                _deliver(inbox, None, res.parcels)
        assert back == 1  # all of the pass's weight came back, once
        film, summed = pass_totals(shards, p)
        films.append(film)
        stats.append(summed)
    return films, stats, early[0]


def _deliver(inbox: dict, early: list | None, parcels: list) -> None:
    """Parcels ((k,) Parcel or None) into the next round's inbox; early: a [count] of
    parcels sent before their step ended, or None."""
    sent = deliver(inbox, parcels)
    if early is not None:
        early[0] += sent


@pytest.mark.parametrize("scene, mode, k", [("forest:small", "exact", 3),
                                            ("city:small", "proxy", 3)])
def test_sending_during_a_step_changes_neither_film_nor_statistics(scene, mode, k):
    s = RenderSettings(width=24, height=16, spp=2, spp_per_pass=2, seed=0, shards=k, mode=mode)
    shards = shards_in_process(open_scene(scene).load(), s, warm=False)
    for sh in shards:
        sh.begin(s)
    films, stats, none = _render(shards, s, None)
    for sh in shards:
        sh.begin(s)
    films_emit, stats_emit, early = _render(shards, s, 1)
    assert none == 0 and early > 0  # parcels did leave during steps
    assert films_emit == films
    assert stats_emit == stats
