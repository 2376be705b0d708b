"""A compiled call's blocks of ticks sent to the recorder as the call computes them.

A recorder holds at most its budget of ticks not yet in its file, so the rows of the compiled
drilling ticks must leave every half budget: 25 ticks for a budget of 50 (the in-process
recorder's at 500 Hz, or a recorder process given ``max_queue=50``; the recorder process's
own, 2,000 ticks, takes whole 256-tick calls). Calls of 25 ticks each cost about 300 us of
Python around the kernel (its arguments, the Python side brought up to date, the world
between calls), which doubled the cost of a recorded tick. Instead a call runs up to 256 ticks
without the interpreter lock
and sends each group of ``every`` ticks to the recorder's process itself, through the
recorder's journal (:func:`~dentibot.telemetry.wire_kernels.send_block`: the bytes, the budget
and the waits for room of ``record_block``), as it finishes the group: :func:`begin`, then
:func:`hold` before each tick, :func:`publish` after it, :func:`end`.

The relay's tuple (:func:`wire_args`, or :data:`OFF` for a call that sends nothing):
``(on, every, ctl, wire, rows_u8, rows, compute_col, k0)``; ``ctl`` holds the cells below.
Each group's compute time (the waits for room left out) is written into its rows'
``compute_col`` before they leave. A group the recorder did not take
(no room in time, the process gone or closed) stops the call before its next tick; the
caller reads why from the wire.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from dentibot.telemetry.fd_kernels import now_ns
from dentibot.telemetry.journal import HEADER_CELLS
from dentibot.telemetry.wire_kernels import OK, ST_SIZE, STATUS, send_block

__all__ = ["ABORT", "CTL_SIZE", "OFF", "PUB", "TAIL_NS", "begin", "end", "hold", "publish",
           "wire_args"]

#: ``ctl``'s cells: ticks sent, nonzero when the call must stop, the compute time (ns) of the
#: ticks after the last group sent; then the call's own bookkeeping: the current group's
#: compute time so far and when its current stretch began
PUB, ABORT, TAIL_NS, BUSY_NS, STRETCH_T0 = range(5)
CTL_SIZE = 5


def wire_args(every: int, ctl: np.ndarray, wire: tuple, rows: np.ndarray, compute_col: int,
              k0: int) -> tuple:
    """The tuple of a call from tick ``k0`` that sends each group of ``every`` ticks
    through ``wire`` (:meth:`~dentibot.telemetry.recorder_process.Wire.begin`'s arguments):
    ``rows`` (float64, C order) are the call's rows, ``compute_col`` their compute time's
    column; ``ctl`` (zeroed here) as the module docstring says."""
    ctl[:] = 0
    return (True, int(every), ctl, wire, rows.view(np.uint8), rows, int(compute_col), int(k0))


#: the tuple of a call that sends nothing (the same types: no other compilation)
OFF = (False, 1, np.zeros(CTL_SIZE, dtype=np.int64),
       (np.zeros(ST_SIZE, dtype=np.int64), np.zeros(HEADER_CELLS, dtype=np.int64),
        np.zeros(1, dtype=np.uint8), np.zeros(1, dtype=np.uint8), 0, 0, 0),
       np.zeros((1, 8), dtype=np.uint8), np.zeros((1, 1)), 0, 0)


@njit(cache=True)
def begin(relay) -> None:
    """At the call's start."""
    on, ctl = relay[0], relay[2]
    if on:
        ctl[BUSY_NS] = 0
        ctl[STRETCH_T0] = now_ns()


@njit(cache=True)
def hold(relay) -> bool:
    """Before a tick: False when the call must stop (a group was not taken)."""
    return relay[2][ABORT] == 0


@njit(cache=True)
def publish(relay, i) -> None:
    """After tick ``i``'s row is written: send the group it completes, if it does, its
    compute time written in its rows first."""
    on, every, ctl = relay[0], relay[1], relay[2]
    if not on or (i + 1) % every != 0:
        return
    (st, hdr, ring, msg, head_size, k0_at, n_at), rows_u8, rows, col, k0 = relay[3:]
    busy_ns = ctl[BUSY_NS] + now_ns() - ctl[STRETCH_T0]
    start = i + 1 - every
    us = busy_ns / every / 1000.0
    for r in range(start, i + 1):
        rows[r, col] = us
    if send_block(st, hdr, ring, msg, head_size, k0_at, n_at, rows_u8, start, i + 1,
                  k0 + start):
        ctl[PUB] = i + 1
    if st[STATUS] != OK:
        ctl[ABORT] = 1
    ctl[BUSY_NS] = 0
    ctl[STRETCH_T0] = now_ns()                    # a wait for room is not compute time


@njit(cache=True)
def end(relay) -> None:
    """At the call's end: the compute time of the ticks after the last group."""
    on, ctl = relay[0], relay[2]
    if on:
        ctl[TAIL_NS] = ctl[BUSY_NS] + now_ns() - ctl[STRETCH_T0]
