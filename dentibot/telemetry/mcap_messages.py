"""Many MCAP messages in one call, for the recorder's writer.

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
from importlib import metadata

from mcap.records import MessageIndex
from mcap.writer import Writer

__all__ = ["CHECKED_VERSION", "add_messages"]

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
