"""Real-time stepping from a monotonic clock."""

from __future__ import annotations

import asyncio

from dentibot.sim import RealTimeStepper, World, WorldConfig


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_catch_up_follows_the_clock():
    w = World(WorldConfig())
    clock = FakeClock()
    rt = RealTimeStepper(w, clock)
    rt.start()
    assert rt.catch_up() == 0
    clock.now += 0.0101
    assert rt.catch_up() == 5 and w.steps == 5
    clock.now += 0.001
    assert rt.catch_up() == 0
    clock.now += 0.001
    assert rt.catch_up() == 1 and abs(w.t - 0.012) < 1e-12


def test_a_long_stall_is_dropped_not_replayed():
    w = World(WorldConfig())
    clock = FakeClock()
    rt = RealTimeStepper(w, clock, max_steps=10)
    rt.start()
    clock.now += 1.0
    assert rt.catch_up() == 10
    assert rt.dropped_steps == 490
    clock.now += 0.004
    assert rt.catch_up() == 2


async def test_run_steps_in_real_time():
    w = World(WorldConfig())
    rt = RealTimeStepper(w)
    stop = asyncio.Event()
    task = asyncio.create_task(rt.run(stop))
    await asyncio.sleep(0.1)
    stop.set()
    await task
    assert 30 <= w.steps <= 60
