"""What a compiled loop running without the interpreter lock needs to hand its results to a
Python thread as it goes: the call's side of a :class:`~dentibot.app.relay.Relay`
(:func:`begin`, :func:`hold` before each tick, :func:`publish` after it, :func:`end`), on
two 8-byte messages through a file descriptor (an ``eventfd``, or a pipe): :func:`post`
wakes a thread blocked in :func:`wait` (the C library's calls of
:mod:`~dentibot.telemetry.fd_kernels`, where the compiler keeps nothing of the shared arrays
across the call).
"""

from __future__ import annotations

from numba import njit

from dentibot.telemetry.fd_kernels import fd_read, fd_write, now_ns
from dentibot.telemetry.wire_kernels import OK, STATUS, send_block

__all__ = ["ABORT", "CTL_SIZE", "LIMIT", "PUB", "TAIL_NS", "begin", "end", "hold", "post",
           "publish", "wait"]


@njit(cache=True)
def post(fd, word) -> int:
    """Write ``word[0]`` (8 bytes) to ``fd``: wakes a thread blocked reading it."""
    return fd_write(fd, word, 0, 8)


@njit(cache=True)
def wait(fd, word) -> int:
    """Read 8 bytes from ``fd`` into ``word[0]``, blocking until something was posted."""
    return fd_read(fd, word, 0, 8)


# ---------------------------------------------------------------------- a call's side
#: ``ctl``'s cells (:class:`~dentibot.app.relay.Relay`): ticks published by the call, ticks
#: it may run (it waits before tick ``ctl[LIMIT]``), nonzero when it must stop, the compute
#: time (ns) of its ticks after the last group published; then the call's own bookkeeping:
#: the current group's compute time so far and when its current stretch began
PUB, LIMIT, ABORT, TAIL_NS, BUSY_NS, STRETCH_T0 = range(6)
CTL_SIZE = 6


@njit(cache=True)
def begin(relay) -> None:
    """At the call's start."""
    on, _, ctl = relay[0], relay[1], relay[2]
    if on:
        ctl[BUSY_NS] = 0
        ctl[STRETCH_T0] = now_ns()


@njit(cache=True)
def hold(relay, i) -> bool:
    """Before tick ``i``: wait while the relay is a group behind; False when the call must
    stop (the relay failed, or the recorder's wire)."""
    on, ctl, granted, word_in, direct = relay[0], relay[2], relay[5], relay[7], relay[8]
    if direct:
        return ctl[ABORT] == 0
    if not on or i < ctl[LIMIT]:
        return True
    t = now_ns()
    ctl[BUSY_NS] += t - ctl[STRETCH_T0]
    while i >= ctl[LIMIT] and ctl[ABORT] == 0:
        wait(granted, word_in)
    ctl[STRETCH_T0] = now_ns()
    return ctl[ABORT] == 0


@njit(cache=True)
def publish(relay, i) -> None:
    """After tick ``i``'s row is written: publish the group it completes, if it does (to the
    relay's thread; or, ``direct``, straight to the recorder's process through its wire:
    :func:`~dentibot.telemetry.wire_kernels.send_block`, the group's compute time written in
    its rows first)."""
    on, every, ctl, busy, posted, word_out = (relay[0], relay[1], relay[2], relay[3],
                                              relay[4], relay[6])
    if not on or (i + 1) % every != 0:
        return
    t = now_ns()
    busy_ns = ctl[BUSY_NS] + t - ctl[STRETCH_T0]
    busy[(i + 1) // every - 1] = busy_ns
    ctl[BUSY_NS] = 0
    ctl[STRETCH_T0] = t
    if not relay[8]:
        ctl[PUB] = i + 1
        post(posted, word_out)
        return
    (st, msg, head_size, k0_at, n_at, incoming, flush), rows_u8, rows, col, k0 = relay[9:]
    start = i + 1 - every
    us = busy_ns / every / 1000.0
    for r in range(start, i + 1):
        rows[r, col] = us
    if send_block(st, msg, head_size, k0_at, n_at, rows_u8, start, i + 1, k0 + start,
                  incoming, flush):
        ctl[PUB] = i + 1
    if st[STATUS] != OK:
        ctl[ABORT] = 1
    ctl[STRETCH_T0] = now_ns()                    # a wait for room is not compute time


@njit(cache=True)
def end(relay) -> None:
    """At the call's end: the compute time of the ticks after the last group."""
    on, ctl = relay[0], relay[2]
    if on:
        ctl[TAIL_NS] = ctl[BUSY_NS] + now_ns() - ctl[STRETCH_T0]
