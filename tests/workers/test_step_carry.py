"""A step that carries what it has left after an iteration into the shard's next step
(`Shard.step`, carry; on Ray once parcels wait in the shard's inbox) only regroups rays into
steps: every pass's weight still comes back exactly once, and the film and every statistic
(rays, ray transfers and bytes, hops, counters) are those of steps that run every ray to its
end, but the onnxruntime calls made (`proxy_net_calls`: a call per mesh a batch asks about,
and the batches are grouped otherwise)."""

from __future__ import annotations

from fractions import Fraction

import pytest

from nprt.scene.store import open_scene
from nprt.workers.passes import iter_passes
from nprt.workers.runtime.remote import CARRY_RAYS, carry_when
from nprt.workers.settings import RenderSettings
from nprt.workers.wavefront.inprocess import shards_in_process
from tests.workers.pass_totals import deliver, pass_totals


def _render(shards, s: RenderSettings, carry: bool):
    """Each pass alone over the shards in process, round by round; with carry, every step
    carries its rays left after the first iteration (a shard holding some steps again next
    round, with or without parcels). Returns per pass the film sums' bytes and the
    statistics summed over shards, and the steps that carried rays."""
    films, stats, carried = [], [], 0
    for p in iter_passes(s):
        inbox = {p.index % len(shards): ([p], [], {p.index: Fraction(1)})}
        back = Fraction(0)
        while inbox or any(sh.carried is not None for sh in shards):
            arrived, inbox = inbox, {}
            for sid, sh in enumerate(shards):
                if sid not in arrived and sh.carried is None:
                    continue
                orders, parcels, credits = arrived.get(sid, ([], [], {}))
                res = sh.step(orders, parcels, credits,
                              carry=(lambda left: True) if carry else None)
                carried += res.carried > 0
                assert (res.carried > 0) == (sh.carried is not None)
                back += sum(res.returned.values(), Fraction(0))
                deliver(inbox, res.parcels)
        assert back == 1  # all of the pass's weight came back, once
        film, summed = pass_totals(shards, p)
        films.append(film)
        stats.append(summed)
    return films, stats, carried


@pytest.mark.parametrize("scene, mode, k", [("forest:small", "exact", 3),
                                            ("city:small", "proxy", 3)])
def test_carrying_rays_to_the_next_step_changes_neither_film_nor_statistics(scene, mode, k):
    s = RenderSettings(width=24, height=16, spp=2, spp_per_pass=2, seed=0, shards=k, mode=mode)
    shards = shards_in_process(open_scene(scene).load(), s, warm=False)
    for sh in shards:
        sh.begin(s)
    films, stats, none = _render(shards, s, carry=False)
    for sh in shards:
        sh.begin(s)
    films_carry, stats_carry, carried = _render(shards, s, carry=True)
    assert none == 0 and carried > 0  # steps did carry rays
    assert films_carry == films
    assert _but_calls(stats_carry) == _but_calls(stats)


def _but_calls(stats: list[dict]) -> list[dict]:
    return [{key: v for key, v in st.items() if key != ("counters", "proxy_net_calls")}
            for st in stats]


def test_a_step_carries_only_when_asked_and_only_a_few_rays():
    """A carry that says no: every ray runs to its end in the step. The runtime's rule
    (`remote.carry_when`) carries fewer than CARRY_RAYS rays, and only when rays wait."""
    s = RenderSettings(width=24, height=16, spp=2, spp_per_pass=2, seed=0, shards=2,
                       mode="exact")
    sh = shards_in_process(open_scene("forest:small").load(), s, warm=False)[0]
    p = next(iter(iter_passes(s)))
    sh.begin(s)
    assert sh.step([p], [], {p.index: Fraction(1)}, carry=lambda left: False).carried == 0
    assert sh.carried is None
    rule = carry_when(lambda: True, CARRY_RAYS)
    assert rule(CARRY_RAYS - 1) and not rule(CARRY_RAYS)
    assert not carry_when(lambda: False, CARRY_RAYS)(1)
    assert carry_when(lambda: True, 0) is None
    sh.begin(s)
    res = sh.step([p], [], {p.index: Fraction(1)}, carry=rule)
    assert 0 < res.carried < CARRY_RAYS and sh.carried_rays == res.carried
    # the weight kept with the carried rays, the parcels' and the returned add up to 1
    kept = sum(sh.carried[2].values(), Fraction(0))
    sent = sum((sum(x.credits.values(), Fraction(0)) for x in res.parcels if x is not None),
               Fraction(0))
    assert kept > 0 and kept + sent + sum(res.returned.values(), Fraction(0)) == 1
    generation = sh.films.generation
    sh.reset()  # drops the carried rays with the passes' state and films
    assert sh.carried is None and sh.carried_rays == 0
    assert sh.films.generation == generation + 1
