"""Stopping a task whose awaited call drops a cancellation (Python 3.11's ``wait_for``)."""

import asyncio

import pytest

from dentibot.io.tasks import cancel_until_done


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
