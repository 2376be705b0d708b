"""MCAP recorder: one message per control tick, written by a thread so the control task never waits.

:class:`McapRecorder` is fed from the 500 Hz control task. ``record(row)`` and ``event(...)``
only append to a :class:`collections.deque` (no lock, no I/O, no serialisation) and return; a
writer thread pops the queue, serialises each item as JSON and writes it to the MCAP file.

Crash safety: the writer finishes the current chunk and flushes the file at least every
``flush_interval_s`` (0.2 s by default), so whatever happens to the process, everything
queued more than about that long ago is in the operating system's hands, in complete MCAP
chunks: a file cut anywhere is readable up to its last complete chunk
(:func:`dentibot.telemetry.reader.read_recording`). ``fsync=True`` also survives a power cut,
at the cost of one ``fsync`` per flush.

If the writer thread dies (disk full, I/O error...), the next ``record()``/``event()`` raises
:class:`TelemetryError` carrying the cause: a recording never stops silently.

Ownership: ``record(row)`` takes the row as it is and serialises it later, in the writer
thread. The caller must not mutate the row (or the lists inside it) after handing it over;
the runtime builds a fresh dict each tick. Numpy arrays and scalars are accepted (converted
with ``tolist()``); non-finite floats are written as ``null`` (JSON has no NaN) and counted.
"""

from __future__ import annotations

import collections
import json
import math
import os
import threading
import time
from importlib import metadata as _importlib_metadata
from pathlib import Path
from typing import Any, BinaryIO, ClassVar

import structlog
from mcap.exceptions import McapError
from mcap.writer import CompressionType, Writer

from dentibot.errors import ConfigError
from dentibot.telemetry.schema import (
    END_STATUSES,
    TOPICS,
    TelemetryError,
    json_schema,
    validate_row,
)

__all__ = ["COMPRESSIONS", "McapRecorder"]

log = structlog.get_logger("dentibot.telemetry")

COMPRESSIONS: dict[str, CompressionType] = {
    "zstd": CompressionType.ZSTD,
    "lz4": CompressionType.LZ4,
    "none": CompressionType.NONE,
}

PROFILE = ""                 # MCAP profile: none (plain JSON messages)
MESSAGE_ENCODING = "json"
SCHEMA_ENCODING = "jsonschema"
RUN_METADATA_NAME = "dentibot.run"    # MCAP metadata record holding the /run fields as text

_YIELD_EVERY = 16            # items written between GIL hand-overs to the control thread
_LOG_FIRST = 5               # problems of each kind logged in full, then only counted


def _json_default(obj: Any) -> Any:
    """numpy arrays and scalars (anything with ``tolist``) become lists / Python numbers."""
    tolist = getattr(obj, "tolist", None)
    if tolist is not None:
        return tolist()
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def _finite(obj: Any) -> Any:
    """``obj`` with every non-finite float replaced by None (numpy values converted)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_finite(v) for v in obj]
    if hasattr(obj, "tolist"):
        return _finite(obj.tolist())
    return obj


def _dumps(obj: Any) -> bytes:
    return json.dumps(obj, allow_nan=False, separators=(",", ":"),
                      default=_json_default).encode()


def _log_time_ns(t: Any, fallback: int) -> int:
    """MCAP log time (ns, unsigned) from ``t`` (s since the run start)."""
    if isinstance(t, (int, float)) and not isinstance(t, bool) and math.isfinite(t) and t >= 0:
        return round(t * 1e9)
    return fallback


class McapRecorder:
    """Record a run to an MCAP file: ``/run`` now, ``/tick`` and ``/events`` as they come,
    ``/run/end`` at :meth:`close`.

    Parameters (defaults in brackets):

    - ``path``: file to create, or a writable binary stream (left open on close).
    - ``metadata``: the run's ``/run`` message (protocol, seed, rate_hz, devices...);
      ``dentibot_version`` is filled in when absent. ``rate_hz`` (> 0) sets the period used
      for ``duration_s`` (ticks x period); without it, the last row's ``t``.
    - ``flush_interval_s`` [0.2]: longest time between flushes (chunk finished, file flushed).
    - ``poll_s`` [0.01]: writer's sleep when the queue is empty.
    - ``chunk_size`` [1 MiB]: a chunk is also finished when it grows past this.
    - ``compression`` ["zstd"]: one of :data:`COMPRESSIONS`.
    - ``max_queue`` [1 000 000 items, ~30 min at 500 Hz]: beyond this, ``record()`` drops the
      row (counted in ``rows_dropped``) rather than exhaust memory or block.
    - ``fsync`` [False]: ``os.fsync`` after each flush (paths only).
    - ``validate`` [True]: check rows against the schema in the writer thread; invalid rows
      are still written, counted in ``rows_invalid`` and logged.
    - ``overwrite`` [False]: replace an existing file instead of refusing.

    The writer is a daemon thread: call :meth:`close` (or use ``with``); a process that ends
    without it leaves a file readable up to its last flush, flagged incomplete.

    Counters: ``rows_queued``, ``ticks_written``, ``events_written``, ``rows_dropped``,
    ``rows_rejected`` (not serialisable, skipped), ``rows_invalid``, ``nonfinite_rows``,
    ``flushes``, ``rows_flushed`` (ticks on disk at the last flush), ``queue_depth_max``.
    """

    def __init__(self, path: str | os.PathLike[str] | BinaryIO,
                 metadata: dict[str, Any] | None = None, *,
                 flush_interval_s: float = 0.2, poll_s: float = 0.01,
                 chunk_size: int = 1 << 20, compression: str = "zstd",
                 max_queue: int = 1_000_000, fsync: bool = False, validate: bool = True,
                 overwrite: bool = False) -> None:
        if not flush_interval_s > 0:
            raise ConfigError("telemetry.flush_interval_s", flush_interval_s, "> 0 s")
        if not poll_s > 0:
            raise ConfigError("telemetry.poll_s", poll_s, "> 0 s")
        if compression not in COMPRESSIONS:
            raise ConfigError("telemetry.compression", compression, f"one of {list(COMPRESSIONS)}")
        if not (isinstance(max_queue, int) and max_queue > 0):
            raise ConfigError("telemetry.max_queue", max_queue, "an integer > 0")
        meta = dict(metadata or {})
        rate = meta.get("rate_hz")
        if rate is not None and not (isinstance(rate, (int, float)) and not isinstance(rate, bool)
                                     and math.isfinite(rate) and rate > 0):
            raise ConfigError("metadata.rate_hz", rate, "a finite number > 0 (Hz)")
        meta.setdefault("dentibot_version", _dentibot_version())
        try:                                 # checked before any file is created
            run_json = json.dumps(meta, allow_nan=False, default=_json_default).encode()
            run_text = {k: v if isinstance(v, str) else json.dumps(v, default=_json_default)
                        for k, v in meta.items()}
        except (TypeError, ValueError) as exc:
            raise ConfigError("metadata", meta, "JSON-serialisable, finite values",
                              str(exc)) from exc
        self.metadata = meta
        self.period_s: float | None = 1.0 / rate if rate else None

        self.flush_interval_s = flush_interval_s
        self.poll_s = poll_s
        self.max_queue = max_queue
        self.validate = validate
        self._fsync = fsync

        # counters (written by one thread each: record() side or writer side)
        self.rows_queued = 0
        self.events_queued = 0
        self.rows_dropped = 0
        self.queue_depth_max = 0
        self.ticks_written = 0
        self.events_written = 0
        self.rows_rejected = 0
        self.rows_invalid = 0
        self.nonfinite_rows = 0
        self.flushes = 0
        self.rows_flushed = 0
        self.bytes_flushed = 0

        self._queue: collections.deque[tuple[str, Any]] = collections.deque()
        self._stop = threading.Event()
        self._error: BaseException | None = None
        self._error_reported = False
        self._closed = False
        self._last_t: float = 0.0
        self._last_tick: int = 0
        self._last_log_ns = 0
        self._unflushed = 0
        self._last_flush = time.monotonic()
        self.end: dict[str, Any] | None = None

        self._owns_file = not hasattr(path, "write")
        self.path = Path(path) if self._owns_file else Path(str(getattr(path, "name", "<stream>")))
        if self._owns_file:
            try:
                self._file: BinaryIO = open(path, "wb" if overwrite else "xb")  # noqa: SIM115
            except FileExistsError:
                raise TelemetryError(path, "file exists; choose another name or pass "
                                     "overwrite=True") from None
            except OSError as exc:
                raise TelemetryError(path, f"cannot create: {exc}") from exc
        else:
            self._file = path  # type: ignore[assignment]
        try:
            self._writer = Writer(self._file, chunk_size=chunk_size,
                                  compression=COMPRESSIONS[compression])
            self._writer.start(profile=PROFILE, library=f"dentibot {meta['dentibot_version']}")
            self._channels: dict[str, int] = {}
            for topic, (title, _fields, _extra) in TOPICS.items():
                schema_id = self._writer.register_schema(
                    name=title, encoding=SCHEMA_ENCODING,
                    data=json.dumps(json_schema(topic)).encode())
                self._channels[topic] = self._writer.register_channel(
                    topic=topic, message_encoding=MESSAGE_ENCODING, schema_id=schema_id)
            self._writer.add_metadata(RUN_METADATA_NAME, run_text)
            self._writer.add_message(self._channels["/run"], 0, run_json, 0)
            self._flush()
        except McapError as exc:                     # compression library missing
            self._abandon()
            raise ConfigError("telemetry.compression", compression, "an installed codec",
                              str(exc)) from exc
        except OSError as exc:
            self._abandon()
            raise TelemetryError(self.path, f"cannot write: {exc}") from exc
        self._thread = threading.Thread(target=self._run, name=f"mcap-writer:{self.path.name}",
                                        daemon=True)
        self._thread.start()
        log.info("telemetry.recording", path=str(self.path), rate_hz=rate)

    # -- caller side (the control task): append and return -------------------------------

    def record(self, row: dict[str, Any]) -> None:
        """Queue one tick row; returns at once. Raises TelemetryError if the writer died."""
        if self._error is not None or self._closed:
            self._raise_dead()
        q = self._queue
        if len(q) >= self.max_queue:
            self.rows_dropped += 1
            return
        q.append(("tick", row))
        self.rows_queued += 1
        depth = len(q)
        self.queue_depth_max = max(self.queue_depth_max, depth)
        t = row.get("t")
        if isinstance(t, (int, float)):
            self._last_t = t
        tick = row.get("tick")
        if isinstance(tick, int):
            self._last_tick = tick

    def event(self, kind: str, detail: str = "", *, t: float | None = None,
              tick: int | None = None) -> None:
        """Queue an ``/events`` message; ``t``/``tick`` default to the last recorded row's."""
        if self._error is not None or self._closed:
            self._raise_dead()
        self._queue.append(("event", {
            "t": self._last_t if t is None else t,
            "tick": self._last_tick if tick is None else tick,
            "kind": kind, "detail": detail}))
        self.events_queued += 1

    @property
    def queue_depth(self) -> int:
        """Items waiting for the writer thread now."""
        return len(self._queue)

    @property
    def error(self) -> BaseException | None:
        """What killed the writer thread, or None."""
        return self._error

    @property
    def closed(self) -> bool:
        return self._closed

    def duration_s(self) -> float:
        """Ticks queued x period when the rate is known, else the last row's ``t``."""
        if self.period_s is not None:
            return self.rows_queued * self.period_s
        return float(self._last_t)

    def close(self, status: str = "ok", reason: str = "",
              duration_s: float | None = None) -> dict[str, Any] | None:
        """Write ``/run/end`` {status, reason, duration_s}, flush, finish the file, join the
        writer. Idempotent (later calls return the first end record). Returns the end record.

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
        self._thread.join()
        log.info("telemetry.closed", path=str(self.path), status=status,
                 ticks_written=self.ticks_written, rows_dropped=self.rows_dropped,
                 queue_depth_max=self.queue_depth_max)
        if self._error is not None and not self._error_reported:
            self._raise_dead()
        return self.end

    def __enter__(self) -> McapRecorder:  # noqa: PYI034
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc is None:
            self.close("ok")
            return
        try:
            self.close("aborted", f"{exc_type.__name__}: {exc}")
        except TelemetryError as err:     # do not hide the exception already in flight
            log.error("telemetry.close_failed", path=str(self.path), error=str(err))

    def _raise_dead(self) -> None:
        if self._error is not None:
            self._error_reported = True
            raise TelemetryError(self.path, f"writer thread died: {self._error!r}; rows since "
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
                        or time.monotonic() - self._last_flush >= self.flush_interval_s):
                    self._flush()
                if stopping:
                    break
                self._stop.wait(self.poll_s)
            self._writer.finish()
            self._file.flush()
            if self._fsync and self._owns_file:
                os.fsync(self._file.fileno())
            if self._owns_file:
                self._file.close()
        except BaseException as exc:  # noqa: BLE001 - reported to the caller, never lost
            self._error = exc
            log.error("telemetry.writer_died", path=str(self.path), error=repr(exc),
                      ticks_written=self.ticks_written, rows_flushed=self.rows_flushed)
            self._abandon()

    def _drain(self) -> None:
        q = self._queue
        n = 0
        while q:
            kind, payload = q.popleft()
            self._HANDLERS[kind](self, payload)
            n += 1
            if n % _YIELD_EVERY == 0:
                time.sleep(0)                     # hand the GIL to the control thread
                if time.monotonic() - self._last_flush >= self.flush_interval_s:
                    self._flush()

    def _encode(self, obj: Any, what: str) -> bytes | None:
        try:
            return _dumps(obj)
        except ValueError:                        # NaN / inf: JSON has none
            pass
        except (TypeError, RecursionError) as exc:
            return self._reject(what, exc)
        try:
            data = _dumps(_finite(obj))
        except (TypeError, ValueError, RecursionError) as exc:
            return self._reject(what, exc)
        self.nonfinite_rows += 1
        if self.nonfinite_rows <= _LOG_FIRST:
            log.warning("telemetry.nonfinite", path=str(self.path), what=what,
                        detail="non-finite floats written as null")
        return data

    def _reject(self, what: str, exc: BaseException) -> None:
        self.rows_rejected += 1
        if self.rows_rejected <= _LOG_FIRST:
            log.error("telemetry.unserialisable", path=str(self.path), what=what,
                      error=str(exc), rows_rejected=self.rows_rejected)

    def _write(self, topic: str, obj: dict[str, Any], t: Any, sequence: int = 0) -> bool:
        data = self._encode(obj, topic)
        if data is None:
            return False
        log_ns = _log_time_ns(t, self._last_log_ns)
        self._last_log_ns = log_ns
        self._writer.add_message(self._channels[topic], log_ns, data, log_ns,
                                 sequence=sequence & 0xFFFFFFFF)
        self._unflushed += 1
        return True

    def _write_tick(self, row: dict[str, Any]) -> None:
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
            return
        tick = row.get("tick")
        if self._write("/tick", row, row.get("t"), tick if isinstance(tick, int) and tick >= 0 else 0):
            self.ticks_written += 1

    def _write_event(self, ev: dict[str, Any]) -> None:
        if self._write("/events", ev, ev["t"], ev["tick"] if isinstance(ev["tick"], int) else 0):
            self.events_written += 1

    def _write_end(self, end: dict[str, Any]) -> None:
        self._write("/run/end", end, self._last_t)

    _HANDLERS: ClassVar[dict[str, Any]] = {"tick": _write_tick, "event": _write_event, "end": _write_end}

    def _flush(self) -> None:
        """Finish the chunk in progress and push everything to the OS (and disk if fsync)."""
        self._writer.flush()
        if self._fsync and self._owns_file:
            os.fsync(self._file.fileno())
        self._last_flush = time.monotonic()
        self._unflushed = 0
        self.flushes += 1
        self.rows_flushed = self.ticks_written
        try:
            self.bytes_flushed = self._file.tell()
        except (OSError, AttributeError, ValueError):
            pass

    def _abandon(self) -> None:
        """Close our file without finishing it (what is flushed stays readable)."""
        if self._owns_file:
            try:
                self._file.close()
            except OSError as exc:
                log.error("telemetry.close_failed", path=str(self.path), error=repr(exc))


def _dentibot_version() -> str:
    try:
        return _importlib_metadata.version("dentibot")
    except _importlib_metadata.PackageNotFoundError:
        return "unknown"
