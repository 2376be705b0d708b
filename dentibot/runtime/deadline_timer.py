"""Waking the event loop at an absolute deadline to the microsecond, without spinning.

asyncio's own timers go through ``epoll_wait``, whose timeout is in whole milliseconds: at
500 Hz a sleep of 0.3 ms becomes 1 ms. The control loop used to sleep coarsely and then spin
(``asyncio.sleep(0)`` until the deadline) for the last 1.5 ms of every 2 ms period, so it
was always runnable: on a machine with other jobs the scheduler time-sliced it against them
and ticks started milliseconds late (p99 0.8 ms with one CPU-bound job beside it, no better
than plain ``asyncio.sleep``).

:class:`DeadlineTimer` is a Linux ``timerfd`` (CLOCK_MONOTONIC, the clock of
``time.perf_counter`` and ``time.monotonic``) armed at the absolute deadline and watched by the
event loop like any socket: the loop serves the device streams while it waits, sleeps in the
kernel, and wakes when the timer expires (high-resolution timers: microseconds). A sleeping
thread that wakes is scheduled at once ahead of CPU-bound jobs (more so with the raised
priority of :func:`~dentibot.runtime.clock.raised_priority`).

The deadline comes first: the expiry's callback puts the waiting task at the head of the
loop's queue of ready callbacks (CPython's ``_ready``, where it exists), ahead of the stream
callbacks that became ready in the same turn, which run right after it. Left at the back,
the tick waited behind them: measured on the wire at 500 Hz with a CPU-bound job beside,
the streams' callbacks take about 100 us each and up to 1 ms when the machine runs slow,
and the tick started late by as much.

``timerfd_create`` and ``timerfd_settime`` are called through ctypes (the ``os`` module has
them only from Python 3.13). :func:`deadline_timer` returns None where there is no timerfd
(other systems, a libc without it): the clock then spins as before.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import ctypes
import os
import sys
import weakref

__all__ = ["DeadlineTimer", "deadline_timer"]

CLOCK_MONOTONIC = 1
TFD_TIMER_ABSTIME = 1
TFD_NONBLOCK = os.O_NONBLOCK
TFD_CLOEXEC = getattr(os, "O_CLOEXEC", 0o2000000)


class _Timespec(ctypes.Structure):
    _fields_ = [("tv_sec", ctypes.c_long), ("tv_nsec", ctypes.c_long)]


class _Itimerspec(ctypes.Structure):
    _fields_ = [("it_interval", _Timespec), ("it_value", _Timespec)]


def _libc():
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        create, settime = libc.timerfd_create, libc.timerfd_settime
    except (OSError, AttributeError):
        return None
    create.argtypes, create.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    settime.argtypes = [ctypes.c_int, ctypes.c_int, ctypes.POINTER(_Itimerspec),
                        ctypes.c_void_p]
    settime.restype = ctypes.c_int
    return create, settime


_LIBC = _libc()


class DeadlineTimer:
    """A timerfd the running event loop waits on: ``await timer.wait_until(t)`` returns once
    ``time.perf_counter() >= t`` (never before: the kernel fires at or after the deadline).
    :meth:`close` releases the descriptor (also when garbage collected)."""

    def __init__(self) -> None:
        create, self._settime = _LIBC
        fd = create(CLOCK_MONOTONIC, TFD_NONBLOCK | TFD_CLOEXEC)
        if fd < 0:
            err = ctypes.get_errno()
            raise OSError(err, f"timerfd_create: {os.strerror(err)}")
        self.fd = fd
        self._loop: asyncio.AbstractEventLoop | None = None   # the loop it is registered with
        self._fut: asyncio.Future | None = None
        self._spec = _Itimerspec()
        self._spec_ref = ctypes.byref(self._spec)

    def arm(self, t: float) -> None:
        """Expire at ``t`` (s on CLOCK_MONOTONIC); a time already past expires at once."""
        ns = max(round(t * 1e9), 1)
        v = self._spec.it_value
        v.tv_sec, v.tv_nsec = divmod(ns, 1_000_000_000)
        if self._settime(self.fd, TFD_TIMER_ABSTIME, self._spec_ref, None) != 0:
            err = ctypes.get_errno()
            raise OSError(err, f"timerfd_settime: {os.strerror(err)}")

    async def wait_until(self, t: float) -> None:
        """Wait in the event loop (serving everything else) until CLOCK_MONOTONIC >= ``t``.
        The descriptor stays registered with the running loop between waits (registering
        it costs two ``epoll_ctl`` calls and a handle per tick); an expiry nobody waits for
        any more (a cancelled wait) is consumed and dropped, and one re-armed over before its
        callback ran wakes nobody."""
        loop = asyncio.get_running_loop()
        if self._loop is not loop:
            self._unregister()
            # the loop holds the callback weakly: a timer nobody keeps any more is collected,
            # and closing it takes it out of the loop and releases its descriptor
            loop.add_reader(self.fd, _call_weakly, weakref.WeakMethod(self._fired))
            self._loop = loop
        fut = self._fut = loop.create_future()
        self.arm(t)
        try:
            await fut
        finally:
            if self._fut is fut:                    # (a newer wait may have begun)
                self._fut = None

    def _fired(self) -> None:
        """The expiry: the waiter's wake-up, just queued by ``set_result``, moved to the
        head of the loop's ready queue (see the module docstring)."""
        try:
            os.read(self.fd, 8)                     # the expiry count: consumed
        except BlockingIOError:                     # re-armed since it was seen readable
            return                                  # (arming clears the count): not ours
        fut = self._fut
        if fut is not None and not fut.done():
            fut.set_result(None)
            ready = getattr(self._loop, "_ready", None)
            if isinstance(ready, collections.deque) and ready:
                ready.rotate(1)

    def _unregister(self) -> None:
        loop, self._loop = self._loop, None
        if loop is not None and not loop.is_closed():
            with contextlib.suppress(Exception):
                loop.remove_reader(self.fd)

    def close(self) -> None:
        self._unregister()
        fd, self.fd = self.fd, -1
        if fd >= 0:
            os.close(fd)

    def __del__(self) -> None:
        with contextlib.suppress(Exception):
            self.close()


def _call_weakly(method: weakref.WeakMethod) -> None:
    """The loop's reader callback of a :class:`DeadlineTimer`: its ``_fired``, if it is
    still there."""
    fired = method()
    if fired is not None:
        fired()


def deadline_timer() -> DeadlineTimer | None:
    """A :class:`DeadlineTimer`, or None where the system has no timerfd."""
    if _LIBC is None:
        return None
    try:
        return DeadlineTimer()
    except OSError:
        return None
