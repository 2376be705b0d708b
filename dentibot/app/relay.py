"""Rows handed over while a compiled call is still running: a thread of this process takes
each group of ticks the call has finished and hands it on (to a recorder, a summary), while
the call, which runs without the interpreter lock, computes the next ones.

Why. A recorder must never hold more than its budget of ticks at risk (the ticks a crash
could lose), so the rows of the compiled drilling ticks must leave every half budget (25 ticks
at 500 Hz). Calls of 25 ticks each cost about 300 us of Python around the kernel (its
arguments, the Python side brought up to date, the world between calls), which doubled the
cost of a recorded tick. With a relay, a call runs up to 256 ticks and its rows still leave
every 25.

How. The call and the thread share a small array (its cells are named in
:mod:`~dentibot.app.relay_kernels`, which holds the call's side) and two file descriptors
(``eventfd``, or pipes where there is none):

- the call publishes each group of ``every`` ticks it has finished (``ctl[PUB]``, with the
  group's compute time, the waits left out, in ``busy[group]``) and posts on ``posted``;
- the thread, woken, hands the group over, then lets the call run to two groups past what it
  has handed over (``ctl[LIMIT]``) and posts on ``granted``;
- the call waits on ``granted`` before a tick at the limit: while the thread hands a group
  over, the call computes the next one, and no more. At most two groups (one budget of a
  recorder's ticks at risk) exist that have not been handed over;
- if handing over fails (the recorder is dead, or full past its wait: a fault of the run),
  the thread keeps the error, sets ``ctl[ABORT]`` and wakes the call, which stops before its
  next tick; :meth:`Relay.finish` raises the error once the call has returned.

The ticks after the last full group are the caller's to hand over, after the call
(:meth:`Relay.finish` first waits until every published group has been handed over). The
thread hands over in the context (:mod:`contextvars`) of the call's start, so its log lines
carry the run's bound fields; it is the only thread running Python of the run while the call
runs (the control task waits for the call).
"""

from __future__ import annotations

import contextvars
import os
import threading
import weakref
from collections.abc import Callable

import numpy as np

from dentibot.app.relay_kernels import ABORT, CTL_SIZE, LIMIT, PUB, TAIL_NS

__all__ = ["Relay"]

_ONE = (1).to_bytes(8, "little")


def _channel() -> tuple[int, int]:
    """A (read end, write end) pair whose 8-byte writes wake a blocked 8-byte read."""
    if hasattr(os, "eventfd"):
        fd = os.eventfd(0, os.EFD_CLOEXEC)
        return fd, fd
    r, w = os.pipe()
    return r, w


#: the direct part of a relay's tuple where there is no wire (the same types)
_NO_WIRE = ((np.zeros(11, dtype=np.int64), np.zeros(1, dtype=np.uint8), 0, 0, 0,
             np.zeros(1, dtype=np.uint8), np.zeros(1, dtype=np.uint8)),
            np.zeros((1, 8), dtype=np.uint8), np.zeros((1, 1)), 0, 0)


class _Link:
    """What the call, the thread and the owner share (the thread holds this, not the
    :class:`Relay`, so that a relay forgotten by its owner is collected and ends it)."""

    def __init__(self, every: int, groups: int) -> None:
        self.every = every
        self.ctl = np.zeros(CTL_SIZE, dtype=np.int64)
        self.busy = np.zeros(groups, dtype=np.int64)
        self.word_out = np.ones(1, dtype=np.int64)     # the call's post
        self.word_in = np.zeros(1, dtype=np.int64)     # the call's wait reads here
        self.posted_r, self.posted_w = _channel()
        self.granted_r, self.granted_w = _channel()
        self.cond = threading.Condition()
        self.hand: Callable[[int, int, int], None] | None = None
        self.ctx: contextvars.Context | None = None
        self.handed = 0
        self.error: BaseException | None = None
        self.closing = False
        self.closed = False
        self.thread = threading.Thread(target=self.serve, name="dentibot-relay", daemon=True)

    def serve(self) -> None:
        try:
            while True:
                os.read(self.posted_r, 8)
                if self.closing:
                    return
                self.catch_up()
        finally:
            self.ctl[ABORT] = 1                   # never leave a call waiting on us
            self.wake_call()
            with self.cond:
                self.cond.notify_all()

    def catch_up(self) -> None:
        while True:
            with self.cond:
                hand, ctx, start = self.hand, self.ctx, self.handed
                stop = min(int(self.ctl[PUB]), start + self.every)   # one group at a time
                if hand is None or stop <= start or self.error is not None:
                    return
            try:
                ctx.run(hand, start, stop, int(self.busy[(stop - 1) // self.every]))
            except BaseException as exc:  # noqa: BLE001 - the call's to raise (finish)
                with self.cond:
                    self.error = exc
                    self.ctl[ABORT] = 1
                    self.cond.notify_all()
                self.wake_call()
                return
            with self.cond:
                self.handed = stop
                self.ctl[LIMIT] = stop + 2 * self.every
                self.cond.notify_all()
            self.wake_call()

    def wake_call(self) -> None:
        try:
            os.write(self.granted_w, _ONE)
        except OSError:
            pass

    def close(self) -> None:
        """End the thread, then close the descriptors (once)."""
        if self.closed:
            return
        self.closed = self.closing = True
        try:
            os.write(self.posted_w, _ONE)
        except OSError:
            pass
        if self.thread.is_alive() and self.thread is not threading.current_thread():
            self.thread.join(timeout=1.0)
        for fd in sorted({self.posted_r, self.posted_w, self.granted_r, self.granted_w}):
            try:
                os.close(fd)
            except OSError:
                pass


class Relay:
    """A thread handing over groups of ``every`` ticks of a compiled call (module
    docstring). ``groups``: most groups one call may publish."""

    def __init__(self, every: int, groups: int) -> None:
        if every < 1:
            raise ValueError(f"every = {every}: a group has at least one tick")
        self.every = int(every)
        self._link = _Link(self.every, max(1, int(groups)))
        self._link.thread.start()
        # a relay forgotten by its owner still ends its thread and closes its descriptors
        self._finalizer = weakref.finalize(self, self._link.close)

    def kernel_args(self) -> tuple:
        """What the compiled call takes: (on, every, ctl, busy, posted, granted, its words,
        then what a call straight to a recorder's wire takes, unused here)."""
        k = self._link
        return (True, self.every, k.ctl, k.busy, k.posted_w, k.granted_r, k.word_out,
                k.word_in, False, *_NO_WIRE)

    @staticmethod
    def off_args() -> tuple:
        """The same tuple for a call without a relay (the same types: no other compilation)."""
        return (False, 1, np.zeros(CTL_SIZE, dtype=np.int64), np.zeros(1, dtype=np.int64), -1, -1,
                np.zeros(1, dtype=np.int64), np.zeros(1, dtype=np.int64), False, *_NO_WIRE)

    @staticmethod
    def direct_args(every: int, ctl: np.ndarray, busy: np.ndarray, wire: tuple,
                    rows: np.ndarray, compute_col: int, k0: int) -> tuple:
        """The tuple for a call that hands each group of ``every`` ticks straight to a
        recorder's process (``wire``: :meth:`~dentibot.telemetry.recorder_process.Wire.begin`'s
        arguments), without a thread: ``rows`` (float64, C order) are the call's rows,
        ``compute_col`` their compute time's column, ``k0`` the call's first tick. ``ctl``
        and ``busy`` as a relay's (zeroed here)."""
        ctl[:] = 0
        return (True, int(every), ctl, busy, -1, -1, np.zeros(1, dtype=np.int64),
                np.zeros(1, dtype=np.int64), True, wire, rows.view(np.uint8), rows,
                int(compute_col), int(k0))

    @property
    def tail_ns(self) -> int:
        """The last call's compute time (ns) for its ticks after its last group."""
        return int(self._link.ctl[TAIL_NS])

    def start(self, hand: Callable[[int, int, int], None]) -> None:
        """Before a call: ``hand(start, stop, busy_ns)`` will get each group of ticks."""
        k = self._link
        if k.closed or not k.thread.is_alive():
            raise RuntimeError("the relay is closed")
        with k.cond:
            k.ctl[:] = 0
            k.ctl[LIMIT] = 2 * self.every
            k.handed = 0
            k.error = None
            k.hand = hand
            k.ctx = contextvars.copy_context()

    def finish(self) -> int:
        """After the call: wait until every group it published has been handed over; how
        many ticks were. Raises the error of a failed hand-over."""
        k = self._link
        with k.cond:
            k.cond.wait_for(lambda: k.handed >= k.ctl[PUB] or k.error is not None
                            or not k.thread.is_alive())
            k.hand = k.ctx = None
            if k.error is not None:
                err, k.error = k.error, None
                raise err
            if k.handed < k.ctl[PUB]:
                raise RuntimeError("the relay's thread ended with ticks not handed over")
            return k.handed

    def close(self) -> None:
        """End the thread and close the descriptors (at most once)."""
        self._finalizer()
