"""Byte-level tests of the CANopen / CiA 402 tables and codecs (dentibot.io.canopen_protocol).

Expected bytes are written out from CiA 301 / CiA 402 and devices.md, not from the code.
"""

from __future__ import annotations

import struct

import pytest
from hypothesis import given
from hypothesis import strategies as st

from dentibot.errors import ConfigError, ProtocolError
from dentibot.io import canopen_protocol as co
from dentibot.io.canopen_protocol import (
    RXPDO1,
    RXPDO2,
    TXPDO1,
    TXPDO2,
    Command,
    NmtCommand,
    NmtState,
    PdoLayout,
    State,
)

# ---------------------------------------------------------------- COB-IDs


@pytest.mark.parametrize("function, node, expected", [
    ("NMT", 0, 0x000), ("SYNC", 0, 0x080), ("EMCY", 1, 0x081), ("TPDO1", 1, 0x181),
    ("RPDO1", 1, 0x201), ("TPDO2", 1, 0x281), ("RPDO2", 1, 0x301), ("TPDO3", 5, 0x385),
    ("RPDO3", 5, 0x405), ("TPDO4", 127, 0x4FF), ("RPDO4", 127, 0x57F),
    ("SDO_TX", 1, 0x581), ("SDO_RX", 1, 0x601), ("HEARTBEAT", 1, 0x701),
])
def test_cob_ids_follow_the_predefined_connection_set(function, node, expected):
    assert co.cob_id(function, node) == expected
    assert co.classify_cob_id(expected) == (function, node if function not in
                                            ("NMT", "SYNC") else 0)


@pytest.mark.parametrize("bad", [0, 128, -1])
def test_node_id_out_of_range_is_a_config_error(bad):
    with pytest.raises(ConfigError, match="1..127"):
        co.cob_id("TPDO1", bad)


@pytest.mark.parametrize("can_id", [0x7E4, 0x7E5, 0x180, 0x800])
def test_cob_ids_outside_the_set_are_protocol_errors(can_id):
    with pytest.raises(ProtocolError):
        co.classify_cob_id(can_id)


# ---------------------------------------------------------------- NMT, SYNC, heartbeat


def test_nmt_frames():
    assert co.encode_nmt(NmtCommand.START, 1) == b"\x01\x01"
    assert co.encode_nmt(NmtCommand.ENTER_PRE_OPERATIONAL, 1) == b"\x80\x01"
    assert co.encode_nmt(NmtCommand.RESET_NODE, 0) == b"\x81\x00"
    assert co.decode_nmt(b"\x82\x05") == (NmtCommand.RESET_COMMUNICATION, 5)
    with pytest.raises(ProtocolError, match="NMT command 0x03"):
        co.decode_nmt(b"\x03\x01")
    with pytest.raises(ProtocolError, match="3 data bytes"):
        co.decode_nmt(b"\x01\x01\x00")


def test_sync_and_heartbeat():
    assert co.encode_sync() == b""
    assert co.encode_sync(7) == b"\x07"
    assert co.decode_sync(b"") is None and co.decode_sync(b"\x07") == 7
    with pytest.raises(ProtocolError):
        co.decode_sync(b"\x00\x00")
    assert co.decode_heartbeat(b"\x05") is NmtState.OPERATIONAL
    assert co.decode_heartbeat(b"\x85") is NmtState.OPERATIONAL      # toggle bit ignored
    assert co.decode_heartbeat(b"\x7f") is NmtState.PRE_OPERATIONAL
    assert co.decode_heartbeat(b"\x00") is NmtState.BOOT_UP
    with pytest.raises(ProtocolError, match="not an NMT state"):
        co.decode_heartbeat(b"\x06")
    with pytest.raises(ProtocolError, match="2 data bytes"):
        co.decode_heartbeat(b"\x05\x00")


# ---------------------------------------------------------------- EMCY


def test_emcy_decode_and_meaning():
    e = co.decode_emcy(bytes([0x10, 0x23, 0x03, 1, 2, 3, 4, 5]))
    assert (e.code, e.register, e.manufacturer) == (0x2310, 0x03, b"\x01\x02\x03\x04\x05")
    assert e.meaning == "Overcurrent error"
    assert "0x2310" in e.describe() and "current" in e.describe()
    assert co.encode_emcy(0x8611, 0x21) == bytes([0x11, 0x86, 0x21, 0, 0, 0, 0, 0])
    assert co.decode_emcy(bytes(8)).is_reset
    with pytest.raises(ProtocolError, match="EMCY frame has 4"):
        co.decode_emcy(b"\x10\x23\x03\x00")


@pytest.mark.parametrize("code, text", [
    (0x1000, "Generic error"), (0x3210, "Overvoltage error"),
    (0x4210, "Thermal overload error"), (0x8611, "Following error"),
    (0xFF02, "Watchdog error"), (0x1083, "Generic initialization error"),
    (0x2399, "current, device output side"), (0x4299, "device temperature"),
    (0xFF99, "device specific"), (0x8199, "communication"),
])
def test_error_meanings_from_the_table_or_the_cia301_class(code, text):
    assert text in co.error_meaning(code)


def test_error_register_bits_follow_the_code_class():
    assert co.error_register_for(0) == 0
    assert co.error_register_for(0x1000) == 0x01
    assert co.error_register_for(0x2310) == 0x03       # generic + current
    assert co.error_register_for(0x3210) == 0x05       # generic + voltage
    assert co.error_register_for(0x4210) == 0x09       # generic + temperature
    assert co.error_register_for(0x8210) == 0x11       # generic + communication
    assert co.error_register_for(0xFF01) == 0x81       # generic + manufacturer


# ---------------------------------------------------------------- SDO


def test_expedited_sdo_frames_match_cia301():
    # write controlword 0x6040:00 = 0x0006 (2 bytes): 0x2B
    assert co.encode_sdo_download(0x6040, 0, b"\x06\x00") == bytes.fromhex("2B40600006000000")
    # write heartbeat 0x1017 = 100 ms (u16) and a u32 (0x23) and a u8 (0x2F)
    assert co.encode_sdo_download(0x1017, 0, struct.pack("<H", 100))[0] == 0x2B
    assert co.encode_sdo_download(0x1A00, 1, struct.pack("<I", 0x60410010)) == \
        bytes.fromhex("23001A0110004160")
    assert co.encode_sdo_download(0x1A00, 0, b"\x02")[0] == 0x2F
    # read statusword: 0x40 41 60 00
    assert co.encode_sdo_upload(0x6041, 0) == bytes.fromhex("4041600000000000")
    # answers
    up = co.decode_sdo_response(bytes.fromhex("4B41600037040000"))
    assert (up.kind, up.index, up.sub, up.payload, up.size) == ("upload", 0x6041, 0,
                                                                b"\x37\x04", 2)
    assert co.decode_sdo_response(bytes.fromhex("6017100000000000")).kind == "download_ack"
    ab = co.decode_sdo_response(bytes.fromhex("8000200000000206"))
    assert (ab.kind, ab.index, ab.abort_code) == ("abort", 0x2000, 0x06020000)
    assert co.sdo_abort_meaning(ab.abort_code).startswith("object does not exist")
    assert co.encode_sdo_abort(0x2000, 0, 0x06020000) == bytes.fromhex("8000200000000206")
    seg = co.decode_sdo_response(bytes.fromhex("4108100014000000"))
    assert (seg.kind, seg.size, seg.expedited) == ("upload_segmented", 20, False)


def test_sdo_request_decoding_covers_server_side_cases():
    d = co.decode_sdo_request(bytes.fromhex("2B40600006000000"))
    assert (d.kind, d.index, d.sub, d.payload) == ("download", 0x6040, 0, b"\x06\x00")
    nosize = co.decode_sdo_request(bytes.fromhex("2240600006000000"))
    assert nosize.size is None and nosize.payload == b"\x06\x00\x00\x00"
    seg = co.decode_sdo_request(bytes.fromhex("2108100004000000"))
    assert (seg.kind, seg.expedited, seg.size) == ("download", False, 4)
    assert co.decode_sdo_request(bytes.fromhex("4041600000000000")).kind == "upload"
    assert co.decode_sdo_request(bytes.fromhex("6000000000000000")).kind == "other"
    with pytest.raises(ProtocolError, match="7 data bytes"):
        co.decode_sdo_request(bytes(7))
    with pytest.raises(ConfigError):
        co.encode_sdo_download(0x6040, 0, b"12345")


def test_data_types_encode_and_check_ranges():
    assert co.I32.encode(-1) == b"\xff\xff\xff\xff"
    assert co.U16.decode(b"\x37\x04") == 0x0437
    assert co.I8.decode(b"\xfd") == -3
    with pytest.raises(ConfigError, match="0..65535"):
        co.U16.encode(70000)
    with pytest.raises(ProtocolError):
        co.U32.decode(b"\x00\x00")


def test_object_table_holds_the_epos4_objects():
    expect = {"controlword": (0x6040, 0, co.U16), "statusword": (0x6041, 0, co.U16),
              "modes_of_operation": (0x6060, 0, co.I8),
              "modes_of_operation_display": (0x6061, 0, co.I8),
              "target_velocity": (0x60FF, 0, co.I32), "velocity_actual": (0x606C, 0, co.I32),
              "position_actual": (0x6064, 0, co.I32), "target_position": (0x607A, 0, co.I32),
              "target_torque": (0x6071, 0, co.I16), "torque_actual": (0x6077, 0, co.I16),
              "motor_rated_torque": (0x6076, 0, co.U32),
              "current_actual_averaged": (0x30D1, 1, co.I32),
              "motor_torque_constant": (0x3001, 5, co.U32),
              "gear_reduction_numerator": (0x3003, 1, co.U32),
              "error_code": (0x603F, 0, co.U16), "sto_inputs": (0x3202, 1, co.U8)}
    for name, (index, sub, dtype) in expect.items():
        o = co.obj(name)
        assert (o.index, o.sub, o.dtype) == (index, sub, dtype), name
        assert co.OBJECTS_BY_ADDRESS[(index, sub)] is o
    assert (0x6078, 0) not in co.OBJECTS_BY_ADDRESS          # the EPOS4 has no 0x6078
    with pytest.raises(ConfigError):
        co.obj("no_such_object")


# ---------------------------------------------------------------- CiA 402


@pytest.mark.parametrize("statusword, state", [
    (0x0040, State.SWITCH_ON_DISABLED), (0x0021, State.READY_TO_SWITCH_ON),
    (0x0023, State.SWITCHED_ON), (0x0027, State.OPERATION_ENABLED),
    (0x0007, State.QUICK_STOP_ACTIVE), (0x0008, State.FAULT),
    (0x0000, State.NOT_READY_TO_SWITCH_ON), (0x000F, State.FAULT_REACTION_ACTIVE),
    # with the bits a real drive adds: voltage enabled, remote, target reached ...
    (0x0637, State.OPERATION_ENABLED), (0x0250, State.SWITCH_ON_DISABLED),
    (0x0231, State.READY_TO_SWITCH_ON), (0x0218, State.FAULT), (0x1637, State.OPERATION_ENABLED),
])
def test_statusword_masks_give_the_devices_md_states(statusword, state):
    assert co.state_from_statusword(statusword) is state


def test_statusword_matching_no_state_is_a_protocol_error():
    with pytest.raises(ProtocolError, match="0x0001"):
        co.state_from_statusword(0x0001)


@given(st.sampled_from(co.STATUSWORD_STATES), st.integers(0, 0xFFFF))
def test_bits_outside_the_mask_do_not_change_the_state(row, noise):
    mask, value, state = row
    assert co.state_from_statusword(value | (noise & ~mask & 0xFFFF)) is state


@given(st.integers(0, 0xFFFF))
def test_every_statusword_decodes_or_raises_protocol_error(sw):
    try:
        state = co.state_from_statusword(sw)
    except ProtocolError:
        return
    mask, value = next((m, v) for m, v, s in co.STATUSWORD_STATES if s is state)
    assert sw & mask == value


def test_state_bits_of_the_drive_decode_to_the_same_state():
    for state, bits in co.STATE_STATUSWORD.items():
        assert co.state_from_statusword(bits | co.SW_REMOTE | co.SW_VOLTAGE_ENABLED) is state


def test_controlword_values_and_decoding():
    assert co.CONTROLWORD[Command.SHUTDOWN] == 0x06
    assert co.CONTROLWORD[Command.SWITCH_ON] == 0x07
    assert co.CONTROLWORD[Command.ENABLE_OPERATION] == 0x0F
    assert co.CONTROLWORD[Command.QUICK_STOP] == 0x02
    assert co.CONTROLWORD[Command.DISABLE_VOLTAGE] == 0x00
    assert co.CONTROLWORD[Command.FAULT_RESET] == 0x80
    for cmd in (Command.SHUTDOWN, Command.SWITCH_ON, Command.ENABLE_OPERATION,
                Command.QUICK_STOP, Command.DISABLE_VOLTAGE):
        assert co.command_from_controlword(co.CONTROLWORD[cmd]) is cmd
    # profile position bits on top of enable operation still mean enable operation
    assert co.command_from_controlword(0x7F) is Command.ENABLE_OPERATION
    assert co.command_from_controlword(0x80) is None


def test_enable_sequence_and_illegal_transitions():
    s = State.SWITCH_ON_DISABLED
    s, tr = co.apply_controlword(s, 0x06, 0x00)
    assert (s, tr) == (State.READY_TO_SWITCH_ON, "2")
    s, tr = co.apply_controlword(s, 0x07, 0x06)
    assert (s, tr) == (State.SWITCHED_ON, "3")
    s, tr = co.apply_controlword(s, 0x0F, 0x07)
    assert (s, tr) == (State.OPERATION_ENABLED, "4")
    # illegal: enable operation straight from switch on disabled is ignored
    assert co.apply_controlword(State.SWITCH_ON_DISABLED, 0x0F, 0x00) == \
        (State.SWITCH_ON_DISABLED, None)
    # quick stop from operation enabled -> quick stop active (11); disable voltage -> 12
    assert co.apply_controlword(State.OPERATION_ENABLED, 0x02, 0x0F)[0] is \
        State.QUICK_STOP_ACTIVE
    assert co.apply_controlword(State.QUICK_STOP_ACTIVE, 0x00, 0x02) == \
        (State.SWITCH_ON_DISABLED, "12")
    # fault: only a rising edge of bit 7 resets it
    assert co.apply_controlword(State.FAULT, 0x80, 0x00) == (State.SWITCH_ON_DISABLED, "15")
    assert co.apply_controlword(State.FAULT, 0x80, 0x80) == (State.FAULT, None)
    assert co.apply_controlword(State.FAULT, 0x0F, 0x00) == (State.FAULT, None)


@given(st.sampled_from(list(State)), st.integers(0, 0xFFFF), st.integers(0, 0xFFFF))
def test_apply_controlword_only_takes_listed_transitions(state, cw, prev):
    new, tr = co.apply_controlword(state, cw, prev)
    if tr is None:
        assert new is state
    elif tr == "15":
        assert state is State.FAULT and cw & 0x80 and not prev & 0x80
    else:
        assert co.TRANSITIONS[(state, co.command_from_controlword(cw))] == (new, tr)


def test_enable_step_table_walks_to_operation_enabled():
    s = State.SWITCH_ON_DISABLED
    for _ in range(5):
        cmd = co.ENABLE_STEP[s]
        if cmd is None:
            break
        s, _ = co.apply_controlword(s, co.CONTROLWORD[cmd], 0)
    assert s is State.OPERATION_ENABLED
    s, _ = co.apply_controlword(State.QUICK_STOP_ACTIVE,
                                co.CONTROLWORD[co.ENABLE_STEP[State.QUICK_STOP_ACTIVE]], 0)
    assert s is State.SWITCH_ON_DISABLED


# ---------------------------------------------------------------- PDO


def test_project_pdo_mapping_bytes():
    assert RXPDO1.layout.size == 7 and RXPDO2.layout.size == 8
    assert TXPDO1.layout.size == 7 and TXPDO2.layout.size == 8
    assert RXPDO1.layout.words == (0x60400010, 0x60FF0020, 0x60600008)
    assert RXPDO2.layout.words == (0x607A0020, 0x60810020)
    assert TXPDO1.layout.words == (0x60410010, 0x606C0020, 0x60610008)
    assert TXPDO2.layout.words == (0x60640020, 0x30D10120)
    assert (RXPDO1.comm_index, RXPDO1.map_index, RXPDO1.cob_id(1)) == (0x1400, 0x1600, 0x201)
    assert (TXPDO2.comm_index, TXPDO2.map_index, TXPDO2.cob_id(1)) == (0x1801, 0x1A01, 0x281)
    # controlword 0x000F, 6700 rpm (100 rpm at the file x 67), mode 3
    assert RXPDO1.layout.pack((0x0F, 6700, 3)) == bytes([0x0F, 0, 0x2C, 0x1A, 0, 0, 3])
    # statusword 0x0637, -4020 rpm, mode 3
    assert TXPDO1.layout.unpack(bytes([0x37, 0x06, 0x4C, 0xF0, 0xFF, 0xFF, 3])) == \
        (0x0637, -4020, 3)
    assert TXPDO2.layout.unpack(struct.pack("<ii", -381, 50)) == (-381, 50)


def test_pdo_wrong_length_and_bad_values():
    with pytest.raises(ProtocolError, match="TxPDO1 has 3 data bytes.*needs 7"):
        TXPDO1.layout.unpack(b"\x37\x06\x00", "TxPDO1")
    with pytest.raises(ProtocolError):
        TXPDO2.layout.unpack(bytes(9))
    with pytest.raises(ConfigError, match="target_velocity"):
        RXPDO1.layout.pack((0x0F, 2**31, 3))
    with pytest.raises(ConfigError):
        RXPDO1.layout.pack((0x0F, 0))


def test_layout_from_mapping_words_checks_objects_and_length():
    lay = PdoLayout.from_words([0x60410010, 0x60640020], "tx")
    assert [o.name for o in lay.objects] == ["statusword", "position_actual"]
    with pytest.raises(ConfigError):                  # controlword is not a TxPDO object
        PdoLayout.from_words([0x60400010], "tx")
    with pytest.raises(ConfigError):                  # wrong length for 0x6041
        PdoLayout.from_words([0x60410020], "tx")
    with pytest.raises(ConfigError, match="64 bits"):
        PdoLayout.from_words([0x60640020, 0x606C0020, 0x60410010], "tx")
    assert co.decode_mapping_word(0x30D10120) == (0x30D1, 1, 32)


def test_i32_wrap_and_unwrap():
    assert co.wrap_i32(2**31) == -(2**31)
    assert co.wrap_i32(-(2**31) - 1) == 2**31 - 1
    assert co.unwrap_i32_delta(-(2**31) + 5, 2**31 - 5) == 10


# ---------------------------------------------------------------- fuzz: never crash untyped

_DECODERS = [co.decode_nmt, co.decode_sync, co.decode_heartbeat, co.decode_emcy,
             co.decode_sdo_request, co.decode_sdo_response,
             TXPDO1.layout.unpack, TXPDO2.layout.unpack, RXPDO1.layout.unpack,
             RXPDO2.layout.unpack]


@given(st.sampled_from(_DECODERS), st.binary(max_size=12))
def test_decoders_return_or_raise_protocol_error(decoder, data):
    try:
        decoder(data)
    except ProtocolError as exc:
        assert exc.device == co.DEVICE


@given(st.binary(min_size=8, max_size=8))
def test_any_8_byte_sdo_frame_decodes(data):
    for f in (co.decode_sdo_request(data), co.decode_sdo_response(data)):
        assert f.index == data[1] | data[2] << 8 and f.sub == data[3]
        assert len(f.payload) <= 4


@given(st.integers(0, 0xFFFF), st.integers(0, 0xFF), st.binary(min_size=5, max_size=5))
def test_emcy_round_trip(code, register, mfr):
    e = co.decode_emcy(co.encode_emcy(code, register, mfr))
    assert (e.code, e.register, e.manufacturer) == (code, register, mfr)
    assert isinstance(e.meaning, str) and e.meaning


@given(st.integers(0, 0xFFFF), st.integers(0, 0xFF), st.binary(min_size=1, max_size=4))
def test_sdo_expedited_round_trip(index, sub, payload):
    req = co.decode_sdo_request(co.encode_sdo_download(index, sub, payload))
    assert (req.kind, req.index, req.sub, req.payload) == ("download", index, sub, payload)
    resp = co.decode_sdo_response(co.encode_sdo_upload_ack(index, sub, payload))
    assert (resp.kind, resp.payload) == ("upload", payload)
