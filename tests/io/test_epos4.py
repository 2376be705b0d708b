"""Epos4Driver against the simulated EPOS4 node on python-can's virtual bus.

Each test gets its own virtual channel; the World is stepped in real time by a
RealTimeStepper, the node answers from it. Expected values come from the vendor / thesis
numbers (Km 16 mNm/A, gear 67), CiA 301/402 and the World's handpiece physics.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import struct
import threading
import time
import uuid
from types import SimpleNamespace
from typing import ClassVar

import can
import canopen
import numpy as np
import pytest
from silent_peer import silent_peer

from dentibot.errors import ConfigError, DeviceFault
from dentibot.io import Handpiece
from dentibot.io import canopen_protocol as co
from dentibot.io.canopen_protocol import RXPDO1, RXPDO2, TXPDO1, TXPDO2, NmtState, State
from dentibot.io.epos4 import (
    DEFAULT_CONSUMER_MS,
    DEFAULT_HOST_HEARTBEAT_PERIOD_S,
    DEFAULT_HOST_NODE_ID,
    DEFAULT_QUICK_STOP_FILE_RPM_S,
    ConfigurationMismatch,
    Epos4Driver,
    SdoAbort,
)
from dentibot.io.interfaces import ConnectTimeout
from dentibot.sim import HandpieceParams, RealTimeStepper, World, WorldConfig
from dentibot.sim.epos4_node import Epos4Node

pytestmark = [pytest.mark.wire, pytest.mark.timeout(30)]

GEAR = 67.0           # thesis 5.1
KM = 16.0             # mNm/A, thesis 5.1


def channel() -> str:
    return f"epos4-test-{uuid.uuid4().hex}"


def frames(bus: can.BusABC) -> list[can.Message]:
    out = []
    while (m := bus.recv(0)) is not None:
        out.append(m)
    return out


@contextlib.asynccontextmanager
async def rig(world: World | None = None, *, connect: bool = True, sync: bool = True,
              tap: bool = False, factory: bool = False, **drv_kw):
    """World (stepped in real time) + Epos4Node + Epos4Driver on one fresh virtual channel;
    ``tap``: a third bus on the channel for the test to inject and watch frames."""
    ch = channel()
    world = world or World(WorldConfig(seed=1))
    stop = asyncio.Event()
    stepper = asyncio.create_task(RealTimeStepper(world).run(stop))
    node_bus = can.Bus(interface="virtual", channel=ch)
    tap_bus = can.Bus(interface="virtual", channel=ch) if tap else None
    node = Epos4Node(world, node_bus)
    drv_kw.setdefault("stale_after_s", 0.5)        # generous: the machine may be loaded
    drv_kw.setdefault("answer_timeout_s", 0.5)
    # these tests script the driver rather than tick it like a control task: supervision
    # by the control path (feed) has tests of its own
    drv_kw.setdefault("feed_timeout_s", None)
    # host and simulated drive share this process's event loop: a stall of the test process
    # (a garbage collection on a loaded machine) is a stall of the host, which the product's
    # 30 ms consumer rightly treats as a lost host. Tests about something else watch with a
    # longer consumer time; the liveness tests pass the product's default.
    drv_kw.setdefault("consumer_ms", 250)
    if factory:      # the driver opens (and owns) a bus made by the caller's factory
        drv = Epos4Driver(lambda: can.Bus(interface="virtual", channel=ch), **drv_kw)
    else:
        drv = Epos4Driver(interface="virtual", channel=ch, **drv_kw)
    try:
        await node.start()
        if connect:
            await drv.connect(sync=sync)
        yield SimpleNamespace(world=world, node=node, drv=drv, tap=tap_bus, channel=ch)
    finally:
        await drv.close()
        await node.close()
        stop.set()
        await stepper
        node_bus.shutdown()
        if tap_bus is not None:
            tap_bus.shutdown()


async def until(pred, timeout: float = 2.0, step: float = 0.005) -> bool:
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > deadline:
            return False
        await asyncio.sleep(step)
    return True


async def read_fault(drv: Epos4Driver, timeout: float = 2.0) -> DeviceFault:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            await drv.read()
        except DeviceFault as exc:
            return exc
        await asyncio.sleep(0.005)
    raise AssertionError("read() never faulted")


def send(bus: can.BusABC, can_id: int, data: bytes) -> None:
    bus.send(can.Message(arbitration_id=can_id, data=data, is_extended_id=False))


# ---------------------------------------------------------------- construction


def test_driver_satisfies_the_handpiece_protocol():
    assert isinstance(Epos4Driver(interface="virtual", channel="x"), Handpiece)


@pytest.mark.parametrize("kw, field", [
    ({"node_id": 0}, "node_id"), ({"sync_period_s": 0.0}, "sync_period_s"),
    ({"gear_ratio": -1.0}, "gear_ratio"), ({"move_rpm": 500.0}, "move_rpm"),
    ({"encoder_counts_per_turn": 0}, "encoder_counts_per_turn"),
    ({"heartbeat_ms": 70000}, "heartbeat_ms"),
])
def test_bad_configuration_is_a_config_error(kw, field):
    with pytest.raises(ConfigError, match=field):
        Epos4Driver(interface="virtual", channel="x", **kw)


async def test_no_node_on_the_bus_times_out_the_first_sdo():
    drv = Epos4Driver(interface="virtual", channel=channel(), sdo_timeout_s=0.1)
    with pytest.raises(DeviceFault, match=r"SDO upload 0x1000:00 not answered within 0.1 s"):
        await drv.connect()
    await drv.close()
    assert drv.sdo_timeouts == 1


async def test_unknown_interface_is_a_device_fault():
    drv = Epos4Driver(interface="no-such-interface", channel="x")
    with pytest.raises(DeviceFault, match="cannot open CAN bus"):
        await drv.connect()
    await drv.close()


# ---------------------------------------------------------------- start-up


async def test_startup_configures_pdos_reads_motor_data_and_enables():
    async with rig(connect=False, tap=True) as r:
        node, drv = r.node, r.drv
        # the node's power-on mapping is not ours: the driver has to configure it
        assert node.tx_layouts[1].words == (0x60410010,)
        assert node.rx_layouts[1].words == (0x60400010,)
        await drv.connect()
        assert drv.state is State.OPERATION_ENABLED
        assert node.state is State.OPERATION_ENABLED
        assert node.transitions == ["2", "3", "4"]             # shutdown, switch on, enable
        assert node.nmt_state is NmtState.OPERATIONAL
        for pdo, layouts in ((RXPDO1, node.rx_layouts), (RXPDO2, node.rx_layouts),
                             (TXPDO1, node.tx_layouts), (TXPDO2, node.tx_layouts)):
            assert layouts[pdo.number].words == pdo.layout.words
        assert drv.km_mnm_per_a == KM
        assert drv.device_gear == (67, 1)
        assert drv.counts_per_turn == 2048
        assert drv.device_type & 0xFFFF == 402
        assert node.value("producer_heartbeat_time") == 100
        assert await until(lambda: drv.received > 5)
        s = await drv.read()
        assert s.enabled and s.fault is None and s.seq == drv.received
        # the wire: boot-up first; NMT pre-op before any SDO; no PDO before NMT start;
        # no SDO after it (SDOs only at start-up)
        seen = frames(r.tap)
        ids = [m.arbitration_id for m in seen]
        assert seen[0].arbitration_id == 0x701 and bytes(seen[0].data) == b"\x00"
        pre_op = next(i for i, m in enumerate(seen) if m.arbitration_id == 0
                      and bytes(m.data) == b"\x80\x01")
        start = next(i for i, m in enumerate(seen) if m.arbitration_id == 0
                     and bytes(m.data) == b"\x01\x01")
        assert ids.index(0x601) > pre_op
        assert not {0x181, 0x281, 0x201, 0x301, 0x080} & set(ids[:start])
        assert not {0x601, 0x581} & set(ids[start:])
        assert {0x201, 0x301, 0x080, 0x181, 0x281} <= set(ids[start:])


async def test_sdo_refusals_are_typed():
    async with rig() as r:
        with pytest.raises(SdoAbort) as e:
            await r.drv.sdo_write("tpdo1_mapped_count", 0)     # PDO mapping in OPERATIONAL
        assert e.value.code == 0x0800_0022 and "present device state" in str(e.value)
        with pytest.raises(SdoAbort) as e:
            await r.drv.sdo_read(co.OdObject("nothing", 0x2345, 0, co.U8))
        assert e.value.code == 0x0602_0000
        with pytest.raises(SdoAbort) as e:
            await r.drv.sdo_write(co.OdObject("sw", 0x6041, 0, co.U16), 0)
        assert e.value.code == 0x0601_0002                     # statusword is read-only
        assert r.drv.sdo_aborts == 3


async def test_enable_timeout_names_the_state_it_is_stuck_in():
    world = World(WorldConfig(seed=1))
    world.estop = True            # safe torque off: the power stage cannot be switched on
    async with rig(world, connect=False, state_timeout_s=0.3) as r:
        with pytest.raises(DeviceFault, match="stuck in READY_TO_SWITCH_ON"):
            await r.drv.connect()
        assert not r.drv.connected
        assert r.node.state is State.READY_TO_SWITCH_ON


# ---------------------------------------------------------------- cyclic exchange


async def test_velocity_60_rpm_at_the_file():
    async with rig() as r:
        drv, world = r.drv, r.world
        await drv.set_velocity(60.0)
        # the World's speed loop: first order, tau 10 ms -> settled after 0.3 s
        assert await until(lambda: abs(world.handpiece.omega_rpm - 60.0) < 1e-3)
        await asyncio.sleep(0.05)
        a = await drv.read()
        assert a.velocity_rpm == pytest.approx(60.0, abs=1 / GEAR)   # 4020 rpm at the motor
        assert a.enabled
        await asyncio.sleep(0.2)
        b = await drv.read()
        # 60 rpm at the file is 360 deg/s of file position
        rate = (b.position_deg - a.position_deg) / (b.t - a.t)
        assert rate == pytest.approx(360.0, rel=0.03)
        assert b.seq > a.seq
        with pytest.raises(ConfigError, match="200"):
            await drv.set_velocity(250.0)
        await drv.stop()             # zero velocity, stays enabled
        assert await until(lambda: abs(world.handpiece.omega_rpm) < 1e-3)
        await asyncio.sleep(0.05)
        s = await drv.read()
        assert s.velocity_rpm == 0.0 and s.enabled


async def test_position_is_unwrapped_across_the_int32_overflow():
    async with rig() as r:
        hp = r.world.handpiece
        inc_per_deg = GEAR * 2048 / 360
        hp.pos_deg = (2**31 - 1) / inc_per_deg - 60.0      # 60 deg before the counter wraps
        await r.drv.set_velocity(100.0)                     # 600 deg/s at the file
        await asyncio.sleep(0.05)
        a = await r.drv.read()
        await asyncio.sleep(0.25)
        b = await r.drv.read()
        assert hp.pos_deg * inc_per_deg > 2**31                # the drive's counter wrapped
        assert (b.position_deg - a.position_deg) / (b.t - a.t) == pytest.approx(600, rel=0.05)


async def test_500_hz_exchange_loses_no_cycles():
    async with rig() as r:
        drv, node = r.drv, r.node
        await drv.set_velocity(100.0)
        s0 = drv.syncs_sent
        await asyncio.sleep(2.0)
        await drv.stop_sync()
        await asyncio.sleep(0.1)           # let the last answers arrive
        # about 1000 in 2 s; a loaded machine skips cycles (counted as overruns), never
        # loses them
        assert drv.syncs_sent - s0 >= 400
        # totals since start-up: only the driver sends SYNC on this channel
        assert node.syncs_received == drv.syncs_sent
        assert node.syncs_answered == node.syncs_received
        assert drv.received == node.syncs_answered            # every answer arrived
        assert drv.lost == 0 and drv.incomplete == 0 and drv.errors == 0
        assert drv.unsolicited == 0
        assert drv.last.seq == drv.received
        assert drv.latency_max_s < drv.answer_timeout_s


async def test_explicit_exchange_drives_the_cycle():
    async with rig(sync=False, factory=True) as r:
        drv, node = r.drv, r.node
        await drv.set_velocity(-30.0)
        for _ in range(200):                   # paced by the caller, like a control task
            await drv.exchange(wait=True)
            await asyncio.sleep(0.002)
        assert drv.received == drv.syncs_sent == node.syncs_answered
        assert drv.lost == 0
        s = await drv.read()
        assert s.velocity_rpm == pytest.approx(-30.0, abs=1 / GEAR)


async def test_set_point_handshake_rearms_for_an_unacknowledged_move():
    async with rig(sync=False) as r:
        drv, node = r.drv, r.node
        n0 = node.setpoints_accepted
        await drv.move_relative(20.0)
        await drv.exchange()              # carries the bit 4 edge; no answer processed yet
        await drv.move_relative(-20.0)    # before any acknowledge: must drop bit 4 first
        sent_bit4 = []
        for _ in range(400):
            await drv.exchange(wait=True)
            sent_bit4.append(drv._last_bit4)
            if drv.move_done:
                break
            await asyncio.sleep(0.002)
        assert drv.move_done
        assert node.setpoints_accepted - n0 == 2
        assert sent_bit4[0] is False      # the low cycle between the two edges


async def test_current_reads_back_as_file_torque():
    # no current noise; the World's no-load current is then exactly the friction current
    world = World(WorldConfig(seed=1, handpiece=HandpieceParams(current_noise_a=0.0,
                                                                friction_current_a=0.05)))
    async with rig(world) as r:
        drv = r.drv
        for rpm, sign in ((60.0, 1), (-60.0, -1)):
            await drv.set_velocity(rpm)
            assert await until(lambda rpm=rpm: abs(world.handpiece.omega_rpm - rpm) < 1e-3)
            await asyncio.sleep(0.05)
            s = await drv.read()
            assert s.current_a == pytest.approx(sign * 0.050, abs=1e-9)   # 50 mA
            assert world.handpiece.current_a == pytest.approx(s.current_a, abs=5e-4)
            # T = I Km GR eta (thesis eq 5.4-5.5), eta 0.7 as the World's gearhead
            assert drv.file_torque_mnm(efficiency=0.7) == \
                pytest.approx(sign * 0.050 * 16 * 67 * 0.7)
        # torque actual 0x6077: per mille of the rated torque 0x6076 (both read over SDO)
        per_mille = await drv.sdo_read("torque_actual")
        assert per_mille == round(-0.050 * KM / drv.rated_torque_mnm * 1000)


async def test_move_relative_minus_90_turns_the_file_back():
    async with rig() as r:
        drv, world = r.drv, r.world
        await drv.set_velocity(60.0)
        await asyncio.sleep(0.2)
        await drv.stop()
        assert await until(lambda: world.handpiece.omega_rpm == 0.0)
        await asyncio.sleep(0.05)
        p_world = world.handpiece.pos_deg
        p_drv = (await drv.read()).position_deg
        assert p_drv == pytest.approx(p_world, abs=0.01)     # increments -> deg at the file
        await drv.move_relative(-90.0)
        await drv.wait_move_done(timeout_s=3.0)
        assert drv.mode_display == co.Mode.PROFILE_POSITION
        await asyncio.sleep(0.1)                               # hold
        assert world.handpiece.pos_deg - p_world == pytest.approx(-90.0, abs=0.5)
        s = await drv.read()
        assert s.position_deg - p_drv == pytest.approx(-90.0, abs=0.5)
        assert s.enabled and s.velocity_rpm == pytest.approx(0.0, abs=1.0)
        # a second move: the set-point handshake works again
        await drv.move_relative(45.0, rpm=150.0)
        await drv.wait_move_done(timeout_s=3.0)
        await asyncio.sleep(0.1)
        assert world.handpiece.pos_deg - p_world == pytest.approx(-45.0, abs=0.5)
        # a new move right after a cycle carried the previous one (acknowledged or not):
        # bit 4 drops and rises again, so the drive takes both set-points
        n0 = r.node.setpoints_accepted
        await drv.move_relative(20.0)
        s0 = drv.syncs_sent
        assert await until(lambda: drv.syncs_sent > s0, step=0.0005)
        await drv.move_relative(-20.0)
        await drv.wait_move_done(timeout_s=3.0)
        assert r.node.setpoints_accepted - n0 == 2


# ---------------------------------------------------------------- faults


async def test_emcy_faults_then_reset_and_enable_again():
    async with rig() as r:
        drv, node, world = r.drv, r.node, r.world
        await drv.set_velocity(60.0)
        await asyncio.sleep(0.1)
        node.inject_emcy(0x2310)
        exc = await read_fault(drv)
        assert "0x2310" in str(exc) and "Overcurrent error" in str(exc)
        assert exc.device == "epos4"
        assert await until(lambda: drv.state is State.FAULT)
        assert drv.last_emcy.register == 0x03                  # generic + current
        assert world.handpiece.cmd_rpm == 0.0                  # the drive stopped the motor
        with pytest.raises(DeviceFault, match="0x2310"):
            await drv.set_velocity(30.0)
        with pytest.raises(DeviceFault, match="fault_reset"):
            await drv.enable()
        await drv.fault_reset()
        assert drv.state is State.SWITCH_ON_DISABLED
        assert r.node.error_code == 0
        await drv.enable()
        assert node.transitions[-4:] == ["15", "2", "3", "4"]
        await drv.set_velocity(30.0)
        assert await until(lambda: abs(world.handpiece.omega_rpm - 30.0) < 1e-3)
        await asyncio.sleep(0.05)
        assert (await drv.read()).velocity_rpm == pytest.approx(30.0, abs=1 / GEAR)


async def test_the_first_emcy_of_an_episode_is_reported_as_its_cause():
    """An over-current, then an under-voltage in its wake: the fault names the over-current
    (the cause), says that more followed, and a reset starts a new episode."""
    async with rig() as r:
        drv, node = r.drv, r.node
        await drv.set_velocity(60.0)
        await asyncio.sleep(0.1)
        node.inject_emcy(0x2310)                               # overcurrent
        node.inject_emcy(0x3210)                               # DC link over-voltage
        assert await until(lambda: drv.emcy_count >= 2)
        exc = await read_fault(drv)
        text = str(exc)
        assert text.index("0x2310") < text.index("0x3210")     # the cause comes first
        assert "first of 2 EMCYs" in text
        assert drv.last_emcy.code == 0x3210
        await drv.fault_reset()
        await drv.enable()
        node.inject_emcy(0x3210)
        exc = await read_fault(drv)
        assert "0x3210" in str(exc) and "0x2310" not in str(exc) and "first of" not in str(exc)


async def test_quick_stop_then_enable():
    async with rig() as r:
        drv = r.drv
        await drv.set_velocity(60.0)
        await asyncio.sleep(0.1)
        await drv.quick_stop()
        assert await until(lambda: drv.state is State.QUICK_STOP_ACTIVE)
        # the quick-stop ramp the driver wrote to 0x6085 takes 60 rpm to 0 in 10 ms
        ramp_s = 60.0 / DEFAULT_QUICK_STOP_FILE_RPM_S
        assert await until(lambda: r.world.handpiece.cmd_rpm == 0.0, timeout=ramp_s + 0.5)
        with pytest.raises(DeviceFault, match="not enabled"):
            await drv.set_velocity(10.0)
        await drv.enable()
        assert r.node.transitions[-4:] == ["12", "2", "3", "4"]
        await drv.set_velocity(10.0)


async def test_wrong_length_frames_are_counted_not_fatal():
    async with rig(tap=True) as r:
        drv, node, tap = r.drv, r.node, r.tap
        await asyncio.sleep(0.05)
        e0 = drv.errors
        for can_id, data in ((0x181, b"\x37\x06\x00"), (0x281, b"\x00\x00"),
                             (0x081, b"\x10\x23\x03\x00"), (0x701, b"\x05\x00"),
                             (0x581, b"\x4b\x41\x60"), (0x181, bytes(8))):
            send(tap, can_id, data)
        assert await until(lambda: drv.errors - e0 == 6)
        await asyncio.sleep(0.05)
        s = await drv.read()                     # still fresh, still enabled
        assert s.enabled and drv.incomplete == 0 and drv.emcy_count == 0
        # the node: an RxPDO1 of 3 bytes instead of 7 -> not processed, EMCY 0x8210, FAULT
        send(tap, 0x201, b"\x0f\x00\x00")
        exc = await read_fault(drv)
        assert "0x8210" in str(exc) and "PDO length" in str(exc)
        assert node.pdo_length_errors == 1
        await drv.fault_reset()
        await drv.enable()
        assert (await drv.read()).enabled


async def test_silent_node_makes_read_stale_and_heartbeat_loss_is_seen():
    async with rig(stale_after_s=0.05, heartbeat_timeout_s=0.3) as r:
        drv, node, world = r.drv, r.node, r.world
        await drv.set_velocity(60.0)
        assert await until(lambda: abs(world.handpiece.omega_rpm - 60.0) < 1e-3)
        await drv.read()
        node.muted = True                        # cable cut, both ways
        exc = await read_fault(drv)
        assert "stale" in str(exc) and "limit 50 ms" in str(exc)
        # the drive misses the host's heartbeat too and stops the file by itself
        assert await until(lambda: node.state is State.FAULT, timeout=2.0)
        assert node.heartbeat_errors == 1 and node.error_code == co.HEARTBEAT_ERROR_CODE
        assert await until(lambda: abs(world.handpiece.omega_rpm) < 1.0)
        node.muted = False                       # the EMCY was lost: the statusword says it
        assert await until(lambda: time.monotonic() - drv.last.t < 0.01)
        exc = await read_fault(drv)
        assert "fault" in str(exc)
        await drv.fault_reset()
        await drv.enable()
        await drv.read()
        # heartbeat producer switched off (over SDO): the driver notices within its timeout
        await drv.sdo_write("producer_heartbeat_time", 0)
        exc = await read_fault(drv, timeout=2.0)
        assert "heartbeat lost" in str(exc) and "limit 300 ms" in str(exc)


async def test_node_reset_is_detected():
    async with rig(tap=True) as r:
        await asyncio.sleep(0.05)
        send(r.tap, 0x000, co.encode_nmt(co.NmtCommand.RESET_NODE, 1))
        exc = await read_fault(r.drv)
        assert "boot-up" in str(exc)
        assert r.node.nmt_state is NmtState.PRE_OPERATIONAL
        assert r.node.tx_layouts[1].words == (0x60410010,)     # power-on mapping again


# ---------------------------------------------------------------- the node alone


async def test_node_nmt_states_gate_pdos():
    ch = channel()
    world = World(WorldConfig(seed=1))
    node_bus = can.Bus(interface="virtual", channel=ch)
    tap = can.Bus(interface="virtual", channel=ch)
    node = Epos4Node(world, node_bus, node_id=3, heartbeat_period_s=0.02)
    try:
        await node.start()

        async def exchange(*msgs):
            for can_id, data in msgs:
                send(tap, can_id, data)
            await asyncio.sleep(0.03)
            return frames(tap)

        got = await exchange((0x080, b""))
        assert next(bytes(m.data) for m in got if m.arbitration_id == 0x703) == b"\x00"
        assert not [m for m in got if m.arbitration_id in (0x183, 0x283)]   # pre-op: no PDO
        assert bytes([m for m in got if m.arbitration_id == 0x703][-1].data) == b"\x7f"
        got = await exchange((0x000, b"\x01\x03"), (0x080, b""))
        tpdo1 = [m for m in got if m.arbitration_id == 0x183]
        assert len(tpdo1) == 1
        # default TxPDO1 = statusword: switch on disabled (0x40) + remote (0x200)
        assert struct.unpack("<H", tpdo1[0].data)[0] == 0x0240
        got = await exchange((0x000, b"\x02\x00"), (0x080, b""))             # stop (all)
        assert not [m for m in got if m.arbitration_id == 0x183]
        assert bytes([m for m in got if m.arbitration_id == 0x703][-1].data) == b"\x04"
        # SDO is not served while STOPPED
        got = await exchange((0x603, co.encode_sdo_upload(0x6041, 0)))
        assert not [m for m in got if m.arbitration_id == 0x583]
        got = await exchange((0x000, b"\x80\x03"), (0x603, co.encode_sdo_upload(0x6041, 0)))
        sdo = [co.decode_sdo_response(bytes(m.data)) for m in got if m.arbitration_id == 0x583]
        assert sdo[0].kind == "upload" and sdo[0].payload == b"\x40\x02"
        # a controlword that skips a step is ignored (switch on disabled + enable operation)
        got = await exchange((0x603, co.encode_sdo_download(0x6040, 0, b"\x0f\x00")))
        assert node.state is State.SWITCH_ON_DISABLED and node.transitions == []
        # a garbage NMT frame is counted, not fatal
        await exchange((0x000, b"\x01"))
        assert node.errors == 1
    finally:
        await node.close()
        node_bus.shutdown()
        tap.shutdown()


async def test_independent_canopen_client_reads_and_writes_the_node():
    """The canopen package's SDO client (a third-party implementation) against the node."""
    ch = channel()
    world = World(WorldConfig(seed=1))
    node_bus = can.Bus(interface="virtual", channel=ch)
    node = Epos4Node(world, node_bus, node_id=2)
    results: dict = {}

    def client() -> None:
        net = canopen.Network()
        net.NOTIFIER_CYCLE = 0.05
        net.connect(interface="virtual", channel=ch)
        try:
            remote = net.add_node(2, canopen.ObjectDictionary())
            results["device_type"] = struct.unpack("<I", remote.sdo.upload(0x1000, 0))[0]
            results["statusword"] = struct.unpack("<H", remote.sdo.upload(0x6041, 0))[0]
            remote.sdo.download(0x1017, 0, struct.pack("<H", 250))
            try:
                remote.sdo.upload(0x2345, 0)
            except canopen.SdoAbortedError as exc:
                results["abort"] = exc.code
        finally:
            net.disconnect()

    try:
        await node.start()
        th = threading.Thread(target=client)
        th.start()
        assert await until(lambda: not th.is_alive(), timeout=10.0)
        th.join()
    finally:
        await node.close()
        node_bus.shutdown()
    assert results == {"device_type": 0x0002_0192, "statusword": 0x0240, "abort": 0x0602_0000}
    assert node.value("producer_heartbeat_time") == 250


# ---------------------------------------------------------------- liveness
#: The World's handpiece speed loop: first order, tau 10 ms (HandpieceParams.tau_s).
TAU_HP = 0.010
#: Scheduling allowance for bounds measured on a loaded, shared machine: the node's event
#: loop, the World's 2 ms steps, the 1 ms ramp updates.
SCHED_S = 0.05


def stop_bound_s(consumer_s: float, decel_file_rpm_s: float, rpm: float = 60.0) -> float:
    """Longest the file turns after the host's last heartbeat: the consumer time, the
    quick-stop ramp from ``rpm``, then the speed loop from at most ``rpm`` to below 1 rpm
    (tau ln(rpm / 1)), plus scheduling."""
    return consumer_s + rpm / decel_file_rpm_s + TAU_HP * math.log(rpm) + SCHED_S


async def test_startup_configures_and_reads_back_the_liveness_objects():
    async with rig(tap=True, consumer_ms=DEFAULT_CONSUMER_MS) as r:
        drv, node = r.drv, r.node
        word = (DEFAULT_HOST_NODE_ID << 16) | DEFAULT_CONSUMER_MS
        assert node.value("consumer_heartbeat_time") == word        # CiA 301 layout
        assert node.consumer == (127, DEFAULT_CONSUMER_MS / 1000)
        assert node.value("abort_connection_option_code") == 1      # fault signal
        assert node.value("quick_stop_deceleration") == round(DEFAULT_QUICK_STOP_FILE_RPM_S
                                                              * GEAR)
        assert drv.liveness == {"quick_stop_deceleration_rpm_s": 402_000,
                                "abort_connection_option": 1,
                                "consumer": (127, DEFAULT_CONSUMER_MS)}
        # the host beats on 0x77F, state operational, every host_heartbeat_period_s
        frames(r.tap)                 # what the connection sent (its length varies)
        await asyncio.sleep(0.2)
        beats = [m for m in frames(r.tap) if m.arbitration_id == 0x77F]
        assert beats and all(bytes(m.data) == b"\x05" for m in beats)
        assert len(beats) <= 0.2 / DEFAULT_HOST_HEARTBEAT_PERIOD_S + 2
        assert node.heartbeats_consumed > 0 and node.heartbeat_errors == 0
    # a clean close switches the consumer off before the host stops beating
    assert node.consumer is None and node.heartbeat_errors == 0
    assert node.state is State.READY_TO_SWITCH_ON


class _ForgetfulNode(Epos4Node):
    """A drive that acknowledges writes of ``forget`` but keeps its own value."""

    forget: ClassVar[dict[str, int]] = {}

    def _write_sdo(self, o, value):
        if o.name in self.forget:
            value = self.forget[o.name]
        super()._write_sdo(o, value)


@pytest.mark.parametrize("name, kept", [("consumer_heartbeat_time", 0),
                                        ("abort_connection_option_code", 3),
                                        ("quick_stop_deceleration", 10_000)])
async def test_a_drive_that_does_not_hold_the_liveness_configuration_fails_connect(
        name, kept, monkeypatch):
    monkeypatch.setattr(_ForgetfulNode, "forget", {name: kept})
    ch = channel()
    world = World(WorldConfig(seed=1))
    node_bus = can.Bus(interface="virtual", channel=ch)
    node = _ForgetfulNode(world, node_bus)
    drv = Epos4Driver(interface="virtual", channel=ch)
    try:
        await node.start()
        with pytest.raises(ConfigurationMismatch) as e:
            await drv.connect()
        assert e.value.obj is co.obj(name) and e.value.read == kept
        assert e.value.device == "epos4" and f"reads back {kept}" in str(e.value)
        assert not drv.connected
        assert node.state is State.SWITCH_ON_DISABLED          # never enabled
    finally:
        await drv.close()
        await node.close()
        node_bus.shutdown()


async def test_lost_host_heartbeat_stops_the_file_on_the_quick_stop_ramp():
    """The host goes silent (its cycle stops): after the consumer time the drive signals a
    heartbeat error (EMCY 0x8130) and its fault reaction decelerates the file at 0x6085."""
    decel = 600.0                       # file rpm/s: 60 rpm to rest in 100 ms, observable
    async with rig(quick_stop_file_rpm_s=decel, consumer_ms=DEFAULT_CONSUMER_MS) as r:
        drv, node, hp = r.drv, r.node, r.world.handpiece
        await drv.set_velocity(60.0)
        assert await until(lambda: abs(hp.omega_rpm - 60.0) < 1e-3)
        ramp: list[tuple[float, float]] = []
        await drv.stop_sync()           # the host is gone: no cycle, no heartbeat
        last_beat = drv._host_hb_t
        deadline = time.monotonic() + 2.0
        while node.state is not State.FAULT and time.monotonic() < deadline:
            if node.state is State.FAULT_REACTION_ACTIVE:
                ramp.append((time.monotonic(), hp.cmd_rpm))
            await asyncio.sleep(0.001)
        assert node.state is State.FAULT
        assert node.heartbeat_errors == 1 and node.error_code == co.HEARTBEAT_ERROR_CODE
        consumer_s = DEFAULT_CONSUMER_MS / 1000
        assert ramp[0][0] - last_beat >= consumer_s             # not before the consumer time
        # the commanded speed falls linearly at the quick-stop deceleration
        t = np.array([p[0] for p in ramp if 5.0 < p[1] < 55.0])
        v = np.array([p[1] for p in ramp if 5.0 < p[1] < 55.0])
        slope = np.polyfit(t - t[0], v, 1)[0]
        assert slope == pytest.approx(-decel, rel=0.1)
        assert await until(lambda: abs(hp.omega_rpm) < 1.0)
        assert time.monotonic() - last_beat <= stop_bound_s(consumer_s, decel)
        # the EMCY reached the driver, which names it
        exc = await read_fault(drv)
        assert "0x8130" in str(exc) and "heartbeat" in str(exc)
        assert drv.last_emcy.register == 0x11                   # generic + communication
        # the host is back: fault reset and enable, the consumer watches again
        drv.start_sync()
        await drv.fault_reset()
        await drv.enable()
        await drv.set_velocity(30.0)
        await asyncio.sleep(0.1)
        assert node.heartbeat_errors == 1 and node.state is State.OPERATION_ENABLED


async def test_a_silent_control_path_withholds_the_heartbeat_while_the_file_turns():
    """The product's 30 ms consumer, the host and the simulated drive in this process's one
    event loop: a stall of the loop past 30 ms while the test ticks is a lost host for the
    drive as well (rightly). The driver measures its longest heartbeat gap; a run whose
    ticking phase broke on such a gap, not on anything the driver did, is tried again (three
    runs at most)."""
    feed_timeout = 0.05
    for attempt in range(3):
        async with rig(feed_timeout_s=feed_timeout, consumer_ms=DEFAULT_CONSUMER_MS) as r:
            drv, node, hp = r.drv, r.node, r.world.handpiece
            await drv.set_velocity(60.0)
            drv.host_heartbeat_gap_max_s = 0.0
            t0 = time.monotonic()
            while time.monotonic() - t0 < 0.3:               # ticking: read every 2 ms
                if drv.received:
                    await drv.read()
                await asyncio.sleep(0.002)
            stalled = drv.host_heartbeat_gap_max_s >= 0.8 * DEFAULT_CONSUMER_MS / 1000
            if (node.heartbeat_errors or drv.withheld) and stalled and attempt < 2:
                continue
            assert node.heartbeat_errors == 0 and drv.withheld == 0, \
                drv.host_heartbeat_gap_max_s
            last_feed = drv._fed_t          # the control task stops; the loop runs on
            assert await until(lambda: node.state is State.FAULT, timeout=2.0)
            assert drv.withheld > 0 and node.error_code == co.HEARTBEAT_ERROR_CODE
            assert await until(lambda: abs(hp.omega_rpm) < 1.0)
            bound = feed_timeout + stop_bound_s(DEFAULT_CONSUMER_MS / 1000,
                                                DEFAULT_QUICK_STOP_FILE_RPM_S)
            assert time.monotonic() - last_feed <= bound
            assert drv.syncs_sent > 0 and drv._sync_task is not None   # only the beat stopped
            return


async def test_a_file_at_rest_keeps_its_heartbeat_without_feeds():
    async with rig(feed_timeout_s=0.05, consumer_ms=DEFAULT_CONSUMER_MS) as r:
        await r.drv.set_velocity(60.0)
        await r.drv.read() if r.drv.received else None
        await r.drv.stop()                  # at rest: nothing to supervise
        await asyncio.sleep(0.3)            # six feed timeouts without a read
        assert r.node.heartbeat_errors == 0 and r.drv.withheld == 0
        assert r.node.state is State.OPERATION_ENABLED


async def test_the_longest_heartbeat_gap_is_measured_through_a_blocked_event_loop():
    """The host's heartbeat comes from the event loop: a loop blocked 60 ms sends none for at
    least that long, and the driver reports the gap (a consumer of 250 ms does not expire)."""
    async with rig() as r:
        drv = r.drv
        assert await until(lambda: drv.host_heartbeats >= 5)
        drv.host_heartbeat_gap_max_s = 0.0
        before = drv.host_heartbeats
        await asyncio.sleep(0.05)
        quiet = drv.host_heartbeat_gap_max_s
        time.sleep(0.06)                                 # the event loop blocked
        assert await until(lambda: drv.host_heartbeats >= before + 15)
        assert quiet < 0.06 <= drv.host_heartbeat_gap_max_s
        assert r.node.heartbeat_errors == 0


@pytest.mark.parametrize("option, state", [
    (co.AbortConnectionOption.QUICK_STOP, State.QUICK_STOP_ACTIVE),     # 0x605A = 6: stay
    (co.AbortConnectionOption.DISABLE_VOLTAGE, State.SWITCH_ON_DISABLED),
])
async def test_abort_connection_options_other_than_fault(option, state):
    async with rig(abort_connection_option=option, consumer_ms=DEFAULT_CONSUMER_MS) as r:
        drv, node, hp = r.drv, r.node, r.world.handpiece
        await drv.set_velocity(60.0)
        assert await until(lambda: abs(hp.omega_rpm - 60.0) < 1e-3)
        await drv.stop_sync()
        assert await until(lambda: node.state is state, timeout=2.0)
        assert node.error_code == co.HEARTBEAT_ERROR_CODE       # signalled, not FAULT
        assert await until(lambda: abs(hp.omega_rpm) < 1.0)
        drv.start_sync()


async def test_sto_opened_by_another_source_cuts_the_power_stage_at_once():
    async with rig() as r:
        drv, node, hp = r.drv, r.node, r.world.handpiece
        await drv.set_velocity(60.0)
        assert await until(lambda: abs(hp.omega_rpm - 60.0) < 1e-3)
        node.set_sto("host-lost relay", True)
        assert node.state is State.FAULT and node.error_code == 0x8A88   # no ramp
        assert hp.cmd_rpm == 0.0 and not hp.enabled
        assert node.value("sto_inputs") == 0
        node.set_sto("host-lost relay", False)
        assert node.state is State.FAULT                        # latched until reset
        exc = await read_fault(drv)
        assert "0x8A88" in str(exc) and "STO" in str(exc)
        await drv.fault_reset()
        await drv.enable()
        assert node.state is State.OPERATION_ENABLED


async def test_socketcand_peer_that_never_greets_is_a_typed_timeout():
    async with silent_peer() as port:
        drv = Epos4Driver(interface="socketcand", host="127.0.0.1", port=port,
                          channel="vcan0", connect_timeout_s=0.3)
        t0 = time.monotonic()
        with pytest.raises(ConnectTimeout) as e:
            await drv.connect()
        assert 0.3 <= time.monotonic() - t0 <= 0.3 + 0.5
        assert e.value.device == "epos4" and f"127.0.0.1:{port}" in str(e.value)
        assert "greeting" in str(e.value)
        await drv.close()
    # nothing listening at all: refused at once, a DeviceFault naming the address
    drv = Epos4Driver(interface="socketcand", host="127.0.0.1", port=port,
                      channel="vcan0", connect_timeout_s=0.3)
    with pytest.raises(DeviceFault, match=f"127.0.0.1:{port}"):
        await drv.connect()
    await drv.close()


def test_liveness_configuration_is_checked_before_anything_is_sent():
    with pytest.raises(ConfigError, match="host_node_id"):
        Epos4Driver(interface="virtual", channel="x", node_id=5, host_node_id=5)
    with pytest.raises(ConfigError, match="consumer_heartbeat_ms"):
        Epos4Driver(interface="virtual", channel="x", consumer_ms=70_000)
    with pytest.raises(ConfigError, match="host_heartbeat_period_s"):
        Epos4Driver(interface="virtual", channel="x", consumer_ms=20,
                    host_heartbeat_period_s=0.01)
    with pytest.raises(ConfigError, match="abort_connection_option"):
        Epos4Driver(interface="virtual", channel="x", abort_connection_option=7)
    with pytest.raises(ConfigError, match="quick_stop_file_rpm_s"):
        Epos4Driver(interface="virtual", channel="x", quick_stop_file_rpm_s=0.0)


async def test_node_consumer_watches_only_after_the_first_heartbeat():
    """CiA 301: monitoring of a producer starts at its first heartbeat; the entry's layout is
    node id << 16 | time ms; a node cannot watch itself (0x06040043)."""
    ch = channel()
    world = World(WorldConfig(seed=1))
    node_bus = can.Bus(interface="virtual", channel=ch)
    tap = can.Bus(interface="virtual", channel=ch)
    node = Epos4Node(world, node_bus, node_id=3, heartbeat_period_s=0.0)
    consumer_ms = 40
    seen: list[can.Message] = []

    async def first(cob: int) -> can.Message:
        async def found() -> can.Message | None:
            seen.extend(frames(tap))
            return next((m for m in seen if m.arbitration_id == cob), None)
        deadline = time.monotonic() + 1.0
        while (m := await found()) is None:
            assert time.monotonic() < deadline, f"no frame 0x{cob:03X}"
            await asyncio.sleep(0.002)
        seen.remove(m)
        return m

    async def sdo_write(index: int, sub: int, value: int) -> co.SdoFrame:
        send(tap, 0x603, co.encode_sdo_download(index, sub, value.to_bytes(4, "little")))
        return co.decode_sdo_response(bytes((await first(0x583)).data))

    try:
        await node.start()
        word = co.encode_consumer_heartbeat(0x7F, consumer_ms)
        assert word == 0x007F_0028
        assert (await sdo_write(0x1016, 1, word)).kind == "download_ack"
        assert node.consumer == (0x7F, consumer_ms / 1000)
        await asyncio.sleep(3 * consumer_ms / 1000)          # no heartbeat yet: not watching
        assert node.heartbeat_errors == 0
        send(tap, 0x77F, b"\x05")                          # the first beat arms it
        t0 = time.monotonic()
        emcy = co.decode_emcy(bytes((await first(0x083)).data))
        assert (emcy.code, emcy.register) == (co.HEARTBEAT_ERROR_CODE, 0x11)
        assert time.monotonic() - t0 >= consumer_ms / 1000 and node.heartbeat_errors == 1
        # watching itself is refused
        abort = await sdo_write(0x1016, 1, co.encode_consumer_heartbeat(3, consumer_ms))
        assert abort.kind == "abort" and abort.abort_code == 0x0604_0043
    finally:
        await node.close()
        node_bus.shutdown()
        tap.shutdown()


async def test_current_limit_is_written_read_back_and_limits_the_motor():
    async with rig() as r:
        drv, hp = r.drv, r.world.handpiece
        assert drv.nominal_current_a == pytest.approx(0.5)       # 0x3001:01 of the motor
        await drv.set_current_limit(0.2)
        assert r.node.value("motor_output_current_limit") == 200  # mA
        assert hp.current_limit_a == pytest.approx(0.2)
        with pytest.raises(ConfigError, match="current_limit_a"):
            await drv.set_current_limit(0.6)                      # above the motor's
        with pytest.raises(SdoAbort) as e:
            await drv.sdo_write("motor_output_current_limit", 600)
        assert e.value.code == 0x0609_0031                        # value too high


async def test_recover_is_the_operators_reset_of_a_drive_fault():
    """``recover`` (what the runtime calls on reset): the fault reset then the enable
    sequence (CiA 402 transitions 15, 2, 3, 4), the file at rest until commanded."""
    async with rig() as r:
        drv, node, world = r.drv, r.node, r.world
        await drv.set_velocity(60.0)
        await asyncio.sleep(0.1)
        node.inject_emcy(0x2310)
        await read_fault(drv)
        assert await until(lambda: drv.state is State.FAULT)
        await drv.recover()
        assert drv.state is State.OPERATION_ENABLED and node.error_code == 0
        assert node.transitions[-4:] == ["15", "2", "3", "4"]
        assert world.handpiece.cmd_rpm == 0.0
        await drv.recover()                                   # nothing to reset: a no-op
        assert drv.state is State.OPERATION_ENABLED


class _LateBeatNode(Epos4Node):
    """A drive whose heartbeat, sent just before the NMT start reached it, is still on its way
    (it says PRE-OPERATIONAL and arrives after the start)."""

    stale_beats = 0

    def on_nmt(self, cmd):
        if cmd is co.NmtCommand.START and self.nmt_state is NmtState.PRE_OPERATIONAL:
            self.send_heartbeat()
            self.stale_beats += 1
        super().on_nmt(cmd)


class _NeverStartsNode(Epos4Node):
    """A drive that ignores the NMT start."""

    def on_nmt(self, cmd):
        if cmd is not co.NmtCommand.START:
            super().on_nmt(cmd)


async def _connect_to(node_cls, **drv_kw):
    ch = channel()
    world = World(WorldConfig(seed=1))
    node_bus = can.Bus(interface="virtual", channel=ch)
    node = node_cls(world, node_bus)
    drv = Epos4Driver(interface="virtual", channel=ch, consumer_ms=250, stale_after_s=0.5,
                      feed_timeout_s=None, **drv_kw)
    return node, node_bus, drv


async def test_a_heartbeat_sent_before_the_start_does_not_leave_the_node_pre_operational():
    """Connect waits for the node's own OPERATIONAL heartbeat: the stale one (PRE-OPERATIONAL,
    sent before the start) arrives first, the next comes a producer period (500 ms) later;
    the first read after connect finds the node OPERATIONAL."""
    node, node_bus, drv = await _connect_to(_LateBeatNode, heartbeat_ms=500)
    try:
        await node.start()
        t0 = time.monotonic()
        await drv.connect(sync=True)
        assert node.stale_beats == 1
        assert drv.nmt_state is NmtState.OPERATIONAL
        await drv.read()                               # no "NMT PRE_OPERATIONAL" fault
        assert time.monotonic() - t0 < 3 * 0.5 + 1.0   # within the bound, not stuck
    finally:
        await drv.close()
        await node.close()
        node_bus.shutdown()


async def test_a_node_that_never_reports_operational_fails_connect_within_three_periods():
    node, node_bus, drv = await _connect_to(_NeverStartsNode, heartbeat_ms=100)
    try:
        await node.start()
        t0 = time.monotonic()
        with pytest.raises(DeviceFault, match=r"did not report OPERATIONAL within 300 ms "
                                              r"of the NMT start \(NMT PRE_OPERATIONAL\)"):
            await drv.connect(sync=True)
        assert time.monotonic() - t0 < 5.0
    finally:
        await drv.close()
        await node.close()
        node_bus.shutdown()
