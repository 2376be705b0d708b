"""Stopping asyncio tasks that await third-party I/O.

On Python 3.11, :func:`asyncio.wait_for` returns its inner future's result and drops a
cancellation that arrives in the same loop iteration as that result (fixed in 3.12, where
``wait_for`` is built on ``asyncio.timeout``). pymodbus awaits every request through
``wait_for``: a task cancelled while its answer comes in goes on running, and whoever
awaits it after one ``cancel()`` waits for ever. :func:`cancel_until_done` cancels again
until the task has really ended.
"""

from __future__ import annotations

import asyncio

#: How long one cancellation is given before the next (s).
RECANCEL_S = 0.1


async def cancel_until_done(task: asyncio.Task | None, *, reraise: bool = True,
                            recancel_s: float = RECANCEL_S) -> BaseException | None:
    """Cancel ``task`` (if any) until it is done. An exception the task ended with (other
    than its cancellation) is raised, or with ``reraise=False`` returned; else None."""
    if task is None:
        return None
    while not task.done():
        task.cancel()
        await asyncio.wait({task}, timeout=recancel_s)
    died = None if task.cancelled() else task.exception()
    if died is not None and reraise:
        raise died
    return died
