"""CiA 406 (CANopen device profile for encoders), as the patient tracker's draw-wire encoders
use it. Data tables only; framing is :mod:`dentibot.io.canopen_protocol`'s.

A draw-wire encoder is a multi-turn absolute rotary encoder on the wire's drum: device type
0x1000 = 0x0002_0196 (profile 406 in the low word, type 2 "multi-turn absolute rotary" in
the high word). With the scaling function on (0x6000 bit 2) the position value 0x6004 counts
measuring units, ``measuring units per revolution`` 0x6001 of them per drum turn, and wraps
at the ``total measuring range`` 0x6002. The preset 0x6003 sets the position value now.

The project's mapping (configured over SDO in PRE-OPERATIONAL by the driver)::

    TPDO1 0x180+id  position value 0x6004 u32 (measuring units)   4 bytes, type n (1..240:
                                                                   every n-th SYNC)

Objects 0x6500-0x650B are the profile's diagnostics (operating status, alarms, warnings,
serial number). Which of them a given encoder implements is the vendor's choice; the driver
reads only 0x1000, 0x1018, 0x6000-0x6002 and the PDO parameters.
"""

from __future__ import annotations

from dentibot.errors import ConfigError
from dentibot.io import canopen_protocol as co
from dentibot.io.canopen_protocol import U16, U32, OdObject, PdoLayout

#: Device name used in errors raised about the encoders.
DEVICE = "tracker"
#: CiA 406 in the low word of 0x1000.
PROFILE = 406
#: Device type 0x1000: multi-turn absolute rotary encoder (the draw-wire drum), profile 406.
DEVICE_TYPE_MULTITURN = 0x0002_0000 | PROFILE
#: 0x6000 bit 2: scaling function control (1 = 0x6001/0x6002 apply).
OPERATING_SCALING = 0x0004
#: 0x6000 bit 0: code sequence (0 = counts up clockwise, seen on the drum's shaft).
OPERATING_CODE_SEQUENCE = 0x0001

ENCODER_OBJECTS: tuple[OdObject, ...] = (
    OdObject("operating_parameters", 0x6000, 0, U16, "rw",
             note="bit 0 code sequence, bit 2 scaling function control",
             label="Operating parameters"),
    OdObject("measuring_units_per_revolution", 0x6001, 0, U32, "rw", unit="units/rev",
             label="Measuring units per revolution"),
    OdObject("total_measuring_range", 0x6002, 0, U32, "rw", unit="units",
             label="Total measuring range in measuring units"),
    OdObject("preset_value", 0x6003, 0, U32, "rw", unit="units", label="Preset value"),
    OdObject("position_value", 0x6004, 0, U32, "ro", "tx", unit="units",
             label="Position value"),
    OdObject("encoder_operating_status", 0x6500, 0, U16, "ro", label="Operating status"),
    OdObject("singleturn_resolution", 0x6501, 0, U32, "ro", unit="units/rev",
             label="Single-turn resolution"),
    OdObject("number_of_revolutions", 0x6502, 0, U16, "ro",
             label="Number of distinguishable revolutions"),
    OdObject("encoder_alarms", 0x6503, 0, U16, "ro", label="Alarms"),
    OdObject("encoder_warnings", 0x6505, 0, U16, "ro", label="Warnings"),
    OdObject("encoder_serial_number", 0x650B, 0, U32, "ro", label="Serial number"),
)
#: The CiA 301 objects the encoders answer (shared definitions).
COMMUNICATION_OBJECTS: tuple[OdObject, ...] = tuple(co.obj(n) for n in (
    "device_type", "error_register", "producer_heartbeat_time", "identity_count",
    "vendor_id", "product_code", "revision_number", "serial_number",
    "tpdo1_highest_sub", "tpdo1_cob_id", "tpdo1_transmission_type", "tpdo1_inhibit_time",
    "tpdo1_event_timer", "tpdo1_mapped_count", *(f"tpdo1_mapping_{s}" for s in range(1, 9))))

OBJECTS: dict[str, OdObject] = {o.name: o for o in COMMUNICATION_OBJECTS + ENCODER_OBJECTS}
OBJECTS_BY_ADDRESS: dict[tuple[int, int], OdObject] = {o.address: o for o in OBJECTS.values()}

#: TPDO1: the position value, 32 bits.
POSITION_TPDO = PdoLayout((OBJECTS["position_value"],))
#: 0x1A00:01 of the project's mapping.
POSITION_MAPPING_WORD = OBJECTS["position_value"].mapping_word


def obj(name: str) -> OdObject:
    """The encoder object called ``name``."""
    try:
        return OBJECTS[name]
    except KeyError:
        raise ConfigError("cia406.object", name, f"one of {sorted(OBJECTS)}") from None


__all__ = ["COMMUNICATION_OBJECTS", "DEVICE", "DEVICE_TYPE_MULTITURN", "ENCODER_OBJECTS",
           "OBJECTS", "OBJECTS_BY_ADDRESS", "OPERATING_CODE_SEQUENCE", "OPERATING_SCALING",
           "POSITION_MAPPING_WORD", "POSITION_TPDO", "PROFILE", "obj"]
