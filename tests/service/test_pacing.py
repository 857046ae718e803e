"""LoopPacer: a burst's steps share the event loop's turns, so what arrives meanwhile (a
health check) waits for a few steps, not for the whole burst."""

from __future__ import annotations

import asyncio

import pytest
import uvloop

from nprt.service.pacing import LoopPacer


async def _burst(pacer: LoopPacer, n: int) -> dict:
    """n tasks of two paced steps each, and a health check arriving once they all wait.
    Returns the steps run per loop turn, the order the first steps ran in, and how many
    steps ran between the health check's arrival and its answer."""
    loop = asyncio.get_running_loop()
    turn, steps, order, done = 0, {}, [], False

    def tick() -> None:  # counts the loop's turns
        nonlocal turn
        turn += 1
        if not done:
            loop.call_soon(tick)

    loop.call_soon(tick)

    def step() -> None:
        steps[turn] = steps.get(turn, 0) + 1

    async def job(i: int) -> None:
        await pacer.turn()
        step()
        order.append(i)
        await asyncio.sleep(0)  # the store write
        await pacer.turn()
        step()

    tasks = [asyncio.ensure_future(job(i)) for i in range(n)]
    await asyncio.sleep(0)
    arrived = sum(steps.values())

    async def health() -> int:
        return sum(steps.values()) - arrived

    behind = await asyncio.ensure_future(health())
    await asyncio.gather(*tasks)
    done = True
    return {"steps": steps, "order": order, "behind": behind}


@pytest.mark.parametrize("run", [asyncio.run, uvloop.run], ids=["asyncio", "uvloop"])
def test_a_burst_runs_at_most_per_turn_steps_a_turn_first_come_first_served(run):
    got = run(_burst(LoopPacer(per_turn=16), 250))
    assert sum(got["steps"].values()) == 500
    assert max(got["steps"].values()) <= 16
    assert got["order"] == list(range(250))
    assert got["behind"] <= 2 * 16  # not the 250 steps a turn without the pacer


def test_pacer_serves_a_new_event_loop_after_the_first_closed():
    pacer = LoopPacer(per_turn=4)
    for _ in range(2):  # an app run again on a fresh loop (a test client, a restart)
        got = asyncio.run(_burst(pacer, 20))
        assert sum(got["steps"].values()) == 40 and max(got["steps"].values()) <= 4


def test_pacer_refuses_no_room():
    with pytest.raises(ValueError, match="per_turn must be >= 1, got 0"):
        LoopPacer(per_turn=0)
