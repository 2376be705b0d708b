"""The real-time benchmark's census of the event loop's callbacks
(``benchmarks/loop_census.py``): each callback counted once under its name (the task it
resumes, the protocol it feeds), and the loop given back as it was. No speed is asserted."""

from __future__ import annotations

import asyncio
from asyncio import events

import pytest


@pytest.fixture
def loop_census(bench_module):
    return bench_module("loop_census")


def plain() -> None:
    pass


class Echo(asyncio.Protocol):
    def __init__(self, got: asyncio.Queue) -> None:
        self.got = got

    def data_received(self, data: bytes) -> None:
        self.got.put_nowait(data)


async def test_each_callback_is_counted_once_under_its_name(loop_census):
    loop = asyncio.get_running_loop()
    run = events.Handle._run
    got: asyncio.Queue = asyncio.Queue()
    server = await loop.create_server(lambda: Echo(got), "127.0.0.1", 0)
    port = server.sockets[0].getsockname()[1]

    async def worker() -> None:
        for _ in range(3):
            await asyncio.sleep(0)

    try:
        with loop_census.census() as seen:
            for _ in range(5):
                loop.call_soon(plain)
            await loop.create_task(worker(), name="worker")
            _, writer = await asyncio.open_connection("127.0.0.1", port)
            writer.write(b"x")
            await asyncio.wait_for(got.get(), 2.0)
            writer.close()
            await writer.wait_closed()
        assert events.Handle._run is run
    finally:
        server.close()
        await server.wait_closed()
    fig = loop_census.figures(seen, ticks=5)
    assert fig["plain"]["calls_per_tick"] == 1.0             # 5 calls over 5 ticks
    assert len(seen["task: worker"]) == 4                     # its first step + 3 wake-ups
    assert len(seen["read: Echo"]) >= 1                       # the byte the server read
    assert all(f["us_per_tick"] > 0 for f in fig.values())
    totals = [f["us_per_tick"] for f in fig.values()]
    assert totals == sorted(totals, reverse=True)             # largest first
