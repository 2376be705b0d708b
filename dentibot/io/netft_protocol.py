"""ATI Net F/T wire protocol: RDT over UDP and the ``/netftapi2.xml`` calibration page.

Pure encoding and decoding, no sockets: both the driver (:mod:`dentibot.io.netft`) and the wire
simulator (:mod:`dentibot.sim.netft_server`) import this module, so the bytes are defined once.

RDT (Raw Data Transfer), UDP port 49152, every field big-endian:

- request, 8 bytes ``>HHI``: header 0x1234, command (:class:`Command`), sample_count
  (0 = until stopped);
- record, 36 bytes ``>III6i``: rdt_sequence (1 for the first record of each request, +1 per
  record), ft_sequence (the box's internal sample counter, keeps counting across requests),
  status (0 = healthy, see :data:`STATUS_BITS`), Fx Fy Fz Tx Ty Tz in counts. A datagram holds
  one record (real-time mode) or several back to back (buffered mode, ``comrdtbsiz`` of them).
- force = counts / counts_per_force, torque = counts / counts_per_torque, in the units the
  calibration page names (``scfgfu``, ``scfgtu``); this module converts to N and N*m.

Sources: the ATI Net F/T manual (9620-05-Net FT, section "Calculating F/T values for RDT": divide
by the Counts per Force / Counts per Torque of ``netftapi2.xml``, elements ``cfgcpf``,
``cfgcpt``); field names ``scfgfu``, ``scfgtu``, ``comrdtrate``, ``comrdtbsiz`` (records per
buffered datagram, 1..40) and a live box's document (root ``<netft>``, units ``N`` and ``Nm``) as
quoted by public clients. Marked *unconfirmed* below where only third-party clients were seen.
"""

from __future__ import annotations

import math
import struct
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from enum import IntEnum

from dentibot.errors import ConfigError, ProtocolError
from dentibot.io.interfaces import WRENCH_SATURATED, Vec3

#: Device name used in every error and log line.
DEVICE = "netft"
#: RDT UDP port of the box (ATI manual).
RDT_PORT = 49152
#: Calibration document path on the box's web server.
CALIBRATION_PATH = "/netftapi2.xml"
#: First field of every RDT request.
RDT_HEADER = 0x1234

REQUEST = struct.Struct(">HHI")
RECORD = struct.Struct(">III6i")
REQUEST_SIZE = REQUEST.size          # 8
RECORD_SIZE = RECORD.size            # 36
#: Largest buffered-mode datagram the box sends (comrdtbsiz 1..40).
MAX_RECORDS_PER_DATAGRAM = 40

_U32 = 1 << 32
_I32_MIN, _I32_MAX = -(1 << 31), (1 << 31) - 1


class Command(IntEnum):
    """RDT request commands (ATI manual, RDT request table)."""

    STOP = 0x0000
    START_REALTIME = 0x0002
    START_BUFFERED = 0x0003
    SET_BIAS = 0x0042


#: Command code -> what it does (for messages and logs).
COMMANDS: dict[int, str] = {
    Command.STOP: "stop streaming",
    Command.START_REALTIME: "start real-time streaming",
    Command.START_BUFFERED: "start buffered streaming",
    Command.SET_BIAS: "set software bias",
}

#: RDT/system status bits -> meaning. Taken from a public client that decodes ATI's "system
#: status code" table (netft-cpp); *unconfirmed* against the ATI manual itself. Bit 31 is the
#: summary bit set together with any error bit.
STATUS_BITS: dict[int, str] = {
    0x80000000: "error summary",
    0x40000000: "CPU or RAM error",
    0x20000000: "digital board error",
    0x10000000: "analog board error",
    0x08000000: "serial link communication error",
    0x04000000: "program memory verification error",
    0x02000000: "halted due to configuration errors",
    0x01000000: "settings validation error",
    0x00800000: "configuration incompatible with calibration",
    0x00400000: "network communication failure",
    0x00200000: "CAN communication error",
    0x00100000: "RDT communication error",
    0x00080000: "EtherNet/IP protocol failure",
    0x00040000: "DeviceNet protocol failure",
    0x00020000: "transducer saturation or A/D error",
    0x00010000: "monitor condition latched",
    0x00004000: "watchdog timeout error",
    0x00002000: "stack check error",
    0x00001000: "serial EEPROM I2C failure",
    0x00000800: "serial flash SPI failure",
    0x00000400: "analog board watchdog timeout",
    0x00000200: "excessive strain gage excitation current",
    0x00000100: "insufficient strain gage excitation current",
    0x00000080: "artificial analog ground out of range",
    0x00000040: "analog board power supply too high",
    0x00000020: "analog board power supply too low",
    0x00000010: "serial link data unavailable",
    0x00000008: "reference voltage or power monitoring error",
    0x00000004: "internal temperature error",
    0x00000002: "HTTP protocol failure",
}
STATUS_ERROR = 0x80000000
STATUS_SATURATION = 0x00020000

#: ``Wrench.status`` bit -> RDT status bits the simulated box reports for it (saturation sets the
#: saturation bit and the summary bit, as a real box would).
WRENCH_TO_RDT_STATUS: dict[int, int] = {
    WRENCH_SATURATED: STATUS_ERROR | STATUS_SATURATION,
}
#: RDT status bit -> ``Wrench.status`` bit (the inverse, for the driver).
RDT_TO_WRENCH_STATUS: dict[int, int] = {
    STATUS_SATURATION: WRENCH_SATURATED,
}

#: Force unit label (``scfgfu``, normalised: lower case without ``-``, ``*``, ``.`` or blanks)
#: -> N per unit. ``N`` is seen on live boxes; the other labels are *unconfirmed* spellings.
FORCE_UNITS: dict[str, float] = {
    "n": 1.0,
    "kn": 1000.0,
    "lbf": 4.4482216152605,
    "klbf": 4448.2216152605,
    "kgf": 9.80665,
    "kg": 9.80665,
}
#: Torque unit label (``scfgtu``, normalised) -> N*m per unit. ``Nm`` is seen on live boxes;
#: the others are *unconfirmed* spellings.
TORQUE_UNITS: dict[str, float] = {
    "nm": 1.0,
    "nmm": 1e-3,
    "knm": 1000.0,
    "lbfin": 0.1129848290276167,
    "lbfft": 1.3558179483314004,
    "kgfcm": 0.0980665,
    "kgcm": 0.0980665,
}


# --------------------------------------------------------------------------- requests
@dataclass(frozen=True, slots=True)
class RdtRequest:
    command: int
    sample_count: int = 0


def encode_request(command: int, sample_count: int = 0) -> bytes:
    """The 8-byte RDT request for ``command`` (a :class:`Command`), ``sample_count`` records
    (0 = until stopped)."""
    if command not in COMMANDS:
        raise ConfigError("netft.command", command, f"one of {_hex_list(COMMANDS)}")
    if not 0 <= sample_count < _U32:
        raise ConfigError("netft.sample_count", sample_count, "0..4294967295 (0 = unlimited)")
    return REQUEST.pack(RDT_HEADER, int(command), int(sample_count))


def decode_request(data: bytes) -> RdtRequest:
    """Parse one RDT request datagram; ProtocolError if it is not one."""
    if len(data) != REQUEST_SIZE:
        raise ProtocolError(DEVICE, f"RDT request is {len(data)} bytes, expected {REQUEST_SIZE}")
    header, command, count = REQUEST.unpack(data)
    if header != RDT_HEADER:
        raise ProtocolError(DEVICE, f"RDT request header 0x{header:04X}, expected 0x{RDT_HEADER:04X}")
    if command not in COMMANDS:
        raise ProtocolError(DEVICE, f"unknown RDT command 0x{command:04X}; known: "
                                    f"{_hex_list(COMMANDS)}")
    return RdtRequest(command, count)


# --------------------------------------------------------------------------- records
@dataclass(frozen=True, slots=True)
class RdtRecord:
    """One RDT record; ``counts`` = (Fx, Fy, Fz, Tx, Ty, Tz) in counts."""

    rdt_sequence: int
    ft_sequence: int
    status: int
    counts: tuple[int, int, int, int, int, int]


def encode_record(record: RdtRecord) -> bytes:
    """36 bytes for one record; ConfigError for a field out of its wire range."""
    for name, v in (("rdt_sequence", record.rdt_sequence), ("ft_sequence", record.ft_sequence),
                    ("status", record.status)):
        if not 0 <= v < _U32:
            raise ConfigError(f"netft.record.{name}", v, "0..4294967295 (u32)")
    if len(record.counts) != 6:
        raise ConfigError("netft.record.counts", record.counts, "6 channels Fx..Tz")
    for c in record.counts:
        if not _I32_MIN <= c <= _I32_MAX:
            raise ConfigError("netft.record.counts", c, f"{_I32_MIN}..{_I32_MAX} (i32)")
    return RECORD.pack(record.rdt_sequence, record.ft_sequence, record.status, *record.counts)


def encode_records(records) -> bytes:
    """A buffered-mode datagram: the records back to back."""
    return b"".join(encode_record(r) for r in records)


def decode_datagram(data: bytes) -> list[RdtRecord]:
    """All records of one RDT datagram (one in real-time mode, N in buffered mode).

    ProtocolError if the datagram is empty or its length is not a multiple of 36 bytes (a
    truncated or foreign datagram: no record of it is trusted).
    """
    n = len(data)
    if n == 0 or n % RECORD_SIZE:
        raise ProtocolError(DEVICE, f"RDT datagram of {n} bytes is not a whole number of "
                                    f"{RECORD_SIZE}-byte records")
    if n > MAX_RECORDS_PER_DATAGRAM * RECORD_SIZE:
        raise ProtocolError(DEVICE, f"RDT datagram of {n} bytes holds more than "
                                    f"{MAX_RECORDS_PER_DATAGRAM} records (comrdtbsiz limit)")
    out = []
    for off in range(0, n, RECORD_SIZE):
        rs, fs, st, *c = RECORD.unpack_from(data, off)
        out.append(RdtRecord(rs, fs, st, tuple(c)))
    return out


# --------------------------------------------------------------------------- units
def counts_to_si(counts, counts_per_force: float, counts_per_torque: float) -> tuple[Vec3, Vec3]:
    """(force N, torque N*m) from six channel counts; counts per N and per N*m."""
    f, t = counts_per_force, counts_per_torque
    return ((counts[0] / f, counts[1] / f, counts[2] / f),
            (counts[3] / t, counts[4] / t, counts[5] / t))


def si_to_counts(force_n, torque_nm, counts_per_force: float,
                 counts_per_torque: float) -> tuple[int, int, int, int, int, int]:
    """Six channel counts (rounded, clamped to i32) from force (N) and torque (N*m)."""
    out = []
    for v, k in ((force_n[0], counts_per_force), (force_n[1], counts_per_force),
                 (force_n[2], counts_per_force), (torque_nm[0], counts_per_torque),
                 (torque_nm[1], counts_per_torque), (torque_nm[2], counts_per_torque)):
        c = round(v * k)
        out.append(min(max(c, _I32_MIN), _I32_MAX))
    return tuple(out)  # type: ignore[return-value]


# --------------------------------------------------------------------------- status
def describe_status(status: int) -> str:
    """Human-readable names of the set status bits, e.g. ``0x80020000 (error summary,
    transducer saturation or A/D error)``; unknown bits are listed as ``bit N``."""
    if status == 0:
        return "0x00000000 (healthy)"
    names = [STATUS_BITS.get(1 << b, f"bit {b}") for b in range(31, -1, -1) if status >> b & 1]
    return f"0x{status:08X} ({', '.join(names)})"


def rdt_status_from_wrench(wrench_status: int) -> int:
    """RDT status word for a ``Wrench.status`` bit field (via :data:`WRENCH_TO_RDT_STATUS`)."""
    out = 0
    for bit, word in WRENCH_TO_RDT_STATUS.items():
        if wrench_status & bit:
            out |= word
    return out


def wrench_status_from_rdt(status: int) -> int:
    """``Wrench.status`` bits for an RDT status word (via :data:`RDT_TO_WRENCH_STATUS`)."""
    out = 0
    for bit, wbit in RDT_TO_WRENCH_STATUS.items():
        if status & bit:
            out |= wbit
    return out


# --------------------------------------------------------------------------- sequences
class SequenceTracker:
    """Classifies rdt_sequence numbers of one stream: new (with the gap before it), duplicate
    or older (out of order). Arithmetic is modulo 2**32, so wrap-around is a normal step.

    A record whose rdt_sequence is not newer but whose ft_sequence is ahead of the last accepted
    one starts a new stream (the box restarts rdt_sequence at 1 on every request, while
    ft_sequence keeps counting): counted in ``restarts``, the records before it as lost.
    """

    def __init__(self) -> None:
        self.reset()
        self.restarts = 0

    def reset(self) -> None:
        self.last: int | None = None
        self.last_ft: int | None = None

    def accept(self, rdt_sequence: int, ft_sequence: int) -> int:
        """-1 for a duplicate or older record (ignore it), else the number of records lost
        between the previous accepted record and this one (0 for the next in line)."""
        last = self.last
        if last is None:
            lost = rdt_sequence - 1 if rdt_sequence >= 1 else 0
        else:
            d = (rdt_sequence - last) % _U32
            if d == 0 or d >= 1 << 31:
                # not newer; within one stream ft_sequence grows with rdt_sequence, so a newer
                # ft_sequence means the box started a new stream (rdt_sequence from 1 again)
                if self.last_ft is not None and 0 < (ft_sequence - self.last_ft) % _U32 < 1 << 31:
                    self.restarts += 1
                    lost = max(rdt_sequence - 1, 0)
                else:
                    return -1
            else:
                lost = d - 1
        self.last, self.last_ft = rdt_sequence, ft_sequence
        return lost


# --------------------------------------------------------------------------- calibration
@dataclass(frozen=True, slots=True)
class NetFTCalibration:
    """Scaling of the active configuration, as the box's ``/netftapi2.xml`` gives it.

    ``counts_per_force`` / ``counts_per_torque`` are per *native* unit (``force_unit``,
    ``torque_unit``); :attr:`counts_per_newton` / :attr:`counts_per_newton_metre` per SI unit.
    ``rdt_rate_hz`` is ``comrdtrate`` (None if absent), ``buffer_size`` is ``comrdtbsiz``.
    """

    counts_per_force: float
    counts_per_torque: float
    force_unit: str = "N"
    torque_unit: str = "Nm"
    rdt_rate_hz: float | None = None
    buffer_size: int | None = None

    @property
    def counts_per_newton(self) -> float:
        return self.counts_per_force / FORCE_UNITS[_norm_unit(self.force_unit)]

    @property
    def counts_per_newton_metre(self) -> float:
        return self.counts_per_torque / TORQUE_UNITS[_norm_unit(self.torque_unit)]


def _norm_unit(label: str) -> str:
    return "".join(ch for ch in label.lower() if ch not in " -*.\u00b7\u22c5")


def parse_calibration_xml(data: bytes | str) -> NetFTCalibration:
    """Counts per unit, units and RDT rate from a ``netftapi2.xml`` document.

    ProtocolError (naming the element, the value and what is allowed) if the document is not
    XML, lacks ``cfgcpf``/``cfgcpt``, or holds a non-positive factor or an unknown unit.
    Missing ``scfgfu``/``scfgtu`` are taken as N and Nm (*assumption*: boxes always send them).
    """
    try:
        root = ET.fromstring(data)
    except ET.ParseError as exc:
        raise ProtocolError(DEVICE, f"{CALIBRATION_PATH} is not well-formed XML: {exc}") from None
    fields: dict[str, str] = {}
    for el in root.iter():
        tag = el.tag.rsplit("}", 1)[-1].lower()
        if tag not in fields and el.text is not None:
            fields[tag] = el.text.strip()

    def number(tag: str, required: bool) -> float | None:
        if tag not in fields:
            if required:
                raise ProtocolError(DEVICE, f"{CALIBRATION_PATH} has no <{tag}> element")
            return None
        try:
            v = float(fields[tag])
        except ValueError:
            raise ProtocolError(DEVICE, f"<{tag}> = {fields[tag]!r} is not a number") from None
        if not (math.isfinite(v) and v > 0):
            raise ProtocolError(DEVICE, f"<{tag}> = {fields[tag]!r}: must be a positive number")
        return v

    cpf = number("cfgcpf", True)
    cpt = number("cfgcpt", True)
    rate = number("comrdtrate", False)
    bsiz = number("comrdtbsiz", False)
    fu = fields.get("scfgfu", "N")
    tu = fields.get("scfgtu", "Nm")
    if _norm_unit(fu) not in FORCE_UNITS:
        raise ProtocolError(DEVICE, f"<scfgfu> = {fu!r}: unknown force unit; known: "
                                    f"{sorted(FORCE_UNITS)}")
    if _norm_unit(tu) not in TORQUE_UNITS:
        raise ProtocolError(DEVICE, f"<scfgtu> = {tu!r}: unknown torque unit; known: "
                                    f"{sorted(TORQUE_UNITS)}")
    return NetFTCalibration(cpf, cpt, fu, tu, rate,  # type: ignore[arg-type]
                            None if bsiz is None else int(bsiz))


def render_calibration_xml(cal: NetFTCalibration, **extra: object) -> bytes:
    """A minimal ``netftapi2.xml`` document (root ``<netft>``) for a simulated box."""
    fields: dict[str, object] = {
        "cfgcpf": _num_text(cal.counts_per_force), "cfgcpt": _num_text(cal.counts_per_torque),
        "scfgfu": cal.force_unit, "scfgtu": cal.torque_unit,
    }
    if cal.rdt_rate_hz is not None:
        fields["comrdtrate"] = _num_text(cal.rdt_rate_hz)
    if cal.buffer_size is not None:
        fields["comrdtbsiz"] = cal.buffer_size
    fields.update(extra)
    root = ET.Element("netft")
    for k, v in fields.items():
        ET.SubElement(root, k).text = str(v)
    return b'<?xml version="1.0"?>' + ET.tostring(root, encoding="utf-8")


def _num_text(v: float) -> str:
    return str(int(v)) if float(v).is_integer() else repr(float(v))


# --------------------------------------------------------------------------- minimal HTTP
#: Largest HTTP response (or request head) either side accepts.
HTTP_MAX_BYTES = 1 << 20

HTTP_REASONS: dict[int, str] = {200: "OK", 400: "Bad Request", 404: "Not Found",
                                405: "Method Not Allowed"}


def http_get_request(host: str, path: str = CALIBRATION_PATH) -> bytes:
    """An HTTP/1.0 GET (the connection closes after the answer)."""
    return (f"GET {path} HTTP/1.0\r\nHost: {host}\r\nAccept: application/xml, text/xml\r\n"
            f"Connection: close\r\n\r\n").encode("ascii")


def parse_http_response(data: bytes) -> tuple[int, bytes]:
    """(status code, body) of a complete HTTP/1.x response read to EOF."""
    head, sep, body = data.partition(b"\r\n\r\n")
    if not sep:
        raise ProtocolError(DEVICE, f"HTTP response without end of headers ({len(data)} bytes)")
    status_line = head.split(b"\r\n", 1)[0]
    parts = status_line.split(b" ", 2)
    if len(parts) < 2 or not parts[0].startswith(b"HTTP/1.") or not parts[1].isdigit():
        raise ProtocolError(DEVICE, f"bad HTTP status line {status_line[:80]!r}")
    return int(parts[1]), body


def parse_http_request_line(line: bytes) -> tuple[str, str]:
    """(method, path) of an HTTP request line such as ``GET /netftapi2.xml HTTP/1.1``."""
    parts = line.strip().split(b" ")
    if len(parts) != 3 or not parts[2].startswith(b"HTTP/1.") or not parts[1].startswith(b"/"):
        raise ProtocolError(DEVICE, f"bad HTTP request line {line[:80]!r}")
    try:
        return parts[0].decode("ascii"), parts[1].decode("ascii")
    except UnicodeDecodeError:
        raise ProtocolError(DEVICE, f"non-ASCII HTTP request line {line[:80]!r}") from None


def http_response(status: int, body: bytes = b"",
                  content_type: str = "text/xml; charset=utf-8") -> bytes:
    """A complete HTTP/1.0 response."""
    head = (f"HTTP/1.0 {status} {HTTP_REASONS.get(status, 'Error')}\r\n"
            f"Content-Type: {content_type}\r\nContent-Length: {len(body)}\r\n"
            f"Connection: close\r\n\r\n")
    return head.encode("ascii") + body


def _hex_list(codes) -> str:
    return ", ".join(f"0x{c:04X}" for c in codes)
