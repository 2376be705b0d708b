"""Stopping asyncio tasks that await third-party I/O, and blocking calls kept off the loop.

On Python 3.11, :func:`asyncio.wait_for` returns its inner future's result and drops a
cancellation that arrives in the same loop iteration as that result (fixed in 3.12, where
``wait_for`` is built on ``asyncio.timeout``). pymodbus awaits every request through
``wait_for``: a task cancelled while its answer comes in goes on running, and whoever
awaits it after one ``cancel()`` waits for ever. :func:`cancel_until_done` cancels again
until the task has really ended.

:func:`in_thread` runs a blocking call (a socketcand handshake, a recorder's process and
journal, a file finished and its writer joined) in a short-lived thread while the loop goes
on: once a drive watches the host's heartbeat (30 ms), the loop must never wait that long.
"""

from __future__ import annotations

import asyncio
import threading
from collections.abc import Callable
from typing import Any

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


async def in_thread(fn: Callable[[], Any], name: str,
                    orphan: Callable[[Any], object] | None = None) -> Any:
    """``fn()`` in a short-lived thread named ``name``, its result (or exception) handed to
    the awaiting task; the thread is joined once it has handed it over. ``orphan(value)``
    takes care of a result nobody awaits any more (the caller was cancelled meanwhile: a
    bus to shut down, a recording to finish), in a thread as well: it may block too."""
    loop = asyncio.get_running_loop()
    fut: asyncio.Future = loop.create_future()

    def deliver(ok: bool, value: Any) -> None:
        if fut.cancelled():
            if ok and orphan is not None:
                threading.Thread(target=orphan, args=(value,), name=f"{name}-orphan",
                                 daemon=True).start()
            return
        if ok:
            fut.set_result(value)
        else:
            fut.set_exception(value)

    def run() -> None:
        try:
            value, ok = fn(), True
        except BaseException as exc:  # noqa: BLE001 - handed to the awaiting task
            value, ok = exc, False
        try:
            loop.call_soon_threadsafe(deliver, ok, value)
        except RuntimeError:              # loop closed meanwhile
            if ok and orphan is not None:
                orphan(value)

    th = threading.Thread(target=run, name=name, daemon=True)
    th.start()
    try:
        return await fut
    finally:
        if not fut.cancelled():
            th.join(timeout=1.0)          # it has handed over its result: microseconds
