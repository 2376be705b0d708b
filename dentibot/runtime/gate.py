"""The gate between two control ticks: work submitted to a running control loop.

A procedure's control task runs all the time (from start to stop), and everything else (the
protocol's steps, the operator's commands, a test) submits work to it. Nothing may reach the
state machine in the middle of a tick: the machine (transitions' asyncio machine) yields
inside ``fire`` and cancels a transition that is still running when another one starts. So
every command goes through a :class:`TickGate`: it is queued and executed by the control task
itself between two ticks (after tick k, before tick k + 1), and the next tick applies the new
state's entry actions. The gate also wakes whoever waits for a condition on the runtime (a
timed step, a safe stop) in the tick where it holds.

The control loop serves the gate after every tick (``Runtime.run(between=gate.between)``) and,
while a held :class:`~dentibot.runtime.clock.LockStepClock` waits for ticks to be granted,
each time work is submitted (``clock.serve = gate.run_actions``).
"""

from __future__ import annotations

import asyncio
import collections
import inspect
from collections.abc import Callable
from typing import Any

from dentibot.errors import DentibotError


class GateClosed(DentibotError):
    """The control task is not running (not connected, stopped, or died)."""


class TickGate:
    """Work done by the control task between two ticks (see the module docstring)."""

    def __init__(self) -> None:
        self.runtime: Any = None
        self._actions: collections.deque = collections.deque()
        self._waiters: list[list] = []
        self._closed: str | None = None
        #: called when work is submitted (a held clock wakes up to serve it)
        self.on_submit: Callable[[], None] | None = None

    @property
    def closed(self) -> str | None:
        """Why the gate is closed (None while the control task serves it)."""
        return self._closed

    def open(self, runtime) -> None:
        self.runtime = runtime
        self._closed = None

    def submit(self, action: Callable[[], Any]) -> asyncio.Future:
        """Run ``action()`` between two ticks (awaited when it returns an awaitable); the
        future gets its result."""
        if self._closed is not None:
            raise GateClosed(self._closed)
        fut = asyncio.get_running_loop().create_future()
        self._actions.append((action, fut))
        if self.on_submit is not None:
            self.on_submit()
        return fut

    def wait(self, until: Callable[[Any], bool] | None = None,
             max_ticks: int | None = None,
             on_done: Callable[[], None] | None = None) -> asyncio.Future:
        """A future done after the first tick where ``until(runtime)`` holds or after
        ``max_ticks`` ticks (counted from now), like ``Runtime.run(until, max_ticks)``.
        ``on_done()`` is called by the control task in that very tick's slack."""
        if self._closed is not None:
            raise GateClosed(self._closed)
        fut = asyncio.get_running_loop().create_future()
        self._waiters.append([fut, until, max_ticks, 0, on_done])
        return fut

    def call_after(self, ticks: int, fn: Callable[[], None]) -> None:
        """Call ``fn()`` in the control task's slack after ``ticks`` more ticks (nobody
        waits: e.g. releasing a simulated pedal press)."""
        if self._closed is not None:
            raise GateClosed(self._closed)
        self._waiters.append([None, None, ticks, 0, fn])

    @property
    def pending(self) -> bool:
        return bool(self._actions)

    def after_tick(self) -> bool:
        """Check the waiters after a tick; True when one of them was woken."""
        woke = False
        keep = []
        for w in self._waiters:
            fut, until, max_ticks = w[0], w[1], w[2]
            if fut is not None and fut.done():   # its waiter was cancelled
                continue
            w[3] += 1
            try:
                hit = (max_ticks is not None and w[3] >= max_ticks) or (
                    until is not None and until(self.runtime))
            except Exception as exc:  # noqa: BLE001 - the waiter's problem, not the tick's
                if fut is not None:
                    fut.set_exception(exc)
                continue
            if hit:
                if fut is not None:
                    fut.set_result(None)
                    woke = True
                if w[4] is not None:
                    w[4]()
            else:
                keep.append(w)
        self._waiters = keep
        return woke

    def ticks_to_next_waiter(self) -> int | None:
        """Ticks until the first waiter whose tick count ends (None: none counts ticks)."""
        left = [w[2] - w[3] for w in self._waiters
                if w[2] is not None and not (w[0] is not None and w[0].done())]
        return min(left) if left else None

    def skip(self, ticks: int) -> None:
        """``ticks`` ticks passed in which no waiter could be woken (they ran in one compiled
        call that stops where a waiter's count would end): the counts advance."""
        for w in self._waiters:
            w[3] += ticks

    async def run_actions(self) -> None:
        while self._actions:
            action, fut = self._actions.popleft()
            if fut.done():                  # cancelled by its caller before it ran
                continue
            try:
                result = action()
                if inspect.isawaitable(result):
                    result = await result
            except Exception as exc:  # noqa: BLE001 - reported to the caller, the loop goes on
                if not fut.done():
                    fut.set_exception(exc)
            else:
                if not fut.done():
                    fut.set_result(result)

    async def between(self) -> None:
        if self.after_tick():
            # let the woken waiter run now (e.g. a timed step ending: its scripted hand
            # force is released and its next command queued before the next tick, exactly
            # as Runtime.run returning after max_ticks)
            await asyncio.sleep(0)
        await self.run_actions()

    def close(self, why: str) -> None:
        """No more ticks: fail what is queued and waiting."""
        self._closed = why
        while self._actions:
            _, fut = self._actions.popleft()
            if not fut.done():
                fut.set_exception(GateClosed(why))
        for w in self._waiters:
            if w[0] is None:
                if w[4] is not None:
                    w[4]()                  # e.g. release a pedal: never leave it pressed
            elif not w[0].done():
                w[0].set_exception(GateClosed(why))
        self._waiters = []
