"""Meca500 text API: code table, framing, command and response encoding, byte by byte."""

from __future__ import annotations

import math

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dentibot.control.kinematics import (
    MECA500_JOINT_LIMITS_DEG,
    MECA500_JOINT_SPEED_LIMITS_DEG_S,
)
from dentibot.errors import ConfigError, ProtocolError
from dentibot.io.meca500_protocol import (
    COMMANDS,
    JOINT_LIMITS_DEG,
    JOINT_SPEED_LIMITS_DEG_S,
    RESPONSE_CODES,
    RT_VALUE_COUNTS,
    Command,
    CommandError,
    FrameSplitter,
    Response,
    RobotStatus,
    decode_command,
    decode_response,
    decode_rt,
    describe_code,
    encode_command,
    encode_response,
    encode_rt,
    is_number,
    kind_of,
)

# Every code devices.md names, plus a few from the programming manual / mecademicpy.
DEVICES_MD_CODES = (
    1005, 1006, 1007, 1011, 1012, 1016, 2000, 2002, 2004, 2005, 2006, 2007, 2026, 2027, 2042,
    2043, 2044, 2081, 2082, 2083, 2096, 2097, 2116, 2117, 2177, 2200, 2201, 2210, 2211, 2212,
    2213, 2230, 3000, 3001, 3012, 3030, 3040,
)
MANUAL_CODES = (1000, 1001, 1002, 1003, 3005, 3026, 3003)


# ------------------------------------------------------------------------- code table
def test_code_table_has_every_named_code_with_its_kind():
    for code in DEVICES_MD_CODES + MANUAL_CODES:
        info = RESPONSE_CODES[code]
        assert info.code == code and info.name and info.meaning
        assert info.kind == {1: "error", 2: "response", 3: "status"}[code // 1000]
        assert info.kind == kind_of(code)


def test_code_table_meanings_are_the_manuals():
    assert RESPONSE_CODES[1005].meaning == "The robot is not activated."
    assert RESPONSE_CODES[1006].meaning == "The robot is not homed."
    assert RESPONSE_CODES[1011].meaning == "The robot is already in error."
    assert RESPONSE_CODES[2044].meaning == "The motion was cleared."
    assert "1007" in describe_code(1007) and "over limit" in describe_code(1007).lower()
    assert describe_code(4242) == "[4242] unknown code"
    # errors during execution put the robot in error mode; refusals do not
    assert {c for c, i in RESPONSE_CODES.items() if i.latches} >= {1007, 1012, 1016}
    assert not any(RESPONSE_CODES[c].latches for c in (1000, 1001, 1002, 1003, 1005, 1006))


def test_command_table_covers_devices_md():
    for name in ("ActivateRobot", "Home", "DeactivateRobot", "ResetError", "GetStatusRobot",
                 "PauseMotion", "ResumeMotion", "ClearMotion", "GetJoints", "GetPose",
                 "GetFwVersion", "GetFwVersionFull", "GetRobotSerial", "GetMonitoringInterval",
                 "SetMonitoringInterval", "GetRealTimeMonitoring", "SetRealTimeMonitoring",
                 "SetCtrlPortMonitoring", "SyncCmdQueue", "ConnectionWatchdog", "SetRtc",
                 "MoveJoints", "MoveJointsVel", "SetVelTimeout", "SetCheckpoint"):
        assert COMMANDS[name.lower()].name == name
    assert COMMANDS["activaterobot"].answers[0] == 2000
    assert COMMANDS["resumemotion"].answers == (2043,)
    assert COMMANDS["movejointsvel"].answers == () and COMMANDS["movejointsvel"].queued
    assert COMMANDS["movejoints"].nargs == (6, 6)


def test_limit_tables_agree_with_the_kinematics():
    assert JOINT_LIMITS_DEG == MECA500_JOINT_LIMITS_DEG
    assert JOINT_SPEED_LIMITS_DEG_S == MECA500_JOINT_SPEED_LIMITS_DEG_S
    assert JOINT_LIMITS_DEG[1] == (-70.0, 90.0) and JOINT_SPEED_LIMITS_DEG_S[5] == 500.0


# ---------------------------------------------------------------------------- framing
def test_splitter_nul_and_newline_and_several_frames_per_read():
    s = FrameSplitter()
    assert s.feed(b"[2000][Motors activated.]\0[2002][Homing done.]\n") == [
        b"[2000][Motors activated.]", b"[2002][Homing done.]"]
    assert s.feed(b"GetJoints\r\n") == [b"GetJoints"]     # CR-LF works too
    assert s.frames == 3


def test_splitter_split_reads_byte_by_byte():
    s = FrameSplitter()
    out = []
    for b in b"[2026][1,2,3,4,5,6]\0[2230][1]\0":
        out += s.feed(bytes([b]))
    assert out == [b"[2026][1,2,3,4,5,6]", b"[2230][1]"]
    assert s.pending == 0


def test_splitter_ignores_empty_frames():
    s = FrameSplitter()
    assert s.feed(b"\0\0\n \0GetJoints\0\0") == [b"GetJoints"]
    assert s.empty == 5


def test_splitter_oversized_garbage_is_a_counted_error_and_resynchronises():
    s = FrameSplitter(max_len=32)
    out = s.feed(b"x" * 100 + b"\0GetJoints\0")
    assert isinstance(out[0], ProtocolError) and "32" in str(out[0])
    assert out[1:] == [b"GetJoints"]
    # oversized across reads: one error, then discard up to the terminator
    out = s.feed(b"y" * 20) + s.feed(b"y" * 20) + s.feed(b"y" * 200) + s.feed(b"yy\0Home\0")
    assert [type(o) for o in out] == [ProtocolError, bytes] and out[1] == b"Home"
    assert s.oversized == 2 and s.pending == 0


@settings(max_examples=100, deadline=None)
@given(frames=st.lists(st.binary(min_size=1, max_size=40).map(
    lambda b: b.replace(b"\0", b"a").replace(b"\n", b"b").strip() or b"z"), max_size=12),
    cuts=st.lists(st.integers(min_value=0, max_value=600), max_size=12),
    term=st.sampled_from([b"\0", b"\n"]))
def test_splitter_any_chunking_gives_the_same_frames(frames, cuts, term):
    stream = b"".join(f + term for f in frames)
    s = FrameSplitter()
    out, prev = [], 0
    for c in sorted(c % (len(stream) + 1) for c in cuts) + [len(stream)]:
        out += s.feed(stream[prev:c])
        prev = c
    assert out == [f.strip() for f in frames if f.strip()]


@settings(max_examples=300, deadline=None)
@given(data=st.lists(st.binary(max_size=300), max_size=10))
def test_splitter_survives_garbage(data):
    s = FrameSplitter(max_len=64)
    for chunk in data:
        for item in s.feed(chunk):
            assert isinstance(item, ProtocolError) or (isinstance(item, bytes)
                                                       and 0 < len(item) <= 64)
        assert s.pending <= 64


# --------------------------------------------------------------------------- commands
def test_encode_command_bytes():
    assert encode_command("GetJoints") == b"GetJoints\0"
    assert encode_command("GetRobotSerial", silent=True) == b"-GetRobotSerial\0"
    assert encode_command("MoveJointsVel", 1, 2.5, -3.0, 0.0, 0.125, -0.000001) == \
        b"MoveJointsVel(1,2.5,-3,0,0.125,-0.000001)\0"
    assert encode_command("SetVelTimeout", 0.01) == b"SetVelTimeout(0.01)\0"


def test_encode_command_refuses_non_finite_or_non_numbers():
    for bad in (math.nan, math.inf, -math.inf, "1", True, None):
        with pytest.raises(ConfigError, match=r"args\[1\]"):
            encode_command("MoveJointsVel", 0.0, bad, 0, 0, 0, 0)


def test_numbers_of_every_kind_a_caller_holds_encode_alike():
    """numpy's scalars (what a velocity array yields), Python's ints and floats and other
    real numbers encode to the same text; bools (numpy's too) are not numbers."""
    from fractions import Fraction

    import numpy as np
    for x, text in ((np.float64(2.5), "2.5"), (2.5, "2.5"), (np.float32(0.5), "0.5"),
                    (np.int64(-3), "-3"), (-3, "-3"), (Fraction(1, 4), "0.25"),
                    (np.float64(-0.0), "0"), (1e-7, "0")):
        assert is_number(x), x
        assert encode_command("SetVelTimeout", x) == f"SetVelTimeout({text})".encode() + b"\0"
    for bad in (True, np.bool_(True), "1", None, 1j):
        assert not is_number(bad), bad
        with pytest.raises(ConfigError, match=r"args\[0\]"):
            encode_command("SetVelTimeout", bad)


def test_encode_command_refuses_bad_names():
    for name in ("", "Move Joints", "MoveJoints(1)", "1abc", "Get\0Joints"):
        with pytest.raises(ConfigError):
            encode_command(name)


def test_decode_command_variants():
    assert decode_command(b"MoveJointsVel(1,2.5,-3,0,0,0)") == Command(
        "MoveJointsVel", (1.0, 2.5, -3.0, 0.0, 0.0, 0.0))
    c = decode_command(b"-movejointsvel( 1 , 2 ,3,4,5,6 )")
    assert c.silent and c.key == "movejointsvel" and c.spec is COMMANDS["movejointsvel"]
    assert c.args == (1.0, 2.0, 3.0, 4.0, 5.0, 6.0)
    assert decode_command(b"Home") == decode_command(b"Home()") == Command("Home")
    assert decode_command(b"GETJOINTS").spec.name == "GetJoints"
    assert decode_command(b"") is None and decode_command(b"  ") is None
    assert decode_command(b"Frobnicate").spec is None     # syntax fine; the robot says 1001


def test_decode_command_errors_carry_the_robots_code():
    for text, code in [
        (b"MoveJoints(1,2", 1002), (b"MoveJoints(1,,2)", 1002), (b"MoveJoints((1)", 1002),
        (b"Home)", 1002), (b"Move,Joints", 1002), (b"MoveJoints(a,b)", 1003),
        (b"SetVelTimeout(nan)", 1003), (b"SetVelTimeout(inf)", 1003), (b"(1,2)", 1001),
        (b"Move Joints(1)", 1001), (b"[2000][x]", 1001), (b"\xff\xfe", 1001), (b"-", 1001),
    ]:
        with pytest.raises(CommandError) as exc:
            decode_command(text)
        assert exc.value.code == code and isinstance(exc.value, ProtocolError), text
        assert str(code) in str(exc.value)


finite = st.floats(min_value=-1e5, max_value=1e5, allow_nan=False, allow_infinity=False)


@settings(max_examples=100, deadline=None)
@given(name=st.sampled_from([s.name for s in COMMANDS.values()]),
       args=st.lists(finite, max_size=7), silent=st.booleans())
def test_command_round_trip(name, args, silent):
    frame = encode_command(name, *args, silent=silent)
    assert frame.endswith(b"\0") and frame.count(b"\0") == 1
    c = decode_command(frame[:-1])
    assert c.name == name and c.silent == silent and len(c.args) == len(args)
    for a, b in zip(c.args, args):
        assert a == pytest.approx(b, abs=1e-6)        # 6 decimals on the wire


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=80))
def test_decode_command_fuzz_only_typed_errors(data):
    try:
        c = decode_command(data)
    except CommandError as exc:
        assert exc.code in (1001, 1002, 1003)
    else:
        assert c is None or (c.name and all(math.isfinite(a) for a in c.args))


# -------------------------------------------------------------------------- responses
def test_response_bytes_and_decoding():
    assert encode_response(3000, "Connected to Meca500 R3 v9.3.0") == \
        b"[3000][Connected to Meca500 R3 v9.3.0]\0"
    assert encode_response(2007, "1,1,0,0,0,1,1") == b"[2007][1,1,0,0,0,1,1]\0"
    r = decode_response(b"[2026][0.1,-20,30.5,0,90,0]")
    assert r == Response(2026, "0.1,-20,30.5,0,90,0") and r.kind == "response"
    assert r.values() == (0.1, -20.0, 30.5, 0.0, 90.0, 0.0)
    # the payload may contain brackets (the robot echoes a bad command)
    r = decode_response(b"[1001][Empty command or command unrecognized. - Command: 'x[1]']")
    assert r.code == 1001 and r.payload.endswith("'x[1]'") and r.info.name == "UNKNOWN_COMMAND"
    assert decode_response(b"[2044][]").payload == ""


def test_decode_response_garbage_and_truncation_are_protocol_errors():
    for bad in (b"", b"[20", b"[2000]", b"[2000][x", b"2000][x]", b"[200][x]", b"[20000][x]",
                b"[abcd][x]", b"garbage", b"\xff[2000][x]"):
        with pytest.raises(ProtocolError):
            decode_response(bad)


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=80))
def test_decode_response_fuzz_only_typed_errors(data):
    try:
        r = decode_response(data)
    except ProtocolError:
        return
    assert 0 <= r.code <= 9999


def test_response_values_errors_name_the_code():
    with pytest.raises(ProtocolError, match=r"\[2026\].*'x'"):
        decode_response(b"[2026][1,x,3]").values()
    with pytest.raises(ProtocolError, match="not finite"):
        decode_response(b"[2026][1,nan,3]").values()


def test_encode_response_refuses_terminators_in_payload():
    with pytest.raises(ConfigError):
        encode_response(2000, "a\0b")
    with pytest.raises(ConfigError):
        encode_response(12345, "")


# ------------------------------------------------------------------------------ status
def test_status_payload():
    s = RobotStatus.from_payload("1,1,0,0,1,0,1")
    assert (s.activated, s.homed, s.sim_mode, s.error, s.paused, s.eob, s.eom) == \
        (True, True, False, False, True, False, True)
    assert s.to_payload() == "1,1,0,0,1,0,1"
    assert RobotStatus.from_payload("1,1,2,0,0,1,1").sim_mode      # newer firmware's sm


def test_status_payload_errors():
    for bad in ("1,1,0,0,0,1", "1,1,0,0,0,1,1,1", "1,2,0,0,0,1,1", "a,1,0,0,0,1,1", "",
                "1,1,0,0,0,1,"):
        with pytest.raises(ProtocolError, match="2007"):
            RobotStatus.from_payload(bad)


# -------------------------------------------------------------------------- monitoring
def test_rt_records():
    frame = encode_rt(2210, 1234567, (1.5, -2, 3, 4, 5, 6))
    assert frame == b"[2210][1234567,1.5,-2,3,4,5,6]\0"
    rec = decode_rt(decode_response(frame[:-1]))
    assert rec.code == 2210 and rec.timestamp_us == 1234567
    assert rec.values == (1.5, -2.0, 3.0, 4.0, 5.0, 6.0)
    end = decode_rt(decode_response(encode_rt(2230, 42)[:-1]))
    assert end.timestamp_us == 42 and end.values == ()
    assert RT_VALUE_COUNTS[2200] == RT_VALUE_COUNTS[2212] == 6


def test_rt_record_errors():
    for bad in (b"[2200][1,2,3]", b"[2200][x,1,2,3,4,5,6]", b"[2200][1.5,1,2,3,4,5,6]",
                b"[2200][]", b"[2230][12,1]", b"[2212][1,1,2,3,4,5,y]"):
        with pytest.raises(ProtocolError):
            decode_rt(decode_response(bad))


def test_encode_rt_checks_the_count():
    with pytest.raises(ConfigError):
        encode_rt(2200, 1, (1, 2, 3))
