"""The recorder process's journal, from compiled code: a compiled loop running without the
interpreter lock puts its blocks of ticks into the journal itself, with the same bytes, the
same budget of ticks and the same waits for room as
:meth:`~dentibot.telemetry.recorder_process.RecorderProcess.record_block`
(:class:`~dentibot.telemetry.recorder_process.Wire` prepares the arrays and reads them back).

A message is its length (4 bytes, big-endian), then a block as
:meth:`~dentibot.telemetry.blocks.TickBlock.packed` gives it (a template of its header and
names, with the first tick and the count written in, then the columns' float64 bytes),
copied into the journal's ring (:mod:`~dentibot.telemetry.journal`), then published by
advancing the header's ``HEAD``.

``st`` (int64) holds the state both sides read: the cells below. A report of the recorder's
process (it died, or closed: its only reports now) stops the sender with :data:`OTHER`; the
Python side reads it.
"""

from __future__ import annotations

from numba import njit

from dentibot.telemetry.fd_kernels import EINTR, errno, fd_poll, fd_write, now_ns
from dentibot.telemetry.journal import HEAD, SETTLED, TAIL

__all__ = ["NO_ROOM", "OK", "OTHER", "PIPE", "send_block"]

#: ``st``'s cells: ticks handed over, the budget of ticks not yet in the file, the doorbell
#: pipe's and the reports pipe's descriptors, the longest wait for room (ms), the most ticks
#: not in the file seen, the outcome (:data:`OK`...)
(QUEUED, BUDGET, ROWS_FD, ACKS_FD, MAX_WAIT_MS, AT_RISK_MAX, STATUS) = range(7)
ST_SIZE = 7
#: outcomes: sent; no room within the longest wait (an overflow); a report of the process
#: (read by the caller); the pipe failed (the process is gone)
OK, NO_ROOM, OTHER, PIPE = range(4)


@njit(cache=True)
def _fits(st, hdr, ring, n, size) -> bool:
    return (st[QUEUED] - hdr[SETTLED] + n <= st[BUDGET]
            and ring.shape[0] - (hdr[HEAD] - hdr[TAIL]) >= size)


@njit(cache=True)
def _room(st, hdr, ring, msg, n, size) -> bool:
    """Wait until ``n`` more ticks fit in the budget and ``size`` bytes in the ring, waking
    the process each millisecond, at most ``st[MAX_WAIT_MS]``; a report of the process stops
    the wait (:data:`OTHER`)."""
    if _fits(st, hdr, ring, n, size):
        return True
    deadline = now_ns() + st[MAX_WAIT_MS] * 1_000_000
    while not _fits(st, hdr, ring, n, size):
        if now_ns() >= deadline:
            st[STATUS] = NO_ROOM
            return False
        fd_write(st[ROWS_FD], msg, 0, 1)          # a doorbell (any byte; a full pipe: no matter)
        r = fd_poll(st[ACKS_FD], 1)
        if r > 0:
            st[STATUS] = OTHER
            return False
        if r < 0 and errno() != EINTR:
            st[STATUS] = PIPE
            return False
    return True


@njit(cache=True)
def send_block(st, hdr, ring, msg, head_size, k0_at, n_at, rows, start, stop, k0) -> bool:
    """Put ticks ``k0``... (``rows[start:stop]``: the rows' float64 bytes, a C-order uint8
    array of a row's bytes per row) into the journal as one block, after waiting for room;
    then look whether the process reported (that sets ``st[STATUS]``: the caller stops there).
    ``msg``: the block's message bytes, the first ``head_size`` of them a template (the
    4-byte length, the header and the names); the first tick and the count are written at
    ``k0_at`` and ``n_at``. False, with ``st[STATUS]`` saying why, when nothing was sent."""
    n = stop - start
    size = head_size + n * rows.shape[1]
    if not _room(st, hdr, ring, msg, n, size):
        return False
    payload = size - 4
    for b in range(4):
        msg[b] = (payload >> (8 * (3 - b))) & 0xFF
    for b in range(8):
        msg[k0_at + b] = (k0 >> (8 * b)) & 0xFF
    for b in range(4):
        msg[n_at + b] = (n >> (8 * b)) & 0xFF
    at = head_size
    w = rows.shape[1]
    for i in range(start, stop):
        dst = msg[at:at + w]      # a view indexed from 0: the copy compiles to a few
        src = rows[i]             # instructions a byte (``msg[at + b]`` takes 20x longer)
        for b in range(w):
            dst[b] = src[b]
        at += w
    cap = ring.shape[0]
    head = hdr[HEAD]
    pos = head % cap
    first = min(size, cap - pos)
    dst = ring[pos:pos + first]
    for b in range(first):
        dst[b] = msg[b]
    if first < size:
        dst = ring[:size - first]
        src = msg[first:size]
        for b in range(size - first):
            dst[b] = src[b]
    now_ns()                      # a call into the C library: the bytes are stored before
    hdr[HEAD] = head + size       # the head that publishes them
    st[QUEUED] += n
    st[AT_RISK_MAX] = max(st[AT_RISK_MAX], st[QUEUED] - hdr[SETTLED])
    if fd_poll(st[ACKS_FD], 0) > 0:               # a report (the process died, or closed)
        st[STATUS] = OTHER
    return True
