"""MCAP recorder: one message per control tick, written by a thread, crash-safe.

:class:`McapRecorder` is fed from the control task: ``record(row)``, ``record_block(block)``
(many ticks' rows in one array, :class:`~dentibot.telemetry.blocks.TickBlock`) and
``event(...)`` append to a :class:`collections.deque` (no I/O, no serialisation) and return; a
writer thread pops the queue, serialises each item (``/tick`` and ``/tf`` as ROS 2 messages
in CDR, :mod:`~dentibot.telemetry.cdr` and :mod:`~dentibot.telemetry.tf_cdr`; the other
channels as JSON) and writes it to the MCAP file (each item's messages into the chunk in one
call: :func:`~dentibot.telemetry.mcap_messages.add_messages`). Without a writer thread
(``writer_thread=False``, the recorder process's way) the caller's thread writes.

What a crash can cost. A recording is the record of a procedure, so a crash (``kill -9``, power
cut without ``fsync``, interpreter abort) must lose at most ``max_at_risk_s`` (0.1 s) of
procedure, in any clock mode and whatever the load. Lock-step runs produce ticks 5-20x faster
than real time, so a bound in wall time alone is not enough: 0.1 s of wall time can be 2 s of
procedure. The bound is therefore kept in ticks, ``budget = max_at_risk_s x rate_hz`` (50 at
500 Hz), and it covers everything a crash would lose, the rows still queued *and* those in the
chunk being built:

- the writer hands what it wrote to the operating system (a flush) every ``budget // 2``
  ticks, and at the latest ``flush_interval_s`` (0.05 s) of wall time after the oldest
  unflushed item was written (for slow or paused producers; with the writer's ``poll_s``
  sleep, a row handed over is on the OS within about 60 ms of wall time);
- ``record()`` applies back-pressure: when ``budget`` ticks are already at risk (handed over,
  not yet flushed), it waits for the writer's next flush. In lock-step time this costs nothing
  (time is simulated; the run just takes the writer's pace); in real time it never happens
  while the writer keeps up (a few microseconds per row, see below) and happens only when the
  disk stalls, itself a fault worth a late tick rather than a hole in the record;
- a wait longer than ``max_wait_s`` (1 s: a stalled disk, not a busy writer) is an overflow:
  the row is dropped and counted (``rows_dropped``, ``overflowed``) and ``record()`` raises
  :class:`TelemetryOverflow`, so the caller faults the run instead of going on with a
  recording that has a hole. The queue never grows without bound and a loss is never silent.

The recorder's own process (:mod:`~dentibot.telemetry.recorder_process`, what ``dentibot run``
uses) runs this recorder with a larger budget (4 s of procedure), because what its file does
not hold yet is kept in a journal beside it, which a crash does not lose.

Readable as written. The file on disk is always a complete MCAP file: each flush writes what is
new *and* a provisional end (DataEnd, a Footer without summary, the closing magic) with one
``write`` at the end of the data, and the next flush overwrites that end. What is new is the
chunk in progress, finished (compressed, indexed) once it holds half of ``chunk_size``; until
then, the records added since the last flush as an uncompressed chunk of their own (a piece),
which the finished chunk is written over. Chunks of about 0.5 MB compress to 0.36 of their
bytes where the 25-tick chunks each flush used to finish kept 0.38, at 1.2 times the speed,
and a recording has 20 times fewer of them to index. A file cut short by
a crash therefore opens in the standard readers (``mcap.reader.make_reader(f).iter_messages()``
reads it linearly, as it does any MCAP without summary) with every message up to the last
flush. Only a kill in the middle of that one ``write`` can leave a damaged end; ``dentibot
recover`` rewrites such a file (:mod:`dentibot.telemetry.recover`). :meth:`close` writes the
real summary (indexes, statistics), which is how readers tell a finished recording from an
interrupted one. ``fsync=True`` also survives a power cut, at the cost of one ``fsync`` per
flush.

Keeping up. A row is packed by one cached struct (about 3 us); a block's rows are written by
copying its columns into copies of one message, its frames by a compiled kernel, and the
records of its ``/tick`` and ``/tf`` messages (with the ``/scene`` messages between them) by
another, into the chunk with one write (:func:`~dentibot.telemetry.mcap_messages.add_tick_messages`); the JSON
messages are serialised with orjson, the standard module being the fallback for values orjson
refuses (integers beyond 64 bits, non-string keys). Chunks are compressed by one zstd
compressor made once (:func:`~dentibot.telemetry.mcap_messages.finish_chunk`). The writer hands the interpreter lock back to the control
thread after each millisecond of continuous work, not after a fixed number of items: a fixed
count let a busy producer take the lock for a whole switch interval each time and starve the
writer.

If the writer thread dies (disk full, I/O error...), the next ``record()``/``event()`` raises
:class:`TelemetryError` carrying the cause: a recording never stops silently.

Time. Every message is logged at wall-clock time: ``log_time = publish_time = start_wall_ns +
t`` (ns), ``start_wall_ns`` being the wall clock at t = 0 (taken when the recorder is built
unless the metadata gives it) and ``t`` the row's procedure time, so viewers show the date and
time of day of the procedure and the messages' order in time is the procedure's. The ``/run``
message carries ``start_wall_ns`` and ``start_time`` (ISO 8601, UTC); ``t`` stays in every
row, and everything DentiBot computes (reader, summaries, ``dentibot report``) works from
``t``. In lock-step time, where procedure seconds pass faster than wall seconds, log times are
the procedure's time laid out from its wall-clock start, not when the row was written.

3D. With a :class:`~dentibot.telemetry.foxglove.FoxgloveView` (the default), each tick also
gets a ``/tf`` message (``foxglove.FrameTransforms``: base, flange, file tip, tooth) and every
``scene_hz`` of procedure time a ``/scene`` message (``foxglove.SceneUpdate``), derived from the
row in the writer thread, after the row itself is written: ``record()`` costs the same, and a
row the view cannot draw (or a caller's ``frames`` callable that fails) is counted in
``view_errors`` and logged, never lost and never fatal. These messages are not ticks: they
count neither against the budget nor in ``ticks_written``.

Nulls. A row's None values (unknown quantities) are left out of the ``/tick`` message, not
written as ``null`` (see :mod:`~dentibot.telemetry.schema`); the reader puts them back.

Ownership: ``record(row)`` takes the row as it is and serialises it later, in the writer
thread. The caller must not mutate the row (or the lists inside it) after handing it over;
the runtime builds a fresh dict each tick. Numpy arrays and scalars are accepted; rows with
non-finite floats are counted (``nonfinite_rows``): in ``/tick`` a NaN is written as it is
and reads back as None, like an unknown value; in the JSON channels a non-finite field is
left out like a None, one inside an array is written as ``null``. A row that does not fit
the ``/tick`` message (a missing string, a pose of five numbers) is not written: counted in
``rows_rejected`` and logged with the field's name.
"""

from __future__ import annotations

import collections
import datetime
import json
import math
import os
import threading
import time
from collections.abc import Callable
from importlib import metadata as _importlib_metadata
from pathlib import Path
from typing import Any, BinaryIO, ClassVar

import numpy as np
import orjson
import structlog
import zstandard
from mcap.data_stream import RecordBuilder
from mcap.exceptions import McapError
from mcap.records import DataEnd, Footer
from mcap.writer import MCAP0_MAGIC, CompressionType, Writer

from dentibot.errors import ConfigError
from dentibot.jsonsafe import finite as _finite
from dentibot.telemetry.blocks import COL, TickBlock
from dentibot.telemetry.cdr import MESSAGE_ENCODING as CDR_ENCODING
from dentibot.telemetry.cdr import SCHEMA_ENCODING as CDR_SCHEMA_ENCODING
from dentibot.telemetry.cdr import TICK_CODEC, TICK_SCHEMA_NAME, CdrError, definition
from dentibot.telemetry.foxglove import (
    FOXGLOVE_TOPICS,
    SCENE_TOPIC,
    TF_TOPIC,
    FoxgloveView,
    as_view,
)
from dentibot.telemetry.mcap_messages import (
    add_messages,
    add_tick_messages,
    chunk_length,
    chunk_piece,
    chunks_finished,
    finish_chunk,
)
from dentibot.telemetry.schema import (
    END_STATUSES,
    TICK_FIELDS,
    TOPICS,
    TelemetryError,
    json_schema,
    validate_row,
)
from dentibot.telemetry.tf_cdr import TF_DEFINITION, TF_SCHEMA_NAME

__all__ = ["COMPRESSIONS", "McapRecorder", "RecorderBase", "TelemetryOverflow"]

log = structlog.get_logger("dentibot.telemetry")

COMPRESSIONS: dict[str, CompressionType] = {
    "zstd": CompressionType.ZSTD,
    "lz4": CompressionType.LZ4,
    "none": CompressionType.NONE,
}

#: zstd's level for the chunks (a fast level; the writer sets the pace of a recorded lock-step
#: run). On a drilling run's 0.5 MB chunks, as a flush finishes them: 563 MB/s for 0.358 of
#: the bytes, against level -1's 426 MB/s for 0.343 and level 1's 386 for 0.335 (level -1 on
#: the 25-tick chunks that each flush used to finish: 461 MB/s for 0.379)
ZSTD_LEVEL = -3
PROFILE = ""                 # MCAP profile: none (JSON and ROS 2 CDR channels side by side)
MESSAGE_ENCODING = "json"
SCHEMA_ENCODING = "jsonschema"
RUN_METADATA_NAME = "dentibot.run"    # MCAP metadata record holding the /run fields as text

DEFAULT_RATE_HZ = 500.0      # budget in ticks when the metadata gives no rate_hz
_SLICE_S = 0.001             # longest stretch the writer keeps the interpreter lock
_LOG_FIRST = 5               # problems of each kind logged in full, then only counted
_ORJSON_OPTIONS = orjson.OPT_SERIALIZE_NUMPY


def _provisional_end() -> bytes:
    """DataEnd + Footer without summary + magic: what makes the data so far a complete MCAP
    file. A Footer whose ``summary_start`` is 0 says "no summary section": readers then read
    the data section front to back."""
    rb = RecordBuilder()
    DataEnd(data_section_crc=0).write(rb)
    Footer(summary_start=0, summary_offset_start=0, summary_crc=0).write(rb)
    return bytes(rb.end()) + MCAP0_MAGIC


PROVISIONAL_END = _provisional_end()


class TelemetryOverflow(TelemetryError):
    """The writer did not make room in time: a row was dropped (the recording has a hole).

    Raised by :meth:`McapRecorder.record` after waiting ``max_wait_s`` for the writer; the
    caller should fault the run. ``rows_dropped`` counts the rows lost so far.
    """

    def __init__(self, path: object, detail: str, rows_dropped: int) -> None:
        self.rows_dropped = rows_dropped
        super().__init__(path, detail)

    def __reduce__(self):
        return type(self), (self.path, self.detail, self.rows_dropped)


def _json_default(obj: Any) -> Any:
    """numpy arrays and scalars (anything with ``tolist``) become lists / Python numbers."""
    tolist = getattr(obj, "tolist", None)
    if tolist is not None:
        return tolist()
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def _without_none(obj: Any) -> Any:
    """``obj`` without its None fields (a dict's only: how the file stores "unknown"). By
    identity: ``None in values`` would compare numpy arrays with ``==``."""
    if type(obj) is dict:
        for v in obj.values():
            if v is None:
                return {k: v for k, v in obj.items() if v is not None}
    return obj


def _dumps(obj: Any) -> bytes:
    """The standard library's encoding: the fallback for what orjson refuses."""
    return json.dumps(obj, allow_nan=False, separators=(",", ":"),
                      default=_json_default).encode()


def _nonfinite(obj: Any) -> bool:
    """True if ``obj`` holds a NaN or an infinity anywhere (orjson writes them as null).

    Cheap on rows: a list of numbers is summed in C (a NaN or infinity makes the sum
    non-finite; only then are its items looked at one by one)."""
    t = type(obj)
    if t is float:
        return obj - obj != 0.0                 # nan and inf give nan; finite gives 0.0
    if t is dict:
        for v in obj.values():
            tv = type(v)
            if tv is float:
                if v - v != 0.0:
                    return True
            elif tv is not int and tv is not str and tv is not bool and v is not None \
                    and _nonfinite(v):
                return True
        return False
    if t is list or t is tuple:
        try:
            s = sum(obj)
        except TypeError:                         # strings, None, nested lists
            return any(map(_nonfinite, obj))
        return s - s != 0.0 and any(map(_nonfinite, obj))
    if isinstance(obj, float):                  # float subclasses (numpy.float64)
        return not math.isfinite(obj)
    dtype = getattr(obj, "dtype", None)
    if dtype is not None and dtype.kind in "fc":
        return not bool(np.isfinite(obj).all())
    return False


_U64_MAX = (1 << 64) - 1


def event_message(kind: str, detail: str, t: Any, tick: Any, last_t: Any,
                  last_tick: Any) -> dict[str, Any]:
    """An ``/events`` message; ``t``/``tick`` None stand for the last row's (``last_t``,
    ``last_tick``)."""
    return {"t": last_t if t is None else t, "tick": last_tick if tick is None else tick,
            "kind": kind, "detail": detail}


def _log_time_ns(start_ns: int, t: Any, fallback: int) -> int:
    """MCAP log time (ns since the epoch, unsigned): ``start_ns`` + ``t`` (s since the run
    start); ``fallback`` when ``t`` is not a usable time."""
    if isinstance(t, (int, float)) and not isinstance(t, bool) and math.isfinite(t) and t >= 0:
        ns = start_ns + round(t * 1e9)
        if ns <= _U64_MAX:
            return ns
    return fallback


def _start_fields(meta: dict[str, Any]) -> None:
    """Fill ``start_wall_ns`` (now, unless given) and ``start_time`` (ISO 8601 UTC of it)."""
    start = meta.setdefault("start_wall_ns", time.time_ns())
    if not (isinstance(start, int) and not isinstance(start, bool) and 0 <= start <= _U64_MAX):
        raise ConfigError("metadata.start_wall_ns", start,
                          "an integer >= 0 (ns since the Unix epoch)")
    if "start_time" not in meta:
        sec, ns = divmod(start, 1_000_000_000)
        when = datetime.datetime.fromtimestamp(sec, datetime.timezone.utc)
        meta["start_time"] = when.strftime("%Y-%m-%dT%H:%M:%S") + f".{ns:09d}Z"


class _Sink:
    """Where the mcap Writer's bytes go. They are staged in memory and written out by
    :meth:`commit`, each time with one write at the end of the data followed by
    :data:`PROVISIONAL_END` (which the next commit overwrites): between two commits, the file
    holds a complete MCAP file. Between two commits, :meth:`provisional` writes pieces of the
    chunk in progress after the data the same way (each followed by the provisional end):
    the next commit writes the finished chunk over them. A stream that cannot seek gets the
    data only (appended), and no pieces."""

    def __init__(self, fd: int | None, stream: BinaryIO | None) -> None:
        self._fd = fd
        self._stream = stream
        self._buf = bytearray()
        #: bytes of pieces written after the data (``pos``) since the last commit
        self.tail = 0
        self._end = 0                           # where the last write ended
        if fd is not None:
            self.pos = 0
            self.rewritable = True
        else:
            self.rewritable = bool(getattr(stream, "seekable", lambda: False)())
            self.pos = stream.tell() if self.rewritable else 0

    # the file-like side the mcap Writer uses
    def write(self, data: bytes) -> int:
        self._buf += data
        return len(data)

    def tell(self) -> int:
        return self.pos + len(self._buf)

    @property
    def staged(self) -> int:
        """Bytes the Writer wrote that are not out yet."""
        return len(self._buf)

    def flush(self) -> None:
        """The Writer calls this after each chunk; :meth:`commit` decides when data goes out."""

    def commit(self, final: bool = False) -> None:
        """Write the staged bytes (and, unless ``final``, the provisional end) at the end of
        the data, over any pieces. ``final``: the Writer's own end (summary, footer) is in the
        staged bytes. Anything left beyond (an older provisional end, longer pieces) is cut
        off."""
        staged = len(self._buf)
        with memoryview(self._buf) as data:
            self._write_at([data, PROVISIONAL_END] if self.rewritable and not final else [data],
                           self.pos)
        self.pos += staged
        self._buf.clear()
        self.tail = 0
        end = self._end
        self._end = self.pos + (0 if final or not self.rewritable else len(PROVISIONAL_END))
        if self.rewritable and (final or end > self._end):
            if self._fd is not None:
                os.ftruncate(self._fd, self._end)
            elif hasattr(self._stream, "truncate"):
                self._stream.truncate(self._end)

    def provisional(self, piece: list) -> None:
        """Write ``piece`` (buffers: a chunk's records as a Chunk of their own) after the data
        and the pieces before it, followed by the provisional end. Rewritable files only."""
        size = sum(len(part) for part in piece)
        self._write_at([*piece, PROVISIONAL_END], self.pos + self.tail)
        self.tail += size
        self._end = max(self._end, self.pos + self.tail + len(PROVISIONAL_END))

    def _write_at(self, parts: list, at: int) -> None:
        """``parts`` (buffers) one after the other from ``at``, in one gathered write."""
        if self._fd is not None:
            views = [memoryview(p).cast("B") for p in parts]
            while views:
                n = os.pwritev(self._fd, views, at)
                if n == 0 and any(len(v) for v in views):
                    raise OSError(f"no progress writing {sum(map(len, views))} bytes at {at}")
                at += n
                while views and n >= len(views[0]):
                    n -= len(views[0])
                    views.pop(0)
                if views and n:
                    views[0] = views[0][n:]
        else:
            if self.rewritable:
                self._stream.seek(at)
            for part in parts:
                self._stream.write(part)
            self._stream.flush()


class RecorderBase:
    """What the in-process recorder and the recorder process share: the run's duration, the
    overflow flag, and use as a context manager (closed "ok" at the end of the block,
    "aborted" with the exception when it raises, without hiding that exception behind a close
    error), the overflow that drops a row loudly. Needs ``rows_queued``, ``period_s``,
    ``_last_t``, ``rows_dropped``, ``_settled``, ``rows_flushed``, ``max_wait_s``, ``path``,
    ``close``."""

    def duration_s(self) -> float:
        """Ticks handed over x period when the rate is known, else the last row's ``t``."""
        if self.period_s is not None:
            return self.rows_queued * self.period_s
        return float(self._last_t)

    @property
    def overflowed(self) -> bool:
        """True once a row was dropped because the writer made no room in time."""
        return self.rows_dropped > 0

    #: what writes the file, in messages
    WRITER = "the writer"

    def _overflow(self, row: Any, count: int = 1) -> None:
        self.rows_dropped += count
        at_risk = self.rows_queued - self._settled
        tick = row.get("tick") if isinstance(row, dict) else None
        what = f"tick {tick}" if count == 1 else f"ticks {tick} to {tick + count - 1}"
        detail = (f"{self.WRITER} made no room in {self.max_wait_s:g} s ({at_risk} ticks waiting "
                  f"to reach the file, {self.rows_flushed} on disk): {what} dropped, "
                  f"{self.rows_dropped} row(s) lost so far; the recording has a hole")
        if self.rows_dropped <= _LOG_FIRST:
            log.error("telemetry.overflow", path=str(self.path), tick=tick,
                      rows_dropped=self.rows_dropped, at_risk=at_risk)
        raise TelemetryOverflow(self.path, detail, self.rows_dropped)

    def _in_parts_or_empty(self, block: TickBlock) -> bool:
        """Before a block is handed over: True when there is nothing more to do with it (empty,
        or larger than the budget and handed over in parts here); else wait until it fits in
        the budget of ticks at risk."""
        n = len(block)
        if n > self.budget:
            for start in range(0, n, self.budget):
                self.record_block(block.part(start, start + self.budget))
            return True
        if n and self.rows_queued - self._settled + n > self.budget:
            self._wait_for_room({"tick": block.k0}, n)
        return not n

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc is None:
            self.close("ok")
            return
        try:
            self.close("aborted", f"{exc_type.__name__}: {exc}")
        except TelemetryError as err:     # do not hide the exception already in flight
            log.error("telemetry.close_failed", path=str(self.path), error=str(err))


class McapRecorder(RecorderBase):
    """Record a run to an MCAP file: ``/run`` now, ``/tick`` and ``/events`` as they come,
    ``/run/end`` at :meth:`close`. See the module docstring for what a crash can cost.

    Parameters (defaults in brackets):

    - ``path``: file to create, or a writable binary stream (left open on close).
    - ``metadata``: the run's ``/run`` message (protocol, seed, rate_hz, devices...);
      ``dentibot_version`` is filled in when absent, and so are ``start_wall_ns`` (the wall
      clock now, ns since the epoch: give it to share one start with a live view) and
      ``start_time``. ``rate_hz`` (> 0) sets the period used for ``duration_s`` (ticks x
      period) and the tick budget; without it, the last row's ``t`` and
      :data:`DEFAULT_RATE_HZ`.
    - ``max_at_risk_s`` [0.1]: most procedure time a crash may lose; the budget in ticks is
      this x rate_hz (at least 1).
    - ``max_queue`` [None]: the budget in ticks, given directly (overrides ``max_at_risk_s``).
    - ``max_wait_s`` [1.0]: longest back-pressure wait in ``record()`` before the row is
      dropped and :class:`TelemetryOverflow` raised; 0: never wait.
    - ``flush_interval_s`` [0.05]: longest wall time an item waits in an unfinished chunk.
    - ``poll_s`` [0.01]: writer's sleep when the queue is empty.
    - ``chunk_size`` [1 MiB]: a flush finishes the chunk in progress once it holds half of
      this (before that, it writes the chunk's new records as a piece of it, see
      :meth:`_flush`), and a chunk that grows past it on the way is finished then.
    - ``compression`` ["zstd"]: one of :data:`COMPRESSIONS`.
    - ``fsync`` [False]: ``os.fsync`` after each flush (paths only).
    - ``validate`` [True]: check rows against the schema in the writer thread; invalid rows
      are still written, counted in ``rows_invalid`` and logged.
    - ``overwrite`` [False]: replace an existing file instead of refusing.
    - ``view`` [True]: the 3D channels ``/tf`` and ``/scene``: a
      :class:`~dentibot.telemetry.foxglove.FoxgloveView` (e.g. with the tool geometry), True
      for the default view, False or None for none.
    - ``on_flush`` [None]: called in the writer thread after each flush, with the recorder
      (its counters are those of the flush); :mod:`~dentibot.telemetry.recorder_process`
      reports flushes to the control process with it. An exception in it kills the writer.
    - ``writer_thread`` [True]: write in a thread of its own; False: write in the caller's
      thread, within ``record()``, ``record_block()`` and ``event()``, the caller calling
      :meth:`flush_due` when it has nothing to hand over (the recorder process, whose only
      work this is).

    The writer is a daemon thread: call :meth:`close` (or use ``with``); a process that ends
    without it leaves a file readable up to its last flush, flagged incomplete.

    Counters: ``rows_queued``, ``ticks_written``, ``events_written``, ``rows_dropped``
    (overflow), ``rows_rejected`` (not serialisable, skipped), ``rows_invalid``,
    ``nonfinite_rows``, ``flushes``, ``rows_flushed`` (ticks on disk at the last flush),
    ``bytes_flushed``, ``queue_depth_max``, ``at_risk_max`` (most ticks handed over and not
    yet flushed, seen by ``record()``), ``backpressure_waits``, ``transforms_written``,
    ``scenes_written``, ``view_errors``.
    """

    def __init__(self, path: str | os.PathLike[str] | BinaryIO,
                 metadata: dict[str, Any] | None = None, *,
                 max_at_risk_s: float = 0.1, max_queue: int | None = None,
                 max_wait_s: float = 1.0, flush_interval_s: float = 0.05, poll_s: float = 0.01,
                 chunk_size: int = 1 << 20, compression: str = "zstd",
                 fsync: bool = False, validate: bool = True, overwrite: bool = False,
                 view: FoxgloveView | bool | None = True,
                 on_flush: Callable[[McapRecorder], None] | None = None,
                 writer_thread: bool = True) -> None:
        if not flush_interval_s > 0:
            raise ConfigError("telemetry.flush_interval_s", flush_interval_s, "> 0 s")
        if not poll_s > 0:
            raise ConfigError("telemetry.poll_s", poll_s, "> 0 s")
        if not (isinstance(max_at_risk_s, (int, float)) and max_at_risk_s > 0):
            raise ConfigError("telemetry.max_at_risk_s", max_at_risk_s, "> 0 s")
        if not (isinstance(max_wait_s, (int, float)) and max_wait_s >= 0):
            raise ConfigError("telemetry.max_wait_s", max_wait_s, ">= 0 s")
        if compression not in COMPRESSIONS:
            raise ConfigError("telemetry.compression", compression, f"one of {list(COMPRESSIONS)}")
        if max_queue is not None and not (isinstance(max_queue, int) and max_queue > 0):
            raise ConfigError("telemetry.max_queue", max_queue, "an integer > 0 (ticks)")
        meta = dict(metadata or {})
        rate = meta.get("rate_hz")
        if rate is not None and not (isinstance(rate, (int, float)) and not isinstance(rate, bool)
                                     and math.isfinite(rate) and rate > 0):
            raise ConfigError("metadata.rate_hz", rate, "a finite number > 0 (Hz)")
        meta.setdefault("dentibot_version", _dentibot_version())
        _start_fields(meta)
        view = as_view(view, "telemetry.view")
        try:                                 # checked before any file is created
            run_json = json.dumps(_without_none(meta), allow_nan=False,
                                  default=_json_default).encode()
            run_text = {k: v if isinstance(v, str) else json.dumps(v, default=_json_default)
                        for k, v in meta.items() if v is not None}
        except (TypeError, ValueError) as exc:
            raise ConfigError("metadata", meta, "JSON-serialisable, finite values",
                              str(exc)) from exc
        self.metadata = meta
        #: wall-clock time of t = 0 (ns since the epoch): messages are logged at this + t
        self.start_wall_ns: int = meta["start_wall_ns"]
        self.view: FoxgloveView | None = view
        self.period_s: float | None = 1.0 / rate if rate else None

        #: most ticks handed over and not yet flushed (queued + in the unfinished chunk)
        self.budget = max_queue if max_queue is not None else \
            max(1, math.floor(max_at_risk_s * (rate or DEFAULT_RATE_HZ) + 1e-9))
        self.flush_interval_s = flush_interval_s
        self.max_wait_s = float(max_wait_s)
        self.poll_s = poll_s
        self.validate = validate
        self._fsync = fsync
        self._on_flush = on_flush
        self._unfinished = False                # close_unfinished(): no summary at the end

        # counters (written by one thread each: record() side or writer side)
        self.rows_queued = 0
        self.events_queued = 0
        self.rows_dropped = 0
        self.queue_depth_max = 0
        self.at_risk_max = 0
        self.backpressure_waits = 0
        self.ticks_written = 0
        self.events_written = 0
        self.rows_rejected = 0
        self.rows_invalid = 0
        self.nonfinite_rows = 0
        self.flushes = 0
        self.rows_flushed = 0
        self.bytes_flushed = 0
        self.transforms_written = 0
        self.scenes_written = 0
        self.view_errors = 0

        self._queue: collections.deque[tuple[str, Any]] = collections.deque()
        #: messages encoded and not yet in the chunk: (channel, log time, data, sequence)
        self._batch: list[tuple[int, int, bytes, int]] = []
        self._stop = threading.Event()
        self._wake = threading.Event()          # queue worth a chunk, a waiting producer, stop
        self._room = threading.Condition(threading.Lock())   # signalled after each flush
        self._error: BaseException | None = None
        self._error_reported = False
        self._closed = False
        self._last_t: float = 0.0
        self._last_tick: int = 0
        self._last_log_ns = self.start_wall_ns
        self._last_scene_t: float | None = None
        self._chunk_size = chunk_size
        self._piece_at = 0                      # bytes of the chunk in progress on disk as pieces
        self._chunks_seen = 0                   # chunks finished at the last flush
        self._ticks_done = 0                    # tick items the writer has dealt with
        self._settled = 0                       # ... of which are flushed (or rejected)
        self._unflushed = 0                     # items in the unfinished chunk
        self._unflushed_ticks = 0
        self._unflushed_since = 0.0             # monotonic time the oldest of them was written
        self.end: dict[str, Any] | None = None

        self._owns_file = not hasattr(path, "write")
        self.path = Path(path) if self._owns_file else Path(str(getattr(path, "name", "<stream>")))
        self._fd: int | None = None
        stream: BinaryIO | None = None
        if self._owns_file:
            flags = os.O_WRONLY | os.O_CREAT | getattr(os, "O_CLOEXEC", 0) | \
                (os.O_TRUNC if overwrite else os.O_EXCL)
            try:
                self._fd = os.open(path, flags, 0o644)
            except FileExistsError:
                raise TelemetryError(path, "file exists; choose another name or pass "
                                     "overwrite=True") from None
            except OSError as exc:
                raise TelemetryError(path, f"cannot create: {exc}") from exc
        else:
            stream = path  # type: ignore[assignment]
        try:
            self._sink = _Sink(self._fd, stream)
            self._writer = Writer(self._sink, chunk_size=chunk_size,
                                  compression=COMPRESSIONS[compression])
            self._compress = zstandard.ZstdCompressor(level=ZSTD_LEVEL).compress \
                if compression == "zstd" else None
            self._writer.start(profile=PROFILE, library=f"dentibot {meta['dentibot_version']}")
            self._channels: dict[str, int] = {}
            schemas = {topic: json_schema(topic) for topic in TOPICS}
            if self.view is not None:
                schemas.update(FOXGLOVE_TOPICS)
            binary = {"/tick": (TICK_SCHEMA_NAME, definition(TICK_FIELDS)),
                      TF_TOPIC: (TF_SCHEMA_NAME, TF_DEFINITION)}
            for topic, schema in schemas.items():
                if topic in binary:                   # CDR: the channels of every tick
                    name, text = binary[topic]
                    schema_id = self._writer.register_schema(
                        name=name, encoding=CDR_SCHEMA_ENCODING, data=text.encode())
                    encoding = CDR_ENCODING
                else:
                    schema_id = self._writer.register_schema(
                        name=schema["title"], encoding=SCHEMA_ENCODING,
                        data=json.dumps(schema).encode())
                    encoding = MESSAGE_ENCODING
                self._channels[topic] = self._writer.register_channel(
                    topic=topic, message_encoding=encoding, schema_id=schema_id)
            self._writer.add_metadata(RUN_METADATA_NAME, run_text)
            self._writer.add_message(self._channels["/run"], self.start_wall_ns, run_json,
                                     self.start_wall_ns)
            self._unflushed = 1
            self._flush()
        except McapError as exc:                     # compression library missing
            self._abandon()
            raise ConfigError("telemetry.compression", compression, "an installed codec",
                              str(exc)) from exc
        except OSError as exc:
            self._abandon()
            raise TelemetryError(self.path, f"cannot write: {exc}") from exc
        self._thread: threading.Thread | None = None
        if writer_thread:
            self._thread = threading.Thread(target=self._run,
                                            name=f"mcap-writer:{self.path.name}", daemon=True)
            self._thread.start()
        log.info("telemetry.recording", path=str(self.path), rate_hz=rate,
                 budget_ticks=self.budget)

    # -- caller side (the control task) ----------------------------------------------------

    def record(self, row: dict[str, Any]) -> None:
        """Queue one tick row. Returns at once unless ``budget`` ticks are at risk; then waits
        for the writer's next flush (back-pressure), at most ``max_wait_s``.

        Raises TelemetryOverflow if the writer made no room in time (the row is dropped),
        TelemetryError if the writer died or the recorder is closed.
        """
        if self._error is not None or self._closed:
            self._raise_dead()
        if self.rows_queued - self._settled >= self.budget:
            self._wait_for_room(row)
        q = self._queue
        q.append(("tick", row))
        self.rows_queued += 1
        depth = len(q)
        if depth > self.queue_depth_max:
            self.queue_depth_max = depth
        at_risk = self.rows_queued - self._settled
        if at_risk > self.at_risk_max:
            self.at_risk_max = at_risk
        if depth == self.flush_ticks:               # a chunk's worth: no need to poll for it
            self._wake.set()
        t = row.get("t")
        if isinstance(t, (int, float)):
            self._last_t = t
        tick = row.get("tick")
        if isinstance(tick, int):
            self._last_tick = tick
        if self._thread is None:
            self._write_now()

    def record_block(self, block: TickBlock) -> None:
        """Queue a block of tick rows (:class:`~dentibot.telemetry.blocks.TickBlock`): the
        same as :meth:`record` of each of its rows, with one wait for room for all of them (a
        block larger than the budget goes in parts)."""
        if self._error is not None or self._closed:
            self._raise_dead()
        if self._in_parts_or_empty(block):
            return
        n = len(block)
        q = self._queue
        q.append(("block", block))
        self.rows_queued += n
        self.queue_depth_max = max(self.queue_depth_max, len(q))
        self.at_risk_max = max(self.at_risk_max, self.rows_queued - self._settled)
        self._wake.set()
        self._last_tick = block.k0 + n - 1
        self._last_t = self._last_tick * block.ts
        if self._thread is None:
            self._write_now()

    def _wait_for_room(self, row: Any, n: int = 1) -> None:
        """Wait until ``n`` more ticks fit in the budget (without a writer thread: make room
        by finishing the chunk now)."""
        self.backpressure_waits += 1
        if self._thread is None:
            self._write_now(flush=True)
            return
        deadline = time.monotonic() + self.max_wait_s
        with self._room:
            while self.rows_queued - self._settled + n > self.budget:
                if self._error is not None:
                    break
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    self._overflow(row, n)
                self._wake.set()
                self._room.wait(remaining)
        if self._error is not None:
            self._raise_dead()

    @property
    def flush_ticks(self) -> int:
        """The writer finishes its chunk at least every this many ticks: half the budget."""
        return max(1, self.budget // 2)

    def event(self, kind: str, detail: str = "", *, t: float | None = None,
              tick: int | None = None) -> None:
        """Queue an ``/events`` message; ``t``/``tick`` default to the last recorded row's.
        Never waits: events are few and ride along with the ticks' budget."""
        if self._error is not None or self._closed:
            self._raise_dead()
        self._queue.append(("event", event_message(kind, detail, t, tick, self._last_t,
                                                   self._last_tick)))
        self.events_queued += 1
        if self._thread is None:
            self._write_now()

    def flush_due(self) -> None:
        """Without a writer thread: finish the chunk if its oldest item has waited
        ``flush_interval_s`` (call it when nothing was handed over for that long)."""
        if self._thread is None and self._unflushed and \
                time.monotonic() - self._unflushed_since >= self.flush_interval_s:
            self._write_now(flush=True)

    def _write_now(self, flush: bool = False) -> None:
        """Without a writer thread: write what is queued (and finish the chunk), here."""
        if self._error is not None:
            self._raise_dead()
        try:
            self._drain()
            if flush and self._unflushed:
                self._flush()
        except BaseException as exc:  # noqa: BLE001 - reported to the caller, never lost
            self._died(exc)
            self._raise_dead()

    @property
    def queue_depth(self) -> int:
        """Items waiting for the writer thread now."""
        return len(self._queue)

    @property
    def at_risk(self) -> int:
        """Ticks handed over and not yet flushed to the OS: what a crash now would lose."""
        return max(self.rows_queued - self._settled, 0)

    @property
    def error(self) -> BaseException | None:
        """What killed the writer thread, or None."""
        return self._error

    @property
    def closed(self) -> bool:
        return self._closed

    def close(self, status: str = "ok", reason: str = "",
              duration_s: float | None = None) -> dict[str, Any] | None:
        """Write ``/run/end`` {status, reason, duration_s}, flush, finish the file (summary),
        join the writer. Idempotent (later calls return the first end record). Returns the
        end record.

        Raises TelemetryError if the writer died and that was not reported yet.
        """
        if self._closed:
            return self.end
        if status not in END_STATUSES:
            raise ConfigError("run.status", status, f"one of {list(END_STATUSES)}")
        self._closed = True
        self.end = {"status": status, "reason": reason,
                    "duration_s": self.duration_s() if duration_s is None else duration_s}
        self._queue.append(("end", self.end))
        self._stop.set()
        self._wake.set()
        self._join()
        log.info("telemetry.closed", path=str(self.path), status=status,
                 ticks_written=self.ticks_written, rows_dropped=self.rows_dropped,
                 queue_depth_max=self.queue_depth_max, at_risk_max=self.at_risk_max,
                 backpressure_waits=self.backpressure_waits)
        if self._error is not None and not self._error_reported:
            self._raise_dead()
        return self.end

    def close_unfinished(self) -> None:
        """Write out everything handed over, then close the file without ``/run/end`` or a
        summary: the file a crash leaves (readers flag it incomplete), but with nothing lost.
        For a producer that is gone (the recorder process's parent died). Idempotent."""
        if self._closed:
            return
        self._closed = True
        self._unfinished = True
        self._stop.set()
        self._wake.set()
        self._join()
        log.warning("telemetry.unfinished", path=str(self.path), ticks_written=self.ticks_written)

    def _join(self) -> None:
        """The writer's end (asked for with ``_stop``): its thread's, or here."""
        if self._thread is not None:
            self._thread.join()
        elif self._error is None:
            self._run()

    def _raise_dead(self) -> None:
        if self._error is not None:
            self._error_reported = True
            writer = "writer" if self._thread is None else "writer thread"
            raise TelemetryError(self.path, f"{writer} died: {self._error!r}; rows since "
                                 f"the last flush ({self.rows_flushed} ticks on disk) are lost"
                                 ) from self._error
        raise TelemetryError(self.path, "recorder is closed")

    # -- writer thread ---------------------------------------------------------------------

    def _run(self) -> None:
        try:
            while True:
                stopping = self._stop.is_set()     # read before draining: nothing follows
                self._drain()
                if self._unflushed and (
                        stopping
                        or time.monotonic() - self._unflushed_since >= self.flush_interval_s):
                    self._flush(whole=stopping)
                if stopping:
                    break
                self._wake.wait(self.poll_s)
                self._wake.clear()
            if self._unfinished:
                self._close_file()
                return
            self._writer.finish()
            self._sink.commit(final=True)
            if self._fsync and self._fd is not None:
                os.fsync(self._fd)
            self.bytes_flushed = self._sink.pos
            self._close_file()
        except BaseException as exc:  # noqa: BLE001 - reported to the caller, never lost
            self._died(exc)

    def _died(self, exc: BaseException) -> None:
        self._error = exc
        log.error("telemetry.writer_died", path=str(self.path), error=repr(exc),
                  ticks_written=self.ticks_written, rows_flushed=self.rows_flushed)
        self._abandon()
        with self._room:
            self._room.notify_all()              # a producer waiting for room learns it now

    def _drain(self) -> None:
        q = self._queue
        handlers = self._HANDLERS
        clock = time.monotonic
        slice_end = clock() + _SLICE_S
        while q:
            kind, payload = q.popleft()
            handlers[kind](self, payload)
            if self._batch:
                self._add_batch()
            now = clock()
            if self._unflushed_ticks >= self.flush_ticks or (
                    self._unflushed and now - self._unflushed_since >= self.flush_interval_s):
                self._flush()
            if now >= slice_end and self._thread is not None:
                time.sleep(0)                     # hand the interpreter lock to the control thread
                slice_end = clock() + _SLICE_S

    def _encode(self, obj: Any, what: str) -> bytes | None:
        try:
            data = orjson.dumps(obj, default=_json_default, option=_ORJSON_OPTIONS)
        except TypeError:                         # beyond orjson: big ints, odd keys, objects
            return self._encode_std(obj, what)
        # orjson writes NaN and infinities as null, and the Nones are left out already: no
        # "null" in the text, nothing non-finite (the exact look only when there is one)
        if b"null" in data and _nonfinite(obj):  # orjson wrote null: leave the field out
            self._count_nonfinite(what)
            data = orjson.dumps(_without_none(_finite(obj)), default=_json_default,
                                option=_ORJSON_OPTIONS)
        return data

    def _encode_std(self, obj: Any, what: str) -> bytes | None:
        try:
            return _dumps(obj)
        except ValueError:                        # NaN / inf: JSON has none
            pass
        except (TypeError, RecursionError) as exc:
            return self._reject(what, exc)
        try:
            data = _dumps(_without_none(_finite(obj)))
        except (TypeError, ValueError, RecursionError) as exc:
            return self._reject(what, exc)
        self._count_nonfinite(what)
        return data

    def _count_nonfinite(self, what: str, rows: int = 1) -> None:
        """``rows`` more rows with a non-finite number (logged while the first few)."""
        logged = self.nonfinite_rows < _LOG_FIRST
        self.nonfinite_rows += rows
        if logged:
            log.warning("telemetry.nonfinite", path=str(self.path), what=what,
                        detail="non-finite floats: a NaN reads back as None" if what == "/tick"
                        else "non-finite floats written as null")

    def _reject(self, what: str, exc: BaseException) -> None:
        self.rows_rejected += 1
        if self.rows_rejected <= _LOG_FIRST:
            log.error("telemetry.unserialisable", path=str(self.path), what=what,
                      error=str(exc), rows_rejected=self.rows_rejected)

    def _write(self, topic: str, obj: dict[str, Any], t: Any, sequence: int = 0) -> bool:
        if topic == "/tick":
            try:
                data = TICK_CODEC.encode(obj)
            except CdrError as exc:
                self._reject(topic, exc)
                return False
            if _nonfinite(obj):                  # kept as it is; a NaN reads back as None
                self._count_nonfinite(topic)
        else:
            data = self._encode(_without_none(obj), topic)
        if data is None:
            return False
        log_ns = _log_time_ns(self.start_wall_ns, t, self._last_log_ns)
        self._last_log_ns = log_ns
        self._batch.append((self._channels[topic], log_ns, data, sequence & 0xFFFFFFFF))
        if not self._unflushed:
            self._unflushed_since = time.monotonic()
        self._unflushed += 1
        return True

    def _write_tick(self, row: dict[str, Any]) -> None:
        self._ticks_done += 1
        if self.validate:
            problems = validate_row(row) if isinstance(row, dict) else ["row is not a dict"]
            if problems:
                self.rows_invalid += 1
                if self.rows_invalid <= _LOG_FIRST:
                    log.warning("telemetry.invalid_row", path=str(self.path),
                                tick=row.get("tick") if isinstance(row, dict) else None,
                                problems=problems[:5], rows_invalid=self.rows_invalid)
        if not isinstance(row, dict):
            self._reject("/tick", TypeError(f"row is a {type(row).__name__}, not a dict"))
        else:
            tick = row.get("tick")
            sequence = tick if isinstance(tick, int) and tick >= 0 else 0
            if self._write("/tick", row, row.get("t"), sequence):
                self.ticks_written += 1
                self._unflushed_ticks += 1
                if self.view is not None:
                    self._write_view(row, sequence)
                return
        # rejected: nothing to write, but the row counts as settled only at the next flush
        # (so the producer's budget is given back even if every row were rejected)
        if not self._unflushed:
            self._unflushed_since = time.monotonic()
        self._unflushed += 1
        self._unflushed_ticks += 1

    def _write_view(self, row: dict[str, Any], sequence: int, tf: bool = True) -> None:
        """The row's ``/tf`` message and, when due, its ``/scene``, at the row's log time
        (:meth:`_view_messages`)."""
        tf_data, scene_data = self._view_messages(row, tf)
        log_ns, sequence = self._last_log_ns, sequence & 0xFFFFFFFF
        if tf_data is not None:
            self._batch.append((self._channels[TF_TOPIC], log_ns, tf_data, sequence))
            self.transforms_written += 1
            self._unflushed += 1
        if scene_data is not None:
            self._batch.append((self._channels[SCENE_TOPIC], log_ns, scene_data, sequence))
            self._unflushed += 1

    def _view_messages(self, row: dict[str, Any],
                       tf: bool = True) -> tuple[bytes | None, bytes | None]:
        """The row's ``/tf`` message (``tf``) and, when due, its ``/scene`` (counted), at the
        row's log time. A failure to draw the row (a malformed row, the caller's ``frames``
        raising) costs the row its 3D messages only (counted, logged); writing them goes the
        way of every message (a write error is the writer's death, reported)."""
        view, log_ns = self.view, self._last_log_ns
        t = row.get("t")
        try:
            tf_data = view.transforms_cdr(row, log_ns) if tf else None
            scene_data = view.scene_json(row, log_ns) \
                if view.scene_due(t, self._last_scene_t) else None
        except Exception as exc:  # noqa: BLE001 - a drawing problem, never the recording's
            self.view_errors += 1
            if self.view_errors <= _LOG_FIRST:
                log.warning("telemetry.view_failed", path=str(self.path), tick=row.get("tick"),
                            error=repr(exc), view_errors=self.view_errors)
            return None, None
        if scene_data is not None:
            self._last_scene_t = float(t)
            self.scenes_written += 1
        return tf_data, scene_data

    def _write_block(self, block: TickBlock) -> None:
        """A block's rows, the messages :meth:`_write_tick` writes for each; the chunk is
        finished every ``flush_ticks`` as between rows. The ``/tick`` messages are copied
        from the block's columns (:meth:`TickBlock.tick_cdr`); with ``validate``, each row
        goes through :meth:`_write_tick`."""
        if self.validate:
            for row in block.rows():
                self._write_tick(row)
                if self._unflushed_ticks >= self.flush_ticks:
                    self._flush()
            return
        channel, wall0 = self._channels["/tick"], self.start_wall_ns
        ts, k0, n = block.ts, block.k0, len(block)
        # wall0 + round(k ts 1e9) of each tick, as _log_time_ns (rint: half to even, as round)
        log_ns = (np.rint(np.arange(k0, k0 + n) * ts * 1e9).astype(np.int64)
                  + wall0).tolist()
        ticks, tick_enc = block.tick_words()
        channels, payloads, sizes = [channel], [ticks.view(np.uint8)], [tick_enc.size]
        view, tfs = self.view, None
        if view is not None:
            tool, ph = COL["tool_pose"], COL["phantom_xyz"]
            try:
                tfs = view.block_transforms_words(block.cols[:, tool:tool + 6],
                                                  block.cols[:, ph:ph + 3],
                                                  block.phantom_euler, log_ns)
            except Exception:  # noqa: BLE001 - drawn row by row below, failures counted
                tfs = None
            if tfs is not None:
                channels.append(self._channels[TF_TOPIC])
                payloads.append(tfs[0].view(np.uint8))
                sizes.append(tfs[1].size)
        nonfinite = n - int(np.isfinite(block.cols).all(axis=1).sum())
        seqs = [k & 0xFFFFFFFF for k in range(k0, k0 + n)]
        j = 0
        while j < n:                              # up to the next flush, then the flush
            stop = min(n, j + max(self.flush_ticks - self._unflushed_ticks, 1))
            if not self._unflushed:
                self._unflushed_since = time.monotonic()
            if view is not None and tfs is None:  # row by row (its failures counted there)
                messages = tick_enc.messages(ticks[j:stop])
                for i in range(j, stop):
                    self._last_log_ns = log_ns[i]
                    self._batch.append((channel, log_ns[i], messages[i - j], seqs[i]))
                    self._write_view(block.rows(i, i + 1)[0], k0 + i)
            else:
                self._write_rows(block, j, stop, tuple(channels), payloads, tuple(sizes),
                                 log_ns, seqs)
            m = stop - j
            self._last_log_ns = log_ns[stop - 1]
            self._ticks_done += m
            self.ticks_written += m
            self._unflushed_ticks += m
            self._unflushed += m
            j = stop
            if self._unflushed_ticks >= self.flush_ticks:
                self._flush()
        if nonfinite:                             # kept as they are; NaN reads back as None
            self._count_nonfinite("/tick", nonfinite)

    def _write_rows(self, block: TickBlock, start: int, stop: int, channels: tuple[int, ...],
                    payloads: list[np.ndarray], sizes: tuple[int, ...], log_ns: list[int],
                    seqs: list[int]) -> None:
        """Rows ``start`` to ``stop`` of a block: each tick's message on each of ``channels``
        (/tick, and /tf with a view), followed by a /scene where one is due (the view's
        period of procedure time), written into the chunk at once."""
        scenes: list[tuple[int, bytes]] = []
        if self.view is not None:
            i = self._next_scene(block, start, stop)
            while i < stop:
                self._last_log_ns = log_ns[i]
                scene = self._view_messages(block.scene_row(i), tf=False)[1]
                if scene is not None:
                    scenes.append((i - start, scene))
                i = self._next_scene(block, i + 1, stop)
            self.transforms_written += stop - start
            self._unflushed += stop - start + len(scenes)
        if self._batch:
            self._add_batch()
        add_tick_messages(self._writer, channels, tuple(p[start:stop] for p in payloads),
                          sizes, log_ns[start:stop], seqs[start:stop], scenes,
                          self._channels.get(SCENE_TOPIC, 0))

    def _next_scene(self, block: TickBlock, start: int, stop: int) -> int:
        """The first of rows ``start`` to ``stop`` of a block due a /scene (``stop``: none):
        the view's :meth:`~dentibot.telemetry.foxglove.FoxgloveView.scene_due` asked of the
        rows from where the period says, a row or two before it."""
        due, last, ts, k0 = self.view.scene_due, self._last_scene_t, block.ts, block.k0
        if due((k0 + start) * ts, last):
            return start
        first = math.ceil((last + self.view.scene_period_s) / ts) - k0 - 2
        for i in range(max(start + 1, first), stop):
            if due((k0 + i) * ts, last):
                return i
        return stop

    def _write_event(self, ev: dict[str, Any]) -> None:
        if self._write("/events", ev, ev["t"], ev["tick"] if isinstance(ev["tick"], int) else 0):
            self.events_written += 1

    def _write_end(self, end: dict[str, Any]) -> None:
        self._write("/run/end", end, self._last_t)

    _HANDLERS: ClassVar[dict[str, Any]] = {"tick": _write_tick, "block": _write_block,
                                           "event": _write_event, "end": _write_end}

    def _add_batch(self) -> None:
        """The messages written since the last call, into the chunk in one call."""
        batch, self._batch = self._batch, []
        add_messages(self._writer, batch)

    def _flush(self, whole: bool = False) -> None:
        """Hand what was written since the last flush, with a provisional end, to the OS in
        one write (and to the disk if fsync); then wake a producer waiting for room.

        What is handed over is the chunk in progress, finished (compressed, indexed) once it
        holds half of ``chunk_size`` (or ``whole``, or where the file cannot be written
        over); before that, the records added since the last flush as an uncompressed chunk
        of their own (:func:`~dentibot.telemetry.mcap_messages.chunk_piece`), which the
        finished chunk is written over. Either way a file cut short there reads back whole
        up to this flush. Finishing a chunk at every flush (25 ticks at 500 Hz, half the
        budget) compressed small chunks, less well and at more cost per byte, and gave a
        recording thousands of chunks to index."""
        if self._batch:
            self._add_batch()
        writer, sink = self._writer, self._sink
        finished = chunks_finished(writer)
        if finished != self._chunks_seen:          # finished on the way (it grew past
            self._chunks_seen, self._piece_at = finished, 0      # chunk_size): pieces start again
        length = chunk_length(writer) if sink.rewritable and not whole else -1
        if 0 <= length < self._chunk_size // 2:
            if sink.staged:                        # a chunk finished on the way goes out first
                sink.commit()
            with chunk_piece(writer, self._piece_at) as piece:
                if piece:
                    sink.provisional(piece)
            self._piece_at = length
        else:
            finish_chunk(writer, self._compress)
            sink.commit()
            self._chunks_seen, self._piece_at = chunks_finished(writer), 0
        if self._fsync and self._fd is not None:
            os.fsync(self._fd)
        self._unflushed = 0
        self._unflushed_ticks = 0
        self.flushes += 1
        self.rows_flushed = self.ticks_written
        self.bytes_flushed = sink.pos + sink.tail
        self._settled = self._ticks_done
        with self._room:
            self._room.notify_all()
        if self._on_flush is not None:
            self._on_flush(self)

    def _close_file(self) -> None:
        if self._fd is not None:
            fd, self._fd = self._fd, None
            os.close(fd)

    def _abandon(self) -> None:
        """Close our file without finishing it (what is flushed stays readable)."""
        try:
            self._close_file()
        except OSError as exc:
            log.error("telemetry.close_failed", path=str(self.path), error=repr(exc))


def _dentibot_version() -> str:
    try:
        return _importlib_metadata.version("dentibot")
    except _importlib_metadata.PackageNotFoundError:
        return "unknown"
