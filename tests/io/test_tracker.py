"""TrackerDriver against the simulated CiA 406 encoders: python-can's virtual bus, and
socketcand on 127.0.0.1.

Expected lengths are derived here from the anchors and the World's poses (flange by the arm's
forward kinematics, phantom by its rest pose and current origin), independently of the
simulator's own model; tolerances from the encoder's step (0.01 mm) and noise.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
import uuid
from types import SimpleNamespace

import can
import numpy as np
import pytest

from dentibot.control import strings
from dentibot.errors import ConfigError, DeviceFault
from dentibot.io import canopen_protocol as co
from dentibot.io import cia406
from dentibot.io.devices import DevicesConfig, tracker_driver
from dentibot.io.interfaces import (
    STRING_FAULT,
    STRING_OK,
    STRING_OVER_RANGE,
    STRING_SLACK,
    STRING_STALE,
    ConnectTimeout,
    PatientTracker,
)
from dentibot.io.tracker import DEFAULT_NODE_IDS, IdentityMismatch, TrackerDriver
from dentibot.sim import RealTimeStepper, TrackerSimParams, World, WorldConfig
from dentibot.sim.serve import ServePorts, VirtualDentiBot
from dentibot.sim.tracker_nodes import PRODUCT_CODE, VENDOR_ID, TrackerNodes

pytestmark = [pytest.mark.wire, pytest.mark.timeout(30)]

STEP = 0.01                      # mm per unit
NOISE = 0.003                    # mm rms (the simulator's default)
#: a reading is within half a step of quantisation plus 5 sigma of noise of the truth
LENGTH_TOL = 0.5 * STEP + 5 * NOISE


def channel() -> str:
    return f"tracker-test-{uuid.uuid4().hex}"


def expected_lengths(world: World, p: TrackerSimParams) -> np.ndarray:
    """|a_i - b_i| with both anchors carried to the robot base {0} by hand."""
    t06 = world.kin.fk(world.arm.q)
    t0m = t06 @ p.mount_in_flange
    a0 = (t0m[:3, :3] @ p.mount_mm.T).T + t0m[:3, 3]
    t0t = np.eye(4)
    t0t[:3, :3] = world.phantom_pose[:3, :3]
    t0t[:3, 3] = world.phantom_origin_0()
    t0t = t0t @ p.tooth_in_phantom
    b0 = (t0t[:3, :3] @ p.tooth_mm.T).T + t0t[:3, 3]
    return np.linalg.norm(a0 - b0, axis=1)


def tooth_in_mount(world: World, p: TrackerSimParams) -> np.ndarray:
    t0m = world.kin.fk(world.arm.q) @ p.mount_in_flange
    t0p = np.eye(4)
    t0p[:3, :3] = world.phantom_pose[:3, :3]
    t0p[:3, 3] = world.phantom_origin_0()
    return np.linalg.inv(t0m) @ t0p @ p.tooth_in_phantom


async def until(pred, timeout: float = 2.0, step: float = 0.005) -> bool:
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > deadline:
            return False
        await asyncio.sleep(step)
    return True


@contextlib.asynccontextmanager
async def rig(*, connect: bool = True, world: World | None = None, **kw):
    ch = channel()
    world = world or World(WorldConfig(seed=1))
    stop = asyncio.Event()
    stepper = asyncio.create_task(RealTimeStepper(world).run(stop))
    node_bus = can.Bus(interface="virtual", channel=ch)
    params = TrackerSimParams()
    nodes = TrackerNodes(world, node_bus, params)
    kw.setdefault("sync_producer", True)
    kw.setdefault("stale_after_s", 0.1)
    drv = TrackerDriver(interface="virtual", channel=ch, **kw)
    try:
        await nodes.start()
        if connect:
            await drv.connect()
        yield SimpleNamespace(world=world, nodes=nodes, drv=drv, params=params, channel=ch)
    finally:
        await drv.close()
        await nodes.close()
        stop.set()
        await stepper
        node_bus.shutdown()


async def fresh_sample(drv: TrackerDriver, after_seq: int = 0, timeout: float = 2.0):
    assert await until(lambda: drv.samples > after_seq + 2, timeout)
    return await drv.read()


def test_driver_satisfies_the_protocol_and_checks_its_configuration():
    assert isinstance(TrackerDriver(interface="virtual", channel="x"), PatientTracker)
    with pytest.raises(ConfigError, match="node_ids"):
        TrackerDriver(interface="virtual", channel="x", node_ids=(0x21, 0x21, 0x22))
    with pytest.raises(ConfigError, match="transmission_type"):
        TrackerDriver(interface="virtual", channel="x", transmission_type=0)
    with pytest.raises(ConfigError, match="heartbeat_timeout_s"):
        TrackerDriver(interface="virtual", channel="x", heartbeat_ms=100,
                      heartbeat_timeout_s=0.15)


async def test_identity_and_configuration_are_read_back():
    async with rig() as r:
        for nid in DEFAULT_NODE_IDS:
            ident = r.drv.nodes[nid].identity
            assert ident == {"vendor_id": VENDOR_ID, "product_code": PRODUCT_CODE,
                             "revision_number": 0x0001_0000, "serial_number": nid,
                             "device_type": 0x0002_0196}
            assert await r.drv.sdo_read(nid, "measuring_units_per_revolution") == 10_000
            assert await r.drv.sdo_read(nid, "total_measuring_range") == 30_000
            assert await r.drv.sdo_read(nid, "tpdo1_transmission_type") == 1   # every SYNC
            assert await r.drv.sdo_read(nid, "tpdo1_mapping_1") == 0x6004_0020
            assert r.nodes.node(nid).nmt_state is co.NmtState.OPERATIONAL


async def test_lengths_match_the_worlds_geometry_and_give_back_its_pose():
    async with rig() as r:
        s = await fresh_sample(r.drv)
        assert s.status == (STRING_OK,) * 6 and s.ok, r.drv.diagnose()
        want = expected_lengths(r.world, r.params)
        assert 50.0 < want.min() and want.max() < 80.0          # the mechanism's scale
        assert np.abs(np.array(s.lengths_mm) - want).max() <= LENGTH_TOL
        assert s.lengths_mm == pytest.approx([20.0 + c * STEP for c in s.counts], abs=1e-12)
        # pose from the driver's lengths, started 1 mm / 1 deg off
        truth = tooth_in_mount(r.world, r.params)
        geo = strings.StringGeometry(r.params.mount_mm, r.params.tooth_mm)
        start = truth.copy()
        start[:3, 3] += 1.0
        sigma = np.hypot(STEP / np.sqrt(12), NOISE)
        est = strings.forward(geo, s.lengths_mm, start, sigma_mm=sigma)
        assert est.ok
        err = est.pose[:3, 3] - truth[:3, 3]
        assert np.all(np.abs(err) <= 5 * est.position_std_mm), (err, est.position_std_mm)
        assert np.linalg.norm(err) < 0.05                        # a few steps at most
        # and with the samples coming at the 500 Hz SYNC, every SYNC (a loaded machine may
        # stretch the SYNC timer's periods, never shorten them)
        n0, t0 = r.drv.samples, time.monotonic()
        await asyncio.sleep(0.5)
        rate = (r.drv.samples - n0) / (time.monotonic() - t0)
        assert 250 < rate <= 505


async def test_another_master_produces_the_sync():
    async with rig(sync_producer=False) as r:
        master = can.Bus(interface="virtual", channel=r.channel)
        try:
            assert r.drv.samples == 0
            for _ in range(40):
                master.send(can.Message(arbitration_id=0x080, data=b"", is_extended_id=False))
                await asyncio.sleep(0.002)
            assert await until(lambda: r.drv.samples >= 6)
            assert r.drv.syncs_sent == 0 and r.drv.syncs_heard >= 40
            s = await r.drv.read()
            assert s.ok
        finally:
            master.shutdown()


async def test_a_stopped_node_turns_stale_then_faulted_within_its_bounds():
    async with rig(stale_after_s=0.1, heartbeat_timeout_s=0.35) as r:
        await fresh_sample(r.drv)
        r.nodes.node(0x23).muted = True
        t0 = time.monotonic()
        seen = None
        while time.monotonic() - t0 < 2.0:
            st = (await r.drv.read()).status
            if st[2] != STRING_OK:
                seen = (st, time.monotonic() - t0)
                break
            await asyncio.sleep(0.005)
        assert seen is not None
        st, dt = seen
        # stale after 0.1 s without a TPDO; the last TPDO may be up to one sample (10 ms)
        # older than the muting, plus scheduling
        assert st[2] == STRING_STALE and 0.08 <= dt <= 0.2, seen
        assert st[:2] + st[3:] == (STRING_OK,) * 5
        assert await until(lambda: r.drv.diagnose()[0x23] is not None, 0.6)
        assert "heartbeat lost" in r.drv.diagnose()[0x23]
        assert (await r.drv.read()).status[2] == STRING_FAULT
        # recovered by restarting the node
        r.nodes.node(0x23).muted = False
        await r.drv.recover()
        assert await until(lambda: r.drv.diagnose()[0x23] is None)
        await fresh_sample(r.drv, r.drv.samples)
        assert (await r.drv.read()).ok


async def test_a_broken_wire_reads_slack_and_a_long_one_over_range():
    async with rig() as r:
        await fresh_sample(r.drv)
        r.nodes.model.broken.add(1)                  # string 2 snapped: drum winds it in
        r.nodes.model.held_mm[4] = 400.0             # string 5 pulled beyond its 300 mm
        n = r.drv.samples
        s = await fresh_sample(r.drv, n)
        assert s.status[1] == STRING_SLACK and s.counts[1] == 0 and s.lengths_mm[1] == 20.0
        assert s.status[4] == STRING_OVER_RANGE and s.counts[4] == 29_999
        assert [s.status[i] for i in (0, 2, 3, 5)] == [STRING_OK] * 4
        assert s.usable == (True, False, True, True, False, True)


async def test_no_encoder_on_the_bus_is_a_connect_timeout():
    drv = TrackerDriver(interface="virtual", channel=channel(), sdo_timeout_s=0.1)
    with pytest.raises(ConnectTimeout, match="node 0x21.*device type 0x1000"):
        await drv.connect()
    await drv.close()


async def test_a_heartbeat_sent_before_the_start_does_not_fault_a_running_node():
    """Node 0x21's heartbeat, sent in PRE-OPERATIONAL, is on the bus when the NMT start
    reaches it. The driver confirms each start by a later heartbeat reporting OPERATIONAL,
    so the first samples after connect read every string (taken as the node's state after
    the start, the old heartbeat faulted string 1 until the next one, 100 ms on)."""
    async with rig(connect=False) as r:
        node = r.nodes.node(0x21)
        on_nmt = node.on_nmt

        def heartbeat_then(cmd):
            if cmd is co.NmtCommand.START:
                node.send_heartbeat()           # still PRE-OPERATIONAL
            on_nmt(cmd)
        node.on_nmt = heartbeat_then
        await r.drv.connect()
        s = await fresh_sample(r.drv)
        assert s.status == (STRING_OK,) * 6, r.drv.diagnose()


async def test_a_node_that_does_not_start_is_a_connect_timeout_naming_it():
    async with rig(connect=False, heartbeat_timeout_s=0.25) as r:
        node = r.nodes.node(0x23)
        on_nmt = node.on_nmt
        node.on_nmt = lambda cmd: None if cmd is co.NmtCommand.START else on_nmt(cmd)
        t0 = time.monotonic()
        with pytest.raises(ConnectTimeout, match=r"node 0x23 \(PRE_OPERATIONAL\).*"
                                                 "OPERATIONAL after the NMT start.*0.25 s"):
            await r.drv.connect()
        assert time.monotonic() - t0 < 5.0


async def test_an_unexpected_vendor_is_refused():
    async with rig(connect=False, vendor_id=0x1234) as r:
        with pytest.raises(IdentityMismatch, match="vendor_id 0x00000000, expected 0x00001234"):
            await r.drv.connect()


async def test_a_node_that_is_not_an_encoder_is_refused():
    async with rig(connect=False) as r:
        r.nodes.node(0x21).od[cia406.obj("device_type").address] = 0x0002_0192
        with pytest.raises(DeviceFault, match="not a CiA 406 encoder"):
            await r.drv.connect()


async def test_through_socketcand_from_the_sim_serve_configuration():
    ports = ServePorts(meca_port=0, netft_port=0, netft_http_port=0, modbus_port=0,
                       can_port=0)
    async with VirtualDentiBot(WorldConfig(seed=1), ports) as bot:
        cfg = bot.devices_config(tracker=True)
        assert cfg.tracker is not None and cfg.tracker.host == "127.0.0.1"
        again = DevicesConfig.model_validate(cfg.model_dump(mode="json"))
        assert again.cross_checks() == []
        # no handpiece driver here: the tracker produces the SYNC itself
        drv = tracker_driver(cfg.tracker.model_copy(update={"sync_producer": True}))
        try:
            await drv.connect()
            s = await fresh_sample(drv, timeout=5.0)
            assert s.ok
            want = expected_lengths(bot.world, bot.tracker_params)
            assert np.abs(np.array(s.lengths_mm) - want).max() <= LENGTH_TOL
        finally:
            await drv.close()


def test_tracker_section_cross_checks():
    base = {
        "arm": {"host": "h"}, "ft": {"host": "h"},
        "handpiece": {"interface": "virtual", "channel": "c", "node_id": 0x21},
        "estop_waiver": "bench with a hardware e-stop",
        "tracker": {"interface": "virtual", "channel": "c",
                    "mount_anchors_mm": [[0, 0, 0]] * 6, "tooth_anchors_mm": [[0, 0, 1]] * 5},
    }
    cfg = DevicesConfig.model_validate(base)
    found = dict(cfg.cross_checks())
    assert "5 entries for 6 strings" in found[("tracker", "tooth_anchors_mm")]
    assert "[33] already used" in found[("tracker", "node_ids")]
    with pytest.raises(ValueError):
        DevicesConfig.model_validate({**base, "tracker": {**base["tracker"],
                                                          "transmission_type": 0}})
