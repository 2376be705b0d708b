"""Read a DentiBot MCAP recording back, including one cut short by a crash.

:func:`read_recording` walks the file front to back with the mcap library's
:class:`~mcap.stream_reader.StreamReader` (it never needs the summary section at the end, which
a crashed run does not have). Chunk CRCs are checked, so a chunk cut in the middle is refused
whole: what comes back is every message of every complete chunk, in file order.

``complete`` says whether the recording was finished by its recorder: read to a footer that
closes a summary section. A recording cut short ends either in the middle of a record or with
the provisional end its recorder keeps after the data (a footer without summary, see
:mod:`dentibot.telemetry.recorder`); a file rewritten by ``dentibot recover`` has a summary but
carries a ``dentibot.recovery`` metadata record (``recovered``): neither is complete.

A field of a topic's table that a message leaves out reads back as None: that is how the
recorder stores an unknown value (:mod:`dentibot.telemetry.schema`), so a row read back equals
the row recorded, None values included. Recordings written with explicit ``null`` values read
the same way. Everything is read by procedure time ``t``; the messages' log times (wall clock)
are not needed. Other channels (the 3D topics ``/tf`` and ``/scene``) are skipped.

:func:`read_table` reads the same messages into typed Arrow tables (one column per field,
None as null) for notebooks and data analysis; ``to_pandas()`` needs pandas
(``pip install 'dentibot[notebook]'``).
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import structlog
from mcap.records import Channel, Footer, Message, Metadata
from mcap.stream_reader import StreamReader
from mcap.writer import MCAP0_MAGIC

from dentibot.errors import ConfigError
from dentibot.telemetry.cdr import MESSAGE_ENCODING as CDR_ENCODING
from dentibot.telemetry.cdr import TICK_CODEC, CdrError
from dentibot.telemetry.schema import (
    EVENT_FIELDS,
    TICK_FIELDS,
    TOPICS,
    Field,
    TelemetryError,
    none_fields,
)

if TYPE_CHECKING:
    import pandas
    import pyarrow

__all__ = ["RECOVERY_METADATA_NAME", "MessageStream", "Recording", "RecordingTables",
           "arrow_schema", "read_recording", "read_table"]

TOPIC_NAMES = frozenset(TOPICS)

#: topic -> every field of its table as None: a decoded message is laid over it
_NONES: dict[str, dict[str, None]] = {topic: none_fields(topic) for topic in TOPICS}

#: MCAP metadata record that ``dentibot recover`` adds to the files it rewrites
RECOVERY_METADATA_NAME = "dentibot.recovery"

log = structlog.get_logger("dentibot.telemetry")

_FIELDS = {f.name: f for f in TICK_FIELDS}


@dataclass
class Recording:
    """What a recording holds.

    ``metadata``: the ``/run`` message ({} if cut before it); ``rows``: the ``/tick`` rows in
    order; ``events``: the ``/events`` messages; ``end``: the ``/run/end`` message or None;
    ``complete``: the recording was finished by its recorder and read to its end;
    ``recovered``: the ``dentibot.recovery`` metadata (source, ticks, ...) of a file rewritten
    by ``dentibot recover``, else None; ``problems``: what could not be read (truncation, no
    summary, undecodable messages), as text.
    """

    path: Path
    metadata: dict[str, Any] = field(default_factory=dict)
    rows: list[dict[str, Any]] = field(default_factory=list)
    events: list[dict[str, Any]] = field(default_factory=list)
    end: dict[str, Any] | None = None
    complete: bool = False
    recovered: dict[str, str] | None = None
    problems: list[str] = field(default_factory=list)

    @property
    def status(self) -> str | None:
        """``/run/end`` status, or None when the run has no end record (crash, still running)."""
        return None if self.end is None else self.end.get("status")

    @property
    def rate_hz(self) -> float | None:
        rate = self.metadata.get("rate_hz")
        return float(rate) if isinstance(rate, (int, float)) and rate > 0 else None

    def column(self, name: str) -> np.ndarray:
        """One tick field over all rows as numpy.

        Numbers and booleans: float array (n,), null -> nan. Fixed-size arrays (q_deg,
        wrench_h, ...): float array (n, size), a null row -> a row of nan. Strings and lists of
        strings: object array (n,).
        """
        if name not in _FIELDS:
            raise ConfigError("telemetry.column", name, f"a tick field: {list(_FIELDS)}")
        f = _FIELDS[name]
        values = [r.get(name) for r in self.rows]
        if f.json_type == "string":
            out = np.empty(len(values), dtype=object)
            out[:] = values
            return out
        if f.length:
            arr = np.full((len(values), f.length), np.nan)
            for i, v in enumerate(values):
                if isinstance(v, list) and len(v) == f.length:
                    arr[i] = [np.nan if x is None else x for x in v]
            return arr
        return np.array([np.nan if v is None else float(v) for v in values], dtype=float)


class MessageStream:
    """The messages of a recording, streamed: iterate for ``(topic, decoded JSON)`` pairs of
    the DentiBot topics (``/run``, ``/tick``, ``/events``, ``/run/end``) in file order, without
    holding the file in memory. After the iteration, ``complete``, ``recovered`` and
    ``problems`` say how it went (as in :class:`Recording`).

    Raises TelemetryError at construction if the file is missing, unreadable or not MCAP.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = Path(path)
        try:
            with open(self.path, "rb") as f:
                magic = f.read(len(MCAP0_MAGIC))
        except FileNotFoundError:
            raise TelemetryError(self.path, "no such file") from None
        except OSError as exc:
            raise TelemetryError(self.path, f"cannot open: {exc}") from exc
        if magic != MCAP0_MAGIC:
            raise TelemetryError(self.path, f"not an MCAP file (starts with {magic[:8]!r}, "
                                 f"expected {MCAP0_MAGIC!r})")
        self.complete = False
        self.recovered: dict[str, str] | None = None
        self.problems: list[str] = []

    def __iter__(self) -> Iterator[tuple[str, Any]]:
        self.complete = False
        self.recovered = None
        self.problems = []
        try:
            f = open(self.path, "rb")  # noqa: SIM115 - closed below
        except OSError as exc:
            raise TelemetryError(self.path, f"cannot open: {exc}") from exc
        with f:
            size = os.fstat(f.fileno()).st_size
            topics: dict[int, str] = {}
            cdr_channels: set[int] = set()
            footer: Footer | None = None
            try:
                for record in StreamReader(f, validate_crcs=True,
                                           record_size_limit=max(size, 1)).records:
                    if isinstance(record, Message):
                        topic = topics.get(record.channel_id, "")
                        if topic in TOPIC_NAMES:
                            obj = self._decode(topic, record,
                                               record.channel_id in cdr_channels)
                            if obj is not _BAD:
                                yield topic, obj
                    elif isinstance(record, Channel):
                        topics[record.id] = record.topic
                        if record.message_encoding == CDR_ENCODING:
                            cdr_channels.add(record.id)
                    elif isinstance(record, Metadata) and record.name == RECOVERY_METADATA_NAME:
                        self.recovered = dict(record.metadata)
                    elif isinstance(record, Footer):
                        footer = record
            except Exception as exc:  # noqa: BLE001 - any damage ends the readable part
                self.problems.append(f"stopped reading at byte {f.tell()} of {size}: "
                                     f"{type(exc).__name__}: {exc}")
            else:
                if footer is not None and footer.summary_start == 0:
                    self.problems.append("the recording was not closed (its file ends without "
                                         "a summary): cut short, or still being written")
                self.complete = (footer is not None and footer.summary_start != 0
                                 and self.recovered is None)
        if self.problems:
            log.warning("telemetry.read_incomplete", path=str(self.path),
                        problems=self.problems[:3])

    def _decode(self, topic: str, msg: Message, cdr: bool = False) -> Any:
        if cdr:                                # /tick, binary (older recordings: JSON)
            try:
                return TICK_CODEC.decode(msg.data) if topic == "/tick" else _BAD
            except CdrError as exc:
                self.problems.append(f"{topic} message at log time {msg.log_time} ns: "
                                     f"bad CDR ({exc})")
                return _BAD
        try:
            obj = json.loads(msg.data)
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            self.problems.append(f"{topic} message at log time {msg.log_time} ns: "
                                 f"bad JSON ({exc})")
            return _BAD
        return _NONES[topic] | obj if isinstance(obj, dict) else obj


_BAD = object()


def read_recording(path: str | os.PathLike[str]) -> Recording:
    """Read ``path`` whole; tolerant of a truncated or still-growing file (``complete=False``).

    Raises TelemetryError if the file is missing, unreadable or not an MCAP file. (For long
    runs, :class:`MessageStream` reads without holding every row.)
    """
    stream = MessageStream(path)
    rec = Recording(path=stream.path)
    for topic, obj in stream:
        _TOPIC_HANDLERS[topic](rec, obj)
    rec.complete = stream.complete
    rec.recovered = stream.recovered
    rec.problems = stream.problems
    return rec


def _set_metadata(rec: Recording, obj: Any) -> None:
    rec.metadata = obj if isinstance(obj, dict) else {"value": obj}


def _set_end(rec: Recording, obj: Any) -> None:
    rec.end = obj if isinstance(obj, dict) else {"value": obj}


# topic -> what to do with a decoded message
_TOPIC_HANDLERS = {
    "/run": _set_metadata,
    "/tick": lambda rec, obj: rec.rows.append(obj),
    "/events": lambda rec, obj: rec.events.append(obj),
    "/run/end": _set_end,
}


# ---------------------------------------------------------------------------- Arrow tables
def arrow_schema(fields: tuple[Field, ...] = TICK_FIELDS) -> pyarrow.Schema:
    """The Arrow schema of a topic's table: one column per field, in order, every column
    nullable; each column's metadata holds its ``unit`` and ``description``.

    number -> float64, integer -> int64, boolean -> bool, string -> string; a fixed-size
    array (``q_deg``, ``wrench_h``...) -> fixed_size_list<float64>[n]; a list of any length
    (``events``) -> list<string>; an object (``devices``) -> map<string, string>.
    """
    import pyarrow as pa

    scalar = {"number": pa.float64(), "integer": pa.int64(), "boolean": pa.bool_(),
              "string": pa.string()}

    def arrow_type(f: Field) -> pyarrow.DataType:
        item = scalar[f.json_type]
        if f.length is None:
            return item
        if f.length == -1:
            return pa.map_(pa.string(), item)
        return pa.list_(item, f.length) if f.length > 0 else pa.list_(item)

    return pa.schema([pa.field(f.name, arrow_type(f), nullable=True,
                               metadata={"unit": f.unit, "description": f.description})
                      for f in fields])


def _table(path: Path, columns: dict[str, list], fields: tuple[Field, ...]) -> pyarrow.Table:
    import pyarrow as pa

    schema = arrow_schema(fields)
    arrays = []
    for f in schema:
        try:
            arrays.append(pa.array(columns[f.name], type=f.type))
        except (pa.ArrowInvalid, pa.ArrowTypeError, TypeError, ValueError) as exc:
            raise TelemetryError(path, f"field {f.name!r}: a value does not fit {f.type} "
                                       f"({exc})") from exc
    return pa.Table.from_arrays(arrays, schema=schema)


@dataclass
class RecordingTables:
    """A recording as Arrow tables (:func:`read_table`).

    ``ticks``: the ``/tick`` rows, one typed column per tick field (:func:`arrow_schema`),
    one row per control tick in file order; ``events``: the ``/events`` messages (t, tick,
    kind, detail); ``metadata``, ``end``, ``complete``, ``recovered``, ``problems``: as in
    :class:`Recording`.
    """

    path: Path
    ticks: pyarrow.Table
    events: pyarrow.Table
    metadata: dict[str, Any] = field(default_factory=dict)
    end: dict[str, Any] | None = None
    complete: bool = False
    recovered: dict[str, str] | None = None
    problems: list[str] = field(default_factory=list)

    @property
    def status(self) -> str | None:
        """``/run/end`` status, or None when the run has no end record (crash, still running)."""
        return None if self.end is None else self.end.get("status")

    def to_pandas(self) -> pandas.DataFrame:
        """``ticks`` as a pandas DataFrame (fixed-size arrays as numpy arrays per cell).
        Raises ImportError when pandas is missing: it comes with ``dentibot[notebook]``."""
        try:
            import pandas  # noqa: F401
        except ImportError as exc:
            raise ImportError("to_pandas() needs pandas, which comes with the notebook extra: "
                              "pip install 'dentibot[notebook]'") from exc
        return self.ticks.to_pandas()


def read_table(path: str | os.PathLike[str]) -> RecordingTables:
    """Read ``path`` into Arrow tables, streamed (no per-row dicts are kept); tolerant of a
    truncated or still-growing file like :func:`read_recording` (``complete=False``).

    Raises TelemetryError if the file is missing, unreadable or not an MCAP file, or a value
    does not fit its field's type.
    """
    stream = MessageStream(path)
    ticks: dict[str, list] = {f.name: [] for f in TICK_FIELDS}
    events: dict[str, list] = {f.name: [] for f in EVENT_FIELDS}
    once: dict[str, Any] = {"/run": {}, "/run/end": None}      # the /run and /run/end records
    skipped = 0
    for topic, obj in stream:
        if topic in once:
            once[topic] = obj if isinstance(obj, dict) else {"value": obj}
        elif not isinstance(obj, dict):
            skipped += 1
        else:
            for name, values in (ticks if topic == "/tick" else events).items():
                values.append(obj.get(name))
    problems = stream.problems + ([f"{skipped} /tick or /events messages are not JSON "
                                   "objects (left out)"] if skipped else [])
    return RecordingTables(
        path=stream.path, ticks=_table(stream.path, ticks, TICK_FIELDS),
        events=_table(stream.path, events, EVENT_FIELDS), metadata=once["/run"],
        end=once["/run/end"], complete=stream.complete, recovered=stream.recovered,
        problems=problems)
