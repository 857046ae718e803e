"""Turns of an API worker's event loop shared out during a burst: at most `per_turn`
admissions run a step (validation, or building the answer) per turn, so a health check or a
read that arrives meanwhile is answered within a turn or two instead of after every
admission of the burst. An event loop runs every callback that is ready at the start of a
turn before it looks at its sockets again: 250 admissions ready at once made a turn of
15-30 ms of CPU (more on a busy host), and a /healthz waited for it."""

from __future__ import annotations

import asyncio
from collections import deque


class LoopPacer:
    """One per event loop (an API worker's). turn() returns at once while this turn has
    room and nobody waits; otherwise the caller waits, first come first served, for a later
    turn. Callers: (async) `await pacer.turn()` before each CPU-heavy step."""

    def __init__(self, per_turn: int = 16):
        if per_turn < 1:
            raise ValueError(f"per_turn must be >= 1, got {per_turn}")
        self.per_turn = per_turn
        self._room = per_turn  # steps still allowed in this turn
        self._waiting: deque[asyncio.Future] = deque()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._next_turn_due = False

    async def turn(self) -> None:
        loop = asyncio.get_running_loop()
        if loop is not self._loop:  # first use, or the app now runs on another loop
            self._loop, self._waiting, self._room = loop, deque(), self.per_turn
            self._next_turn_due = False
        if not self._waiting and self._room > 0:
            self._take()
            return
        future = self._loop.create_future()
        self._waiting.append(future)
        self._schedule()
        await future

    def _take(self) -> None:
        self._room -= 1
        self._schedule()

    def _schedule(self) -> None:
        """Open the next turn's room in the next turn (call_soon runs after the callbacks
        already queued for it, the steps released in this one among them)."""
        if not self._next_turn_due:
            self._next_turn_due = True
            self._loop.call_soon(self._new_turn)

    def _new_turn(self) -> None:
        self._next_turn_due = False
        self._room = self.per_turn
        while self._waiting and self._room > 0:
            future = self._waiting.popleft()
            if not future.done():  # its caller went away
                future.set_result(None)
                self._room -= 1
        if self._waiting or self._room < self.per_turn:
            self._schedule()
