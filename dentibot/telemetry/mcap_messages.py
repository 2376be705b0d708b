"""Many MCAP messages in one call, and a chunk finished, for the recorder's writer.

The mcap library's ``Writer.add_message`` costs about 7 us of Python a message (a ``Message``
object, six writes into the chunk, the chunk's and the file's statistics): with a ``/tick`` and
a ``/tf`` message per tick, more than the rest of the recording put together.
:func:`add_messages` adds a list of messages to the chunk being built with one packed header
each, and updates the chunk's message indexes and the file's statistics as ``add_message``
does: the file is the same, byte for byte.

It works on the writer's state, which the library does not publish: it is used with the
version it was written against (:data:`CHECKED_VERSION`, which the project pins), and a test
compares its file with the library's own, byte for byte. With another version, or a writer
without chunks, each message goes through ``add_message``.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Callable
from importlib import metadata

from mcap.records import Chunk, ChunkIndex, MessageIndex
from mcap.writer import CompressionType, IndexType, Writer

__all__ = ["CHECKED_VERSION", "add_messages", "finish_chunk"]

#: the mcap version whose writer state :func:`add_messages` updates
CHECKED_VERSION = "1.6.0"
#: a Message record's opcode, its length (u64), then channel id (u16), sequence (u32), log
#: time and publish time (u64), little-endian (the MCAP specification's Message record)
_OPCODE_MESSAGE = 0x05
_HEAD = struct.Struct("<BQHIQQ")
_FIELDS = _HEAD.size - 9                   # the record's length counts what follows it


def _fast() -> bool:
    try:
        return metadata.version("mcap") == CHECKED_VERSION
    except metadata.PackageNotFoundError:
        return False


FAST = _fast()


def add_messages(writer: Writer, messages: list[tuple[int, int, bytes, int]]) -> None:
    """Add ``messages`` (channel id, log time = publish time in ns, data, sequence), in
    order: the same file as ``writer.add_message`` of each."""
    chunk = getattr(writer, "_Writer__chunk_builder", None) if FAST else None
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
    if pos + sum(len(m[2]) for m in messages) + _HEAD.size * len(messages) > size:
        _one_by_one(writer, chunk, stats, size, messages)
        return
    counts = stats.channel_message_counts
    indexes = chunk.message_indices
    pack = _HEAD.pack
    parts: list[bytes] = []
    entries: dict[int, list] = {}
    for channel, log_ns, data, seq in messages:
        records = entries.get(channel)
        if records is None:
            index = indexes.get(channel)
            if not index:
                index = indexes[channel] = MessageIndex(channel_id=channel, records=[])
            records = entries[channel] = index.records
        records.append((log_ns, pos))
        counts[channel] += 1
        parts.append(pack(_OPCODE_MESSAGE, _FIELDS + len(data), channel, seq, log_ns, log_ns))
        parts.append(data)
        pos += _HEAD.size + len(data)
    buf.write(b"".join(parts))
    times = [m[1] for m in messages]
    lo, hi = min(times), max(times)
    if stats.message_count == 0 or lo < stats.message_start_time:
        stats.message_start_time = lo
    stats.message_end_time = max(stats.message_end_time, hi)
    stats.message_count += len(messages)
    if chunk.num_messages == 0 or lo < chunk.message_start_time:
        chunk.message_start_time = lo
    chunk.message_end_time = max(chunk.message_end_time, hi)
    chunk.num_messages += len(messages)


def _one_by_one(writer: Writer, chunk, stats, size: int,
                messages: list[tuple[int, int, bytes, int]]) -> None:
    """:func:`add_messages` where the chunk fills up on the way: as ``add_message``, the
    chunk is finished after the message that takes it past the writer's chunk size."""
    counts = stats.channel_message_counts
    indexes = chunk.message_indices
    pack = _HEAD.pack
    buf = chunk.record_writer._buffer
    for channel, log_ns, data, seq in messages:
        if stats.message_count == 0 or log_ns < stats.message_start_time:
            stats.message_start_time = log_ns
        stats.message_end_time = max(stats.message_end_time, log_ns)
        counts[channel] += 1
        stats.message_count += 1
        if chunk.num_messages == 0 or log_ns < chunk.message_start_time:
            chunk.message_start_time = log_ns
        chunk.message_end_time = max(chunk.message_end_time, log_ns)
        index = indexes.get(channel)
        if not index:
            index = indexes[channel] = MessageIndex(channel_id=channel, records=[])
        index.records.append((log_ns, buf.tell()))
        chunk.num_messages += 1
        buf.write(pack(_OPCODE_MESSAGE, _FIELDS + len(data), channel, seq, log_ns, log_ns))
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
    chunk = getattr(writer, "_Writer__chunk_builder", None) if FAST else None
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
