"""MCAP Message records of many ticks at once, written by compiled code.

A block's ``/tick`` messages all have one length, and so do its ``/tf`` messages: each is a
row of a float64 buffer (:class:`~dentibot.telemetry.cdr.WordBlock`, the message 4 bytes into
its row). :func:`message_records` writes the Message record of each (the MCAP specification's:
opcode 0x05, the record's length (u64), then channel id (u16), sequence (u32), log time and
publish time (u64), little-endian, then the data), tick by tick, with the few messages of
other lengths that follow some ticks (``/scene``), into one byte array, and where each record
starts, so that one write puts them all in the chunk
(:func:`~dentibot.telemetry.mcap_messages.add_tick_messages`).

The kernel is compiled (or loaded from numba's cache) when the module is imported
(:func:`warm_up`): the recorder's process imports it before it forks, and its first block
must not wait for a compilation (the producer waits for room at most ``max_wait_s``).
"""

from __future__ import annotations

import struct

import numpy as np
from numba import njit

__all__ = ["HEAD", "HEAD_FIELDS", "HEAD_SIZE", "META_SIZE", "OPCODE_MESSAGE",
           "message_records", "warm_up"]

#: a Message record's opcode, its length (u64), then channel id (u16), sequence (u32), log
#: time and publish time (u64), little-endian (the MCAP specification's Message record)
OPCODE_MESSAGE = 0x05
HEAD = struct.Struct("<BQHIQQ")
#: a Message record's bytes before its data
HEAD_SIZE = HEAD.size
HEAD_FIELDS = HEAD_SIZE - 9                 # the record's length counts what follows it
#: ``meta``'s cells: each of the two row channels' data size and channel id, how many of the
#: two the ticks have (1 or 2), the channel id of the other messages
(SIZE0, CHANNEL0, SIZE1, CHANNEL1, ROW_CHANNELS, EXTRA_CHANNEL) = range(6)
META_SIZE = 6


@njit(cache=True, inline="always")
def _le(dst, at, value, width) -> None:
    for b in range(width):
        dst[at + b] = (value >> (8 * b)) & 0xFF


@njit(cache=True, inline="always")
def _record(out, pos, channel, seq, t, src, start, size) -> int:
    """One record at ``pos``, its data ``src[start:start + size]``; the position after it."""
    head = out[pos:pos + HEAD_SIZE]               # views indexed from 0 compile to plain
    head[0] = OPCODE_MESSAGE                      # stores (an offset index costs 20x)
    _le(head, 1, HEAD_FIELDS + size, 8)
    _le(head, 9, channel, 2)
    _le(head, 11, seq, 4)
    _le(head, 15, t, 8)
    _le(head, 23, t, 8)
    dst = out[pos + HEAD_SIZE:pos + HEAD_SIZE + size]
    data = src[start:start + size]
    for b in range(size):
        dst[b] = data[b]
    return pos + HEAD_SIZE + size


@njit(cache=True)
def message_records(out, rows0, rows1, meta, log_ns, seqs, extra, extra_row, extra_at,
                    offsets, extra_offsets) -> int:
    """The records of ``n`` ticks into ``out`` (uint8): tick ``i``'s on channel
    ``meta[CHANNEL0]`` holding ``meta[SIZE0]`` bytes of row ``i`` of ``rows0`` (uint8, C
    order) from byte 4, then (``meta[ROW_CHANNELS]`` 2) the same of ``rows1``, both at
    ``log_ns[i]`` with sequence ``seqs[i]``; then each message ``j`` with ``extra_row[j]``
    ``i`` (ascending): ``extra[extra_at[j]:extra_at[j + 1]]`` on ``meta[EXTRA_CHANNEL]``, at
    tick ``i``'s time and sequence. ``offsets[c, i]`` and ``extra_offsets[j]`` are where the
    records start in ``out``. Returns the bytes written."""
    pos = 0
    j = 0
    size0, ch0, size1, ch1 = meta[SIZE0], meta[CHANNEL0], meta[SIZE1], meta[CHANNEL1]
    two = meta[ROW_CHANNELS] == 2
    for i in range(log_ns.shape[0]):
        t, seq = log_ns[i], seqs[i]
        offsets[0, i] = pos
        pos = _record(out, pos, ch0, seq, t, rows0[i], 4, size0)
        if two:
            offsets[1, i] = pos
            pos = _record(out, pos, ch1, seq, t, rows1[i], 4, size1)
        while j < extra_row.shape[0] and extra_row[j] == i:
            extra_offsets[j] = pos
            pos = _record(out, pos, meta[EXTRA_CHANNEL], seq, t, extra, extra_at[j],
                          extra_at[j + 1] - extra_at[j])
            j += 1
    return pos


def warm_up() -> None:
    """Compile (or load) the kernel for the types
    :func:`~dentibot.telemetry.mcap_messages.add_tick_messages` calls it with (the rows:
    slices of a buffer's bytes; the other messages' bytes read-only, from ``frombuffer``)."""
    rows = np.zeros((2, 16), dtype=np.float64).view(np.uint8)[0:1]
    meta = np.array([8, 1, 8, 2, 2, 3], dtype=np.int64)
    one = np.zeros(1, dtype=np.int64)
    message_records(np.empty(3 * HEAD_SIZE + 17, dtype=np.uint8), rows, rows, meta, one, one,
                    np.frombuffer(b"\0", np.uint8), one, np.array([0, 1], dtype=np.int64),
                    np.empty((2, 1), dtype=np.int64), np.empty(1, dtype=np.int64))


warm_up()
