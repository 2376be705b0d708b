"""ROS 2 messages in CDR: the recording's per-tick channel in a binary encoding Foxglove reads.

A ``/tick`` message in JSON is about 1.2 kB of text whose numbers must be printed, parsed and
compressed; in CDR (the ROS 2 wire format, ``cdr`` message encoding with a ``ros2msg``
schema, which Foxglove, Lichtblick and the ROS 2 tools decode) it is 0.4 kB of little-endian
numbers, and a block of the simulator's compiled ticks is written by copying its columns into
a template (:class:`BlockEncoder`).

The message definition is derived from a field table (:class:`~dentibot.telemetry.schema.Field`),
never written by hand (:func:`definition`):

=================================  ======================================================
field                              ROS 2 type
=================================  ======================================================
number / integer / boolean         ``float64`` / ``int64`` / ``bool``
string                             ``string`` (UTF-8)
array of ``length`` items          ``float64[6]`` (fixed); nullable: ``float64[]``, empty
                                   when unknown; ``length`` 0: a sequence (``string[]``)
nullable number                    ``float64``, NaN when unknown
=================================  ======================================================

Reading back (:func:`decode`) gives the row's dict: NaN and empty nullable sequences become
None, as the JSON encoding's left-out fields do, so a row read back equals the row recorded
either way.

CDR here: a 4-byte encapsulation header (``00 01 00 00``: plain CDR, little-endian), then the
fields in order, each primitive aligned to its own size counted from the end of the header;
a string is its byte length + 1 (uint32), its bytes and a NUL; a sequence its item count
(uint32), then the items. ``mcap_ros2`` (Foxglove's Python package) reads and writes the
same bytes: the tests hold the two to each other.
"""

from __future__ import annotations

import math
import struct
from typing import Any

import numpy as np

from dentibot.telemetry.schema import TICK_FIELDS, Field

__all__ = ["CDR_LE", "MESSAGE_ENCODING", "SCHEMA_ENCODING", "TICK_CODEC", "TICK_SCHEMA_NAME",
           "BlockEncoder", "CdrError", "Codec", "WordBlock", "definition"]

#: the MCAP encodings of a channel in CDR: its schema's and its messages'
SCHEMA_ENCODING = "ros2msg"
MESSAGE_ENCODING = "cdr"
#: the /tick messages' type (a ROS 2 package name of its own: the viewers show it)
TICK_SCHEMA_NAME = "dentibot_msgs/msg/Tick"
#: the encapsulation header of plain little-endian CDR
CDR_LE = b"\x00\x01\x00\x00"
_ROS_TYPES = {"number": "float64", "integer": "int64", "boolean": "bool", "string": "string"}
#: struct code and size of each primitive
_CODES = {"float64": ("d", 8), "int64": ("q", 8), "bool": ("?", 1)}
_NAN = float("nan")
_U32 = struct.Struct("<I")


class CdrError(ValueError):
    """A row that does not fit its message definition (names the field and the value)."""


def _ros_type(f: Field) -> tuple[str, str]:
    """(item type, array suffix) of a field: suffix "" (scalar), "[k]" or "[]"."""
    if f.length == -1:
        raise CdrError(f"{f.name}: an object field has no ROS 2 type")
    item = _ROS_TYPES[f.json_type]
    if f.length is None:
        if f.nullable and f.json_type != "number":
            raise CdrError(f"{f.name}: a nullable {f.json_type} has no unknown value in CDR")
        return item, ""
    if f.length == 0 or f.nullable:
        return item, "[]"
    return item, f"[{f.length}]"


def definition(fields: tuple[Field, ...]) -> str:
    """The ``ros2msg`` text of a message with ``fields``: one line per field, its unit and
    description as a comment."""
    lines = []
    for f in fields:
        item, suffix = _ros_type(f)
        note = f"{f.unit}: {f.description}" if f.unit else f.description
        if f.nullable:
            note += " (NaN when unknown)" if suffix == "" else \
                f" ({f.length} items, none when unknown)"
        lines.append(f"{item}{suffix} {f.name}  # {note}")
    return "\n".join(lines) + "\n"


class _Plan:
    """A message's layout as it is written: struct format pieces, the values in order, and
    the offset (in the message, header included) of each numeric field's first number."""

    __slots__ = ("fmt", "offsets", "pos", "values")

    def __init__(self) -> None:
        self.fmt: list[str] = ["<4s"]
        self.values: list[Any] = [CDR_LE]
        self.pos = 0                          # offset after the header
        self.offsets: dict[str, int] = {}

    def align(self, size: int) -> None:
        pad = -self.pos % size
        if pad:
            self.fmt.append(f"{pad}x")
            self.pos += pad

    def prim(self, ros: str, values: list, name: str | None = None) -> None:
        code, size = _CODES[ros]
        if not values:
            return
        self.align(size)
        if name is not None:
            self.offsets[name] = self.pos + 4
        self.fmt.append(f"{len(values)}{code}")
        self.values.extend(values)
        self.pos += size * len(values)

    def count(self, n: int) -> None:
        self.align(4)
        self.fmt.append("I")
        self.values.append(n)
        self.pos += 4

    def string(self, data: bytes) -> None:
        """A string, its UTF-8 bytes ``data``."""
        self.count(len(data) + 1)
        self.fmt.append(f"{len(data) + 1}s")           # struct pads the NUL
        self.values.append(data)
        self.pos += len(data) + 1

    def pack(self) -> bytes:
        """The message."""
        return struct.pack("".join(self.fmt), *self.values)


def _text(f: Field, v: Any) -> bytes:
    """The UTF-8 bytes of the string field ``f``'s value ``v``."""
    if not isinstance(v, str):
        raise CdrError(f"{f.name}: {v!r} is not a string")
    try:
        return v.encode()
    except UnicodeEncodeError as exc:
        raise CdrError(f"{f.name}: {v!r} is not UTF-8 text ({exc.reason})") from None


def _number(f: Field, v: Any) -> float:
    if v is None:
        return _NAN
    if isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer)):
        raise CdrError(f"{f.name}: {v!r} is not a number")
    return float(v)


def _plan(fields: tuple[Field, ...], row: dict[str, Any]) -> _Plan:
    plan = _Plan()
    for f in fields:
        item, suffix = _ros_type(f)
        v = row.get(f.name)
        if suffix == "":
            if item == "string":
                plan.string(_text(f, v))
            elif item == "float64":
                plan.prim(item, [_number(f, v)], f.name)
            elif item == "int64":
                if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
                    raise CdrError(f"{f.name}: {v!r} is not an integer")
                plan.prim(item, [int(v)], f.name)
            else:
                if not isinstance(v, (bool, np.bool_)):
                    raise CdrError(f"{f.name}: {v!r} is not a boolean")
                plan.prim(item, [bool(v)])
            continue
        items = [] if v is None and f.nullable else v
        if not isinstance(items, (list, tuple, np.ndarray)):
            raise CdrError(f"{f.name}: {v!r} is not a list")
        n = len(items)
        if f.length and n not in ((0, f.length) if f.nullable else (f.length,)):
            raise CdrError(f"{f.name}: {n} items, expected {f.length}")
        if suffix == "[]":
            plan.count(n)
        if item == "string":
            for s in items:
                plan.string(_text(f, s))
        elif item == "float64":
            plan.prim(item, [_number(f, x) for x in items], f.name)
        else:
            raise CdrError(f"{f.name}: arrays of {item} are not written")
    return plan


def _kind(f: Field) -> str:
    """How a field is written: f (float64), q (int64), ? (bool), s (string), F (fixed
    float64 array), N (nullable float64 sequence), S (string sequence)."""
    item, suffix = _ros_type(f)
    if suffix == "":
        return {"float64": "f", "int64": "q", "bool": "?", "string": "s"}[item]
    if item == "string":
        return "S"
    if item != "float64":
        raise CdrError(f"{f.name}: arrays of {item} are not written")
    return "F" if suffix != "[]" else "N"


class Codec:
    """The CDR messages of one field table: :meth:`encode` a row, :meth:`decode` a message.

    Both work from a layout computed once per shape (the byte lengths of the strings and the
    item counts of the sequences) and cached: a row is packed, and a message unpacked, by
    one struct call. A message's shape is recognised by its size and the counts it holds."""

    def __init__(self, fields: tuple[Field, ...]) -> None:
        self.fields = fields
        self._ops = [(f.name, _kind(f), f.length) for f in fields]
        self._packers: dict[tuple, struct.Struct] = {}
        #: message size -> the layouts of that size met so far, with the counts they hold
        self._known: dict[int, list[tuple[list, struct.Struct, list]]] = {}

    def encode(self, row: dict[str, Any]) -> bytes:
        """The message of ``row`` (None where unknown). Raises :class:`CdrError` naming the
        field a value does not fit."""
        vals: list[Any] = [CDR_LE]
        shape: list[int] = []
        try:
            for name, kind, _ in self._ops:
                v = row.get(name)
                if kind == "f":
                    vals.append(_NAN if v is None else v)
                elif kind == "F":
                    vals.extend(v)
                elif kind == "s":
                    b = v.encode()
                    shape.append(len(b))
                    vals += (len(b) + 1, b)
                elif kind == "N":
                    n = 0 if v is None else len(v)
                    shape.append(n)
                    vals.append(n)
                    if n:
                        vals.extend(v)
                elif kind == "S":
                    shape.append(len(v))
                    vals.append(len(v))
                    for text in v:
                        b = text.encode()
                        shape.append(len(b))
                        vals += (len(b) + 1, b)
                else:
                    vals.append(v)
            st = self._packers.get(tuple(shape))
            if st is None:
                st = self._packer(row, tuple(shape))
            return st.pack(*vals)
        except (TypeError, AttributeError, ValueError, struct.error):
            return _plan(self.fields, row).pack()    # names the field, or writes it anyway

    def _packer(self, row: dict[str, Any], key: tuple) -> struct.Struct:
        st = struct.Struct("".join(_plan(self.fields, row).fmt))
        if len(self._packers) > 256:
            self._packers.clear()
        self._packers[key] = st
        return st

    def decode(self, data: bytes) -> dict[str, Any]:
        """The row of a message: NaN and empty nullable sequences as None. Raises
        :class:`CdrError` if the message is not one of this table's."""
        if data[:4] != CDR_LE:
            raise CdrError(f"not little-endian plain CDR (header {bytes(data[:4])!r})")
        try:
            for checks, st, spans in self._known.get(len(data), ()):
                if all(_U32.unpack_from(data, at)[0] == n for at, n in checks):
                    break
            else:
                st, spans = self._layout(data)
            flat = st.unpack_from(data)
        except struct.error as exc:
            raise CdrError(f"a message of {len(data)} bytes does not fit: {exc}") from None
        out: dict[str, Any] = {}
        i = 0
        for name, kind, n in spans:
            if kind == "f":
                x = flat[i]
                out[name] = None if math.isnan(x) else x
                i += 1
            elif kind == "q" or kind == "?":
                out[name] = flat[i]
                i += 1
            elif kind == "s":
                out[name] = flat[i].decode()
                i += 1
            elif kind == "S":
                out[name] = [b.decode() for b in flat[i:i + n]]
                i += n
            elif n == 0 and kind == "N":
                out[name] = None
            else:                                      # F, N
                out[name] = [None if math.isnan(x) else x for x in flat[i:i + n]]
                i += n
        return out

    def _layout(self, data: bytes) -> tuple[struct.Struct, list]:
        """The struct that unpacks ``data`` (strings without their length and NUL) and what
        each field takes of its values: (name, kind, count)."""
        fmt, spans, checks = ["<4x"], [], []
        pos = 0                                       # after the header
        unpack = struct.unpack_from

        def align(size: int) -> None:
            nonlocal pos
            pad = -pos % size
            if pad:
                fmt.append(f"{pad}x")
                pos += pad

        def count() -> int:
            nonlocal pos
            align(4)
            (n,) = unpack("<I", data, pos + 4)
            checks.append((pos + 4, n))
            fmt.append("4x")
            pos += 4
            return n

        def string() -> None:
            nonlocal pos
            n = count()
            fmt.append(f"{max(n - 1, 0)}s{min(n, 1)}x")
            pos += n

        for name, kind, length in self._ops:
            if kind == "f" or kind == "q":
                align(8)
                fmt.append("d" if kind == "f" else "q")
                pos += 8
                spans.append((name, kind, 1))
            elif kind == "?":
                fmt.append("?")
                pos += 1
                spans.append((name, kind, 1))
            elif kind == "s":
                string()
                spans.append((name, kind, 1))
            elif kind == "S":
                n = count()
                for _ in range(n):
                    string()
                spans.append((name, kind, n))
            else:                                     # F, N
                n = count() if kind == "N" else length
                if n:
                    align(8)
                    fmt.append(f"{n}d")
                    pos += 8 * n
                spans.append((name, kind, n))
        st = struct.Struct("".join(fmt))
        known = self._known.setdefault(st.size, [])
        if len(known) < 8:                            # the shapes met: found by their counts
            known.append((checks, st, spans))
        return st, spans


class WordBlock:
    """``n`` copies of one message, to be written with no Python per number: every 8-byte
    number of a CDR message lies 4 bytes (the header) past a multiple of 8, so a message
    placed 4 bytes into a row of float64 words puts each of its numbers in one word
    (:meth:`word`): the block is a float64 array ``n`` x :attr:`words`, and writing a field
    of all its rows is one numpy assignment (``buf.view(np.int64)`` for an int64 field,
    ``buf.view("<u4")`` with ``(offset + 4) // 4`` for a 4-byte one)."""

    def __init__(self, template: bytes) -> None:
        self.size = len(template)
        #: float64 words a message takes, with the 4 bytes before it and padding after
        self.words = (self.size + 4 + 7) // 8
        base = np.zeros(self.words * 8, dtype=np.uint8)
        base[4:4 + self.size] = np.frombuffer(template, dtype=np.uint8)
        self._base = base.view("<f8")

    @staticmethod
    def word(offset: int) -> int:
        """The word holding the 8-byte number at ``offset`` in the message."""
        return (offset + 4) // 8

    def buffer(self, n: int) -> np.ndarray:
        """``n`` copies of the template (n x :attr:`words` float64)."""
        buf = np.empty((n, self.words), dtype="<f8")
        buf[:] = self._base
        return buf

    def messages(self, buf: np.ndarray) -> list[bytes]:
        """The messages of ``buf``, one per row."""
        data, stride, size = buf.tobytes(), self.words * 8, self.size
        return [data[i + 4:i + 4 + size] for i in range(0, len(data), stride)]


class BlockEncoder(WordBlock):
    """The messages of many rows of a field table that share their shape (the same strings
    and sequence lengths), from one template, the message of one of them (a
    :class:`WordBlock`): a field of every row is written through :meth:`slot`."""

    def __init__(self, fields: tuple[Field, ...], row: dict[str, Any]) -> None:
        plan = _plan(fields, row)
        super().__init__(plan.pack())
        #: each numeric field's offset in the message (its first number)
        self.offsets = plan.offsets

    def slot(self, name: str, item: int = 0) -> int:
        """The word holding item ``item`` of the numeric field ``name``."""
        return self.word(self.offsets[name]) + item


#: the ``/tick`` messages' codec
TICK_CODEC = Codec(TICK_FIELDS)
