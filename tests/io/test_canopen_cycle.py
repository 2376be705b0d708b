"""The CANopen master's own cycle (``CanOpenMaster._cyclic``) paced by a control task: a cycle
right after each tick that asks for one (``cycle_soon``), none of its own while the ticks
come, its own period again when they stop, and asks faster than half a period ignored.
Periods of 20 ms: the figures hold on a loaded machine."""

from __future__ import annotations

import asyncio
from itertools import pairwise

import pytest

from dentibot.io.canopen_master import CanOpenMaster

PERIOD = 0.02


def _master() -> CanOpenMaster:
    return CanOpenMaster(None, interface="virtual", channel="unused", host="", port=0,
                         bus_kwargs=None, sdo_timeout_s=0.1, connect_timeout_s=0.1,
                         sync_period_s=PERIOD, heartbeat_ms=None, heartbeat_timeout_s=0.1,
                         name="master")


async def _running(master: CanOpenMaster, cycles: list[float]):
    loop = asyncio.get_running_loop()

    async def tick() -> None:
        cycles.append(loop.time())

    return loop.create_task(master._cyclic(tick))


async def test_alone_it_keeps_its_own_period():
    master, cycles = _master(), []
    task = await _running(master, cycles)
    await asyncio.sleep(10.5 * PERIOD)
    task.cancel()
    gaps = [b - a for a, b in pairwise(cycles)]
    assert 9 <= len(cycles) <= 12
    assert sum(gaps) / len(gaps) == pytest.approx(PERIOD, rel=0.15)


async def test_paced_a_cycle_follows_each_ask_and_none_runs_on_its_own():
    loop = asyncio.get_running_loop()
    master, cycles = _master(), []
    task = await _running(master, cycles)
    await asyncio.sleep(PERIOD / 2)
    asks: list[float] = []
    for k in range(12):
        # ticks at the period but off its phase, one of them 0.2 periods late
        await asyncio.sleep(PERIOD * (1.2 if k == 6 else 1.0))
        asks.append(loop.time())
        master.cycle_soon()
    await asyncio.sleep(PERIOD / 4)
    paced = [t for t in cycles if t >= asks[2]]
    task.cancel()
    # every ask after the first two got its cycle right after it, and no other cycle ran
    assert len(paced) == len(asks) - 2
    for ask, cycle in zip(asks[2:], paced):
        assert 0.0 <= cycle - ask < PERIOD / 2, (ask, cycle)


async def test_when_the_asks_stop_the_cycle_runs_on_its_own_again():
    loop = asyncio.get_running_loop()
    master, cycles = _master(), []
    task = await _running(master, cycles)
    for _ in range(5):
        await asyncio.sleep(PERIOD)
        master.cycle_soon()
    last_ask = loop.time()
    await asyncio.sleep(6 * PERIOD)
    task.cancel()
    after = [t for t in cycles if t > last_ask + PERIOD / 4]
    assert len(after) >= 3                                   # it did not stop
    assert after[0] - last_ask == pytest.approx(1.5 * PERIOD, abs=PERIOD / 2)


async def test_asks_faster_than_half_a_period_are_ignored():
    master, cycles = _master(), []
    task = await _running(master, cycles)
    await asyncio.sleep(PERIOD / 2)
    for _ in range(40):                                      # a tick at 8x the cycle's rate
        await asyncio.sleep(PERIOD / 8)
        master.cycle_soon()
    task.cancel()
    gaps = [b - a for a, b in pairwise(cycles)]
    assert min(gaps) >= PERIOD / 2 - 0.002
