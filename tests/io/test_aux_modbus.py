"""Auxiliary I/O over Modbus TCP: register map, driver against the simulator on loopback, raw
MBAP bytes, a plain pymodbus client reading the documented addresses, and misbehaving devices.

Expected numbers come from the Modbus spec (MBAP layout, exception codes), the documented map,
two's complement arithmetic, and the World's physics (a 500 Hz step counter; the thesis's
square moving the phantom at 3 mm/s along x), never from what the code printed.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import re
import socket
import struct
import time
from pathlib import Path

import numpy as np
import pytest
from silent_peer import silent_peer
from hypothesis import given, settings
from hypothesis import strategies as st
from pymodbus.client import AsyncModbusTcpClient
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from dentibot.errors import ConfigError, DeviceFault, ProtocolError
from dentibot.io import AuxIO
from dentibot.io.aux_modbus import AuxModbusDriver, WatchdogOverwritten
from dentibot.io.tasks import cancel_until_done
from dentibot.io.aux_registers import (
    INDICATORS,
    REGISTER_MAP,
    AuxInputs,
    Kind,
    Point,
    Table,
    check_map,
    decode_bits,
    decode_inputs,
    decode_setpoint,
    doc_rows,
    encode_inputs,
    encode_setpoint,
    int32_to_words,
    words_to_int32,
)
from dentibot.io.interfaces import ConnectTimeout
from dentibot.sim import RealTimeStepper, World, WorldConfig
from dentibot.sim.aux_modbus_server import AuxModbusServer

DOC = Path(__file__).resolve().parents[2] / "docs" / "aux-io-register-map.md"
LOCAL = "127.0.0.1"

pytestmark = [pytest.mark.wire, pytest.mark.timeout(30)]


# ---------------------------------------------------------------------------- helpers
@contextlib.asynccontextmanager
async def rig(world: World | None = None, step: bool = True):
    """A simulator on an ephemeral loopback port, its World stepped in real time."""
    world = world or World(WorldConfig())
    server = AuxModbusServer(world, port=0)
    stepper = _Stepper(world)
    await server.start()
    try:
        if step:
            stepper.start()
        yield world, server, stepper
    finally:
        await stepper.stop()
        await server.close()


class _Stepper:
    def __init__(self, world: World) -> None:
        self.world = world
        self.task: asyncio.Task | None = None
        self.halt = asyncio.Event()

    def start(self) -> None:
        self.halt = asyncio.Event()
        self.task = asyncio.create_task(RealTimeStepper(self.world).run(self.halt))

    async def stop(self) -> None:
        if self.task is not None:
            self.halt.set()
            await self.task
            self.task = None


def driver(port: int, **kw) -> AuxModbusDriver:
    # stale_after_s generous: these tests must not fail because a busy machine stalled the loop
    kw = {"stale_after_s": 1.0, "reconnect_period_s": 0.05} | kw
    return AuxModbusDriver(LOCAL, port, **kw)


async def sample_where(drv: AuxModbusDriver, pred, timeout: float = 5.0):
    """The first fresh sample satisfying ``pred`` (faults while waiting are retried)."""
    loop = asyncio.get_running_loop()
    end = loop.time() + timeout
    while loop.time() < end:
        with contextlib.suppress(DeviceFault):
            s = await drv.read()
            if pred(s):
                return s
        await asyncio.sleep(0.002)
    raise AssertionError("condition not met in time")


async def fault_within(drv: AuxModbusDriver, timeout: float = 5.0) -> DeviceFault:
    loop = asyncio.get_running_loop()
    end = loop.time() + timeout
    while loop.time() < end:
        try:
            await drv.read()
        except DeviceFault as exc:
            return exc
        await asyncio.sleep(0.005)
    raise AssertionError("no DeviceFault in time")


def free_port() -> int:
    with socket.socket() as s:
        s.bind((LOCAL, 0))
        return s.getsockname()[1]


def documented_rows() -> list[tuple[str, ...]]:
    """The rows of the register table in docs/aux-io-register-map.md, as written."""
    text = DOC.read_text()
    section = text.split("## The map", 1)[1].split("\n## ", 1)[0]
    rows = []
    for line in section.splitlines():
        if line.startswith("|") and not line.startswith("| ---") and "| table |" not in line:
            rows.append(tuple(c.strip() for c in line.strip().strip("|").split("|")))
    return rows


# ---------------------------------------------------------------------------- the map
def test_document_matches_the_table_row_for_row():
    rows = documented_rows()
    assert rows == doc_rows()
    # every point of the map is documented, and the doc's address column is the table's
    named = {(r[0], r[3]): r[1] for r in rows}
    for p in REGISTER_MAP:
        addr = named[(str(p.table), p.name)]
        assert int(addr.split("-")[0]) == p.address


def test_map_check_rejects_overlaps_gaps_and_duplicates():
    check_map(REGISTER_MAP)
    a = Point(Table.INPUT_REGISTER, 0, "a", Kind.I32, "")
    with pytest.raises(ConfigError, match="address"):
        check_map((a, Point(Table.INPUT_REGISTER, 1, "b", Kind.U16, "")))    # overlaps a
    with pytest.raises(ConfigError, match="address"):
        check_map((a, Point(Table.INPUT_REGISTER, 3, "b", Kind.U16, "")))    # gap at 2
    with pytest.raises(ConfigError, match="unique"):
        check_map((a, Point(Table.INPUT_REGISTER, 2, "a", Kind.U16, "")))
    with pytest.raises(ConfigError, match="kind"):
        check_map((Point(Table.COIL, 0, "c", Kind.U16, ""),))


def test_int32_is_twos_complement_high_word_first_on_the_wire():
    words = encode_setpoint((1.0, -0.01, 25.0))          # 100, -1, 2500 counts of 0.01 mm
    assert words == [0x0000, 0x0064, 0xFFFF, 0xFFFF, 0x0000, 0x09C4]
    assert struct.pack(">6H", *words) == bytes.fromhex("00000064ffffffff000009c4")
    assert decode_setpoint(words) == (1.0, -0.01, 25.0)
    # pymodbus's own converter (big word order, the documented one) agrees
    conv = AsyncModbusTcpClient.convert_to_registers
    for v in (-250, 0, 1, -(1 << 31), (1 << 31) - 1, 123456):
        assert int32_to_words(v) == conv(v, AsyncModbusTcpClient.DATATYPE.INT32)


def test_setpoint_checks_name_axis_value_and_limit():
    with pytest.raises(ConfigError) as e:
        encode_setpoint((0.0, 25.01, 0.0))
    assert e.value.field == "platform_setpoint.y" and e.value.value == 25.01
    assert "25" in e.value.limit and "mm" in e.value.limit
    with pytest.raises(ConfigError, match="platform_setpoint.x"):
        encode_setpoint((math.nan, 0, 0))
    with pytest.raises(ConfigError, match="platform_setpoint.z"):
        encode_setpoint((0, 0, -math.inf))
    for bad in ((1.0, 2.0), (1, 2, 3, 4), "abc", None, 3.0):
        with pytest.raises(ConfigError, match="platform_setpoint"):
            encode_setpoint(bad)


@settings(max_examples=300, deadline=None)
@given(st.lists(st.integers(min_value=-(1 << 20), max_value=1 << 20), max_size=16))
def test_decode_inputs_never_crashes_on_any_register_list(words):
    try:
        inp = decode_inputs(words)
    except ProtocolError as exc:
        assert exc.device == "aux-modbus"
        assert len(words) != 11 or any(not 0 <= w <= 0xFFFF for w in words)
    else:
        assert len(words) == 11 and isinstance(inp, AuxInputs)


c32 = st.integers(min_value=-(1 << 31), max_value=(1 << 31) - 1)


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 1 << 20), st.booleans(), st.booleans(), st.booleans(), st.booleans(),
       st.booleans(), st.tuples(c32, c32, c32))
def test_inputs_round_trip(hb, pedal, estop, moving, fault, rejected, counts):
    mm = tuple(c / 100 for c in counts)
    words = encode_inputs(heartbeat=hb, pedal=pedal, estop=estop, platform_mm=mm,
                          platform_moving=moving, platform_fault=fault,
                          setpoint_rejected=rejected)
    assert all(0 <= w <= 0xFFFF for w in words) and words[:2] == [0x4442, 0x0101]
    inp = decode_inputs(words)
    assert inp == AuxInputs(0x4442, 0x0101, hb % 65536, pedal, estop, moving, fault, rejected,
                            mm)
    assert inp.identity_ok


@settings(max_examples=300, deadline=None)
@given(st.tuples(*[st.floats(allow_nan=True, allow_infinity=True, width=64)] * 3))
def test_setpoint_round_trip_or_config_error(mm):
    inside = all(math.isfinite(v) and -25.0 <= v <= 25.0 for v in mm)
    if not inside:
        with pytest.raises(ConfigError, match=r"platform_setpoint\.[xyz]"):
            encode_setpoint(mm)
        return
    back = decode_setpoint(encode_setpoint(mm))
    assert all(abs(b - v) <= 0.005 + 1e-12 for b, v in zip(back, mm, strict=True))


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 0xFFFF), st.integers(0, 0xFFFF))
def test_int32_words_invert(hi, lo):
    v = words_to_int32(hi, lo)
    assert -(1 << 31) <= v < (1 << 31)
    assert int32_to_words(v) == [hi, lo]


def test_short_bit_image_is_a_protocol_error():
    with pytest.raises(ProtocolError):
        decode_bits(Table.COIL, [True, False])
    assert decode_bits(Table.COIL, [False, True, False, False] + [True] * 4)["drilling"]


# ---------------------------------------------------------------------------- raw MBAP bytes
def mbap(tid: int, unit: int, pdu: bytes) -> bytes:
    """Modbus TCP ADU: transaction id, protocol 0, length (unit + PDU), unit, PDU."""
    return struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu


async def exchange(reader, writer, frame: bytes, split: int | None = None) -> bytes:
    if split is None:
        writer.write(frame)
    else:                                   # a request arriving in two TCP segments
        writer.write(frame[:split])
        await writer.drain()
        await asyncio.sleep(0.02)
        writer.write(frame[split:])
    await writer.drain()
    head = await asyncio.wait_for(reader.readexactly(6), 5.0)
    return head + await asyncio.wait_for(reader.readexactly(struct.unpack(">H", head[4:])[0]),
                                         5.0)


async def test_simulator_speaks_mbap_byte_for_byte_and_survives_bad_bytes():
    async with rig(step=False) as (world, server, _):
        world.run(0.02)                                     # 10 steps: heartbeat = 10
        r, w = await asyncio.open_connection(LOCAL, server.port)
        try:
            # FC4, IR 0..2, split inside the MBAP header
            req = mbap(0x1234, 1, struct.pack(">BHH", 4, 0, 3))
            assert await exchange(r, w, req, split=3) == bytes.fromhex(
                "1234 0000 0009 01 04 06 4442 0101 000a".replace(" ", ""))
            # beyond the map: exception 2 (illegal data address)
            req = mbap(0x1235, 1, struct.pack(">BHH", 4, 11, 1))
            assert await exchange(r, w, req) == bytes.fromhex("123500000003018402")
            # another unit id: exception 11 (gateway target failed to respond)
            req = mbap(0x1236, 7, struct.pack(">BHH", 4, 0, 1))
            assert await exchange(r, w, req) == bytes.fromhex("12360000000307840b")
            # FC16 x = 30 mm: refused with exception 3, the World unchanged
            pdu = struct.pack(">BHHB6H", 16, 0, 6, 12, 0, 3000, 0, 0, 0, 0)
            assert await exchange(r, w, mbap(0x1237, 1, pdu)) == bytes.fromhex(
                "123700000003019003")
            assert world.platform_mm == (0.0, 0.0, 0.0) and server.refused == 1
            # FC5 coil 1 on (0xFF00): echoed, lands in the World
            pdu = struct.pack(">BHH", 5, 1, 0xFF00)
            assert await exchange(r, w, mbap(0x1238, 1, pdu)) == mbap(0x1238, 1, pdu)
            assert world.indicators["drilling"] is True
        finally:
            w.close()
            await w.wait_closed()
        # garbage and a truncated request on other connections do not hurt the server
        for junk in (b"\xff" * 40, mbap(1, 1, struct.pack(">BHH", 4, 0, 3))[:9], b"\x00"):
            _r2, w2 = await asyncio.open_connection(LOCAL, server.port)
            w2.write(junk)
            await w2.drain()
            w2.close()
            await w2.wait_closed()
        r, w = await asyncio.open_connection(LOCAL, server.port)
        try:
            got = await exchange(r, w, mbap(9, 1, struct.pack(">BHH", 2, 0, 4)))
            assert got == bytes.fromhex("0009 0000 0004 01 02 01 00".replace(" ", ""))
        finally:
            w.close()
            await w.wait_closed()


# ---------------------------------------------------------------------------- driver vs sim
async def test_driver_connects_checks_identity_and_reads():
    async with rig() as (world, server, _):
        drv = driver(server.port)
        assert isinstance(drv, AuxIO)
        with pytest.raises(DeviceFault, match="no sample"):
            await drv.read()
        async with drv:
            assert drv.identity == (0x4442, 0x0101)
            s = await drv.read()
            assert (s.pedal, s.estop, s.platform_mm) == (False, False, (0.0, 0.0, 0.0))
            s2 = await sample_where(drv, lambda x: x.seq >= s.seq + 3)
            assert s2.t > s.t
            # the heartbeat is the World's step counter (no wrap yet: < 65536 steps)
            assert 0 < drv.inputs.heartbeat <= world.steps < 65536
            assert drv.errors == 0
        await drv.close()                                   # idempotent
        with pytest.raises(DeviceFault, match="closed"):
            await drv.read()


async def test_an_unforeseen_error_in_a_poll_is_counted_and_the_reader_goes_on():
    async with rig() as (_, server, _), driver(server.port) as drv:
        await drv.read()
        real = drv._client.read_input_registers

        async def broken(*a, **kw):
            raise ValueError("library bug")

        drv._client.read_input_registers = broken
        exc = await fault_within(drv)
        assert "unexpected ValueError: library bug" in str(exc)
        drv._client.read_input_registers = real
        seq = drv.seq
        await sample_where(drv, lambda s: s.seq > seq)
        assert drv.errors > 0


async def test_pedal_and_estop_are_seen_within_two_polls():
    async with rig() as (_, server, _), driver(server.port) as drv:
        await drv.read()
        for hook, field in ((server.press_pedal, "pedal"), (server.set_estop, "estop")):
            for state in (True, False):
                seq0 = drv.seq
                hook(state)
                s = await sample_where(drv, lambda x, f=field, v=state: getattr(x, f) is v)
                # the poll in flight may predate the change; the next one must show it
                assert s.seq - seq0 <= 2, (field, state, s.seq - seq0)


async def test_indicators_land_in_the_world_and_unknown_names_are_refused():
    async with rig() as (world, server, _), driver(server.port) as drv:
        for name in INDICATORS:
            await drv.set_indicator(name, True)
            assert world.indicators[name] is True
        await drv.set_indicator("fault", False)
        assert world.indicators == {"ready": True, "drilling": True, "fault": False,
                                    "buzzer": True}
        writes = server.requests.get(5, 0)
        with pytest.raises(ConfigError) as e:
            await drv.set_indicator("blue_lamp", True)
        assert e.value.field == "indicator" and e.value.value == "blue_lamp"
        assert all(n in str(e.value) for n in ("ready", "drilling", "fault", "buzzer"))
        assert server.requests.get(5, 0) == writes


async def test_platform_setpoint_lands_in_the_world_and_moves_the_phantom():
    async with rig() as (world, server, _), driver(server.port) as drv:
        o0 = world.phantom_origin_0()
        await drv.set_platform((1.25, -2.5, 3.0))
        assert world.platform_mm == (1.25, -2.5, 3.0)
        o1 = world.phantom_origin_0()
        assert [b - a for a, b in zip(o0, o1, strict=True)] == pytest.approx(
            [1.25, -2.5, 3.0], abs=1e-9)
        # static motion profile: the actual position is the setpoint
        s = await sample_where(drv, lambda x: x.platform_mm != (0.0, 0.0, 0.0))
        assert s.platform_mm == (1.25, -2.5, 3.0)
        # resolution 0.01 mm: 1.234 is sent as 123 counts
        await drv.set_platform((1.234, 0, 0))
        assert world.platform_mm == (1.23, 0.0, 0.0)


async def test_out_of_range_setpoint_is_refused_before_anything_is_sent():
    async with rig() as (world, server, _), driver(server.port) as drv:
        await drv.set_platform((1.0, 2.0, 3.0))
        sent = server.requests.get(16, 0)
        for bad, field in (((0.0, 25.01, 0.0), "platform_setpoint.y"),
                           ((-30.0, 0.0, 0.0), "platform_setpoint.x"),
                           ((0.0, 0.0, math.nan), "platform_setpoint.z"),
                           ((1.0, 2.0), "platform_setpoint")):
            with pytest.raises(ConfigError) as e:
                await drv.set_platform(bad)
            assert e.value.field == field
        assert server.requests.get(16, 0) == sent
        assert world.platform_mm == (1.0, 2.0, 3.0)
        assert drv.writes == 1


async def test_device_refuses_bad_setpoints_from_other_clients_and_reports_it():
    async with rig() as (world, server, _), driver(server.port) as drv:
        await drv.set_platform((1.0, 0.0, 0.0))
        other = AsyncModbusTcpClient(LOCAL, port=server.port, reconnect_delay=0)
        await other.connect()
        try:
            rr = await other.write_registers(2, [0, 3000], device_id=1)      # y = 30 mm
            assert rr.isError() and rr.exception_code == 3
            # a half-written int32: high word of z = 0x0001 -> 655.36 mm, refused as well
            rr = await other.write_register(4, 1, device_id=1)
            assert rr.isError() and rr.exception_code == 3
            # the low word alone is fine: y = 0.07 mm
            rr = await other.write_register(3, 7, device_id=1)
            assert not rr.isError()
        finally:
            other.close()
        assert world.platform_mm == (1.0, 0.07, 0.0)
        assert server.refused == 2
        # the latched flag was cleared by the accepted write; set it again and watch it
        server.setpoint_rejected = True
        await sample_where(drv, lambda _: drv.inputs.setpoint_rejected)
        await drv.set_platform((0.0, 0.0, 0.0))
        await sample_where(drv, lambda _: not drv.inputs.setpoint_rejected)
        server.set_platform_fault()
        await sample_where(drv, lambda _: drv.inputs.platform_fault)


async def test_server_stopped_means_device_fault_then_recovery_on_restart():
    world = World(WorldConfig())
    async with rig(world) as (_, server, _), driver(server.port) as drv:
        port = server.port
        await drv.read()
        await server.close()
        exc = await fault_within(drv, timeout=3.0)
        assert exc.device == "aux-modbus"
        assert "down" in str(exc) or "failed" in str(exc)
        assert not drv.connected or drv.errors > 0
        seq = drv.seq
        async with AuxModbusServer(world, port=port):
            s = await sample_where(drv, lambda x: x.seq > seq)
            assert s.seq > seq and drv.reconnects >= 1
        await fault_within(drv, timeout=3.0)
        await asyncio.wait_for(drv.close(), 2.0)        # also while it is reconnecting


async def test_frozen_world_means_stale_heartbeat_and_device_fault():
    async with rig() as (_, server, stepper), driver(server.port, stale_after_s=0.15) as drv:
        await drv.read()
        await stepper.stop()                        # the PLC's scan cycle stops
        unchanged = drv.unchanged
        exc = await fault_within(drv, timeout=3.0)
        assert "stale" in str(exc) and "heartbeat" in str(exc)
        assert drv.connected and drv.unchanged > unchanged
        stepper.start()
        await sample_where(drv, lambda _: True)


@contextlib.asynccontextmanager
async def plain_device(ir_values: list[int]):
    """Some other Modbus device (pymodbus, no DentiBot code) with the given input registers."""
    dev = SimDevice(1, simdata=[SimData(0, values=ir_values, datatype=DataType.REGISTERS)])
    srv = ModbusTcpServer(dev, address=(LOCAL, 0))
    await srv.serve_forever(background=True)
    try:
        yield srv.transport.sockets[0].getsockname()[1]
    finally:
        await srv.shutdown()
        for _ in range(3):
            await asyncio.sleep(0)


@pytest.mark.parametrize(("regs", "read", "expected"), [
    ([0x1234, 0x0100] + [0] * 9, "0x1234", "0x4442"),          # wrong magic
    ([0x4442, 0x0200] + [0] * 9, "2.0", "1.x"),                 # wrong major version
    ([0x4442], "exception 2", "0x4442"),                        # no IR 1 at all
])
async def test_wrong_magic_or_version_is_a_device_fault(regs, read, expected):
    async with plain_device(regs) as port:
        drv = driver(port)
        with pytest.raises(DeviceFault) as e:
            await drv.connect()
        assert read in str(e.value) and expected in str(e.value)
        assert not drv.connected
        await drv.close()


async def test_cannot_connect_is_a_device_fault():
    drv = driver(free_port(), request_timeout_s=0.5)
    with pytest.raises(DeviceFault, match="cannot connect"):
        await drv.connect()
    await drv.close()


def test_constructor_checks_its_arguments():
    assert AuxModbusDriver().host == "192.168.0.50" and AuxModbusDriver().port == 502
    for kw in ({"poll_period_s": 0}, {"stale_after_s": -1}, {"request_timeout_s": math.nan},
               {"device_id": 300}, {"port": 0}):
        with pytest.raises(ConfigError):
            AuxModbusDriver(**kw)


# ---------------------------------------------------------------------------- a rogue device
class RogueDevice:
    """A Modbus TCP device written by hand (no pymodbus, no DentiBot code): answers the
    identity read properly, then polls according to ``mode``: "good", "short" (a well-framed
    answer with 2 registers instead of 11), "garbage" (bytes that are not Modbus) or "silent"."""

    def __init__(self) -> None:
        self.mode = "good"
        self.heartbeat = 0
        self.polls = 0
        self.server: asyncio.Server | None = None
        self.writers: list[asyncio.StreamWriter] = []

    async def start(self) -> int:
        self.server = await asyncio.start_server(self._serve, LOCAL, 0)
        return self.server.sockets[0].getsockname()[1]

    async def close(self) -> None:
        self.server.close()
        for w in self.writers:
            w.close()
            with contextlib.suppress(Exception):
                await w.wait_closed()
        await self.server.wait_closed()

    async def _serve(self, r: asyncio.StreamReader, w: asyncio.StreamWriter) -> None:
        self.writers.append(w)
        with contextlib.suppress(asyncio.IncompleteReadError, ConnectionError):
            while True:
                tid, _, n, unit = struct.unpack(">HHHB", await r.readexactly(7))
                fc, _addr, count = struct.unpack(">BHH", (await r.readexactly(n - 1))[:5])
                if count == 2:
                    regs = [0x4442, 0x0100]
                else:
                    self.polls += 1
                    self.heartbeat += 1
                    regs = [0x4442, 0x0100, self.heartbeat] + [0] * 8
                    if self.mode == "short":
                        regs = regs[:2]
                    elif self.mode == "garbage":
                        w.write(b"\x13\x37" * 20)
                        continue
                    elif self.mode == "silent":
                        continue
                pdu = struct.pack(f">BB{len(regs)}H", fc, 2 * len(regs), *regs)
                w.write(struct.pack(">HHHB", tid, 0, len(pdu) + 1, unit) + pdu)


async def test_malformed_and_garbage_answers_are_counted_and_never_stop_the_reader():
    rogue = RogueDevice()
    port = await rogue.start()
    try:
        async with driver(port, request_timeout_s=0.05) as drv:
            await sample_where(drv, lambda s: s.seq >= 3)
            for mode, words in (("short", "malformed"), ("garbage", None),
                                ("silent", None)):
                rogue.mode = mode
                errors = drv.errors
                exc = await fault_within(drv)
                if words:
                    assert words in str(exc)
                await asyncio.sleep(0.1)
                assert drv.errors > errors
                assert drv._task is not None and not drv._task.done()
                rogue.mode = "good"
                s = await sample_where(drv, lambda _: True)
                assert s.seq > 0
            assert drv.received > 0 and drv.polls >= drv.received + drv.errors - 1
    finally:
        await rogue.close()


# ---------------------------------------------------------------------------- the document
async def test_plain_client_reads_the_documented_addresses():
    """Every row of the document's table, read with a plain pymodbus client at the documented
    address and decoded by the documented type: values the World's physics predicts."""
    world = World(WorldConfig(motion="square"))
    world.run(1.0)             # 500 steps; the square's first side: x = 3 mm/s * 1 s, moving
    world.platform_mm = (1.25, -2.5, 0.75)
    world.pedal = True
    world.indicators["drilling"] = True
    expected = {
        "pedal": True, "estop": False, "platform_moving": True, "platform_fault": False,
        "ready": False, "drilling": True, "fault": False, "buzzer": False,
        "magic": 0x4442, "map_version": 0x0101, "heartbeat": 500,
        "inputs": 0b01, "setpoint_rejected": False, "host_lost": False,
        "host_watchdog": 0, "watchdog_ms": 0,
        "platform_status": 0b001,
        "platform_x": 3.0 + 1.25, "platform_y": -2.5, "platform_z": 0.75,
        "setpoint_x": 1.25, "setpoint_y": -2.5, "setpoint_z": 0.75,
    }
    read_fn = {"coil": "read_coils", "discrete input": "read_discrete_inputs",
               "input register": "read_input_registers",
               "holding register": "read_holding_registers"}
    rows = documented_rows()
    assert {r[3] for r in rows} == set(expected)
    async with rig(world, step=False) as (_, server, _):
        client = AsyncModbusTcpClient(LOCAL, port=server.port, reconnect_delay=0)
        await client.connect()
        try:
            for table, address, _ref, name, kind, _access, units, _meaning in rows:
                read = getattr(client, read_fn[table])
                if "." in address:                       # a bit of a flags register
                    reg, bit = (int(x) for x in address.split("."))
                    rr = await read(reg, count=1, device_id=1)
                    got = bool(rr.registers[0] >> bit & 1)
                elif kind == "bit":
                    got = (await read(int(address), count=1, device_id=1)).bits[0]
                elif kind == "int32":
                    first = int(address.split("-")[0])
                    rr = await read(first, count=2, device_id=1)
                    got = client.convert_from_registers(rr.registers, client.DATATYPE.INT32)
                    assert units.startswith("0.01 mm")
                    got /= 100
                else:
                    got = (await read(int(address), count=1, device_id=1)).registers[0]
                if units.startswith("= "):
                    assert got == int(units[2:], 0)
                assert got == pytest.approx(expected[name], abs=1e-9), name
        finally:
            client.close()
    assert re.search(r"high word first", DOC.read_text())


# ---------------------------------------------------------------------------- host watchdog
async def _wait_for(pred, timeout: float = 3.0) -> float:
    """Seconds until ``pred()`` holds (polled every 5 ms); fails after ``timeout``."""
    loop = asyncio.get_running_loop()
    t0 = loop.time()
    while not pred():
        assert loop.time() - t0 < timeout, "condition not reached"
        await asyncio.sleep(0.005)
    return loop.time() - t0


async def test_the_device_holds_the_platform_and_lights_fault_when_the_host_goes_silent():
    """A plain pymodbus client arms a 100 ms watchdog, feeds it once, then goes silent: after
    100 ms (not before) the device reports host_lost (IR 4 bit 3), DRILLING is off, FAULT on,
    the setpoint held; a new value clears host_lost."""
    async with rig() as (world, server, _):
        world.indicators["drilling"] = True
        client = AsyncModbusTcpClient(LOCAL, port=server.port, reconnect_delay=0)
        await client.connect()
        try:
            await client.write_registers(0, encode_setpoint((1.0, 2.0, 3.0)), device_id=1)
            assert not (await client.write_register(7, 100, device_id=1)).isError()
            assert not (await client.write_register(6, 1, device_id=1)).isError()
            fed = asyncio.get_running_loop().time()
            # the same value again does not feed it
            assert not (await client.write_register(6, 1, device_id=1)).isError()
            await _wait_for(lambda: server.host_lost)
            since_feed = asyncio.get_running_loop().time() - fed
            # not before 100 ms; then within the 10 ms check (generous: a busy machine)
            assert 0.1 <= since_feed < 0.5
            rr = await client.read_input_registers(4, count=1, device_id=1)
            assert rr.registers[0] >> 3 & 1 == 1
            assert world.indicators["drilling"] is False and world.indicators["fault"] is True
            assert world.platform_mm == (1.0, 2.0, 3.0)
            hr = await client.read_holding_registers(6, count=2, device_id=1)
            assert hr.registers == [1, 100]
            await client.write_register(6, 2, device_id=1)
            assert not server.host_lost
            rr = await client.read_input_registers(4, count=1, device_id=1)
            assert rr.registers[0] >> 3 & 1 == 0
            # a watchdog time beyond 10 s is refused (exception 3) and the old one stays
            rr = await client.write_register(7, 10_001, device_id=1)
            assert rr.isError() and rr.exception_code == 3
            assert server.watchdog_ms == 100
            # 0 switches it off: silence is then no fault
            await client.write_register(7, 0, device_id=1)
            await asyncio.sleep(0.25)
            assert not server.host_lost and server.watchdog_expiries == 1
        finally:
            client.close()


async def test_slow_answers_stretch_neither_the_feeds_nor_go_unmeasured():
    """A device answering every request 15 ms late (longer than the 10 ms poll period): the
    driver still feeds the 200 ms watchdog a quarter of it (50 ms, by the clock) after the
    last feed, at the end of the poll in progress then: at most one poll's two answers and
    the last feed's own later, 50 + 3 x 15 ms, where counting five polls of two requests
    each would have stretched it to 150 ms and more; and the round trips it measures are at
    least the 15 ms delay."""
    world = World(WorldConfig())
    server = AuxModbusServer(world, port=0)
    answer = server._on_access

    async def late(*args):
        await asyncio.sleep(0.015)
        return await answer(*args)
    server._on_access = late
    await server.start()
    stepper = _Stepper(world)
    stepper.start()
    drv = driver(server.port)
    loop = asyncio.get_running_loop()
    try:
        await drv.connect()
        fed_at: list[float] = []
        feed = drv._feed

        async def noted_feed():
            fed_at.append(loop.time())
            await feed()
        drv._feed = noted_feed
        p0 = drv.polls
        drv.reset_request_times()
        await asyncio.sleep(0.6)
        gaps = np.diff(fed_at)
        # never before 50 ms; at most 50 ms + three late answers, each with 10 ms of
        # scheduling on a loaded machine
        assert len(gaps) >= 3 and gaps.min() >= 0.05
        assert gaps.max() <= 0.05 + 3 * (0.015 + 0.010), gaps
        assert not server.host_lost and server.watchdog_expiries == 0
        assert drv.polls - p0 < 0.6 / 0.030 + 1     # polls slowed down: two requests each
        assert 15.0 <= drv.request_ms_worst < 200.0 and drv.request_ms >= 15.0
    finally:
        await drv.close()
        await asyncio.sleep(0.05)                   # the late answer in flight, answered
        await stepper.stop()
        await server.close()


async def test_a_stall_of_the_simulators_own_loop_is_not_the_hosts_silence():
    """The simulated PLC's watchdog counts its scan's time: a 300 ms stall of the process that
    runs it (the host's feed held up by the same stall) is not counted, since a PLC on its own
    CPU would have read the host's frames meanwhile; silence while the scan runs on time still
    trips it after the 100 ms watchdog, not before."""
    async with rig(step=False) as (_world, server, _):
        client = AsyncModbusTcpClient(LOCAL, port=server.port, reconnect_delay=0)
        await client.connect()
        try:
            assert not (await client.write_register(7, 100, device_id=1)).isError()
            assert not (await client.write_register(6, 1, device_id=1)).isError()
            await asyncio.sleep(0.03)                   # scans on time: 30 ms counted
            time.sleep(0.3)  # noqa: ASYNC251 - the stall under test: the whole process
            await asyncio.sleep(0.03)                   # a few scans after it
            assert not server.host_lost and server.watchdog_expiries == 0
            # the stall beyond two scans (20 ms) is what was discounted
            assert 0.3 - 2 * 0.010 - 0.01 <= server.stalled_s <= 0.3 + 0.05
            # silence, the scan on time: tripped after the rest of the 100 ms, not before
            t0 = asyncio.get_running_loop().time()
            await _wait_for(lambda: server.host_lost, timeout=1.0)
            counted_before = 0.03 + 0.03 + 2 * 0.010    # scans counted around the stall
            waited = asyncio.get_running_loop().time() - t0
            assert 0.1 - counted_before - 0.015 <= waited < 0.5
        finally:
            client.close()


async def test_the_driver_arms_and_feeds_the_watchdog_and_its_death_trips_it():
    async with rig() as (world, server, _):
        drv = driver(server.port)
        await drv.connect()
        try:
            assert server.watchdog_ms == 200
            await asyncio.sleep(0.6)                 # 3 watchdog times of normal polling
            assert not server.host_lost and server.watchdog_expiries == 0
            # fed every 50 ms (a quarter of 200 ms, 5 polls of 10 ms), plus once at connect:
            # at most 13 in 0.6 s; fewer when a busy machine skips polls
            assert 3 <= drv.feeds <= 14
            assert drv.writes == 0                   # watchdog traffic is not an operator write
            await drv.set_indicator("drilling", True)
        finally:
            await drv.close()                        # DentiBot gone
        await _wait_for(lambda: server.host_lost, timeout=1.0)
        assert world.indicators["drilling"] is False and world.indicators["fault"] is True


def test_watchdog_time_is_checked_before_anything_is_sent():
    for bad in (-1, 10_001, 1.5, "200", True):
        with pytest.raises(ConfigError, match="watchdog_ms"):
            AuxModbusDriver(LOCAL, 502, watchdog_ms=bad)
    assert AuxModbusDriver(LOCAL, 502, watchdog_ms=0).watchdog_ms == 0


async def test_a_second_client_switching_the_watchdog_off_is_a_latched_fault():
    """Modbus has no authentication: another client writes HR 7 = 0 (watchdog off). The
    driver reads HR 6-7 back every poll period and faults within about one of them; the
    next feed restores the watchdog time."""
    async with rig() as (_, server, _stepper):
        drv = driver(server.port)
        await drv.connect()
        other = AsyncModbusTcpClient(LOCAL, port=server.port, reconnect_delay=0)
        await other.connect()
        try:
            await _wait_for(lambda: drv.readbacks > 2)
            assert drv.watchdog_fault is None
            await drv.read()
            assert not (await other.write_register(7, 0, device_id=1)).isError()
            written = asyncio.get_running_loop().time()
            assert server.watchdog_ms == 0                       # protection gone
            exc = await fault_within(drv, timeout=2.0)
            seen = asyncio.get_running_loop().time() - written
            assert isinstance(exc, WatchdogOverwritten)
            assert exc.found[1] == 0 and exc.expected[1] == 200
            assert "watchdog OFF" in str(exc) and f"{LOCAL}:{server.port}" in str(exc)
            # one poll period (10 ms) plus two requests; generous for a loaded machine
            assert seen < drv.poll_period_s + 0.25
            await _wait_for(lambda: server.watchdog_ms == 200)   # restored by the driver
            # latched until the operator's reset, although the registers are right again
            await asyncio.sleep(0.05)
            with pytest.raises(WatchdogOverwritten):
                await drv.read()
            drv.clear_watchdog_fault()
            await sample_where(drv, lambda s: True)
            # another client feeding the watchdog (it would hide DentiBot's death) too; it
            # insists, as a panel would: one write that lands while the driver's own feed is
            # on its way is overwritten by that feed before any read-back sees it
            await _wait_for(lambda: drv._fed_value is not None)    # no feed in flight
            foreign = (drv._fed_value + 1000) & 0xFFFF or 1

            async def feed_too() -> None:
                while True:
                    await other.write_register(6, foreign, device_id=1)
                    await asyncio.sleep(0.01)

            feeder = asyncio.get_running_loop().create_task(feed_too())
            try:
                exc = await fault_within(drv, timeout=2.0)
            finally:
                await cancel_until_done(feeder, reraise=False)
            assert isinstance(exc, WatchdogOverwritten) and "someone else feeds" in str(exc)
        finally:
            other.close()
            await drv.close()


async def test_host_lost_is_a_relay_output():
    async with rig() as (_, server, _stepper):
        seen: list[bool] = []
        server.host_lost_outputs.append(seen.append)
        drv = driver(server.port, watchdog_ms=100)
        await drv.connect()
        await asyncio.sleep(0.2)
        await drv.close()
        await _wait_for(lambda: seen == [True], timeout=1.0)
        drv = driver(server.port, watchdog_ms=100)
        await drv.connect()                                      # back: a new counter
        try:
            await _wait_for(lambda: seen == [True, False], timeout=1.0)
        finally:
            await drv.close()


async def test_connect_to_a_peer_that_never_answers_is_a_typed_timeout():
    async with silent_peer() as port:
        drv = driver(port, request_timeout_s=5.0, connect_timeout_s=0.3)
        loop = asyncio.get_running_loop()
        t0 = loop.time()
        with pytest.raises(ConnectTimeout) as e:
            await drv.connect()
        assert 0.3 <= loop.time() - t0 <= 0.3 + 0.5
        assert e.value.device == "aux-modbus" and f"{LOCAL}:{port}" in str(e.value)
        assert "identification" in str(e.value)
        await drv.close()
