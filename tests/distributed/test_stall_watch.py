"""The coordinator's guard against weight that never comes back: every shard answering
idle on its own clock for STALL_S while a pass waits means a lost pass, which is re-run
instead of waited for forever; answers read late, or a shard that worked in between, are
no silence."""

from __future__ import annotations

from fractions import Fraction

from nprt.workers.runtime.coordinator import STALL_S, StallWatch
from nprt.workers.runtime.protocol import PollReply


def reply(shard: int, at: float, idle: bool = True, steps: int = 3, parcels_in: int = 5,
          returned=()) -> PollReply:
    return PollReply(shard, "inc", 1, list(returned), steps=steps, parcels_in=parcels_in,
                     idle=idle, at=at)


def test_every_shard_idle_on_its_own_clock_for_stall_s_is_a_stall():
    watch = StallWatch(2)
    for s, t0 in ((0, 100.0), (1, 7.0)):  # the shards' clocks need not agree
        watch.seen(reply(s, t0))
        watch.seen(reply(s, t0 + STALL_S + 1))
    assert watch.stalled(waiting_for_weight=True)
    assert not watch.stalled(waiting_for_weight=False)  # nothing waits: all done


def test_answers_read_late_are_no_silence():
    """A coordinator busy elsewhere reads answers given moments apart: the shard's clock,
    not the time of reading, measures the silence."""
    watch = StallWatch(2)
    for s in (0, 1):
        for at in (10.0, 10.25, 10.5):
            watch.seen(reply(s, at))
    assert not watch.stalled(waiting_for_weight=True)


def test_a_shard_that_worked_between_idle_answers_starts_a_new_quiet_spell():
    watch = StallWatch(2)
    watch.seen(reply(0, 0.0))
    watch.seen(reply(0, STALL_S + 1, steps=4))  # a step ran in between
    watch.seen(reply(1, 0.0))
    watch.seen(reply(1, STALL_S + 1))
    assert not watch.stalled(waiting_for_weight=True)
    watch.seen(reply(0, 2 * STALL_S + 2, steps=4))
    assert watch.stalled(waiting_for_weight=True)


def test_a_busy_shard_or_weight_handed_back_is_no_silence():
    watch = StallWatch(2)
    watch.seen(reply(0, 0.0))
    watch.seen(reply(0, STALL_S + 1))
    watch.seen(reply(1, 0.0))
    watch.seen(reply(1, STALL_S + 1, idle=False))
    assert not watch.stalled(waiting_for_weight=True)
    watch.seen(reply(1, STALL_S + 2, returned=[(0, Fraction(1, 2))]))
    watch.seen(reply(1, 3 * STALL_S))
    assert not watch.stalled(waiting_for_weight=True)
