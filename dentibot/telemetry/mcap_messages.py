"""Many MCAP messages in one call, and a chunk finished, for the recorder's writer.

The mcap library's ``Writer.add_message`` costs about 7 us of Python a message (a ``Message``
object, six writes into the chunk, the chunk's and the file's statistics): with a ``/tick`` and
a ``/tf`` message per tick, more than the rest of the recording put together.
:func:`add_messages` adds a list of messages to the chunk being built with one packed header
each, and updates the chunk's message indexes and the file's statistics as ``add_message``
does: the file is the same, byte for byte. :func:`add_tick_messages` does the same for the
messages of many ticks of one shape (a block's ``/tick`` and ``/tf``), their records written
by compiled code (:mod:`~dentibot.telemetry.record_kernels`). :func:`chunk_piece` cuts the
records added to the chunk in progress since a given byte of it as an uncompressed chunk of
their own, which a file holds until the chunk is finished.

It works on the writer's state, which the library does not publish: it is used with the
version it was written against (:data:`CHECKED_VERSION`, which the project pins), and a test
compares its file with the library's own, byte for byte. With another version, or a writer
without chunks, each message goes through ``add_message``.
"""

from __future__ import annotations

import contextlib
import struct
import zlib
from collections.abc import Callable, Iterator
from importlib import metadata

import numpy as np
from mcap.records import Chunk, ChunkIndex, MessageIndex
from mcap.writer import CompressionType, IndexType, Writer

from dentibot.telemetry.record_kernels import (
    HEAD,
    HEAD_FIELDS,
    HEAD_SIZE,
    OPCODE_MESSAGE,
    message_records,
)

__all__ = ["CHECKED_VERSION", "add_messages", "add_tick_messages", "chunk_length",
           "chunk_piece", "chunks_finished", "finish_chunk"]

#: the mcap version whose writer state :func:`add_messages` updates
CHECKED_VERSION = "1.6.0"


def _fast() -> bool:
    try:
        return metadata.version("mcap") == CHECKED_VERSION
    except metadata.PackageNotFoundError:
        return False


FAST = _fast()


def _chunk_builder(writer: Writer):
    """The writer's chunk in progress, where this module may work on it (the checked
    version, a writer with chunks); else None."""
    return getattr(writer, "_Writer__chunk_builder", None) if FAST else None


def _index(chunk, channel: int) -> list:
    """The chunk's message index entries of ``channel`` (made when it has none yet)."""
    index = chunk.message_indices.get(channel)
    if not index:
        index = chunk.message_indices[channel] = MessageIndex(channel_id=channel, records=[])
    return index.records


def _counted(stats, chunk, lo: int, hi: int, count: int) -> None:
    """``count`` more messages logged from ``lo`` to ``hi`` (ns) in the file's statistics and
    the chunk's times, as ``add_message`` keeps them."""
    if stats.message_count == 0 or lo < stats.message_start_time:
        stats.message_start_time = lo
    stats.message_end_time = max(stats.message_end_time, hi)
    stats.message_count += count
    if chunk.num_messages == 0 or lo < chunk.message_start_time:
        chunk.message_start_time = lo
    chunk.message_end_time = max(chunk.message_end_time, hi)
    chunk.num_messages += count


def add_messages(writer: Writer, messages: list[tuple[int, int, bytes, int]]) -> None:
    """Add ``messages`` (channel id, log time = publish time in ns, data, sequence), in
    order: the same file as ``writer.add_message`` of each."""
    chunk = _chunk_builder(writer)
    if chunk is None:
        for channel, log_ns, data, seq in messages:
            writer.add_message(channel, log_ns, data, log_ns, sequence=seq)
        return
    stats = writer._Writer__statistics
    size = writer._Writer__chunk_size
    buf = chunk.record_writer._buffer
    pos = buf.tell()
    if not messages:
        return
    if pos + sum(len(m[2]) for m in messages) + HEAD_SIZE * len(messages) > size:
        _one_by_one(writer, chunk, stats, size, messages)
        return
    counts = stats.channel_message_counts
    pack = HEAD.pack
    parts: list[bytes] = []
    entries: dict[int, list] = {}
    for channel, log_ns, data, seq in messages:
        records = entries.get(channel)
        if records is None:
            records = entries[channel] = _index(chunk, channel)
        records.append((log_ns, pos))
        counts[channel] += 1
        parts.append(pack(OPCODE_MESSAGE, HEAD_FIELDS + len(data), channel, seq, log_ns, log_ns))
        parts.append(data)
        pos += HEAD_SIZE + len(data)
    buf.write(b"".join(parts))
    times = [m[1] for m in messages]
    _counted(stats, chunk, min(times), max(times), len(messages))


def add_tick_messages(writer: Writer, channels: tuple[int, ...],
                      payloads: tuple[np.ndarray, ...], sizes: tuple[int, ...],
                      log_ns: list[int], seqs: list[int],
                      extra: list[tuple[int, bytes]] = (), extra_channel: int = 0) -> None:
    """:func:`add_messages` of ``n`` ticks' messages: for tick ``i``, one on each of
    ``channels`` (one or two), its data ``sizes[c]`` bytes of row ``i`` of ``payloads[c]``
    (uint8, C order) from byte 4 (a :class:`~dentibot.telemetry.cdr.WordBlock`'s rows), at
    ``log_ns[i]`` (non-decreasing) with sequence ``seqs[i]``; then each of ``extra``'s
    (tick, data) messages of that tick (in order), on ``extra_channel``. The same file, byte
    for byte: the records are written by compiled code in one write, the chunk's indexes and
    the statistics kept as :func:`add_messages` keeps them; or through :func:`add_messages`
    where that would not be the library's file (another version of the library, a chunk that
    fills up on the way)."""
    n = len(log_ns)
    if n == 0:
        return
    chunk = _chunk_builder(writer)
    total = n * sum(HEAD_SIZE + size for size in sizes) + sum(
        HEAD_SIZE + len(data) for _i, data in extra)
    if chunk is None or chunk.record_writer._buffer.tell() + total > \
            writer._Writer__chunk_size:
        add_messages(writer, _tick_messages(channels, payloads, sizes, log_ns, seqs, extra,
                                            extra_channel))
        return
    buf = chunk.record_writer._buffer
    out = np.empty(total, dtype=np.uint8)
    offsets = np.empty((2, n), dtype=np.int64)
    meta = np.array([sizes[0], channels[0], sizes[-1], channels[-1], len(channels),
                     extra_channel], dtype=np.int64)
    rows = [i for i, _data in extra]
    extra_offsets = np.empty(len(extra), dtype=np.int64)
    message_records(out, payloads[0], payloads[-1], meta, np.array(log_ns, dtype=np.int64),
                    np.array(seqs, dtype=np.int64),
                    np.frombuffer(b"".join(data for _i, data in extra) or b"\0", np.uint8),
                    np.array(rows, dtype=np.int64),
                    np.cumsum([0] + [len(data) for _i, data in extra], dtype=np.int64),
                    offsets, extra_offsets)
    at = buf.tell()
    buf.write(out)
    stats = writer._Writer__statistics
    counts = stats.channel_message_counts
    entries = [(channel, log_ns, offsets[c]) for c, channel in enumerate(channels)]
    if extra:
        entries.append((extra_channel, [log_ns[i] for i in rows], extra_offsets))
    for channel, times, starts in entries:
        _index(chunk, channel).extend(zip(times, (starts + at).tolist()))
        counts[channel] += len(times)
    _counted(stats, chunk, log_ns[0], log_ns[-1], n * len(channels) + len(extra))


def _tick_messages(channels, payloads, sizes, log_ns, seqs, extra, extra_channel) -> list:
    """:func:`add_tick_messages`'s messages as :func:`add_messages` takes them."""
    out, j = [], 0
    for i, (t, seq) in enumerate(zip(log_ns, seqs)):
        out += [(ch, t, bytes(p[i, 4:4 + size]), seq)
                for ch, p, size in zip(channels, payloads, sizes)]
        while j < len(extra) and extra[j][0] == i:
            out.append((extra_channel, t, extra[j][1], seq))
            j += 1
    return out


def _one_by_one(writer: Writer, chunk, stats, size: int,
                messages: list[tuple[int, int, bytes, int]]) -> None:
    """:func:`add_messages` where the chunk fills up on the way: as ``add_message``, the
    chunk is finished after the message that takes it past the writer's chunk size."""
    counts = stats.channel_message_counts
    pack = HEAD.pack
    buf = chunk.record_writer._buffer
    for channel, log_ns, data, seq in messages:
        counts[channel] += 1
        _counted(stats, chunk, log_ns, log_ns, 1)
        _index(chunk, channel).append((log_ns, buf.tell()))
        buf.write(pack(OPCODE_MESSAGE, HEAD_FIELDS + len(data), channel, seq, log_ns, log_ns))
        buf.write(data)
        if buf.tell() > size:                     # as add_message: the chunk is full
            writer._Writer__maybe_finalize_chunk()
            buf = chunk.record_writer._buffer

_OPCODE_MESSAGE_INDEX = 0x07
_INDEX_HEAD = struct.Struct("<BQHI")               # opcode, length, channel id, entries' bytes


def finish_chunk(writer: Writer, compress: Callable[[bytes], bytes] | None = None) -> None:
    """``writer.flush()``: the chunk in progress finished and everything written to the
    stream, with the chunk compressed by ``compress`` (a zstd compressor made once; the
    writer's own makes one per chunk, which costs as much as compressing) and its message
    indexes packed in one call each (the library writes them number by number). With
    ``compress`` None, or another version of the library, this is ``writer.flush()``. For
    the same compression the file is the library's, byte for byte."""
    chunk = _chunk_builder(writer)
    if (chunk is None or compress is None
            or writer._Writer__compression != CompressionType.ZSTD):
        writer.flush()
        return
    stream = writer._Writer__stream
    if chunk.num_messages:
        records = writer._Writer__record_builder
        flush = writer._Writer__flush
        writer._Writer__statistics.chunk_count += 1
        data = chunk.end()
        compressed = compress(data)
        record = Chunk(compression="zstd", data=compressed,
                       message_start_time=chunk.message_start_time,
                       message_end_time=chunk.message_end_time,
                       uncompressed_crc=zlib.crc32(data) if writer._Writer__enable_crcs else 0,
                       uncompressed_size=len(data))
        flush()
        start = stream.tell()
        record.write(records)
        index = ChunkIndex(message_start_time=record.message_start_time,
                           message_end_time=record.message_end_time,
                           chunk_start_offset=start, chunk_length=records.count,
                           message_index_offsets={}, message_index_length=0,
                           compression="zstd", compressed_size=len(compressed),
                           uncompressed_size=len(data))
        flush()
        index_start = stream.tell()
        if writer._Writer__index_types & IndexType.MESSAGE:
            for channel, message_index in chunk.message_indices.items():
                index.message_index_offsets[channel] = index_start + records.count
                entries = message_index.records
                flat = [v for entry in entries for v in entry]
                records.write(_INDEX_HEAD.pack(_OPCODE_MESSAGE_INDEX, 6 + 16 * len(entries),
                                               channel, 16 * len(entries)))
                records.write(struct.pack(f"<{len(flat)}Q", *flat))
        index.message_index_length = records.count
        flush()
        writer._Writer__chunk_indices.append(index)
        chunk.reset()
    writer._Writer__flush()
    stream.flush()


#: an uncompressed Chunk record's bytes before its records: opcode, length, message start and
#: end time, uncompressed size, CRC, the compression's name (empty: its length 0), the records'
#: length
_PIECE_HEAD = struct.Struct("<BQQQQIIQ")
_OPCODE_CHUNK = 0x06


def chunks_finished(writer: Writer) -> int:
    """Chunks the writer has finished so far (its statistics' count)."""
    return writer._Writer__statistics.chunk_count


def chunk_length(writer: Writer) -> int:
    """Bytes in the chunk in progress; -1 where :func:`chunk_piece` cannot cut pieces of it
    (another version of the library, a writer without chunks)."""
    chunk = _chunk_builder(writer)
    return -1 if chunk is None else chunk.record_writer._buffer.tell()


@contextlib.contextmanager
def chunk_piece(writer: Writer, start: int) -> Iterator[list]:
    """The records added to the chunk in progress from its byte ``start`` on, as an
    uncompressed Chunk record of their own with their own message times (buffers to write
    one after the other, valid within the ``with``; empty if none was added). A file may hold
    such pieces where the chunk will go until it is finished: each is a valid chunk to a
    reader (the recorder's flushes between two finished chunks; the finished chunk is
    written over them, so a piece has no CRC: 0, "not computed"). Needs
    :func:`chunk_length` >= 0."""
    chunk = writer._Writer__chunk_builder
    buf = chunk.record_writer._buffer
    end = buf.tell()
    if end <= start:
        yield []
        return
    lo = hi = None
    for index in chunk.message_indices.values():   # each in the order of its offsets
        for log_ns, at in reversed(index.records):
            if at < start:
                break
            lo = log_ns if lo is None or log_ns < lo else lo
            hi = log_ns if hi is None or log_ns > hi else hi
    size = end - start
    head = _PIECE_HEAD.pack(_OPCODE_CHUNK, _PIECE_HEAD.size - 9 + size, lo or 0, hi or 0,
                            size, 0, 0, size)
    with buf.getbuffer() as whole, whole[start:end] as records:
        yield [head, records]                      # released before the buffer grows again
