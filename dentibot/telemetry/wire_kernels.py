"""The recorder process's pipe, from compiled code: a compiled loop running without the
interpreter lock hands its blocks of ticks to the recorder's process itself, with the same
bytes, the same budget of ticks at risk and the same flush reports as
:meth:`~dentibot.telemetry.recorder_process.RecorderProcess.record_block`
(:class:`~dentibot.telemetry.recorder_process.Wire` prepares the arrays and reads them back).

The bytes are multiprocessing's: each message is its length (4 bytes, big-endian), then the
message. A block is :meth:`~dentibot.telemetry.blocks.TickBlock.packed`'s (a template of its
header and names, with the first tick and the count written in, then the columns' float64
bytes); the process's flush report is a tag byte, then the ticks settled and its counters
(int64, little-endian).

``st`` (int64) holds the state both sides read: the cells below. Any report that is not a
flush (the process died, or closed) stops the sender with :data:`OTHER`, its length in
``st[OTHER_LEN]`` and its bytes read (``st[OTHER_READ]`` 1, in ``incoming``) or not yet
(0): the Python side reads it, as it reads every report.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from dentibot.telemetry.fd_kernels import EINTR, errno, fd_poll, fd_read, fd_write, now_ns

__all__ = ["FLUSHED_TAG", "NO_ROOM", "OK", "OTHER", "PIPE", "send_block"]

#: ``st``'s cells: ticks handed over, ticks the process reported on disk, the budget of ticks
#: at risk, the two pipes' descriptors, the longest wait for room (ms), the most ticks at
#: risk seen, the outcome (:data:`OK`...), a report's length and whether it was read, flush
#: reports read
(QUEUED, SETTLED, BUDGET, ROWS_FD, ACKS_FD, MAX_WAIT_MS, AT_RISK_MAX, STATUS, OTHER_LEN,
 OTHER_READ, FLUSHES) = range(11)
ST_SIZE = 11
#: outcomes: sent; no room within the longest wait (an overflow); a report that is not a
#: flush; the pipe failed (the process is gone)
OK, NO_ROOM, OTHER, PIPE = range(4)
#: the first byte of the process's flush report (the others are pickles, from 0x80)
FLUSHED_TAG = b"F"
_FLUSHED_BYTE = FLUSHED_TAG[0]
_RETRIES = 1000                 # an interrupted call is tried again; a failing one is not


@njit(cache=True)
def _io_all(fd, buf, start, size, reading) -> bool:
    """All ``size`` bytes of ``buf`` from ``start`` written to (read from) ``fd``."""
    done = 0
    tries = 0
    while done < size:
        r = fd_read(fd, buf, start + done, size - done) if reading \
            else fd_write(fd, buf, start + done, size - done)
        if r > 0:
            done += r
        elif r < 0 and errno() == EINTR and tries < _RETRIES:
            tries += 1
        else:
            return False
    return True


@njit(cache=True)
def _report(st, incoming, flush) -> bool:
    """Read one report of the process; True when it was a flush (``st[SETTLED]`` and
    ``flush`` updated), else ``st[STATUS]`` says why not."""
    fd = st[ACKS_FD]
    if not _io_all(fd, incoming, 0, 4, True):
        st[STATUS] = PIPE
        return False
    size = (incoming[0] << 24) | (incoming[1] << 16) | (incoming[2] << 8) | incoming[3]
    if size != flush.shape[0]:
        st[STATUS], st[OTHER_LEN], st[OTHER_READ] = OTHER, size, 0
        return False
    if not _io_all(fd, incoming, 4, size, True):
        st[STATUS] = PIPE
        return False
    if incoming[4] != _FLUSHED_BYTE:
        st[STATUS], st[OTHER_LEN], st[OTHER_READ] = OTHER, size, 1
        return False
    for b in range(size):
        flush[b] = incoming[4 + b]
    settled = 0
    for b in range(8):
        settled |= np.int64(flush[1 + b]) << (8 * b)
    st[SETTLED] = settled
    st[FLUSHES] += 1
    return True


@njit(cache=True)
def _room(st, n, incoming, flush) -> bool:
    """Wait until ``n`` more ticks fit in the budget, reading reports, at most
    ``st[MAX_WAIT_MS]``."""
    if st[QUEUED] - st[SETTLED] + n <= st[BUDGET]:
        return True
    deadline = now_ns() + st[MAX_WAIT_MS] * 1_000_000
    while st[QUEUED] - st[SETTLED] + n > st[BUDGET]:
        left = (deadline - now_ns()) // 1_000_000
        if left <= 0:
            st[STATUS] = NO_ROOM
            return False
        r = fd_poll(st[ACKS_FD], left)
        if r < 0 and errno() != EINTR:
            st[STATUS] = PIPE
            return False
        if r > 0 and not _report(st, incoming, flush):
            return False
    return True


@njit(cache=True)
def send_block(st, msg, head_size, k0_at, n_at, rows, start, stop, k0, incoming, flush) -> bool:
    """Hand ticks ``k0``... (``rows[start:stop]``: the rows' float64 bytes, a C-order uint8
    array of a row's bytes per row) to the process as one block, after waiting for room in
    the budget; then read the reports already there (one that is not a flush sets
    ``st[STATUS]``: the caller stops there).
    ``msg``: the block's message bytes, the first ``head_size`` of them a template (the
    4-byte length, the header and the names); the first tick and the count are written at
    ``k0_at`` and ``n_at``. False, with ``st[STATUS]`` saying why, when nothing was sent."""
    n = stop - start
    if not _room(st, n, incoming, flush):
        return False
    size = head_size + n * rows.shape[1]
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
    if not _io_all(st[ROWS_FD], msg, 0, size, False):
        st[STATUS] = PIPE
        return False
    st[QUEUED] += n
    st[AT_RISK_MAX] = max(st[AT_RISK_MAX], st[QUEUED] - st[SETTLED])
    while fd_poll(st[ACKS_FD], 0) > 0:              # the reports already there
        if not _report(st, incoming, flush):
            break
    return True
