"""CANopen (CiA 301) framing and the CiA 402 drive profile, as used with the Maxon EPOS4.

Pure functions and data tables: no I/O, no asyncio. Both the driver (:mod:`dentibot.io.epos4`)
and the simulated node (:mod:`dentibot.sim.epos4_node`) import this module, so the bytes they
exchange come from one encoder and one decoder.

Contents
--------
- COB-ID functions (:data:`COB_BASE`): NMT 0x000, SYNC 0x080, EMCY 0x080+id, TPDO1..4
  0x180/0x280/0x380/0x480+id, RPDO1..4 0x200/0x300/0x400/0x500+id, SDO server->client 0x580+id,
  client->server 0x600+id, heartbeat 0x700+id.
- NMT commands and states, SYNC, heartbeat, EMCY (u16 LE error code, u8 error register,
  5 manufacturer bytes) with the EPOS4 error-code table (:data:`EPOS4_ERROR_CODES`) and the
  CiA 301 generic error classes as fall-back (:func:`error_meaning`).
- Liveness: the heartbeat consumer entry 0x1016:xx (CiA 301: producer node id in bits
  23..16, consumer time in ms in bits 15..0; :func:`encode_consumer_heartbeat`), the
  heartbeat error code 0x8130 (:data:`HEARTBEAT_ERROR_CODE`), the abort connection option
  code 0x6007 (:class:`AbortConnectionOption`) and the quick stop option code 0x605A
  (:data:`QUICK_STOP_OPTIONS`), CiA 402: the standards' definitions, which the driver
  writes and reads back at start-up.
- Expedited SDO (1..4 data bytes, all this project needs): requests, responses, aborts and the
  CiA 301 abort-code table (:data:`SDO_ABORT_CODES`). Segmented and block transfers are not
  implemented (a decoder reports them as ``kind="other"``/``"upload_segmented"``).
- The objects used (:data:`OBJECTS`, by name and by (index, sub)), with data type, unit and
  the parameter name of the EPOS4's electronic data sheet; the records and arrays they form
  (:data:`OBJECT_GROUPS`) and their highest sub-indices (:data:`HIGHEST_SUB_INDEX`).
- CiA 402: statusword masks -> states (:data:`STATUSWORD_STATES`), controlword commands
  (:data:`CONTROLWORD`, :data:`CONTROLWORD_COMMANDS`), the state transitions
  (:data:`TRANSITIONS`, :func:`apply_controlword`), controlword/statusword bits of the profile
  position and profile velocity modes, the bits of "supported drive modes" 0x6502
  (:data:`SUPPORTED_DRIVE_MODE_BITS`).
- The project's fixed PDO mapping (:data:`RXPDO1`, :data:`RXPDO2`, :data:`TXPDO1`,
  :data:`TXPDO2`) and a generic packer for any mapping (:class:`PdoLayout`).

Our fixed PDO mapping (configured over SDO in PRE-OPERATIONAL by the driver)::

    RxPDO1 0x200+id  controlword 0x6040 u16 | target velocity 0x60FF i32 (rpm, motor)
                     | modes of operation 0x6060 i8                      7 bytes, type 255
    RxPDO2 0x300+id  target position 0x607A i32 (inc) | profile velocity 0x6081 u32 (rpm,
                     motor)                                              8 bytes, type 255
    TxPDO1 0x180+id  statusword 0x6041 u16 | velocity actual 0x606C i32 (rpm, motor)
                     | modes of operation display 0x6061 i8              7 bytes, type 1
    TxPDO2 0x280+id  position actual 0x6064 i32 (inc) | current actual averaged 0x30D1:01
                     i32 (mA)                                            8 bytes, type 1

Transmission type 1 = synchronous, sent on every SYNC; 255 = asynchronous, acted on at
reception. All multi-byte CANopen values are little-endian.

Wrong frame lengths and unknown command bytes raise :class:`ProtocolError` (device
:data:`DEVICE`); callers count them and carry on.
"""

from __future__ import annotations

import struct
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from enum import Enum, IntEnum

from dentibot.errors import ConfigError, ProtocolError

#: Device name used in errors raised by this module.
DEVICE = "epos4"

# ============================================================================ COB-IDs
#: COB-ID function code -> base identifier (CiA 301 predefined connection set). The node id
#: (1..127) is added to all but NMT and SYNC.
COB_BASE: dict[str, int] = {
    "NMT": 0x000,
    "SYNC": 0x080,
    "EMCY": 0x080,
    "TPDO1": 0x180,
    "RPDO1": 0x200,
    "TPDO2": 0x280,
    "RPDO2": 0x300,
    "TPDO3": 0x380,
    "RPDO3": 0x400,
    "TPDO4": 0x480,
    "RPDO4": 0x500,
    "SDO_TX": 0x580,      # server (drive) -> client (driver)
    "SDO_RX": 0x600,      # client (driver) -> server (drive)
    "HEARTBEAT": 0x700,
}
#: Functions without a node id.
BROADCAST_FUNCTIONS = frozenset({"NMT", "SYNC"})
_FUNCTION_BY_BASE: dict[int, str] = {
    base: name for name, base in COB_BASE.items() if name not in BROADCAST_FUNCTIONS
}


def check_node_id(node_id: int) -> int:
    """``node_id`` if it is a valid CANopen node id (1..127), else :class:`ConfigError`."""
    if not isinstance(node_id, int) or not 1 <= node_id <= 127:
        raise ConfigError("epos4.node_id", node_id, "an integer 1..127 (CiA 301)")
    return node_id


def cob_id(function: str, node_id: int = 0) -> int:
    """The 11-bit COB-ID of ``function`` (a key of :data:`COB_BASE`) for ``node_id``."""
    if function not in COB_BASE:
        raise ConfigError("canopen.function", function, f"one of {sorted(COB_BASE)}")
    if function in BROADCAST_FUNCTIONS:
        return COB_BASE[function]
    return COB_BASE[function] + check_node_id(node_id)


def classify_cob_id(can_id: int) -> tuple[str, int]:
    """(function, node id) of a received COB-ID; node id 0 for NMT and SYNC.

    Raises :class:`ProtocolError` for identifiers outside the predefined connection set
    (e.g. LSS 0x7E4/0x7E5, or a base with node id 0).
    """
    if can_id == COB_BASE["NMT"]:
        return "NMT", 0
    if can_id == COB_BASE["SYNC"]:
        return "SYNC", 0
    base, node = can_id & 0x780, can_id & 0x07F
    name = _FUNCTION_BY_BASE.get(base)
    if name is None or node == 0 or can_id > 0x7FF:
        raise ProtocolError(DEVICE, f"COB-ID 0x{can_id:03X} is not in the predefined "
                                    "connection set (CiA 301)")
    return name, node


#: Bit 31 of a PDO COB-ID entry (0x14xx:01 / 0x18xx:01): 1 = PDO not valid (disabled).
PDO_COB_INVALID = 0x8000_0000
#: Bit 30 of a TPDO COB-ID entry: 1 = no RTR allowed.
PDO_COB_NO_RTR = 0x4000_0000


# ============================================================================ NMT, SYNC, heartbeat
class NmtCommand(IntEnum):
    """NMT command specifiers (first byte of a COB-ID 0x000 frame)."""

    START = 0x01
    STOP = 0x02
    ENTER_PRE_OPERATIONAL = 0x80
    RESET_NODE = 0x81
    RESET_COMMUNICATION = 0x82


class NmtState(IntEnum):
    """NMT states as reported in the heartbeat byte (bit 7, the toggle bit, masked off)."""

    BOOT_UP = 0x00
    STOPPED = 0x04
    OPERATIONAL = 0x05
    PRE_OPERATIONAL = 0x7F


#: State an NMT command leads to (the resets pass through BOOT_UP, then PRE_OPERATIONAL).
NMT_COMMAND_STATE: dict[NmtCommand, NmtState] = {
    NmtCommand.START: NmtState.OPERATIONAL,
    NmtCommand.STOP: NmtState.STOPPED,
    NmtCommand.ENTER_PRE_OPERATIONAL: NmtState.PRE_OPERATIONAL,
    NmtCommand.RESET_NODE: NmtState.PRE_OPERATIONAL,
    NmtCommand.RESET_COMMUNICATION: NmtState.PRE_OPERATIONAL,
}


def _check_len(what: str, data: bytes, allowed: Iterable[int]) -> None:
    allowed = tuple(allowed)
    if len(data) not in allowed:
        want = " or ".join(str(n) for n in allowed)
        raise ProtocolError(DEVICE, f"{what} frame has {len(data)} data bytes, expected {want}")


def encode_nmt(command: NmtCommand, node_id: int) -> bytes:
    """NMT frame payload (2 bytes); ``node_id`` 0 addresses all nodes."""
    if node_id != 0:
        check_node_id(node_id)
    return bytes((NmtCommand(command), node_id))


def decode_nmt(data: bytes) -> tuple[NmtCommand, int]:
    """(command, addressed node id; 0 = all) of an NMT frame."""
    _check_len("NMT", data, (2,))
    try:
        cmd = NmtCommand(data[0])
    except ValueError:
        raise ProtocolError(DEVICE, f"NMT command 0x{data[0]:02X} is unknown "
                                    f"(CiA 301: {[f'0x{c:02X}' for c in NmtCommand]})") from None
    if data[1] > 127:
        raise ProtocolError(DEVICE, f"NMT node id {data[1]} is not 0..127")
    return cmd, data[1]


def encode_sync(counter: int | None = None) -> bytes:
    """SYNC payload: empty, or the 1-byte counter 1..240 (CiA 301, 0x1019 > 1)."""
    if counter is None:
        return b""
    if not 1 <= counter <= 240:
        raise ConfigError("canopen.sync_counter", counter, "1..240 (CiA 301)")
    return bytes((counter,))


def decode_sync(data: bytes) -> int | None:
    """SYNC counter, or None for a plain SYNC."""
    _check_len("SYNC", data, (0, 1))
    return data[0] if data else None


def encode_heartbeat(state: NmtState) -> bytes:
    return bytes((NmtState(state),))


#: Largest consumer heartbeat time an 0x1016 entry can hold (ms, UNSIGNED16).
CONSUMER_TIME_MAX_MS = 0xFFFF


def encode_consumer_heartbeat(node_id: int, time_ms: int) -> int:
    """The 0x1016:xx entry that makes a node watch ``node_id``'s heartbeat (CiA 301, object
    1016h): bits 23..16 the producer's node id, bits 15..0 the consumer time in ms. A time of
    0 (or node id 0) leaves the entry unused; :func:`encode_consumer_heartbeat` (0, 0) is 0."""
    if (node_id, time_ms) != (0, 0):
        check_node_id(node_id)
    if isinstance(time_ms, bool) or not isinstance(time_ms, int) \
            or not 0 <= time_ms <= CONSUMER_TIME_MAX_MS:
        raise ConfigError("canopen.consumer_heartbeat_ms", time_ms,
                          f"an integer 0..{CONSUMER_TIME_MAX_MS} ms (0 = entry unused)")
    return (node_id << 16) | time_ms


def decode_consumer_heartbeat(word: int) -> tuple[int, int]:
    """(producer node id, consumer time ms) of an 0x1016:xx entry; bits 31..24 are reserved
    and ignored (CiA 301). The entry is in use only when both are non-zero and the node id is
    at most 127."""
    return (word >> 16) & 0xFF, word & 0xFFFF


def consumer_entry_active(word: int) -> bool:
    """Whether an 0x1016:xx entry makes the node monitor a producer (CiA 301: an entry with
    time 0, node id 0 or node id > 127 is not used)."""
    node, ms = decode_consumer_heartbeat(word)
    return ms > 0 and 1 <= node <= 127


def decode_heartbeat(data: bytes) -> NmtState:
    """NMT state in a heartbeat (or boot-up) frame; the toggle bit 7 is ignored."""
    _check_len("heartbeat", data, (1,))
    try:
        return NmtState(data[0] & 0x7F)
    except ValueError:
        raise ProtocolError(DEVICE, f"heartbeat state 0x{data[0]:02X} is not an NMT state "
                                    "(0x00, 0x04, 0x05, 0x7F)") from None


# ============================================================================ EMCY
#: EPOS4 error codes (0x603F and EMCY). From the error-code list of the EPOS4 Firmware
#: Specification as reproduced by public EPOS4 clients; not checked against the PDF here
#: (unconfirmed). Unknown codes fall back to the CiA 301 class (:data:`ERROR_CLASSES`).
EPOS4_ERROR_CODES: dict[int, str] = {
    0x0000: "No error",
    0x1000: "Generic error",
    0x1090: "Firmware incompatibility error",
    0x2310: "Overcurrent error",
    0x2320: "Power stage protection error",
    0x3210: "Overvoltage error",
    0x3220: "Undervoltage error",
    0x4210: "Thermal overload error",
    0x4380: "Thermal motor overload error",
    0x5113: "Logic supply voltage too low error",
    0x5280: "Hardware defect error",
    0x5281: "Hardware incompatibility error",
    0x6080: "Sign of life error",
    0x6081: "Extension 1 watchdog error",
    0x6320: "Software parameter error",
    0x6380: "Persistent parameter corrupt error",
    0x7320: "Position sensor error",
    0x7380: "Position sensor breach error",
    0x7381: "Position sensor resolution error",
    0x7382: "Position sensor index error",
    0x7388: "Hall sensor error",
    0x7389: "Hall sensor not found error",
    0x738A: "Hall angle detection error",
    0x738C: "SSI sensor error",
    0x7390: "Missing main sensor error",
    0x7391: "Missing commutation sensor error",
    0x7392: "Main sensor direction error",
    0x8110: "CAN overrun error (object lost)",
    0x8111: "CAN overrun error",
    0x8120: "CAN passive mode error",
    0x8130: "CAN heartbeat error",
    0x8150: "CAN PDO COB-ID collision",
    0x81FD: "CAN bus turned off",
    0x81FE: "CAN Rx queue overflow",
    0x81FF: "CAN Tx queue overflow",
    0x8210: "CAN PDO length error",
    0x8250: "RPDO timeout",
    0x8611: "Following error",
    0x8A80: "Negative limit switch error",
    0x8A81: "Positive limit switch error",
    0x8A82: "Software position limit error",
    0x8A88: "STO error",
    0xFF01: "System overloaded error",
    0xFF02: "Watchdog error",
    0xFF0B: "System peak overloaded error",
    0xFF10: "Controller gain error",
    0xFF11: "Auto tuning identification error",
    0xFF12: "Auto tuning current limit error",
    0xFF13: "Auto tuning identification current error",
    0xFF14: "Auto tuning data sampling error",
    0xFF15: "Auto tuning sample mismatch error",
    0xFF16: "Auto tuning parameter error",
    0xFF17: "Auto tuning amplitude mismatch error",
    0xFF19: "Auto tuning timeout error",
    0xFF20: "Auto tuning standstill error",
    0xFF21: "Auto tuning torque invalid error",
    0xFF22: "Auto tuning max system speed error",
    0xFF23: "Auto tuning motor connection error",
    0xFF24: "Auto tuning sensor signal error",
}
#: Ranges of EPOS4 codes with one meaning (same source, unconfirmed): (first, last, meaning).
EPOS4_ERROR_RANGES: tuple[tuple[int, int, str], ...] = (
    (0x1080, 0x1088, "Generic initialization error"),
    (0x5480, 0x5483, "Hardware error"),
    (0x6180, 0x61F0, "Internal software error"),
)
#: CiA 301 error code of a heartbeat consumer that missed its producer ("life guard error or
#: heartbeat error"; the EPOS4 lists it as "CAN heartbeat error").
HEARTBEAT_ERROR_CODE = 0x8130
#: CiA 301 emergency error code classes, most specific prefix first: (mask, value, meaning).
ERROR_CLASSES: tuple[tuple[int, int, str], ...] = (
    (0xFF00, 0x0000, "error reset or no error"),
    (0xFF00, 0x1000, "generic error"),
    (0xFF00, 0x2100, "current, device input side"),
    (0xFF00, 0x2200, "current inside the device"),
    (0xFF00, 0x2300, "current, device output side"),
    (0xF000, 0x2000, "current"),
    (0xFF00, 0x3100, "mains voltage"),
    (0xFF00, 0x3200, "voltage inside the device"),
    (0xFF00, 0x3300, "output voltage"),
    (0xF000, 0x3000, "voltage"),
    (0xFF00, 0x4100, "ambient temperature"),
    (0xFF00, 0x4200, "device temperature"),
    (0xF000, 0x4000, "temperature"),
    (0xF000, 0x5000, "device hardware"),
    (0xFF00, 0x6100, "internal software"),
    (0xFF00, 0x6200, "user software"),
    (0xFF00, 0x6300, "data set"),
    (0xF000, 0x6000, "device software"),
    (0xF000, 0x7000, "additional modules"),
    (0xFF00, 0x8100, "communication"),
    (0xFF00, 0x8200, "protocol error"),
    (0xF000, 0x8000, "monitoring"),
    (0xF000, 0x9000, "external error"),
    (0xFF00, 0xF000, "additional functions"),
    (0xFF00, 0xFF00, "device specific"),
)
#: Error register 0x1001 bits (CiA 301).
ERROR_REGISTER_BITS: dict[int, str] = {
    0x01: "generic",
    0x02: "current",
    0x04: "voltage",
    0x08: "temperature",
    0x10: "communication",
    0x20: "device profile specific",
    0x40: "reserved",
    0x80: "manufacturer specific",
}
#: Error register bit set for an error code, by code prefix: (mask, value, bit); bit 0
#: (generic) is set for every error (CiA 301).
_REGISTER_BY_CLASS: tuple[tuple[int, int, int], ...] = (
    (0xF000, 0x2000, 0x02),
    (0xF000, 0x3000, 0x04),
    (0xF000, 0x4000, 0x08),
    (0xFF00, 0x8100, 0x10),
    (0xFF00, 0x8200, 0x10),
    (0xFF00, 0x8600, 0x20),
    (0xFF00, 0x8A00, 0x20),
    (0xFF00, 0xFF00, 0x80),
)


def error_meaning(code: int) -> str:
    """Meaning of an EPOS4/CiA 301 error code: the EPOS4 table, else the CiA 301 class."""
    if code in EPOS4_ERROR_CODES:
        return EPOS4_ERROR_CODES[code]
    for first, last, meaning in EPOS4_ERROR_RANGES:
        if first <= code <= last:
            return meaning
    for mask, value, meaning in ERROR_CLASSES:
        if code & mask == value:
            return f"unlisted code, CiA 301 class: {meaning}"
    return "unknown error code"


def error_register_for(code: int) -> int:
    """The error register (0x1001) a device sets for ``code``: 0 for 0x0000, else bit 0 plus
    the class bit."""
    if code == 0:
        return 0
    reg = 0x01
    for mask, value, bit in _REGISTER_BY_CLASS:
        if code & mask == value:
            reg |= bit
            break
    return reg


def describe_error_register(register: int) -> str:
    names = [name for bit, name in ERROR_REGISTER_BITS.items() if register & bit]
    return ", ".join(names) if names else "none"


@dataclass(frozen=True, slots=True)
class Emcy:
    """An emergency message: error code, error register, 5 manufacturer-specific bytes."""

    code: int
    register: int
    manufacturer: bytes = bytes(5)

    @property
    def meaning(self) -> str:
        return error_meaning(self.code)

    @property
    def is_reset(self) -> bool:
        """Code 0x0000: "error reset or no error" (sent when the error is gone)."""
        return self.code == 0

    def describe(self) -> str:
        return (f"EMCY 0x{self.code:04X} ({self.meaning}), error register "
                f"0x{self.register:02X} ({describe_error_register(self.register)})")


def encode_emcy(code: int, register: int, manufacturer: bytes = bytes(5)) -> bytes:
    if len(manufacturer) != 5:
        raise ConfigError("canopen.emcy.manufacturer", manufacturer, "exactly 5 bytes")
    return struct.pack("<HB", code, register) + bytes(manufacturer)


def decode_emcy(data: bytes) -> Emcy:
    _check_len("EMCY", data, (8,))
    code, register = struct.unpack_from("<HB", data)
    return Emcy(code, register, bytes(data[3:8]))


# ============================================================================ data types, objects
@dataclass(frozen=True, slots=True)
class DataType:
    """A CiA 301 basic data type: name, struct format (one char), size in bits, type index."""

    name: str
    fmt: str
    bits: int
    code: int

    @property
    def size(self) -> int:
        return self.bits // 8

    @property
    def signed(self) -> bool:
        return self.fmt.islower()

    @property
    def range(self) -> tuple[int, int]:
        if self.signed:
            return -(1 << (self.bits - 1)), (1 << (self.bits - 1)) - 1
        return 0, (1 << self.bits) - 1

    def encode(self, value: int, field: str = "value") -> bytes:
        lo, hi = self.range
        if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
            raise ConfigError(field, value, f"an integer in {lo}..{hi} ({self.name})")
        return struct.pack("<" + self.fmt, value)

    def decode(self, data: bytes, what: str = "value") -> int:
        if len(data) != self.size:
            raise ProtocolError(DEVICE, f"{what}: {len(data)} bytes for a {self.name} "
                                        f"({self.size} bytes)")
        return struct.unpack("<" + self.fmt, data)[0]


U8 = DataType("UNSIGNED8", "B", 8, 0x0005)
U16 = DataType("UNSIGNED16", "H", 16, 0x0006)
U32 = DataType("UNSIGNED32", "I", 32, 0x0007)
I8 = DataType("INTEGER8", "b", 8, 0x0002)
I16 = DataType("INTEGER16", "h", 16, 0x0003)
I32 = DataType("INTEGER32", "i", 32, 0x0004)


@dataclass(frozen=True, slots=True)
class OdObject:
    """One object dictionary entry: where it is, its type, access ("ro", "rw", "wo", "const"),
    whether it can be mapped into an RxPDO ("rx") or a TxPDO ("tx"), its unit, a note and its
    parameter name in the EPOS4's electronic data sheet (``label``; CiA 306 ParameterName)."""

    name: str
    index: int
    sub: int
    dtype: DataType
    access: str = "rw"
    pdo: str | None = None
    unit: str = ""
    note: str = ""
    label: str = ""

    @property
    def address(self) -> tuple[int, int]:
        return self.index, self.sub

    @property
    def mapping_word(self) -> int:
        """The PDO mapping entry for this object: index << 16 | sub << 8 | length in bits."""
        return mapping_word(self.index, self.sub, self.dtype.bits)

    @property
    def parameter_name(self) -> str:
        """The name an EDS gives the entry (``label``, else ``name`` in words)."""
        return self.label or self.name.replace("_", " ").capitalize()

    def __str__(self) -> str:
        return f"0x{self.index:04X}:{self.sub:02X} {self.name}"


#: Name of sub-index 0 of a record or array: the highest sub-index it supports (CiA 301).
HIGHEST_SUB = "Highest sub-index supported"

_BASE_OBJECTS: tuple[OdObject, ...] = (
    OdObject("device_type", 0x1000, 0, U32, "ro", note="low 16 bits: device profile (402)",
             label="Device type"),
    OdObject("error_register", 0x1001, 0, U8, "ro", "tx", label="Error register"),
    OdObject("consumer_heartbeat_count", 0x1016, 0, U8, "ro",
             note="number of consumer heartbeat entries", label=HIGHEST_SUB),
    OdObject("consumer_heartbeat_time", 0x1016, 1, U32, "rw",
             note="bits 23..16 producer node id, 15..0 consumer time ms (CiA 301)",
             label="Consumer 1 heartbeat time"),
    OdObject("producer_heartbeat_time", 0x1017, 0, U16, "rw", unit="ms", note="0 = off",
             label="Producer heartbeat time"),
    OdObject("identity_count", 0x1018, 0, U8, "ro", label=HIGHEST_SUB),
    OdObject("vendor_id", 0x1018, 1, U32, "ro",
             note="0x000000FB for maxon motor ag", label="Vendor ID"),
    OdObject("product_code", 0x1018, 2, U32, "ro", label="Product code"),
    OdObject("revision_number", 0x1018, 3, U32, "ro",
             note="high word: firmware version", label="Revision number"),
    OdObject("serial_number", 0x1018, 4, U32, "ro", label="Serial number"),
    OdObject("axis_configuration_count", 0x3000, 0, U8, "ro", label=HIGHEST_SUB),
    OdObject("axis_main_sensor_resolution", 0x3000, 5, U32, "ro", unit="inc/turn",
             note="increments per motor turn of the main position sensor",
             label="Main sensor resolution"),
    OdObject("motor_data_count", 0x3001, 0, U8, "ro", label=HIGHEST_SUB),
    OdObject("motor_nominal_current", 0x3001, 1, U32, "rw", unit="mA",
             label="Nominal current"),
    OdObject("motor_output_current_limit", 0x3001, 2, U32, "rw", unit="mA",
             label="Output current limit"),
    OdObject("motor_torque_constant", 0x3001, 5, U32, "rw", unit="uNm/A",
             note="unit micro-Nm per A (unconfirmed)", label="Torque constant"),
    OdObject("gear_configuration_count", 0x3003, 0, U8, "ro", label=HIGHEST_SUB),
    OdObject("gear_reduction_numerator", 0x3003, 1, U32, "rw",
             label="Gear reduction numerator"),
    OdObject("gear_reduction_denominator", 0x3003, 2, U32, "rw",
             label="Gear reduction denominator"),
    OdObject("current_actual_values_count", 0x30D1, 0, U8, "ro", label=HIGHEST_SUB),
    OdObject("current_actual_averaged", 0x30D1, 1, I32, "ro", "tx", unit="mA",
             label="Current actual value averaged"),
    OdObject("current_actual", 0x30D1, 2, I32, "ro", "tx", unit="mA",
             label="Current actual value"),
    OdObject("functional_safety_count", 0x3202, 0, U8, "ro", label=HIGHEST_SUB),
    OdObject("sto_inputs", 0x3202, 1, U8, "ro", "tx", note="STO input states (type unconfirmed)",
             label="STO input states"),
    OdObject("error_code", 0x603F, 0, U16, "ro", "tx", label="Error code"),
    OdObject("controlword", 0x6040, 0, U16, "rw", "rx", label="Controlword"),
    OdObject("statusword", 0x6041, 0, U16, "ro", "tx", label="Statusword"),
    OdObject("abort_connection_option_code", 0x6007, 0, I16, "rw",
             note="0 none, 1 fault, 2 disable voltage, 3 quick stop (CiA 402)",
             label="Abort connection option code"),
    OdObject("quick_stop_option_code", 0x605A, 0, I16, "rw", label="Quick stop option code"),
    OdObject("modes_of_operation", 0x6060, 0, I8, "rw", "rx", label="Modes of operation"),
    OdObject("modes_of_operation_display", 0x6061, 0, I8, "ro", "tx",
             label="Modes of operation display"),
    OdObject("position_actual", 0x6064, 0, I32, "ro", "tx", unit="inc",
             label="Position actual value"),
    OdObject("velocity_actual", 0x606C, 0, I32, "ro", "tx", unit="rpm",
             note="velocity unit 0x60A9 assumed rpm (EPOS4 default)",
             label="Velocity actual value"),
    OdObject("target_torque", 0x6071, 0, I16, "rw", "rx", unit="per mille of 0x6076",
             label="Target torque"),
    OdObject("motor_rated_torque", 0x6076, 0, U32, "rw", unit="uNm",
             note="unit micro-Nm (unconfirmed)", label="Motor rated torque"),
    OdObject("torque_actual", 0x6077, 0, I16, "ro", "tx", unit="per mille of 0x6076",
             label="Torque actual value"),
    OdObject("target_position", 0x607A, 0, I32, "rw", "rx", unit="inc", label="Target position"),
    OdObject("profile_velocity", 0x6081, 0, U32, "rw", "rx", unit="rpm",
             label="Profile velocity"),
    OdObject("profile_acceleration", 0x6083, 0, U32, "rw", "rx", unit="rpm/s",
             label="Profile acceleration"),
    OdObject("profile_deceleration", 0x6084, 0, U32, "rw", "rx", unit="rpm/s",
             label="Profile deceleration"),
    OdObject("quick_stop_deceleration", 0x6085, 0, U32, "rw", unit="rpm/s",
             label="Quick stop deceleration"),
    OdObject("target_velocity", 0x60FF, 0, I32, "rw", "rx", unit="rpm", label="Target velocity"),
    OdObject("supported_drive_modes", 0x6502, 0, U32, "ro", "tx",
             note="bit per mode of operation (CiA 402): SUPPORTED_DRIVE_MODE_BITS",
             label="Supported drive modes"),
)

_ORDINALS = {1: "1st", 2: "2nd", 3: "3rd"}


def _pdo_parameter_objects() -> tuple[OdObject, ...]:
    out = []
    for kind, comm0 in (("rx", 0x1400), ("tx", 0x1800)):
        label = "rpdo" if kind == "rx" else "tpdo"
        for k in range(4):
            comm, mapping = comm0 + k, comm0 + 0x200 + k
            n = k + 1
            pdo = f"{'RxPDO' if kind == 'rx' else 'TxPDO'} {n}"
            out.append(OdObject(f"{label}{n}_highest_sub", comm, 0, U8, "ro", label=HIGHEST_SUB))
            out.append(OdObject(f"{label}{n}_cob_id", comm, 1, U32, "rw",
                                note="bit 31 = PDO not valid", label=f"COB-ID used by {pdo}"))
            out.append(OdObject(f"{label}{n}_transmission_type", comm, 2, U8, "rw",
                                note="1..240 synchronous (every n-th SYNC), 254/255 async",
                                label=f"Transmission type {pdo}"))
            if kind == "tx":
                out.append(OdObject(f"{label}{n}_inhibit_time", comm, 3, U16, "rw",
                                    unit="100 us", label=f"Inhibit time {pdo}"))
                out.append(OdObject(f"{label}{n}_event_timer", comm, 5, U16, "rw", unit="ms",
                                    label=f"Event timer {pdo}"))
            out.append(OdObject(f"{label}{n}_mapped_count", mapping, 0, U8, "rw",
                                label=f"Number of mapped objects in {pdo}"))
            for s in range(1, 9):
                out.append(OdObject(f"{label}{n}_mapping_{s}", mapping, s, U32, "rw",
                                    label=f"{_ORDINALS.get(s, f'{s}th')} mapped object in {pdo}"))
    return tuple(out)


#: Every object this project uses, by name.
OBJECTS: dict[str, OdObject] = {o.name: o for o in _BASE_OBJECTS + _pdo_parameter_objects()}
#: The same objects by (index, sub).
OBJECTS_BY_ADDRESS: dict[tuple[int, int], OdObject] = {o.address: o for o in OBJECTS.values()}

#: CiA 301 object codes (an EDS's ObjectType): a variable, an array (sub-indices 1..n of one
#: type) and a record (sub-indices of any type).
OBJECT_CODE_VAR = 0x7
OBJECT_CODE_ARRAY = 0x8
OBJECT_CODE_RECORD = 0x9
#: Indices with sub-indices: index -> (parameter name, object code), the names and codes of
#: the EPOS4's own electronic data sheet (the identity object is a record, CiA 301).
OBJECT_GROUPS: dict[int, tuple[str, int]] = {
    0x1016: ("Consumer heartbeat time", OBJECT_CODE_ARRAY),
    0x1018: ("Identity object", OBJECT_CODE_RECORD),
    **{0x1400 + k: (f"Receive PDO {k + 1} parameter", OBJECT_CODE_RECORD) for k in range(4)},
    **{0x1600 + k: (f"Receive PDO {k + 1} mapping", OBJECT_CODE_RECORD) for k in range(4)},
    **{0x1800 + k: (f"Transmit PDO {k + 1} parameter", OBJECT_CODE_RECORD) for k in range(4)},
    **{0x1A00 + k: (f"Transmit PDO {k + 1} mapping", OBJECT_CODE_RECORD) for k in range(4)},
    0x3000: ("Axis configuration", OBJECT_CODE_ARRAY),
    0x3001: ("Motor data", OBJECT_CODE_RECORD),
    0x3003: ("Gear configuration", OBJECT_CODE_ARRAY),
    0x30D1: ("Current actual values", OBJECT_CODE_ARRAY),
    0x3202: ("Functional safety", OBJECT_CODE_ARRAY),
}
#: Sub-index 0 entries that hold the highest sub-index of their record or array (read-only,
#: unlike a PDO mapping's sub-index 0, the number of mapped objects).
HIGHEST_SUB_OBJECTS: frozenset[str] = frozenset(
    o.name for o in OBJECTS.values() if o.sub == 0 and o.label == HIGHEST_SUB)

#: The highest sub-index of each index with sub-indices (the value of its sub-index 0 where
#: that is a :data:`HIGHEST_SUB_OBJECTS` entry).
HIGHEST_SUB_INDEX: dict[int, int] = {
    index: max(s for i, s in OBJECTS_BY_ADDRESS if i == index) for index in OBJECT_GROUPS}


def obj(name: str) -> OdObject:
    """The object called ``name`` (a key of :data:`OBJECTS`)."""
    try:
        return OBJECTS[name]
    except KeyError:
        raise ConfigError("canopen.object", name, "a name in canopen_protocol.OBJECTS") from None


def mapping_word(index: int, sub: int, bits: int) -> int:
    return (index << 16) | (sub << 8) | bits


def decode_mapping_word(word: int) -> tuple[int, int, int]:
    """(index, sub, length in bits) of a PDO mapping entry."""
    return (word >> 16) & 0xFFFF, (word >> 8) & 0xFF, word & 0xFF


# ============================================================================ SDO (expedited)
#: SDO abort codes (CiA 301).
SDO_ABORT_CODES: dict[int, str] = {
    0x0503_0000: "toggle bit not alternated",
    0x0504_0000: "SDO protocol timed out",
    0x0504_0001: "client/server command specifier not valid or unknown",
    0x0504_0005: "out of memory",
    0x0601_0000: "unsupported access to an object",
    0x0601_0001: "attempt to read a write-only object",
    0x0601_0002: "attempt to write a read-only object",
    0x0602_0000: "object does not exist in the object dictionary",
    0x0604_0041: "object cannot be mapped to the PDO",
    0x0604_0042: "number and length of the objects to be mapped would exceed the PDO length",
    0x0604_0043: "general parameter incompatibility",
    0x0604_0047: "general internal incompatibility in the device",
    0x0606_0000: "access failed due to a hardware error",
    0x0607_0010: "data type does not match, length of service parameter does not match",
    0x0607_0012: "data type does not match, length of service parameter too high",
    0x0607_0013: "data type does not match, length of service parameter too low",
    0x0609_0011: "sub-index does not exist",
    0x0609_0030: "invalid value for parameter (download only)",
    0x0609_0031: "value of parameter written too high (download only)",
    0x0609_0032: "value of parameter written too low (download only)",
    0x0800_0000: "general error",
    0x0800_0020: "data cannot be transferred or stored to the application",
    0x0800_0021: "data cannot be transferred or stored because of local control",
    0x0800_0022: "data cannot be transferred or stored because of the present device state",
    0x0800_0023: "object dictionary not present",
    0x0800_0024: "no data available",
}

# Command byte bits (CiA 301): ccs/scs in bits 7..5, n in 3..2, e bit 1, s bit 0.
_CS_SHIFT = 5
_CCS_DOWNLOAD, _CCS_UPLOAD, _CS_ABORT = 1, 2, 4      # client command specifiers used
_SCS_DOWNLOAD_ACK, _SCS_UPLOAD = 3, 2                # server command specifiers used
_EXPEDITED, _SIZE_INDICATED = 0x02, 0x01


def sdo_abort_meaning(code: int) -> str:
    return SDO_ABORT_CODES.get(code, "unknown abort code")


@dataclass(frozen=True, slots=True)
class SdoFrame:
    """A decoded SDO frame.

    ``kind``: requests "download", "upload", "abort", "other"; responses "download_ack",
    "upload", "upload_segmented", "abort", "other". ``payload`` is the data of an expedited
    transfer; ``abort_code`` is set for aborts; ``size`` is the indicated size (or None).
    """

    kind: str
    index: int
    sub: int
    payload: bytes = b""
    abort_code: int = 0
    size: int | None = None
    expedited: bool = True


def _sdo_head(data: bytes, what: str) -> tuple[int, int, int]:
    _check_len(what, data, (8,))
    index, sub = struct.unpack_from("<HB", data, 1)
    return data[0], index, sub


def _expedited_payload(cmd: int, data: bytes) -> tuple[bytes, int | None]:
    if cmd & _SIZE_INDICATED:
        n = (cmd >> 2) & 0x3
        return bytes(data[4:8 - n]), 4 - n
    return bytes(data[4:8]), None


def encode_sdo_download(index: int, sub: int, payload: bytes) -> bytes:
    """Expedited download (write) request with the size indicated (1..4 data bytes)."""
    n = len(payload)
    if not 1 <= n <= 4:
        raise ConfigError("canopen.sdo.payload", payload, "1..4 bytes (expedited transfer)")
    cmd = (_CCS_DOWNLOAD << _CS_SHIFT) | ((4 - n) << 2) | _EXPEDITED | _SIZE_INDICATED
    return struct.pack("<BHB", cmd, index, sub) + bytes(payload) + bytes(4 - n)


def encode_sdo_upload(index: int, sub: int) -> bytes:
    """Upload (read) initiate request."""
    return struct.pack("<BHB4x", _CCS_UPLOAD << _CS_SHIFT, index, sub)


def encode_sdo_download_ack(index: int, sub: int) -> bytes:
    return struct.pack("<BHB4x", _SCS_DOWNLOAD_ACK << _CS_SHIFT, index, sub)


def encode_sdo_upload_ack(index: int, sub: int, payload: bytes) -> bytes:
    """Expedited upload response with the size indicated (1..4 data bytes)."""
    n = len(payload)
    if not 1 <= n <= 4:
        raise ConfigError("canopen.sdo.payload", payload, "1..4 bytes (expedited transfer)")
    cmd = (_SCS_UPLOAD << _CS_SHIFT) | ((4 - n) << 2) | _EXPEDITED | _SIZE_INDICATED
    return struct.pack("<BHB", cmd, index, sub) + bytes(payload) + bytes(4 - n)


def encode_sdo_abort(index: int, sub: int, code: int) -> bytes:
    return struct.pack("<BHBI", _CS_ABORT << _CS_SHIFT, index, sub, code)


def decode_sdo_request(data: bytes) -> SdoFrame:
    """Decode a client->server SDO frame (COB-ID 0x600+id)."""
    cmd, index, sub = _sdo_head(data, "SDO request")
    ccs = cmd >> _CS_SHIFT
    if ccs == _CCS_DOWNLOAD:
        if cmd & _EXPEDITED:
            payload, size = _expedited_payload(cmd, data)
            return SdoFrame("download", index, sub, payload, size=size)
        size = struct.unpack_from("<I", data, 4)[0] if cmd & _SIZE_INDICATED else None
        return SdoFrame("download", index, sub, size=size, expedited=False)
    if ccs == _CCS_UPLOAD:
        return SdoFrame("upload", index, sub)
    if ccs == _CS_ABORT:
        return SdoFrame("abort", index, sub, abort_code=struct.unpack_from("<I", data, 4)[0])
    return SdoFrame("other", index, sub)


def decode_sdo_response(data: bytes) -> SdoFrame:
    """Decode a server->client SDO frame (COB-ID 0x580+id)."""
    cmd, index, sub = _sdo_head(data, "SDO response")
    scs = cmd >> _CS_SHIFT
    if scs == _SCS_DOWNLOAD_ACK:
        return SdoFrame("download_ack", index, sub)
    if scs == _SCS_UPLOAD:
        if cmd & _EXPEDITED:
            payload, size = _expedited_payload(cmd, data)
            return SdoFrame("upload", index, sub, payload, size=size)
        size = struct.unpack_from("<I", data, 4)[0] if cmd & _SIZE_INDICATED else None
        return SdoFrame("upload_segmented", index, sub, size=size, expedited=False)
    if scs == _CS_ABORT:
        return SdoFrame("abort", index, sub, abort_code=struct.unpack_from("<I", data, 4)[0])
    return SdoFrame("other", index, sub)


# ============================================================================ CiA 402
class State(Enum):
    """CiA 402 power drive system states."""

    NOT_READY_TO_SWITCH_ON = "not ready to switch on"
    SWITCH_ON_DISABLED = "switch on disabled"
    READY_TO_SWITCH_ON = "ready to switch on"
    SWITCHED_ON = "switched on"
    OPERATION_ENABLED = "operation enabled"
    QUICK_STOP_ACTIVE = "quick stop active"
    FAULT_REACTION_ACTIVE = "fault reaction active"
    FAULT = "fault"


#: Statusword (mask, value) -> state, as in CiA 402 (all eight states, "not ready to switch
#: on" and "fault reaction active" included).
STATUSWORD_STATES: tuple[tuple[int, int, State], ...] = (
    (0x4F, 0x00, State.NOT_READY_TO_SWITCH_ON),
    (0x4F, 0x40, State.SWITCH_ON_DISABLED),
    (0x6F, 0x21, State.READY_TO_SWITCH_ON),
    (0x6F, 0x23, State.SWITCHED_ON),
    (0x6F, 0x27, State.OPERATION_ENABLED),
    (0x6F, 0x07, State.QUICK_STOP_ACTIVE),
    (0x4F, 0x0F, State.FAULT_REACTION_ACTIVE),
    (0x4F, 0x08, State.FAULT),
)
#: The state bits a drive reports in each state (statusword bits 0..6).
STATE_STATUSWORD: dict[State, int] = {
    State.NOT_READY_TO_SWITCH_ON: 0x00,
    State.SWITCH_ON_DISABLED: 0x40,
    State.READY_TO_SWITCH_ON: 0x21,
    State.SWITCHED_ON: 0x23,
    State.OPERATION_ENABLED: 0x27,
    State.QUICK_STOP_ACTIVE: 0x07,
    State.FAULT_REACTION_ACTIVE: 0x0F,
    State.FAULT: 0x08,
}

# Statusword bits beyond the state bits (CiA 402).
SW_VOLTAGE_ENABLED = 0x0010
SW_QUICK_STOP = 0x0020          # 0 = quick stop active (part of the state pattern)
SW_WARNING = 0x0080
SW_REMOTE = 0x0200
SW_TARGET_REACHED = 0x0400
SW_INTERNAL_LIMIT = 0x0800
SW_SETPOINT_ACK = 0x1000        # profile position mode
SW_SPEED_ZERO = 0x1000          # profile velocity mode (same bit)
SW_FOLLOWING_ERROR = 0x2000

#: Statusword bit -> meaning (state bits 0..6 are decoded by :func:`state_from_statusword`).
STATUSWORD_BITS: dict[int, str] = {
    SW_VOLTAGE_ENABLED: "voltage enabled",
    SW_WARNING: "warning",
    SW_REMOTE: "remote",
    SW_TARGET_REACHED: "target reached",
    SW_INTERNAL_LIMIT: "internal limit active",
    SW_SETPOINT_ACK: "set-point acknowledge / speed zero",
    SW_FOLLOWING_ERROR: "following error",
}


def state_from_statusword(statusword: int) -> State:
    """The CiA 402 state encoded in a statusword; :class:`ProtocolError` if none matches."""
    for mask, value, state in STATUSWORD_STATES:
        if statusword & mask == value:
            return state
    raise ProtocolError(DEVICE, f"statusword 0x{statusword:04X} matches no CiA 402 state")


def describe_statusword(statusword: int) -> str:
    try:
        state = state_from_statusword(statusword).value
    except ProtocolError:
        state = "no CiA 402 state"
    bits = [name for bit, name in STATUSWORD_BITS.items() if statusword & bit]
    return f"0x{statusword:04X} ({state}{'; ' + ', '.join(bits) if bits else ''})"


class Command(Enum):
    """CiA 402 device control commands (controlword bits 0..3 and 7)."""

    SHUTDOWN = "shutdown"
    SWITCH_ON = "switch on"           # also "disable operation" from operation enabled
    ENABLE_OPERATION = "enable operation"
    DISABLE_VOLTAGE = "disable voltage"
    QUICK_STOP = "quick stop"
    FAULT_RESET = "fault reset"


#: Controlword value a master sends for each command (CiA 402). Fault reset acts on the
#: rising edge of bit 7: send a word with bit 7 clear first.
CONTROLWORD: dict[Command, int] = {
    Command.SHUTDOWN: 0x06,
    Command.SWITCH_ON: 0x07,
    Command.ENABLE_OPERATION: 0x0F,
    Command.DISABLE_VOLTAGE: 0x00,
    Command.QUICK_STOP: 0x02,
    Command.FAULT_RESET: 0x80,
}
#: Disable operation is the same word as switch on (0x07), taken from operation enabled.
DISABLE_OPERATION = CONTROLWORD[Command.SWITCH_ON]
#: Controlword (mask, value) -> command, how a drive decodes bits 7, 3..0 (CiA 402).
CONTROLWORD_COMMANDS: tuple[tuple[int, int, Command], ...] = (
    (0x8F, 0x0F, Command.ENABLE_OPERATION),
    (0x8F, 0x07, Command.SWITCH_ON),
    (0x87, 0x06, Command.SHUTDOWN),
    (0x86, 0x02, Command.QUICK_STOP),
    (0x82, 0x00, Command.DISABLE_VOLTAGE),
)

# Controlword bits beyond the command bits (CiA 402 profile position / velocity modes).
CW_NEW_SETPOINT = 0x0010
CW_CHANGE_SET_IMMEDIATELY = 0x0020
CW_RELATIVE = 0x0040
CW_FAULT_RESET = 0x0080
CW_HALT = 0x0100

#: (state, command) -> (next state, CiA 402 transition number). Pairs not listed are illegal
#: and ignored by the drive. Fault reset (15) is edge-triggered: see :func:`apply_controlword`.
TRANSITIONS: dict[tuple[State, Command], tuple[State, str]] = {
    (State.SWITCH_ON_DISABLED, Command.SHUTDOWN): (State.READY_TO_SWITCH_ON, "2"),
    (State.READY_TO_SWITCH_ON, Command.SWITCH_ON): (State.SWITCHED_ON, "3"),
    (State.READY_TO_SWITCH_ON, Command.ENABLE_OPERATION): (State.OPERATION_ENABLED, "3+4"),
    (State.SWITCHED_ON, Command.ENABLE_OPERATION): (State.OPERATION_ENABLED, "4"),
    (State.OPERATION_ENABLED, Command.SWITCH_ON): (State.SWITCHED_ON, "5"),
    (State.SWITCHED_ON, Command.SHUTDOWN): (State.READY_TO_SWITCH_ON, "6"),
    (State.READY_TO_SWITCH_ON, Command.DISABLE_VOLTAGE): (State.SWITCH_ON_DISABLED, "7"),
    (State.READY_TO_SWITCH_ON, Command.QUICK_STOP): (State.SWITCH_ON_DISABLED, "7"),
    (State.OPERATION_ENABLED, Command.SHUTDOWN): (State.READY_TO_SWITCH_ON, "8"),
    (State.OPERATION_ENABLED, Command.DISABLE_VOLTAGE): (State.SWITCH_ON_DISABLED, "9"),
    (State.SWITCHED_ON, Command.DISABLE_VOLTAGE): (State.SWITCH_ON_DISABLED, "10"),
    (State.SWITCHED_ON, Command.QUICK_STOP): (State.SWITCH_ON_DISABLED, "10"),
    (State.OPERATION_ENABLED, Command.QUICK_STOP): (State.QUICK_STOP_ACTIVE, "11"),
    (State.QUICK_STOP_ACTIVE, Command.DISABLE_VOLTAGE): (State.SWITCH_ON_DISABLED, "12"),
    (State.QUICK_STOP_ACTIVE, Command.ENABLE_OPERATION): (State.OPERATION_ENABLED, "16"),
}


def command_from_controlword(controlword: int) -> Command | None:
    """The command in bits 7, 3..0 of ``controlword``; None if they encode none (bit 7 set
    means a fault reset request, which is decided by its edge)."""
    for mask, value, cmd in CONTROLWORD_COMMANDS:
        if controlword & mask == value:
            return cmd
    return None


def apply_controlword(state: State, controlword: int,
                      previous: int) -> tuple[State, str | None]:
    """The drive's next state after receiving ``controlword`` (``previous`` is the word before
    it, for the fault-reset edge). Returns (state, transition number or None if unchanged)."""
    if controlword & CW_FAULT_RESET and not previous & CW_FAULT_RESET:
        if state is State.FAULT:
            return State.SWITCH_ON_DISABLED, "15"
        return state, None
    cmd = command_from_controlword(controlword)
    if cmd is None:
        return state, None
    nxt = TRANSITIONS.get((state, cmd))
    if nxt is None:
        return state, None
    return nxt


#: What a master sends to move a drive one step towards "operation enabled" from each state
#: (None: wait, the drive moves by itself). Quick stop active goes back through switch on
#: disabled, which works whatever the quick stop option code.
ENABLE_STEP: dict[State, Command | None] = {
    State.NOT_READY_TO_SWITCH_ON: None,
    State.SWITCH_ON_DISABLED: Command.SHUTDOWN,
    State.READY_TO_SWITCH_ON: Command.SWITCH_ON,
    State.SWITCHED_ON: Command.ENABLE_OPERATION,
    State.OPERATION_ENABLED: None,
    State.QUICK_STOP_ACTIVE: Command.DISABLE_VOLTAGE,
    State.FAULT_REACTION_ACTIVE: None,
    State.FAULT: Command.FAULT_RESET,
}


class AbortConnectionOption(IntEnum):
    """Abort connection option code 0x6007 (CiA 402): what an enabled drive does on an "abort
    connection" event -- its heartbeat consumer missed the master, a life-guarding or bus-off
    error, or NMT taking it out of OPERATIONAL."""

    NO_ACTION = 0
    FAULT = 1
    DISABLE_VOLTAGE = 2
    QUICK_STOP = 3


#: What each 0x6007 value does (CiA 402). FAULT runs the drive's fault reaction, which on the
#: EPOS4 is a stop on the quick-stop ramp 0x6085 before the power stage goes off (assumption:
#: the EPOS4 firmware specification's "fault reaction active" describes a quick stop, the
#: exact wording was not checked here); it latches FAULT, so only a fault reset followed by
#: the enable sequence turns the motor again. QUICK_STOP stops on the same ramp but ends in
#: QUICK STOP ACTIVE, from which "enable operation" alone (transition 16) restarts motion.
ABORT_CONNECTION_OPTIONS: dict[AbortConnectionOption, str] = {
    AbortConnectionOption.NO_ACTION: "no action",
    AbortConnectionOption.FAULT: "fault signal (fault reaction: quick-stop ramp, then FAULT)",
    AbortConnectionOption.DISABLE_VOLTAGE: "disable voltage (power stage off at once)",
    AbortConnectionOption.QUICK_STOP: "quick stop (quick-stop ramp, then QUICK STOP ACTIVE)",
}

#: Quick stop option code 0x605A (CiA 402) -> the state after the quick-stop function has
#: brought the motor to rest: None = stay in QUICK STOP ACTIVE, else switch on disabled.
#: 0 disables the drive function at once (no ramp); 1 and 5 use the slow-down ramp, 2 and 6
#: the quick-stop ramp (the simulated drive has one ramp, 0x6085, for both).
QUICK_STOP_OPTIONS: dict[int, State | None] = {
    0: State.SWITCH_ON_DISABLED,
    1: State.SWITCH_ON_DISABLED,
    2: State.SWITCH_ON_DISABLED,
    5: None,
    6: None,
}


class Mode(IntEnum):
    """Modes of operation 0x6060/0x6061 (CiA 402, those the EPOS4 offers)."""

    PROFILE_POSITION = 1
    PROFILE_VELOCITY = 3
    HOMING = 6
    CYCLIC_SYNC_POSITION = 8
    CYCLIC_SYNC_VELOCITY = 9
    CYCLIC_SYNC_TORQUE = 10


#: Bit of each mode in "supported drive modes" 0x6502 (CiA 402: bit 0 profile position, 1
#: velocity, 2 profile velocity, 3 profile torque, 5 homing, 6 interpolated position, 7..9
#: cyclic synchronous position, velocity, torque). A real EPOS4 reports 0x000003A5.
SUPPORTED_DRIVE_MODE_BITS: dict[Mode, int] = {
    Mode.PROFILE_POSITION: 0,
    Mode.PROFILE_VELOCITY: 2,
    Mode.HOMING: 5,
    Mode.CYCLIC_SYNC_POSITION: 7,
    Mode.CYCLIC_SYNC_VELOCITY: 8,
    Mode.CYCLIC_SYNC_TORQUE: 9,
}


# ============================================================================ PDO
@dataclass(frozen=True)
class PdoLayout:
    """The packing of a PDO whose mapping lists ``objects`` in order (little-endian, byte
    aligned: every object here is 8, 16 or 32 bits)."""

    objects: tuple[OdObject, ...]
    _fmt: str = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "_fmt", "<" + "".join(o.dtype.fmt for o in self.objects))

    @property
    def size(self) -> int:
        return struct.calcsize(self._fmt)

    @property
    def words(self) -> tuple[int, ...]:
        return tuple(o.mapping_word for o in self.objects)

    def pack(self, values: Sequence[int], what: str = "PDO") -> bytes:
        if len(values) != len(self.objects):
            raise ConfigError(f"{what}.values", values, f"{len(self.objects)} values")
        for o, v in zip(self.objects, values, strict=True):
            lo, hi = o.dtype.range
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
                raise ConfigError(f"{what}.{o.name}", v, f"an integer in {lo}..{hi} "
                                                        f"({o.dtype.name})")
        return struct.pack(self._fmt, *values)

    def unpack(self, data: bytes, what: str = "PDO") -> tuple[int, ...]:
        if len(data) != self.size:
            raise ProtocolError(DEVICE, f"{what} has {len(data)} data bytes, its mapping "
                                        f"({', '.join(o.name for o in self.objects)}) "
                                        f"needs {self.size}")
        return struct.unpack(self._fmt, data)

    @classmethod
    def from_words(cls, words: Iterable[int], direction: str) -> PdoLayout:
        """Layout of a mapping given as mapping entries; raises :class:`ConfigError` naming
        the entry for an unknown object, a wrong length, a wrong direction ("rx"/"tx") or
        more than 64 bits."""
        objs = []
        for word in words:
            index, sub, bits = decode_mapping_word(word)
            o = OBJECTS_BY_ADDRESS.get((index, sub))
            if o is None or o.pdo != direction or o.dtype.bits != bits:
                raise ConfigError("canopen.pdo_mapping", f"0x{word:08X}",
                                  f"a mappable {direction} object with its own length")
            objs.append(o)
        layout = cls(tuple(objs))
        if layout.size > 8:
            raise ConfigError("canopen.pdo_mapping", [f"0x{w:08X}" for w in layout.words],
                              "at most 64 bits per PDO")
        return layout


@dataclass(frozen=True)
class PdoMapping:
    """One PDO of the project's fixed mapping: direction "rx" (to the drive) or "tx" (from
    it), number 1..4, the mapped object names and the transmission type."""

    name: str
    direction: str
    number: int
    object_names: tuple[str, ...]
    transmission_type: int

    @property
    def layout(self) -> PdoLayout:
        return PdoLayout(tuple(obj(n) for n in self.object_names))

    @property
    def function(self) -> str:
        return f"{'RPDO' if self.direction == 'rx' else 'TPDO'}{self.number}"

    @property
    def comm_index(self) -> int:
        return (0x1400 if self.direction == "rx" else 0x1800) + self.number - 1

    @property
    def map_index(self) -> int:
        return self.comm_index + 0x200

    def cob_id(self, node_id: int) -> int:
        return cob_id(self.function, node_id)


RXPDO1 = PdoMapping("RxPDO1", "rx", 1,
                    ("controlword", "target_velocity", "modes_of_operation"), 255)
RXPDO2 = PdoMapping("RxPDO2", "rx", 2, ("target_position", "profile_velocity"), 255)
TXPDO1 = PdoMapping("TxPDO1", "tx", 1,
                    ("statusword", "velocity_actual", "modes_of_operation_display"), 1)
TXPDO2 = PdoMapping("TxPDO2", "tx", 2, ("position_actual", "current_actual_averaged"), 1)
#: The mapping the driver configures, in configuration order.
PROJECT_PDOS: tuple[PdoMapping, ...] = (RXPDO1, RXPDO2, TXPDO1, TXPDO2)


def wrap_i32(value: int) -> int:
    """``value`` wrapped into the INTEGER32 range (how a position counter overflows)."""
    return ((value + (1 << 31)) % (1 << 32)) - (1 << 31)


def unwrap_i32_delta(new: int, old: int) -> int:
    """Signed difference ``new - old`` of two INTEGER32 counter readings across a wrap."""
    return wrap_i32(new - old)
