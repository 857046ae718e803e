"""A shard's long poll left over from an earlier run (the coordinator drops its last one
when a frame or a re-run ends) must not take the weight of the run that follows: that
weight would reach no one, and the pass would never complete (bench_frames --smoke hung
so in CI). The mailbox is driven in this process, with its real wavefront thread idle."""

from __future__ import annotations

import threading
from fractions import Fraction

from nprt.workers.runtime.protocol import ShardConfig
from nprt.workers.runtime.remote import ShardActor
from nprt.workers.settings import RenderSettings


def _finish_step(actor: ShardActor, weight: list) -> None:
    """What a step that ends a pass's rays does (ShardActor._run): hand back its weight."""
    with actor._cv:
        actor._returned += weight
        actor._cv.notify_all()


def test_a_poll_of_an_earlier_run_leaves_the_next_runs_weight():
    actor = ShardActor(ShardConfig(0, 1, RenderSettings()))
    with actor._cv:
        actor._epoch = 1
    stale: list = []
    waiter = threading.Thread(target=lambda: stale.append(actor.poll(1, 30.0)))
    waiter.start()
    with actor._cv:  # the next run begins (ShardActor.begin) while that poll still waits
        actor._epoch = 2
    _finish_step(actor, [(7, Fraction(1))])
    waiter.join(timeout=30.0)
    assert not waiter.is_alive()
    assert stale[0].returned == []
    assert actor.poll(2, 0.0).returned == [(7, Fraction(1))]
