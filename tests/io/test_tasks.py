"""Stopping a task whose awaited call drops a cancellation (Python 3.11's ``wait_for``), and
blocking calls run off the event loop."""

import asyncio
import threading
import time

import pytest

from dentibot.io.tasks import cancel_until_done, in_thread


async def _loses_cancellations(lost: int, steps: list[int]) -> None:
    """Like a loop around a pymodbus request: the first ``lost`` cancellations are dropped,
    as ``asyncio.wait_for`` drops one that coincides with its answer."""
    while True:
        try:
            await asyncio.sleep(0.001)
        except asyncio.CancelledError:
            if lost == 0:
                raise
            lost -= 1
            asyncio.current_task().uncancel()
        steps.append(1)


async def test_a_task_that_drops_cancellations_is_cancelled_until_it_ends():
    steps: list[int] = []
    task = asyncio.create_task(_loses_cancellations(2, steps))
    await asyncio.sleep(0.005)
    task.cancel()                       # what a single cancel does: the task runs on
    await asyncio.wait({task}, timeout=0.05)
    assert not task.done()
    assert await cancel_until_done(task, recancel_s=0.01) is None
    assert task.cancelled()
    n = len(steps)
    await asyncio.sleep(0.01)
    assert len(steps) == n              # nothing runs any more


async def test_what_the_task_died_of_is_raised_or_returned():
    async def dies() -> None:
        raise ValueError("the link is gone")

    task = asyncio.create_task(dies())
    await asyncio.sleep(0)
    with pytest.raises(ValueError, match="the link is gone"):
        await cancel_until_done(task)
    task = asyncio.create_task(dies())
    await asyncio.sleep(0)
    died = await cancel_until_done(task, reraise=False)
    assert isinstance(died, ValueError)
    assert await cancel_until_done(None) is None


async def test_a_result_nobody_awaits_is_handed_to_its_orphan_off_the_loop():
    """in_thread: the caller cancelled while the call runs; its result goes to ``orphan``,
    which runs in a thread of its own (it may block: a bus's shutdown, a file's end), and
    the loop never waits for it."""
    release = threading.Event()
    orphaned: list[tuple[str, str]] = []

    def slow():
        release.wait(2.0)
        return "bus"

    def orphan(value):
        orphaned.append((value, threading.current_thread().name))
        time.sleep(0.3)                          # blocking, off the loop

    task = asyncio.ensure_future(in_thread(slow, "t-open", orphan=orphan))
    await asyncio.sleep(0.01)
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task
    release.set()
    t0 = time.monotonic()
    while not orphaned and time.monotonic() - t0 < 2.0:
        await asyncio.sleep(0.005)
    waited = time.monotonic() - t0
    assert orphaned == [("bus", "t-open-orphan")]
    assert waited < 0.25, waited                 # the orphan's 0.3 s were not the loop's
    assert await in_thread(lambda: 42, "t-plain") == 42
    with pytest.raises(ZeroDivisionError):
        await in_thread(lambda: 1 / 0, "t-error")
