"""Epos4Driver against the simulated EPOS4 node on python-can's virtual bus.

Each test gets its own virtual channel; the World is stepped in real time by a
RealTimeStepper, the node answers from it. Expected values come from the vendor / thesis
numbers (Km 16 mNm/A, gear 67), CiA 301/402 and the World's handpiece physics.
"""

from __future__ import annotations

import asyncio
import contextlib
import struct
import threading
import time
import uuid
from types import SimpleNamespace

import can
import canopen
import pytest

from dentibot.errors import ConfigError, DeviceFault
from dentibot.io import Handpiece
from dentibot.io import canopen_protocol as co
from dentibot.io.canopen_protocol import RXPDO1, RXPDO2, TXPDO1, TXPDO2, NmtState, State
from dentibot.io.epos4 import Epos4Driver, SdoAbort
from dentibot.sim import FileFractured, HandpieceParams, RealTimeStepper, World, WorldConfig
from dentibot.sim.epos4_node import Epos4Node

pytestmark = pytest.mark.timeout(30)

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


async def test_file_fracture_sends_emcy_and_faults():
    async with rig() as r:
        await r.drv.set_velocity(60.0)
        await asyncio.sleep(0.05)
        r.world.fractured = FileFractured("torsion", r.world.t, 70.0, 5.0)
        exc = await read_fault(r.drv)
        assert "0x8611" in str(exc) and "Following error" in str(exc)
        assert r.drv.last.fault is not None


async def test_quick_stop_then_enable():
    async with rig() as r:
        drv = r.drv
        await drv.set_velocity(60.0)
        await asyncio.sleep(0.1)
        await drv.quick_stop()
        assert await until(lambda: drv.state is State.QUICK_STOP_ACTIVE)
        assert r.world.handpiece.cmd_rpm == 0.0
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
        drv, node = r.drv, r.node
        await asyncio.sleep(0.05)
        await drv.read()
        node.muted = True                        # cable cut
        exc = await read_fault(drv)
        assert "stale" in str(exc) and "limit 50 ms" in str(exc)
        node.muted = False
        assert await until(lambda: time.monotonic() - drv.last.t < 0.01)
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
