"""The DentiBot auxiliary I/O register map (Modbus TCP) as one data table, and its codecs.

There is no vendor standard for the clinic's auxiliary I/O: this map is the project's own. The
table :data:`REGISTER_MAP` is the single source of truth. The driver
(:mod:`dentibot.io.aux_modbus`), the simulator (:mod:`dentibot.sim.aux_modbus_server`) and the
integrators' document (``docs/aux-io-register-map.md``, rendered by :func:`markdown_table`)
all derive from it; nothing else spells an address.

Conventions (see the document for wiring):

- Addresses are the 0-based protocol addresses carried in the request PDU (what pymodbus's
  ``address=`` takes). The 1-based "Modicon" reference is given for PLC tools that want it
  (coil 0 = 00001, discrete input 0 = 10001, input register 0 = 30001, holding register 0 =
  40001).
- ``int32``: two's complement over two registers, **high word first** (at the lower address),
  each word big-endian on the wire (byte order ABCD, Modbus's usual convention).
- Lengths are int32 counts of 0.01 mm (:data:`COUNTS_PER_MM`); x, y, z are the platform axes,
  parallel to the robot base axes.
- ``flags`` registers: bit 0 is the least significant bit; bits not listed are reserved, sent
  as 0 and ignored on reception (a later minor version may define them).

This module is pure: it encodes and decodes register images and checks values; it does no I/O.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from dentibot.errors import ConfigError, ProtocolError

#: Device name used in errors and logs.
DEVICE = "aux-modbus"
#: Value of input register 0 on a DentiBot-map device: ASCII "DB".
MAGIC = 0x4442
#: Map version (major, minor) served by this code. A client accepts any minor of its major
#: (minor versions only add registers or flag bits); a different major is refused.
MAP_VERSION = (1, 1)
#: Length counts per mm in the int32 position registers (0.01 mm resolution).
COUNTS_PER_MM = 100
#: Platform axes, in register order.
AXES = ("x", "y", "z")
# assumption: the lab's Stewart platform travels at least +-25 mm on each axis around its home
# (the thesis's experiment 1 draws a 15 mm square). Checked on both sides of the wire.
PLATFORM_LIMIT_MM = 25.0
#: Longest host watchdog time the device accepts (ms).
WATCHDOG_MAX_MS = 10_000


class Table(enum.StrEnum):
    """The four Modbus data tables."""

    COIL = "coil"
    DISCRETE_INPUT = "discrete input"
    INPUT_REGISTER = "input register"
    HOLDING_REGISTER = "holding register"


@dataclass(frozen=True, slots=True)
class TableInfo:
    access: str                      # "R" or "R/W" (from the client's side)
    read_fc: int                     # function code that reads the table
    write_fcs: tuple[int, ...]       # function codes that write it
    reference_base: int              # 1-based Modicon reference of address 0
    is_bits: bool


TABLES: dict[Table, TableInfo] = {
    Table.COIL: TableInfo("R/W", 1, (5, 15), 1, True),
    Table.DISCRETE_INPUT: TableInfo("R", 2, (), 10001, True),
    Table.INPUT_REGISTER: TableInfo("R", 4, (), 30001, False),
    Table.HOLDING_REGISTER: TableInfo("R/W", 3, (6, 16, 22, 23), 40001, False),
}

#: Function code -> table it addresses (the standard Modbus data model).
FUNCTION_TABLE: dict[int, Table] = {
    fc: table
    for table, info in TABLES.items()
    for fc in (info.read_fc, *info.write_fcs)
}

#: Modbus exception codes (Modbus Application Protocol v1.1b3, section 7) -> meaning.
EXCEPTION_CODES: dict[int, str] = {
    1: "illegal function",
    2: "illegal data address",
    3: "illegal data value",
    4: "server device failure",
    5: "acknowledge",
    6: "server device busy",
    8: "memory parity error",
    10: "gateway path unavailable",
    11: "gateway target device failed to respond",
}


class Kind(enum.StrEnum):
    """How a point is stored."""

    BIT = "bit"          # one coil or discrete input
    U16 = "uint16"       # one register, unsigned
    FLAGS = "flags"      # one register, named bits (bit 0 = LSB)
    I32 = "int32"        # two registers, two's complement, high word first


#: Registers per kind (bits occupy one bit address).
WORDS: dict[Kind, int] = {Kind.BIT: 1, Kind.U16: 1, Kind.FLAGS: 1, Kind.I32: 2}


@dataclass(frozen=True, slots=True)
class Point:
    """One entry of the register map.

    ``counts_per_unit``: the register holds ``round(value * counts_per_unit)`` (1 = raw).
    ``limits``: allowed engineering range for writable points (inclusive, in ``limit_unit``),
    checked by the client before sending and by the device on reception. ``flags``: (name, meaning) of bits
    0, 1, ... of a FLAGS register. ``const``: the fixed value of an identification register.
    """

    table: Table
    address: int
    name: str
    kind: Kind
    meaning: str
    unit: str = ""
    counts_per_unit: int = 1
    limits: tuple[float, float] | None = None
    flags: tuple[tuple[str, str], ...] = ()
    const: int | None = None
    limit_unit: str = "mm"

    @property
    def words(self) -> int:
        return WORDS[self.kind]

    @property
    def access(self) -> str:
        return TABLES[self.table].access

    @property
    def reference(self) -> int:
        """1-based Modicon reference (e.g. 30001 for input register 0)."""
        return TABLES[self.table].reference_base + self.address


_LIM = (-PLATFORM_LIMIT_MM, PLATFORM_LIMIT_MM)
_C, _DI, _IR, _HR = Table.COIL, Table.DISCRETE_INPUT, Table.INPUT_REGISTER, Table.HOLDING_REGISTER

#: The map. Within a table, points are contiguous from address 0 (checked at import).
REGISTER_MAP: tuple[Point, ...] = (
    # discrete inputs: what the PLC reads from the clinic
    Point(_DI, 0, "pedal", Kind.BIT, "foot pedal pressed (1 = pressed)"),
    Point(_DI, 1, "estop", Kind.BIT,
          "emergency stop active (1 = pressed or STO chain open); monitoring only"),
    Point(_DI, 2, "platform_moving", Kind.BIT, "motion platform moving (mirror of IR 4 bit 0)"),
    Point(_DI, 3, "platform_fault", Kind.BIT, "motion platform fault (mirror of IR 4 bit 1)"),
    # coils: indicator outputs written by DentiBot
    Point(_C, 0, "ready", Kind.BIT, "lamp READY (green): system ready, file may enter"),
    Point(_C, 1, "drilling", Kind.BIT, "lamp DRILLING (amber): file turning in the canal"),
    Point(_C, 2, "fault", Kind.BIT, "lamp FAULT (red): treatment stopped on a fault"),
    Point(_C, 3, "buzzer", Kind.BIT, "buzzer"),
    # input registers: one FC4 read of 0..10 is a consistent snapshot (what the driver polls)
    Point(_IR, 0, "magic", Kind.U16, "0x4442 (ASCII 'DB'): this device serves the DentiBot map",
          const=MAGIC),
    Point(_IR, 1, "map_version", Kind.U16, "map version, major in the high byte, minor in the low",
          const=(MAP_VERSION[0] << 8) | MAP_VERSION[1]),
    Point(_IR, 2, "heartbeat", Kind.U16,
          "counter incremented by the device's scan cycle (wraps at 65535); frozen = stale",
          unit="counts"),
    Point(_IR, 3, "inputs", Kind.FLAGS, "mirror of discrete inputs 0-1 (one FC4 poll reads all)",
          flags=(("pedal", "foot pedal pressed (= DI 0)"),
                 ("estop", "emergency stop active (= DI 1)"))),
    Point(_IR, 4, "platform_status", Kind.FLAGS, "motion platform status",
          flags=(("platform_moving", "platform moving (= DI 2)"),
                 ("platform_fault", "platform drive fault (= DI 3)"),
                 ("setpoint_rejected", ("last setpoint write refused (out of range); "
                                        "cleared by the next accepted setpoint")),
                 ("host_lost", ("the host watchdog expired (HR 6-7): platform held, DRILLING "
                                "off, FAULT on; cleared by the next new host_watchdog value "
                                "(v1.1)")))),
    Point(_IR, 5, "platform_x", Kind.I32, "platform actual position x", "0.01 mm",
          COUNTS_PER_MM),
    Point(_IR, 7, "platform_y", Kind.I32, "platform actual position y", "0.01 mm",
          COUNTS_PER_MM),
    Point(_IR, 9, "platform_z", Kind.I32, "platform actual position z", "0.01 mm",
          COUNTS_PER_MM),
    # holding registers: platform setpoint written by DentiBot (one FC16 write of 0..5)
    Point(_HR, 0, "setpoint_x", Kind.I32, "platform setpoint x", "0.01 mm", COUNTS_PER_MM, _LIM),
    Point(_HR, 2, "setpoint_y", Kind.I32, "platform setpoint y", "0.01 mm", COUNTS_PER_MM, _LIM),
    Point(_HR, 4, "setpoint_z", Kind.I32, "platform setpoint z", "0.01 mm", COUNTS_PER_MM, _LIM),
    # the host watchdog (v1.1): DentiBot arms it at connect and feeds it while it polls
    Point(_HR, 6, "host_watchdog", Kind.U16,
          "host alive: any new value feeds the watchdog (DentiBot writes a counter)",
          unit="counts"),
    Point(_HR, 7, "watchdog_ms", Kind.U16,
          "host watchdog time: no new host_watchdog value for this long -> host_lost; "
          "0 = off (the power-on value, so 1.0 hosts work)", "ms",
          limits=(0, WATCHDOG_MAX_MS), limit_unit="ms"),
)
#: Holding registers 0..5: the platform setpoint (written together in one FC16).
SETPOINT_WORDS = 6


def points(table: Table) -> tuple[Point, ...]:
    """The points of one table, by address."""
    return _POINTS[table]


def span(table: Table) -> tuple[int, int]:
    """(first address, number of bits or registers) of a table's block."""
    return _SPANS[table]


def point(table: Table, name: str) -> Point:
    try:
        return _BY_NAME[table][name]
    except KeyError:
        raise ConfigError(f"{table}.name", name, f"one of {sorted(_BY_NAME[table])}") from None


def check_map(entries: Sequence[Point]) -> None:
    """Raise ConfigError unless every table is contiguous from 0 with unique names."""
    for table in Table:
        pts = sorted((p for p in entries if p.table is table), key=lambda p: p.address)
        nxt = 0
        names: set[str] = set()
        for p in pts:
            if p.address != nxt:
                raise ConfigError(f"{table}[{p.name}].address", p.address,
                                  f"next free address {nxt} (contiguous, no overlap)")
            if TABLES[table].is_bits != (p.kind is Kind.BIT):
                raise ConfigError(f"{table}[{p.name}].kind", str(p.kind), "bits only in "
                                  "coils/discrete inputs, registers only in register tables")
            if len(p.flags) > 16 or (p.flags and p.kind is not Kind.FLAGS):
                raise ConfigError(f"{table}[{p.name}].flags", p.flags, "<= 16, FLAGS only")
            for n in (p.name, *(f for f, _ in p.flags)):
                if n in names:
                    raise ConfigError(f"{table}.name", n, "unique within its table")
                names.add(n)
            nxt += p.words


check_map(REGISTER_MAP)
_POINTS = {t: tuple(sorted((p for p in REGISTER_MAP if p.table is t), key=lambda p: p.address))
           for t in Table}
_SPANS = {t: (0, sum(p.words for p in _POINTS[t])) for t in Table}
_BY_NAME = {t: {p.name: p for p in _POINTS[t]} for t in Table}

#: Indicator names accepted by ``set_indicator`` -> coil address.
INDICATORS: dict[str, int] = {p.name: p.address for p in points(Table.COIL)}


# ---------------------------------------------------------------------------- word codecs
def int32_to_words(value: int) -> list[int]:
    """Two's complement int32 -> [high word, low word]."""
    if not -(1 << 31) <= value < (1 << 31):
        raise ConfigError("int32", value, f"{-(1 << 31)}..{(1 << 31) - 1}")
    u = value & 0xFFFFFFFF
    return [u >> 16, u & 0xFFFF]


def words_to_int32(hi: int, lo: int) -> int:
    """[high word, low word] -> signed int32."""
    u = (hi << 16) | lo
    return u - (1 << 32) if u & 0x80000000 else u


def version_text(word: int) -> str:
    return f"{word >> 8}.{word & 0xFF}"


def _to_counts(p: Point, value) -> int:
    v = float(value)
    if not math.isfinite(v):
        raise ConfigError(p.name, value, "a finite number")
    return round(v * p.counts_per_unit)


def encode_registers(table: Table, values: Mapping[str, object]) -> list[int]:
    """Register image of a whole register table from engineering values.

    Missing names encode as 0 (flags as cleared); identification registers always carry their
    constant. FLAGS points take their bits by flag name from ``values``.
    """
    out: list[int] = []
    for p in points(table):
        if p.const is not None:
            out.append(p.const)
        elif p.kind is Kind.FLAGS:
            out.append(sum(1 << i for i, (f, _) in enumerate(p.flags) if values.get(f)))
        elif p.kind is Kind.I32:
            out.extend(int32_to_words(_to_counts(p, values.get(p.name, 0.0))))
        else:
            w = int(values.get(p.name, 0)) & 0xFFFF
            out.append(w)
    return out


def decode_registers(table: Table, words: Sequence[int]) -> dict[str, object]:
    """Engineering values by name from a whole register table's image.

    FLAGS points yield one bool per flag name (reserved bits ignored); I32 points yield
    ``counts / counts_per_unit`` (float when scaled). Raises ProtocolError on a wrong length or
    a word outside 0..65535 (bytes that cannot have come from a Modbus register).
    """
    _, n = span(table)
    if len(words) != n:
        raise ProtocolError(DEVICE, f"{table} image has {len(words)} registers, expected {n}")
    for i, w in enumerate(words):
        if not isinstance(w, int) or not 0 <= w <= 0xFFFF:
            raise ProtocolError(DEVICE, f"{table} {i} = {w!r} is not a 16-bit register value")
    out: dict[str, object] = {}
    for p in points(table):
        a = p.address
        if p.kind is Kind.FLAGS:
            for i, (f, _) in enumerate(p.flags):
                out[f] = bool(words[a] >> i & 1)
        elif p.kind is Kind.I32:
            c = words_to_int32(words[a], words[a + 1])
            out[p.name] = c / p.counts_per_unit if p.counts_per_unit != 1 else c
        else:
            out[p.name] = words[a]
    return out


def encode_bits(table: Table, values: Mapping[str, object]) -> list[bool]:
    """Bit image of a whole coil / discrete-input table (missing names = off)."""
    return [bool(values.get(p.name, False)) for p in points(table)]


def decode_bits(table: Table, bits: Sequence[bool]) -> dict[str, bool]:
    """Values by name from a bit image (extra trailing bits, e.g. byte padding, ignored)."""
    _, n = span(table)
    if len(bits) < n:
        raise ProtocolError(DEVICE, f"{table} image has {len(bits)} bits, expected {n}")
    return {p.name: bool(bits[p.address]) for p in points(table)}


# ---------------------------------------------------------------------------- typed views
@dataclass(frozen=True, slots=True)
class AuxInputs:
    """The input-register snapshot (IR 0..10) in engineering units."""

    magic: int
    map_version: int
    heartbeat: int
    pedal: bool
    estop: bool
    platform_moving: bool
    platform_fault: bool
    setpoint_rejected: bool
    platform_mm: tuple[float, float, float]
    host_lost: bool = False

    @property
    def identity_ok(self) -> bool:
        return self.magic == MAGIC and self.map_version >> 8 == MAP_VERSION[0]


def decode_inputs(words: Sequence[int]) -> AuxInputs:
    """IR 0..10 -> :class:`AuxInputs` (ProtocolError on a malformed image)."""
    v = decode_registers(Table.INPUT_REGISTER, words)
    return AuxInputs(
        magic=v["magic"], map_version=v["map_version"], heartbeat=v["heartbeat"],
        pedal=v["pedal"], estop=v["estop"], platform_moving=v["platform_moving"],
        platform_fault=v["platform_fault"], setpoint_rejected=v["setpoint_rejected"],
        platform_mm=tuple(v[f"platform_{a}"] for a in AXES), host_lost=v["host_lost"],
    )


def encode_inputs(*, heartbeat: int, pedal: bool, estop: bool, platform_mm,
                  platform_moving: bool = False, platform_fault: bool = False,
                  setpoint_rejected: bool = False, host_lost: bool = False) -> list[int]:
    """IR 0..10 image (the device side); the heartbeat is taken modulo 65536."""
    values: dict[str, object] = {
        "heartbeat": heartbeat & 0xFFFF, "pedal": pedal, "estop": estop,
        "platform_moving": platform_moving, "platform_fault": platform_fault,
        "setpoint_rejected": setpoint_rejected, "host_lost": host_lost,
    }
    values.update({f"platform_{a}": float(x) for a, x in zip(AXES, platform_mm, strict=True)})
    return encode_registers(Table.INPUT_REGISTER, values)


def check_setpoint(mm) -> tuple[float, float, float]:
    """Validate a platform setpoint (x, y, z mm); ConfigError names axis, value and limit."""
    try:
        vals = [float(x) for x in mm]
    except (TypeError, ValueError):
        raise ConfigError("platform_setpoint", mm, "three numbers (x, y, z) in mm") from None
    if len(vals) != len(AXES):
        raise ConfigError("platform_setpoint", mm, "three numbers (x, y, z) in mm")
    for a, v in zip(AXES, vals, strict=True):
        lo, hi = point(Table.HOLDING_REGISTER, f"setpoint_{a}").limits
        if not (math.isfinite(v) and lo <= v <= hi):
            raise ConfigError(f"platform_setpoint.{a}", v, f"{lo:g}..{hi:g} mm")
    return tuple(vals)


def encode_setpoint(mm) -> list[int]:
    """HR 0..5 image of a checked platform setpoint (0.01 mm counts, high word first)."""
    x = check_setpoint(mm)
    return encode_registers(Table.HOLDING_REGISTER,
                            {f"setpoint_{a}": v for a, v in zip(AXES, x, strict=True)}
                            )[:SETPOINT_WORDS]


def check_watchdog_ms(ms) -> int:
    """Validate a host watchdog time (ms, 0 = off); ConfigError names value and limit."""
    lo, hi = point(Table.HOLDING_REGISTER, "watchdog_ms").limits
    if isinstance(ms, bool) or not isinstance(ms, int) or not lo <= ms <= hi:
        raise ConfigError("watchdog_ms", ms, f"an integer {lo:g}..{hi:g} ms (0 = off)")
    return ms


def decode_setpoint(words: Sequence[int]) -> tuple[float, float, float]:
    """HR 0..5 (or the whole holding-register image) -> (x, y, z) mm, range-checked
    (ConfigError when outside the limits)."""
    words = list(words)
    if len(words) == SETPOINT_WORDS:
        words += [0] * (span(Table.HOLDING_REGISTER)[1] - SETPOINT_WORDS)
    v = decode_registers(Table.HOLDING_REGISTER, words)
    return check_setpoint([v[f"setpoint_{a}"] for a in AXES])


# ---------------------------------------------------------------------------- document
DOC_COLUMNS = ("table", "address", "ref", "name", "type", "access", "units", "meaning")


def doc_rows() -> list[tuple[str, ...]]:
    """One row per point (and per flag bit), as in the integrators' document."""
    rows = []
    for table in (Table.DISCRETE_INPUT, Table.COIL, Table.INPUT_REGISTER,
                  Table.HOLDING_REGISTER):
        for p in points(table):
            addr, ref = str(p.address), f"{p.reference:05d}"
            if p.words == 2:
                addr, ref = f"{addr}-{p.address + 1}", f"{ref}-{p.reference + 1:05d}"
            unit = p.unit
            if p.limits:
                unit += f" ({p.limits[0]:g}..{p.limits[1]:g} {p.limit_unit})"
            if p.const is not None:
                unit = f"= 0x{p.const:04X}"
            rows.append((str(table), addr, ref, p.name, str(p.kind), p.access, unit,
                         p.meaning))
            for i, (f, meaning) in enumerate(p.flags):
                rows.append((str(table), f"{p.address}.{i}", "", f, "bit", p.access, "",
                             meaning))
    return rows


def markdown_table() -> str:
    """The map as a Markdown table (the document embeds exactly this)."""
    lines = ["| " + " | ".join(DOC_COLUMNS) + " |",
             "|" + "|".join(" --- " for _ in DOC_COLUMNS) + "|"]
    lines += ["| " + " | ".join(r) + " |" for r in doc_rows()]
    return "\n".join(lines)
