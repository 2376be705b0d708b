"""Real-time stepping of a World from a monotonic clock (for the wire simulators).

Lock-step time needs nothing here: the owner calls ``world.step()`` once per tick.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable

from dentibot.sim.world import World


class RealTimeStepper:
    """Keeps ``world.t`` following a monotonic clock: ``catch_up()`` steps the world as often
    as the clock has advanced since ``start()``, at most ``max_steps`` at once (a stall longer
    than that is dropped, not replayed, and counted in ``dropped_steps``)."""

    def __init__(self, world: World, clock: Callable[[], float] = time.monotonic,
                 max_steps: int = 50) -> None:
        self.world = world
        self.clock = clock
        self.max_steps = max_steps
        self.dropped_steps = 0
        self._t0: float | None = None
        self._offset = 0

    def start(self) -> None:
        self._t0 = self.clock()
        self._offset = self.world.steps

    def catch_up(self) -> int:
        """Step the world up to the clock; returns how many steps were taken."""
        if self._t0 is None:
            self.start()
        due = int((self.clock() - self._t0) / self.world.ts) + self._offset - self.world.steps
        if due > self.max_steps:
            self.dropped_steps += due - self.max_steps
            self._offset -= due - self.max_steps
            due = self.max_steps
        for _ in range(max(due, 0)):
            self.world.step()
        return max(due, 0)

    async def run(self, stop: asyncio.Event) -> None:
        """Step in real time until ``stop`` is set (sleeps about one period between)."""
        self.start()
        while not stop.is_set():
            self.catch_up()
            await asyncio.sleep(self.world.ts / 2)
