"""python-canopen, with the shipped EDS, against the simulated EPOS4 node.

A third-party CANopen master (python-canopen's ``BaseNode402`` built from
``dentibot/io/epos4.eds``) drives the node on python-can's ``virtual`` bus, through the
socketcand endpoint on loopback, and through ``dentibot sim serve``'s bus attachment.

Expected values come from the documents, not from the code under test: the CiA 301 identity
object holding maxon motor ag's vendor id 0x000000FB, and maxon's own configuration file for an
EPOS4 Module 50/15 (product code 0x65520000, revision 0x01700000, device type 0x00020192, the
default PDO mapping); CiA 402's bit assignment of 0x6502 (bit 0 profile position, bit 2 profile
velocity: the two modes the node documents); the node's documented quick-stop ramp (0x6085,
motor rpm/s, the power stage on) and velocity window (20 motor rpm); the handpiece's 67:1 gear
and 10 ms speed loop.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import math
import threading
import time
import uuid
from configparser import RawConfigParser

import can
import canopen
import pytest
from canopen.profiles.p402 import BaseNode402

from dentibot.errors import ConfigError
from dentibot.io import canopen_protocol as co
from dentibot.io.canopen_protocol import NmtState, State
from dentibot.sim import RealTimeStepper, World, WorldConfig
from dentibot.sim.can_bus_attach import CanBusBridge, open_bus
from dentibot.sim.epos4_node import EDS_PATH, Epos4Node, render_eds
from dentibot.sim.serve import ServePorts, VirtualDentiBot
from dentibot.sim.socketcand import SocketcandServer

pytestmark = [pytest.mark.wire, pytest.mark.timeout(60)]

MAXON_VENDOR_ID = 0x0000_00FB          # CiA vendor id of maxon motor ag
EPOS4_PRODUCT_CODE = 0x6552_0000       # EPOS4 Module 50/15 (maxon's configuration file)
EPOS4_REVISION = 0x0170_0000           # firmware 0x0170 in the high word
DEVICE_TYPE_402 = 0x0002_0192          # CiA 402 drive (low word 402), servo (high word 2)
PP_BIT, PV_BIT, CSV_BIT = 0, 2, 8      # CiA 402, object 6502h
GEAR = 67.0                            # handpiece gear, thesis 5.1
TAU_S = 0.010                          # the handpiece's speed loop (HandpieceParams.tau_s)
VELOCITY_WINDOW_RPM = 20               # the node's "target reached" window (motor rpm)
SPEED_ZERO_RPM = 10                    # the node's "speed zero" threshold (motor rpm)
SCHED_S = 0.08                         # scheduling allowance on a loaded, shared machine
SW_TARGET_REACHED = 1 << 10            # statusword bit 10 (CiA 402)


def channel() -> str:
    return f"canopen-eds-{uuid.uuid4().hex}"


async def in_thread(fn, timeout: float = 40.0):
    """Run the blocking python-canopen client ``fn`` in a thread while this event loop keeps
    serving the node; its exception, if any, is raised here."""
    box: dict = {}

    def run() -> None:
        try:
            box["result"] = fn()
        except BaseException as exc:  # noqa: BLE001 - handed to the test's thread
            box["error"] = exc

    th = threading.Thread(target=run, name="python-canopen-client", daemon=True)
    th.start()
    deadline = time.monotonic() + timeout
    while th.is_alive() and time.monotonic() < deadline:
        await asyncio.sleep(0.01)
    assert not th.is_alive(), "the python-canopen client did not finish"
    th.join()
    if "error" in box:
        raise box["error"]
    return box.get("result")


@contextlib.contextmanager
def master(node_id: int, **bus):
    """A python-canopen network on ``bus`` with a BaseNode402 built from the shipped EDS."""
    net = canopen.Network()
    net.NOTIFIER_CYCLE = 0.05
    net.connect(**bus)
    try:
        node = net.add_node(BaseNode402(node_id, str(EDS_PATH)))
        # the drive answers at once; the allowances are for a loaded machine
        node.TIMEOUT_SWITCH_OP_MODE = 3.0
        node.TIMEOUT_SWITCH_STATE_FINAL = 5.0
        node.TIMEOUT_SWITCH_STATE_SINGLE = 2.0
        node.TIMEOUT_CHECK_TPDO = 1.0
        node.sdo.RESPONSE_TIMEOUT = 2.0
        yield net, node
    finally:
        net.sync.stop()
        net.disconnect()


@contextlib.asynccontextmanager
async def drive(node_id: int = 3):
    """A World stepped in real time and an Epos4Node on a fresh virtual channel."""
    ch = channel()
    world = World(WorldConfig(seed=1))
    stop = asyncio.Event()
    stepper = asyncio.create_task(RealTimeStepper(world).run(stop))
    bus = can.Bus(interface="virtual", channel=ch)
    node = Epos4Node(world, bus, node_id)
    try:
        await node.start()
        yield ch, node
    finally:
        await node.close()
        stop.set()
        await stepper
        bus.shutdown()


def eds_variables(od: canopen.ObjectDictionary):
    for obj in od.values():
        if isinstance(obj, canopen.objectdictionary.ODVariable):
            yield obj
        else:
            yield from obj.values()


# ---------------------------------------------------------------- the file


def test_the_shipped_eds_is_the_rendered_object_table():
    assert EDS_PATH.is_file()
    assert EDS_PATH.read_text(encoding="utf-8") == render_eds(), (
        "dentibot/io/epos4.eds is out of date: regenerate it with "
        "python -c 'from dentibot.sim.epos4_node import write_eds; write_eds()'")


def test_the_eds_is_a_cia_306_file_python_canopen_reads():
    eds = RawConfigParser(inline_comment_prefixes=(";",))
    eds.optionxform = str
    eds.read(EDS_PATH, encoding="utf-8")
    for section in ("FileInfo", "DeviceInfo", "DummyUsage", "MandatoryObjects",
                    "OptionalObjects", "ManufacturerObjects"):
        assert eds.has_section(section), section
    # CiA 301's mandatory objects, listed as such
    listed = {int(eds.get("MandatoryObjects", str(k)), 0)
              for k in range(1, eds.getint("MandatoryObjects", "SupportedObjects") + 1)}
    assert listed == {0x1000, 0x1001, 0x1018}
    # every object section is listed in exactly one of the three lists
    objects = {int(s, 16) for s in eds.sections() if len(s) == 4 and s.isalnum()
               and all(c in "0123456789ABCDEF" for c in s)}
    lists = []
    for title in ("MandatoryObjects", "OptionalObjects", "ManufacturerObjects"):
        n = eds.getint(title, "SupportedObjects")
        lists += [int(eds.get(title, str(k)), 0) for k in range(1, n + 1)]
    assert sorted(lists) == sorted(objects)
    # a record's SubNumber counts its sub-index sections
    for index in objects:
        if eds.has_option(f"{index:04X}", "SubNumber"):
            subs = [s for s in eds.sections() if s.upper().startswith(f"{index:04X}SUB")]
            assert eds.getint(f"{index:04X}", "SubNumber") == len(subs)
    od = canopen.import_od(str(EDS_PATH), 3)
    info = od.device_information
    assert info.vendor_number == MAXON_VENDOR_ID
    assert info.product_number == EPOS4_PRODUCT_CODE
    assert info.revision_number == EPOS4_REVISION
    assert (info.nr_of_RXPDO, info.nr_of_TXPDO) == (4, 4)
    # the objects python-canopen's CiA 402 node relies on, by index and by name
    for index in (0x6040, 0x6041, 0x6060, 0x6061, 0x6502, 0x606C, 0x60FF, 0x607A, 0x6071):
        assert index in od, hex(index)
    assert od["Identity object"]["Vendor ID"].index == 0x1018
    assert od["Supported drive modes"].index == 0x6502
    assert od["Controlword"].pdo_mappable and od["Statusword"].pdo_mappable
    assert od[0x1800][1].default == 0x4000_0180 + 3      # $NODEID-relative COB-ID


# ---------------------------------------------------------------- over the wire


async def test_every_eds_object_is_served_with_its_declared_type_and_access():
    """Both ways: every EDS entry answers an SDO upload with its declared length (and its
    declared default), refuses a download exactly when read-only; the node serves nothing
    the EDS leaves out."""
    node_id = 5
    od = canopen.import_od(str(EDS_PATH), node_id)
    declared = {(v.index, v.subindex) for v in eds_variables(od)}

    async with drive(node_id) as (ch, node):
        assert node.object_addresses == declared

        def client():
            problems = []
            with master(node_id, interface="virtual", channel=ch) as (_, remote):
                for var in eds_variables(od):
                    where = f"0x{var.index:04X}:{var.subindex:02X} {var.name}"
                    assert var.readable, where              # no write-only objects here
                    # the bytes as sent (sdo.upload would cut them to the declared size)
                    with remote.sdo.open(var.index, var.subindex, buffering=0) as fp:
                        indicated, data = fp.size, fp.read()
                    size = var.STRUCT_TYPES[var.data_type].size
                    if (indicated, len(data)) != (size, size):
                        problems.append(f"{where}: {indicated} bytes, declared {size}")
                        continue
                    value = var.decode_raw(data)
                    if var.default is not None and value != var.default:
                        problems.append(f"{where}: reads {value}, EDS default {var.default}")
                    try:
                        remote.sdo.download(var.index, var.subindex, data)
                        refused = None
                    except canopen.SdoAbortedError as exc:
                        refused = exc.code
                    if var.writable and refused == 0x0601_0002:
                        problems.append(f"{where}: declared {var.access_type}, read-only")
                    if not var.writable and refused != 0x0601_0002:
                        problems.append(f"{where}: declared {var.access_type}, "
                                        f"write answered {refused}")
                # what the EDS leaves out is not there: sub-indices past or between the
                # declared ones, and objects of CiA 301/402 and the EPOS4 not implemented
                for index in sorted({i for i, _ in declared}):
                    subs = {s for i, s in declared if i == index}
                    for sub in set(range(max(subs) + 2)) - subs:
                        code = _abort(remote, index, sub)
                        if code != 0x0609_0011:
                            problems.append(f"0x{index:04X}:{sub:02X}: {code} (no sub)")
                for index in (0x1002, 0x1003, 0x1005, 0x1008, 0x100C, 0x1010, 0x1014, 0x1200,
                              0x1404, 0x1804, 0x2000, 0x3002, 0x30D2, 0x6062, 0x6065, 0x606B,
                              0x6078, 0x6098, 0x60F4, 0x6402):
                    code = _abort(remote, index, 0)
                    if code != 0x0602_0000:
                        problems.append(f"0x{index:04X}: {code} (no object)")
            return problems

        assert await in_thread(client) == []
        assert node.state is State.SWITCH_ON_DISABLED      # writing values back moved nothing


def _abort(remote, index: int, sub: int) -> int | None:
    try:
        remote.sdo.upload(index, sub)
    except canopen.SdoAbortedError as exc:
        return exc.code
    return None


async def test_identity_and_supported_drive_modes_by_sdo():
    async with drive(3) as (ch, _):
        def client():
            with master(3, interface="virtual", channel=ch) as (_, remote):
                ident = remote.sdo["Identity object"]
                return {
                    "device_type": remote.sdo["Device type"].raw,
                    "count": ident[0].raw,
                    "vendor": ident["Vendor ID"].raw,
                    "product": ident["Product code"].raw,
                    "revision": ident["Revision number"].raw,
                    "serial": ident["Serial number"].raw,
                    "modes": remote.sdo[0x6502].raw,
                    "pv": remote.is_op_mode_supported("PROFILED VELOCITY"),
                    "pp": remote.is_op_mode_supported("PROFILED POSITION"),
                    "csv": remote.is_op_mode_supported("CYCLIC SYNCHRONOUS VELOCITY"),
                }

        got = await in_thread(client)
    assert got["device_type"] == DEVICE_TYPE_402 and got["device_type"] & 0xFFFF == 402
    assert got["count"] == 4
    assert got["vendor"] == MAXON_VENDOR_ID
    assert got["product"] == EPOS4_PRODUCT_CODE
    assert got["revision"] == EPOS4_REVISION
    assert isinstance(got["serial"], int)
    assert got["modes"] == (1 << PP_BIT) | (1 << PV_BIT)
    assert (got["pv"], got["pp"], got["csv"]) == (True, True, False)


async def test_op_mode_is_read_and_set_through_basenode402():
    async with drive(3) as (ch, node):
        def client():
            with master(3, interface="virtual", channel=ch) as (_, remote):
                seen = [remote.op_mode]
                remote.op_mode = "PROFILED VELOCITY"
                seen.append(remote.op_mode)
                remote.op_mode = "PROFILED POSITION"
                seen.append(remote.op_mode)
                with pytest.raises(TypeError):       # not advertised in 0x6502
                    remote.op_mode = "CYCLIC SYNCHRONOUS VELOCITY"
                seen.append(remote.op_mode)
                return seen

        seen = await in_thread(client)
        assert seen == ["NO MODE", "PROFILED VELOCITY", "PROFILED POSITION",
                        "PROFILED POSITION"]
        assert node.value("modes_of_operation_display") == co.Mode.PROFILE_POSITION


async def test_state_machine_velocity_and_quick_stop_through_basenode402():
    """Enable through python-canopen's CiA 402 state machine, turn the file at 150 rpm, then
    quick stop: the speed falls on the 0x6085 ramp, and enable operation restarts it."""
    target = round(150 * GEAR)                   # motor rpm (0x60FF is on the motor side)
    decel = round(300 * GEAR)                    # 0x6085, motor rpm/s: 0.5 s from 150 rpm
    async with drive(3) as (ch, node):
        def client():
            with master(3, interface="virtual", channel=ch) as (_, remote):
                out = {}
                remote.op_mode = "PROFILED VELOCITY"
                remote.sdo["Quick stop deceleration"].raw = decel
                remote.state = "OPERATION ENABLED"
                out["enabled"] = remote.state
                remote.sdo["Target velocity"].raw = target
                deadline = time.monotonic() + 3.0
                while time.monotonic() < deadline:
                    sw = remote.sdo["Statusword"].raw
                    v = remote.sdo["Velocity actual value"].raw
                    if sw & SW_TARGET_REACHED and abs(v - target) <= VELOCITY_WINDOW_RPM:
                        break
                out["running"] = (sw, v)
                time.sleep(0.1)                       # steady: well past 5 tau
                v0 = remote.sdo["Velocity actual value"].raw
                t_w0 = time.monotonic()
                remote.controlword = 0x02             # quick stop (CiA 402)
                t_w1 = time.monotonic()
                samples = []
                while time.monotonic() - t_w0 < 1.5:
                    s0 = time.monotonic()
                    v = remote.sdo["Velocity actual value"].raw
                    samples.append((s0, time.monotonic(), v))
                    if abs(v) <= SPEED_ZERO_RPM and len(samples) > 3:
                        break
                out.update(v0=v0, t_w=(t_w0, t_w1), samples=samples)
                time.sleep(0.05)
                out["after_stop"] = remote.state      # 0x605A = 6: stays in quick stop
                remote.state = "OPERATION ENABLED"    # transition 16
                deadline = time.monotonic() + 3.0
                while time.monotonic() < deadline:
                    v = remote.sdo["Velocity actual value"].raw
                    if abs(v - target) <= VELOCITY_WINDOW_RPM:
                        break
                out["restarted"] = (remote.state, v)
                remote.state = "SWITCH ON DISABLED"
                out["disabled"] = remote.state
                return out

        out = await in_thread(client)
        assert "16" in node.transitions and node.transitions[-1] in ("9", "7")
    assert out["enabled"] == "OPERATION ENABLED"
    sw, v = out["running"]
    assert sw & SW_TARGET_REACHED and abs(v - target) <= VELOCITY_WINDOW_RPM
    v0 = out["v0"]
    assert abs(v0 - target) <= VELOCITY_WINDOW_RPM
    t_w0, t_w1 = out["t_w"]
    samples = out["samples"]
    ramp = [s for s in samples if s[2] > SPEED_ZERO_RPM]
    assert len(ramp) >= 5, samples
    for s0, s1, v in samples:
        # the node read 0x606C somewhere in [s0, s1] and took the quick stop in [t_w0, t_w1];
        # the motor follows the ramp v0 - decel t through a first-order loop (lag decel tau)
        lo = v0 - decel * (s1 - t_w0 + SCHED_S) - VELOCITY_WINDOW_RPM
        hi = v0 - decel * (s0 - t_w1 - SCHED_S) + decel * TAU_S + VELOCITY_WINDOW_RPM
        assert max(lo, -VELOCITY_WINDOW_RPM) <= v <= min(hi, v0 + VELOCITY_WINDOW_RPM), (
            s0 - t_w0, v, lo, hi)
    # at rest after v0 / decel (0.5 s), plus the loop's lag decaying to the speed-zero band
    stopped = next(s0 for s0, _, v in samples if abs(v) <= SPEED_ZERO_RPM)
    t_rest = v0 / decel
    settle = TAU_S * (1 + max(0.0, math.log(decel * TAU_S / SPEED_ZERO_RPM)))
    assert t_rest - SCHED_S <= stopped - t_w0 <= t_rest + settle + 2 * SCHED_S
    assert out["after_stop"] == "QUICK STOP ACTIVE"
    assert out["restarted"][0] == "OPERATION ENABLED"
    assert abs(out["restarted"][1] - target) <= VELOCITY_WINDOW_RPM
    assert out["disabled"] == "SWITCH ON DISABLED"


async def test_heartbeat_and_nmt_through_python_canopen():
    async with drive(3) as (ch, node):
        def client():
            with master(3, interface="virtual", channel=ch) as (_, remote):
                first = remote.nmt.wait_for_heartbeat(timeout=2.0)
                beats = []
                remote.nmt.add_heartbeat_callback(lambda state: beats.append(time.monotonic()))
                time.sleep(0.55)
                default_beats = len(beats)
                remote.sdo["Producer heartbeat time"].raw = 50
                remote.nmt.state = "OPERATIONAL"
                second = remote.nmt.wait_for_heartbeat(timeout=2.0)
                beats.clear()
                time.sleep(0.5)
                fast = list(beats)
                remote.nmt.state = "PRE-OPERATIONAL"
                third = remote.nmt.wait_for_heartbeat(timeout=2.0)
                return first, default_beats, second, fast, third

        first, default_beats, second, fast, third = await in_thread(client)
        assert node.nmt_state is NmtState.PRE_OPERATIONAL
    assert first == "PRE-OPERATIONAL"
    # the default producer time is 100 ms (the EDS's DefaultValue): 5 or so in 0.55 s
    assert 3 <= default_beats <= 7
    assert second == "OPERATIONAL"
    gaps = [b - a for a, b in itertools.pairwise(fast)]
    assert len(gaps) >= 5
    assert 0.040 <= sum(gaps) / len(gaps) <= 0.050 + SCHED_S / 2
    assert third == "PRE-OPERATIONAL"


async def test_pdo_mapping_read_configured_and_used_by_basenode402():
    """The default mapping read over SDO is the EDS's default; a master remaps it with
    python-canopen, and BaseNode402 then runs the state machine over PDOs and SYNC."""
    target = round(100 * GEAR)
    async with drive(3) as (ch, node):
        def client():
            with master(3, interface="virtual", channel=ch) as (net, remote):
                remote.nmt.wait_for_heartbeat(timeout=2.0)
                remote.tpdo.read()
                remote.rpdo.read()
                read = {f"T{n}": (m.enabled, m.cob_id, m.trans_type, [v.index for v in m])
                        for n, m in remote.tpdo.map.items()}
                read |= {f"R{n}": (m.enabled, m.cob_id, m.trans_type, [v.index for v in m])
                         for n, m in remote.rpdo.map.items()}
                # the same maps from the EDS's default values alone (no bus)
                shadow = canopen.Network().add_node(BaseNode402(3, str(EDS_PATH)))
                shadow.tpdo.read(from_od=True)
                shadow.rpdo.read(from_od=True)
                from_eds = {f"T{n}": (m.enabled, m.cob_id, m.trans_type,
                                      [v.index for v in m])
                            for n, m in shadow.tpdo.map.items()}
                from_eds |= {f"R{n}": (m.enabled, m.cob_id, m.trans_type,
                                       [v.index for v in m])
                             for n, m in shadow.rpdo.map.items()}
                # remap: RxPDO2 = mode + target velocity, TxPDO2 = statusword + mode
                # display + velocity actual, on every SYNC
                rx2 = remote.rpdo[2]
                rx2.clear()
                rx2.add_variable("Modes of operation")
                rx2.add_variable("Target velocity")
                rx2.enabled = True
                tx2 = remote.tpdo[2]
                tx2.clear()
                tx2.add_variable("Statusword")
                tx2.add_variable("Modes of operation display")
                tx2.add_variable("Velocity actual value")
                tx2.trans_type = 1
                tx2.enabled = True
                remote.rpdo.save()
                remote.tpdo.save()
                mapped = [remote.sdo[0x1601][1].raw, remote.sdo[0x1601][2].raw,
                          remote.sdo[0x1A01][3].raw]
                remote.nmt.state = "OPERATIONAL"
                net.sync.start(0.01)
                remote.setup_402_state_machine(read_pdos=False)
                rx2["Target velocity"].raw = 0
                remote.op_mode = "PROFILED VELOCITY"          # over RxPDO2
                mode = remote.op_mode                         # from TxPDO2
                remote.state = "OPERATION ENABLED"            # controlword over RxPDO1
                enabled = remote.state
                rx2["Target velocity"].raw = target
                rx2.transmit()
                deadline = time.monotonic() + 3.0
                while time.monotonic() < deadline:
                    tx2.wait_for_reception(1.0)
                    v = tx2["Velocity actual value"].raw
                    if abs(v - target) <= VELOCITY_WINDOW_RPM:
                        break
                remote.state = "SWITCH ON DISABLED"
                net.sync.stop()
                return read, from_eds, mapped, mode, enabled, v

        read, from_eds, mapped, mode, enabled, v = await in_thread(client)
        assert node.rx_layouts[2].words == (0x6060_0008, 0x60FF_0020)
    # the EPOS4's default mapping (maxon's EDS: TxPDO1 statusword, TxPDO2 statusword + mode
    # display, RxPDO1 controlword, RxPDO2 controlword + mode), the same read either way
    assert read == from_eds
    assert read["T1"] == (True, 0x183, 1, [0x6041])
    assert read["T2"] == (True, 0x283, 1, [0x6041, 0x6061])
    assert read["R1"] == (True, 0x203, 255, [0x6040])
    assert read["R2"] == (True, 0x303, 255, [0x6040, 0x6060])
    assert not read["T3"][0] and not read["R4"][0]
    assert mapped == [0x6060_0008, 0x60FF_0020, 0x606C_0020]
    assert mode == "PROFILED VELOCITY"
    assert enabled == "OPERATION ENABLED"
    assert abs(v - target) <= VELOCITY_WINDOW_RPM


# ---------------------------------------------------------------- other buses


async def test_python_canopen_through_the_socketcand_endpoint():
    ch = channel()
    world = World(WorldConfig(seed=1))
    node_bus = can.Bus(interface="virtual", channel=ch)
    server_bus = can.Bus(interface="virtual", channel=ch)
    node = Epos4Node(world, node_bus, 4)
    server = SocketcandServer(server_bus, port=0)
    try:
        await node.start()
        await server.start()

        def client():
            with master(4, interface="socketcand", host="127.0.0.1", port=server.port,
                        channel="vcan0") as (_, remote):
                state = remote.nmt.wait_for_heartbeat(timeout=3.0)
                vendor = remote.sdo["Identity object"]["Vendor ID"].raw
                remote.op_mode = "PROFILED VELOCITY"
                remote.state = "OPERATION ENABLED"
                enabled = remote.state
                remote.state = "SWITCH ON DISABLED"
                return state, vendor, remote.op_mode, enabled

        got = await in_thread(client)
    finally:
        await server.close()
        await node.close()
        node_bus.shutdown()
        server_bus.shutdown()
    assert got == ("PRE-OPERATIONAL", MAXON_VENDOR_ID, "PROFILED VELOCITY", "OPERATION ENABLED")
    assert server.clients_served == 1


def test_the_bridge_forwards_both_ways_without_echo():
    inner_ch, outer_ch = channel(), channel()
    inner_peer = can.Bus(interface="virtual", channel=inner_ch)
    outer_peer = can.Bus(interface="virtual", channel=outer_ch)
    bridge = CanBusBridge(can.Bus(interface="virtual", channel=inner_ch),
                          can.Bus(interface="virtual", channel=outer_ch), own_buses=True)
    try:
        with bridge:
            inner_peer.send(can.Message(arbitration_id=0x701, data=b"\x7f",
                                        is_extended_id=False))
            got = outer_peer.recv(2.0)
            assert (got.arbitration_id, bytes(got.data), got.is_extended_id) == \
                (0x701, b"\x7f", False)
            outer_peer.send(can.Message(arbitration_id=0x1234567, data=b"\x01\x02",
                                        is_extended_id=True))
            got = inner_peer.recv(2.0)
            assert (got.arbitration_id, bytes(got.data), got.is_extended_id) == \
                (0x1234567, b"\x01\x02", True)
            time.sleep(0.1)
            # nothing came back to where it was sent from
            assert inner_peer.recv(0.05) is None and outer_peer.recv(0.05) is None
        assert (bridge.to_outer, bridge.to_inner, bridge.send_errors) == (1, 1, 0)
    finally:
        bridge.close()
        inner_peer.shutdown()
        outer_peer.shutdown()


def test_a_missing_kernel_interface_names_the_set_up_step():
    with pytest.raises(ConfigError, match="ip link add dev dbnovcan9 type vcan"):
        open_bus("socketcan", "dbnovcan9")


async def test_sim_serve_attaches_the_node_to_another_python_can_bus():
    """``dentibot sim serve --can-interface virtual --can-channel X``: a master on that bus
    and a socketcand client see the same node."""
    ext = channel()
    ports = ServePorts(meca_port=0, netft_port=0, netft_http_port=0, modbus_port=0,
                       can_port=0, can_channel=ext, can_interface="virtual", node_id=6)
    async with VirtualDentiBot(WorldConfig(seed=1), ports) as bot:
        assert bot.ports["can_interface"] == "virtual"

        def client():
            sock_bus = can.Bus(interface="socketcand", host="127.0.0.1",
                               port=bot.ports["can_port"], channel=ext)
            try:
                with master(6, interface="virtual", channel=ext) as (_, remote):
                    state = remote.nmt.wait_for_heartbeat(timeout=3.0)
                    product = remote.sdo["Identity object"]["Product code"].raw
                    remote.op_mode = "PROFILED VELOCITY"
                    remote.state = "OPERATION ENABLED"
                    enabled = remote.state
                    remote.state = "SWITCH ON DISABLED"
                # the socketcand client saw the master's SDO requests, the node's answers
                # and its heartbeat
                seen: set[int] = set()
                deadline = time.monotonic() + 3.0
                while not {0x606, 0x586, 0x706} <= seen and time.monotonic() < deadline:
                    if (m := sock_bus.recv(0.1)) is not None:
                        seen.add(m.arbitration_id)
            finally:
                sock_bus.shutdown()
            return state, product, enabled, seen

        *got, seen = await in_thread(client)
        assert bot.can_bridge is not None and bot.can_bridge.send_errors == 0
        assert bot.can_bridge.to_outer > 0 and bot.can_bridge.to_inner > 0
    assert got == ["PRE-OPERATIONAL", EPOS4_PRODUCT_CODE, "OPERATION ENABLED"]
    assert {0x606, 0x586, 0x706} <= seen
