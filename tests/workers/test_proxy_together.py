"""Proxy mode asks a step's rays and the shadow rays of its last shading together
(`Shard._wavefront_together`: one call of each mesh's nets, not one per ray kind). That
only moves the calls: the film and every statistic but the net-call count are those of
asking per ray kind, and the calls are fewer."""

from __future__ import annotations

from fractions import Fraction

import pytest

from nprt.scene.store import open_scene
from nprt.workers.passes import iter_passes
from nprt.workers.settings import RenderSettings
from nprt.workers.wavefront.inprocess import shards_in_process
from tests.workers.pass_totals import deliver, pass_totals

NET_CALLS = "proxy_net_calls"


def _render(shards, s: RenderSettings) -> tuple[list[bytes], list[dict]]:
    """Each pass run alone over the shards in process, its parcels delivered round by
    round; returns per pass the film sums' bytes and the statistics summed over shards."""
    films, stats = [], []
    for p in iter_passes(s):
        inbox = {p.index % len(shards): ([p], [], {p.index: Fraction(1)})}
        back = Fraction(0)
        while inbox:
            arrived, inbox = inbox, {}
            for sid, (orders, parcels, credits) in sorted(arrived.items()):
                res = shards[sid].step(orders, parcels, credits)
                back += sum(res.returned.values(), Fraction(0))
                deliver(inbox, res.parcels)
        assert back == 1  # every ray of the pass ended
        film, summed = pass_totals(shards, p)
        films.append(film)
        stats.append(summed)
    return films, stats


@pytest.mark.parametrize("k", [3, 4])
def test_asking_both_ray_kinds_together_changes_only_the_net_calls(k):
    # city: every shard asks proxies (forest:small's 24x16 asks none a net answers)
    s = RenderSettings(width=24, height=16, spp=2, spp_per_pass=2, seed=0, shards=k,
                       mode="proxy")
    shards = shards_in_process(open_scene("city:small").load(), s, warm=False)
    runs = {}
    for together in (False, True):
        for sh in shards:
            sh.ask_together = together
        runs[together] = _render(shards, s)
    (films_apart, stats_apart), (films, stats) = runs[False], runs[True]
    assert films == films_apart
    calls = sum(st.pop(("counters", NET_CALLS), 0) for st in stats)
    calls_apart = sum(st.pop(("counters", NET_CALLS), 0) for st in stats_apart)
    assert stats == stats_apart
    assert sum(st.get(("counters", "proxy_queries"), 0) for st in stats) > 0
    assert 0 < calls < calls_apart


def test_shadow_rays_asked_alone_count_their_net_calls_on_their_own_pass():
    """A step whose iteration has only shadow rays left asks the proxies with no ray batch
    bound; the net calls go on the shadow rays' pass, whatever batch (perhaps one of no
    rows, as on a 14-shard render) the step's statistics had bound before."""
    import numpy as np

    from nprt.workers.stats.counters import RenderStats, SplitStats
    from nprt.workers.wavefront.batch import ShadowRayBatch

    s = RenderSettings(width=24, height=16, spp=1, seed=0, shards=3, mode="proxy")
    shards = shards_in_process(open_scene("city:small").load(), s, warm=False)
    rays = shards[0].integrator.primary(next(iter_passes(s)))
    n = len(rays)
    shadow = ShadowRayBatch(origin=rays.origin, direction=rays.direction,
                            tmax=np.full(n, np.inf, np.float32),
                            contribution=np.ones((n, 3), np.float32), pixel=rays.pixel,
                            visited=np.zeros(n, np.uint64), hops=np.zeros(n, np.uint8))
    calls = 0
    for sh in shards:
        stats = SplitStats([RenderStats(), RenderStats()]).bind(np.zeros(0, np.int64))
        tok = np.ones(n, np.int64)  # every shadow ray belongs to the step's second pass
        sh.policy.route_together(None, None, shadow, tok, stats)
        per_pass = stats._counters.get("proxy_net_calls", np.zeros(2, np.int64))
        assert per_pass[0] == 0
        calls += per_pass[1]
    assert calls > 0  # some shard's nets were asked
