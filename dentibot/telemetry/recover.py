"""Rewrite a recording cut short into a finished MCAP file: ``dentibot recover``.

A recorder killed mid-run leaves a file readable up to its last flush (see
:mod:`dentibot.telemetry.recorder`): it ends with a provisional end without summary, or, if
the kill came in the middle of a write, in the middle of a record. Readers that need the
summary section (indexes, statistics, message counts: Foxglove's seeking, ``mcap info``) and
readers that stop at damage do better with a finished file. :func:`recover_recording` reads
the source front to back with the mcap library's stream reader, CRCs checked, keeps every
complete record up to the first damage (a chunk is kept whole or not at all, so every message
kept is exactly as written), and writes them with the mcap Writer into a new file that has its
summary and footer. Nothing is invented: no ``/run/end`` is added (the run's end was not
recorded), and a ``dentibot.recovery`` metadata record says where the file comes from and what
was saved, so that readers and ``dentibot report`` call the recording incomplete.

A recording written by the recorder's own process has a journal beside it while it is open
(``run.mcap.journal``, :mod:`~dentibot.telemetry.journal`): the ticks, events and end handed
over that the file may not hold yet. When a crash left one, the recovery adds what it holds
beyond the file: the ``/tick`` messages of the ticks after the last one in the file, the
``/events`` not in it, and ``/run/end`` if the run had handed its end over. Their ``/tf`` and
``/scene`` (the 3D views drawn from the rows) are not redrawn. The journal is read, never
changed or deleted.

A source that its recorder finished (footer with summary, read without damage) is intact:
nothing is written unless ``rewrite=True`` (then a plain re-indexed copy, without the recovery
record). An existing output is never replaced without ``force=True``; the output is written
beside it under a temporary name and renamed into place, so a failed recovery leaves nothing
half-written.
"""

from __future__ import annotations

import os
import pickle
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field, fields
from pathlib import Path

import orjson
from mcap.records import (
    Attachment,
    Channel,
    Footer,
    Header,
    McapRecord,
    Message,
    Metadata,
    Schema,
)
from mcap.stream_reader import StreamReader
from mcap.writer import MCAP0_MAGIC, CompressionType, Writer

from dentibot.telemetry.cdr import CDR_LE, TICK_CODEC, CdrError
from dentibot.telemetry.journal import items_of, journal_path, read_journal
from dentibot.telemetry.reader import RECOVERY_METADATA_NAME
from dentibot.telemetry.recorder import _dumps, _log_time_ns, _without_none, event_message
from dentibot.telemetry.schema import TelemetryError

__all__ = ["RecoveryResult", "default_output", "recover_recording"]


@dataclass
class RecoveryResult:
    """What :func:`recover_recording` found and wrote.

    ``intact``: the source was finished by its recorder (nothing to recover); ``out``: the
    file written, or None; ``ticks``/``events``/``messages``: ``/tick`` and ``/events``
    messages and messages of any topic saved; ``first_tick``/``last_tick``: the tick numbers
    of the first and last row saved; ``missing_ticks``: tick numbers absent between them;
    ``has_end``: a ``/run/end`` message was among them; ``rate_hz``: from ``/run``;
    ``bytes_used`` of ``bytes_total``: where the last complete record ended; ``stopped``: why
    reading stopped before a finished end ('' if it did not); ``recovered_before``: the
    source was itself written by a recovery (its recovery record); ``journal_ticks``,
    ``journal_events``: what its journal added (counted in ``ticks`` and ``events`` too);
    ``journal``: the journal read, or why it could not be ('' without one).
    """

    source: Path
    out: Path | None = None
    intact: bool = False
    ticks: int = 0
    events: int = 0
    messages: int = 0
    first_tick: int | None = None
    last_tick: int | None = None
    missing_ticks: int = 0
    has_end: bool = False
    rate_hz: float | None = None
    bytes_used: int = 0
    bytes_total: int = 0
    stopped: str = ""
    recovered_before: dict[str, str] | None = None
    skipped: list[str] = field(default_factory=list)
    journal_ticks: int = 0
    journal_events: int = 0
    journal: str = ""
    # what the journal is checked against: the file's events (tick, kind, detail) and start
    _events: set = field(default_factory=set, repr=False, compare=False)
    _start_ns: int | None = field(default=None, repr=False, compare=False)

    @property
    def seconds(self) -> float | None:
        """Procedure time saved: ticks x period (None without a rate)."""
        return self.ticks / self.rate_hz if self.rate_hz else None

    def to_dict(self) -> dict:
        """Every field, paths as strings, plus ``seconds`` (``dentibot recover --json``)."""
        out = {f.name: getattr(self, f.name) for f in fields(self) if f.repr}
        out["source"] = str(self.source)
        out["out"] = None if self.out is None else str(self.out)
        out["seconds"] = self.seconds
        return out


def default_output(source: str | os.PathLike[str]) -> Path:
    """``run.mcap`` -> ``run.recovered.mcap`` beside it."""
    src = Path(source)
    return src.with_name(f"{src.stem}.recovered{src.suffix or '.mcap'}")


class _Tracked:
    """A binary file that counts what the stream reader consumed, so the end of the last
    complete record is known even though the reader raises mid-record."""

    def __init__(self, f) -> None:
        self._f = f
        self.count = 0

    def fileno(self) -> int:
        return self._f.fileno()

    def read(self, n: int = -1) -> bytes:
        data = self._f.read(n)
        self.count += len(data)
        return data


def recover_recording(source: str | os.PathLike[str], out: str | os.PathLike[str] | None = None,
                      *, force: bool = False, rewrite: bool = False) -> RecoveryResult:
    """Rewrite the complete records of ``source`` into ``out`` (default
    :func:`default_output`), a finished MCAP file. See the module docstring.

    Raises TelemetryError if ``source`` is missing, unreadable, not an MCAP file (or has no
    readable header), if ``out`` exists and ``force`` is not set, or if ``out`` cannot be
    written.
    """
    src = Path(source)
    dst = Path(out) if out is not None else default_output(src)
    try:
        f = open(src, "rb")  # noqa: SIM115 - closed below
    except FileNotFoundError:
        raise TelemetryError(src, "no such file") from None
    except OSError as exc:
        raise TelemetryError(src, f"cannot open: {exc}") from exc
    with f:
        magic = f.read(len(MCAP0_MAGIC))
        if magic != MCAP0_MAGIC:
            raise TelemetryError(src, f"not an MCAP file (starts with {magic[:8]!r}, "
                                 f"expected {MCAP0_MAGIC!r})")
        f.seek(0)
        result, n_records = _scan(f, src)
        if n_records == 0:
            raise TelemetryError(src, "not a readable MCAP recording: no complete header "
                                 f"record ({result.stopped})")
        if result.intact and not rewrite:
            return result
        if dst.exists() and not force:
            raise TelemetryError(dst, "output file exists; choose another name or pass --force")
        if dst.resolve() == src.resolve() and not result.intact:
            raise TelemetryError(dst, "the output must not replace the recording it is read "
                                 "from")
        extra = [] if result.intact else _from_journal(journal_path(src), result)
        f.seek(0)
        _write(_records(f, n_records), result, dst, extra)
    result.out = dst
    return result


def _reader(f) -> StreamReader:
    size = os.fstat(f.fileno()).st_size
    return StreamReader(f, validate_crcs=True, record_size_limit=max(size, 1))


def _records(f, n: int) -> Iterator[McapRecord]:
    """The first ``n`` records of ``f`` (chunks expanded): those :func:`_scan` found whole.
    Reading is deterministic, so a second pass meets the same records; the file is streamed
    twice rather than held in memory (a long run has close to a million messages)."""
    if n <= 0:
        return
    for i, record in enumerate(_reader(f).records, start=1):
        yield record
        if i >= n:                                # never ask the reader for the damaged one
            return


def _scan(f, src: Path) -> tuple[RecoveryResult, int]:
    """The figures of what ``f`` holds up to the first damage, and how many records (chunks
    expanded into their records, footer excluded) come before it."""
    size = os.fstat(f.fileno()).st_size
    result = RecoveryResult(source=src, bytes_total=size)
    tracked = _Tracked(f)
    n_records = 0
    topics: dict[int, str] = {}
    ticks: list[int | None] = []
    footer: Footer | None = None
    try:
        for record in _reader(tracked).records:
            # a chunk's records come out together, after the whole chunk was read and checked
            result.bytes_used = tracked.count
            if isinstance(record, Footer):
                footer = record
                continue
            n_records += 1
            if isinstance(record, Metadata) and record.name == RECOVERY_METADATA_NAME:
                result.recovered_before = dict(record.metadata)
            elif isinstance(record, Channel):
                topics[record.id] = record.topic
            elif isinstance(record, Message):
                result.messages += 1
                topic = topics.get(record.channel_id)
                if topic == "/tick":
                    ticks.append(_tick_of(record.data))
                elif topic == "/events":
                    result.events += 1
                    result._events.add(_event_key(record.data))
                elif topic == "/run/end":
                    result.has_end = True
                elif topic == "/run" and result.rate_hz is None:
                    result.rate_hz, result._start_ns = _run_of(record.data)
        result.bytes_used = tracked.count
    except Exception as exc:  # noqa: BLE001 - any damage ends the readable part
        result.stopped = (f"stopped at byte {result.bytes_used} of {size}: "
                          f"{type(exc).__name__}: {exc}").rstrip(": ")
    else:
        if footer is not None and footer.summary_start == 0:
            result.stopped = "the file ends without a summary (its recorder did not close it)"
        elif footer is None:
            result.stopped = f"no footer at byte {result.bytes_used} of {size}"
    result.intact = footer is not None and footer.summary_start != 0 and not result.stopped
    result.ticks = len(ticks)
    known = [t for t in ticks if t is not None]
    if known:
        result.first_tick, result.last_tick = known[0], known[-1]
        result.missing_ticks = max(known[-1] - known[0] + 1 - len(set(known)), 0)
    return result, n_records


def _tick_of(data: bytes) -> int | None:
    try:
        if data[:4] == CDR_LE:                     # a binary /tick (older recordings: JSON)
            tick = TICK_CODEC.decode(data)["tick"]
        else:
            tick = orjson.loads(data).get("tick")
    except (orjson.JSONDecodeError, AttributeError, CdrError):
        return None
    return tick if isinstance(tick, int) and not isinstance(tick, bool) else None


def _run_of(data: bytes) -> tuple[float | None, int | None]:
    """The ``/run`` message's rate (Hz) and wall-clock start (ns), None where unusable."""
    try:
        run = orjson.loads(data)
        rate, start = run.get("rate_hz"), run.get("start_wall_ns")
    except (orjson.JSONDecodeError, AttributeError):
        return None, None
    ok = isinstance(rate, (int, float)) and not isinstance(rate, bool) and rate > 0
    start_ok = isinstance(start, int) and not isinstance(start, bool) and start >= 0
    return (float(rate) if ok else None), (start if start_ok else None)


def _event_key(data: bytes) -> tuple | None:
    try:
        ev = orjson.loads(data)
        return ev.get("tick"), ev.get("kind"), ev.get("detail", "")
    except (orjson.JSONDecodeError, AttributeError):
        return None


def _from_journal(path: Path, result: RecoveryResult) -> list[tuple[str, int, bytes, int]]:
    """The messages the journal at ``path`` adds to the file's (topic, log time, data,
    sequence): see the module docstring. Its figures go into ``result``; a journal that
    cannot be read is said there and adds nothing."""
    if not path.exists():
        return []
    start = result._start_ns
    if start is None:
        result.journal = f"{path.name}: not used (the file has no /run with its start)"
        return []
    try:
        cells, messages = read_journal(path)
        items = [item for m in messages for item in items_of(m)]
    except (OSError, TelemetryError, ValueError, pickle.UnpicklingError, EOFError) as exc:
        result.journal = f"{path.name}: unreadable ({exc})"
        return []
    out: list[tuple[str, int, bytes, int]] = []
    last = -1 if result.last_tick is None else result.last_tick
    last_t, last_ns, added = 0.0, start, []
    for kind, payload in items:
        rows = payload.rows() if kind == "block" else [payload] if kind == "tick" else []
        for row in rows:
            tick = row.get("tick")
            if not isinstance(tick, int) or tick <= last:
                continue
            try:
                data = TICK_CODEC.encode(row)
            except CdrError as exc:
                result.skipped.append(f"journal tick {tick}: {exc}")
                continue
            last_ns = _log_time_ns(start, row.get("t"), last_ns)
            last_t = row.get("t", last_t)
            out.append(("/tick", last_ns, data, tick & 0xFFFFFFFF))
            added.append(tick)
            last = tick
        if kind == "event":
            ev_kind, detail, t, tick = payload
            ev = event_message(ev_kind, detail, t, tick, last_t, last)
            if (ev["tick"], ev_kind, detail) in result._events:
                continue
            out.append(("/events", _log_time_ns(start, ev["t"], last_ns),
                        _dumps(_without_none(ev)),
                        ev["tick"] & 0xFFFFFFFF if isinstance(ev["tick"], int) else 0))
            result.journal_events += 1
        elif kind == "end" and not result.has_end:
            status, reason, duration = payload
            out.append(("/run/end", last_ns, _dumps({"status": status, "reason": reason,
                                                     "duration_s": duration}), 0))
            result.has_end = True
    if added:
        if result.first_tick is None:
            result.first_tick = added[0]
            result.missing_ticks = added[-1] - added[0] + 1 - len(added)
        else:
            result.missing_ticks += added[-1] - result.last_tick - len(added)
        result.last_tick = added[-1]
    result.journal_ticks = len(added)
    result.ticks += len(added)
    result.events += result.journal_events
    result.journal = (f"{path.name}: {len(added)} ticks, {result.journal_events} events"
                      f"{', the run end' if any(k == 'end' for k, _ in items) else ''} added "
                      f"({cells['head'] - cells['tail']} bytes beyond the file)")
    return out


def _write(records: Iterable[McapRecord], result: RecoveryResult, dst: Path,
           extra: list[tuple[str, int, bytes, int]]) -> None:
    """The records, then ``extra`` messages (by topic), into a finished MCAP file at ``dst``
    (temporary name, then renamed)."""
    tmp = dst.with_name(f".{dst.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "xb") as out:
            _write_records(out, records, result, extra)
            out.flush()
            os.fsync(out.fileno())
        os.replace(tmp, dst)
    except OSError as exc:
        raise TelemetryError(dst, f"cannot write: {exc}") from exc
    finally:
        if tmp.exists():
            tmp.unlink()


def _write_records(out, records: Iterable[McapRecord], result: RecoveryResult,
                   extra: list[tuple[str, int, bytes, int]]) -> None:
    writer = Writer(out, compression=CompressionType.ZSTD)
    schema_ids: dict[int, int] = {}
    channel_ids: dict[int, int] = {}
    by_topic: dict[str, int] = {}
    started = False
    for record in records:
        if isinstance(record, Header):
            library = record.library if result.intact else f"{record.library} (recovered)"
            writer.start(profile=record.profile, library=library)
            started = True
            continue
        if not started:                           # the stream reader always yields it first
            writer.start()
            started = True
        if isinstance(record, Schema):
            if record.id not in schema_ids:
                schema_ids[record.id] = writer.register_schema(
                    name=record.name, encoding=record.encoding, data=record.data)
        elif isinstance(record, Channel):
            if record.id not in channel_ids:
                channel_ids[record.id] = writer.register_channel(
                    topic=record.topic, message_encoding=record.message_encoding,
                    schema_id=schema_ids.get(record.schema_id, 0),
                    metadata=dict(record.metadata))
                by_topic.setdefault(record.topic, channel_ids[record.id])
        elif isinstance(record, Message):
            channel = channel_ids.get(record.channel_id)
            if channel is None:
                result.skipped.append(f"message on unknown channel {record.channel_id} at "
                                      f"log time {record.log_time} ns")
                continue
            writer.add_message(channel, record.log_time, record.data, record.publish_time,
                               sequence=record.sequence)
        elif isinstance(record, Metadata):
            writer.add_metadata(record.name, dict(record.metadata))
        elif isinstance(record, Attachment):
            writer.add_attachment(record.create_time, record.log_time, record.name,
                                  record.media_type, record.data)
    for topic, log_ns, data, sequence in extra:
        channel = by_topic.get(topic)
        if channel is None:
            result.skipped.append(f"journal message on {topic}: the file has no such channel")
            continue
        writer.add_message(channel, log_ns, data, log_ns, sequence=sequence)
    if not result.intact:
        writer.add_metadata(RECOVERY_METADATA_NAME, {
            "source": result.source.name,
            "ticks": str(result.ticks),
            "events": str(result.events),
            "messages": str(result.messages - len(result.skipped)),
            "first_tick": "" if result.first_tick is None else str(result.first_tick),
            "last_tick": "" if result.last_tick is None else str(result.last_tick),
            "missing_ticks": str(result.missing_ticks),
            "run_end": "yes" if result.has_end else "no",
            "bytes_used": str(result.bytes_used),
            "bytes_total": str(result.bytes_total),
            "stopped": result.stopped,
            "journal": result.journal,
            "journal_ticks": str(result.journal_ticks),
        })
    writer.finish()
