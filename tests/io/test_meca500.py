"""Meca500 driver against the Meca500 wire simulator over TCP on 127.0.0.1.

The World is stepped in real time by a RealTimeStepper. Expected motions are derived from the
commands the simulated robot actually executed (recorded at ``world.arm.command_velocity``, in
world time) and from the documented servo model (first-order lag, tau = 8 ms, ts = 2 ms):

- the velocity reference is on while the newest MoveJointsVel is younger than the velocity
  timeout; a first-order lag with unit DC gain moves a joint, once back at rest, by exactly
  ``rate x (time the reference was on)``;
- while moving, it lags that by ``LAG * qdot`` whatever the history: tau q'' = ref - q'
  integrates to ``integral(ref) - q = tau q'``; with the exact discretisation
  v_k = v_(k-1) + a (ref_k - v_(k-1)), a = 1 - exp(-ts/tau), the sum gives
  LAG = ts (1/a - 1) = 7.04 ms for tau = 8 ms (tau - ts/2 to first order).
Tolerances: one world step per start/stop of the reference (``rate x ts``) and the 0.001 deg
encoder quantum of the measured joints (twice, start and end).
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import time
from types import SimpleNamespace

import numpy as np
import pytest
from silent_peer import silent_peer

from dentibot.errors import ConfigError, DeviceFault
from dentibot.io import Arm
from dentibot.io.interfaces import ConnectTimeout
from dentibot.io.meca500 import Meca500Driver
from dentibot.io.meca500_protocol import RobotStatus, decode_response
from dentibot.sim import RealTimeStepper, World, WorldConfig
from dentibot.sim.meca500_server import Meca500Server
from dentibot.sim.world import HOME_Q_DEG

TS = 0.002          # World period (s)
TAU = 0.008         # servo lag of the World's arm (s), ArmParams.servo_tau_s
Q_RES = 0.001       # encoder quantum of the measured joints (deg)
LAG = TS * (1.0 / -math.expm1(-TS / TAU) - 1.0)
V = (10.0, -5.0, 8.0, 20.0, -15.0, 30.0)

pytestmark = [pytest.mark.wire, pytest.mark.timeout(30)]


@contextlib.asynccontextmanager
async def rig(step: bool = True, **server_kw):
    """World (+ real-time stepper) + simulator on ephemeral ports + driver factory; everything
    is closed on exit, inside the test (the suite's leak guard checks right after it)."""
    world = World(WorldConfig())
    stop = asyncio.Event()
    task = asyncio.create_task(RealTimeStepper(world).run(stop)) if step else None
    server = Meca500Server(world, port=0, **server_kw)
    drivers: list[Meca500Driver] = []

    def make(**kw) -> Meca500Driver:
        # these tests script the driver with pauses longer than a control period: the
        # connection watchdog has tests of its own
        kw.setdefault("connection_watchdog_s", 0)
        d = Meca500Driver("127.0.0.1", server.port, server.monitor_port, **kw)
        drivers.append(d)
        return d

    try:
        await server.start()
        yield SimpleNamespace(world=world, server=server, make=make)
    finally:
        for d in drivers:
            await d.close()
        await server.close()
        if task is not None:
            stop.set()
            await task


async def ready(d: Meca500Driver) -> Meca500Driver:
    await d.connect()
    await d.activate()
    await d.home()
    await d.sync()
    return d


async def until(cond, timeout: float = 3.0, what: str = "condition") -> None:
    end = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > end:
            raise AssertionError(f"timed out waiting for {what}")
        await asyncio.sleep(0.002)


async def world_wait(world: World, seconds: float) -> None:
    t0 = world.t
    await until(lambda: world.t >= t0 + seconds - 1e-9, timeout=10 * seconds + 2,
                what=f"world time +{seconds} s")


async def fresh(d: Meca500Driver):
    """A joint state from a cycle that started after this call (and its cycle)."""
    n = d.received
    await until(lambda: d.received >= n + 2, what="two monitoring cycles")
    return await d.read(), d.last_cycle


def record_vel_commands(world: World) -> list[float]:
    """World times at which the robot applied a MoveJointsVel."""
    arm = world.arm
    times: list[float] = []
    original = arm.command_velocity

    def recording(qdot, t):
        times.append(t)
        return original(qdot, t)

    arm.command_velocity = recording
    return times


def reference_on(times: list[float], timeout: float, until_t: float = math.inf):
    """(seconds the velocity reference was on up to ``until_t``, number of on-segments)."""
    total, segments = 0.0, 0
    for i, t in enumerate(times):
        if t >= until_t:
            break
        end = min(t + timeout, until_t)
        if i + 1 < len(times) and times[i + 1] < end:
            end = times[i + 1]
        else:
            segments += 1                   # the reference drops after this command
        total += end - t
    return total, max(segments, 1)


async def stream(d: Meca500Driver, v, seconds: float, rate_hz: float = 500.0,
                 on_tick=None) -> int:
    """MoveJointsVel at ``rate_hz`` on absolute deadlines; returns the commands sent."""
    loop = asyncio.get_running_loop()
    t0 = nxt = loop.time()
    n = 0
    while loop.time() - t0 < seconds:
        await d.move_joints_vel(v)
        n += 1
        if on_tick is not None:
            await on_tick(loop.time() - t0)
        nxt += 1.0 / rate_hz
        await asyncio.sleep(max(0.0, nxt - loop.time()))
    return n


async def read_frame(reader: asyncio.StreamReader, skip=()) -> bytes:
    while True:
        frame = (await asyncio.wait_for(reader.readuntil(b"\0"), 3.0))[:-1]
        if decode_response(frame).code not in skip:
            return frame


# --------------------------------------------------------------------------- handshake
async def test_official_client_handshake_raw_sockets():
    """Exactly the vendor client's connect sequence (devices.md), with raw bytes."""
    async with rig(step=False) as r:
        reader, writer = await asyncio.open_connection("127.0.0.1", r.server.port)
        try:
            assert await read_frame(reader) == b"[3000][Connected to Meca500 R3 v9.3.0]"
            writer.write(b"\0" b"-GetRobotSerial\0" b"-GetFwVersionFull\0"
                         b"-GetRealTimeMonitoring\0" b"-GetMonitoringInterval\0"
                         b"-SetRtc(1700000000)\0" b"-SetCtrlPortMonitoring(1)\0")
            frames = [decode_response(await read_frame(reader)) for _ in range(6)]
            assert [f.code for f in frames] == [2083, 2082, 2117, 2116, 2096, 2007]
            assert frames[0].payload and frames[1].payload.startswith("9.3")
            assert frames[2].payload == ""                          # no optional data yet
            assert frames[3].values()[0] == pytest.approx(1 / 60, abs=1e-6)  # 6 decimals
            assert RobotStatus.from_payload(frames[5].payload) == RobotStatus(
                False, False, False, False, False, True, True)
            assert r.server.rtc_s == 1700000000 and r.server.bad_frames == 0
            # from now on the monitoring cycles come on the control port too
            codes = []
            while 2230 not in codes or 2200 not in codes:
                codes.append(decode_response(await read_frame(reader)).code)
            assert codes[codes.index(2200):codes.index(2200) + 3] == [2200, 2201, 2230]
        finally:
            writer.close()
            await writer.wait_closed()


async def test_second_control_client_is_refused():
    async with rig(step=False) as r:
        d = r.make()
        await d.connect()
        reader, writer = await asyncio.open_connection("127.0.0.1", r.server.port)
        try:
            assert await reader.read() == \
                b"[3001][Another user is already connected, closing connection.]\0"
        finally:                                       # read() returned at EOF: closed by it
            writer.close()
            await writer.wait_closed()
        d2 = r.make()
        with pytest.raises(DeviceFault, match=r"3001.*one control client"):
            await d2.connect()
        assert not d2.connected and r.server.refused_clients == 2
        assert await d.get_joints() == pytest.approx(HOME_Q_DEG)   # the first one still works
        assert isinstance(d, Arm)


# ------------------------------------------------------------------- refusals and faults
async def test_refusals_before_activation_and_homing():
    async with rig() as r:
        d = r.make()
        await d.connect()
        with pytest.raises(DeviceFault, match=r"Home refused: \[1005\]"):
            await d.home()
        await d.move_joints_vel((5.0, 0, 0, 0, 0, 0))     # no answer expected on success
        await d.sync()
        with pytest.raises(DeviceFault, match=r"\[1005\] NOT_ACTIVATED"):
            await d.read()
        with pytest.raises(DeviceFault, match="1005"):
            await d.move_joints_vel((5.0, 0, 0, 0, 0, 0))
        assert d.error_code == 1005
        assert await d.reset_error() == 2006          # the robot itself was not in error
        await d.read()
        assert r.world.arm.q == list(HOME_Q_DEG)      # nothing moved
        await d.activate()
        await d.move_joints_vel((5.0, 0, 0, 0, 0, 0))
        await d.sync()
        with pytest.raises(DeviceFault, match=r"\[1006\] NOT_HOMED.*reset_error"):
            await d.read()
        await d.reset_error()
        assert r.world.arm.q == list(HOME_Q_DEG)
        await d.home()
        await d.move_joints_vel((5.0, 0, 0, 0, 0, 0))
        await d.sync()
        await world_wait(r.world, 0.05)
        assert r.world.arm.q[0] > 0.0
        assert d.activated and d.homed and not d.paused and d.error_code == 0


async def test_limits_are_checked_before_sending():
    d = Meca500Driver()                                 # not even connected
    with pytest.raises(ConfigError, match=r"J3.*180.0 deg/s"):
        await d.move_joints_vel((0, 0, 181.0, 0, 0, 0))
    with pytest.raises(ConfigError, match=r"J2.*-70.0 <= q <= 90.0"):
        await d.move_joints((0, 95.0, 0, 0, 0, 0))
    with pytest.raises(ConfigError, match="6 values"):
        await d.move_joints_vel((0, 0, 0))
    with pytest.raises(ConfigError, match=r"J1.*finite"):
        await d.move_joints_vel((math.nan, 0, 0, 0, 0, 0))
    with pytest.raises(DeviceFault, match="link down"):
        await d.move_joints_vel(np.zeros(6))              # numpy is fine, the link is not
    with pytest.raises(DeviceFault, match="link down"):
        await d.read()
    assert d.commands_sent == 0
    with pytest.raises(ConfigError, match="vel_timeout_s"):
        Meca500Driver(vel_timeout_s=2.0)
    with pytest.raises(ConfigError, match="monitoring_interval_s"):
        Meca500Driver(monitoring_interval_s=0.0)
    with pytest.raises(DeviceFault, match="cannot connect"):
        await Meca500Driver("127.0.0.1", 1, 2, connect_timeout_s=1.0).connect()


async def test_joint_limit_error_is_a_typed_fault_and_reset():
    async with rig() as r:
        r.world.teleport_arm((170.0, -10.0, 20.0, 0.0, 80.0, 0.0))
        d = await ready(r.make(vel_timeout_s=0.2))        # keeps moving through stalls
        with pytest.raises(DeviceFault, match="1007"):     # J1 reaches 175 deg in ~0.25 s
            await stream(d, (20.0, 0, 0, 0, 0, 0), 2.0)
        await until(lambda: d.status.error, what="status es=1")
        with pytest.raises(DeviceFault, match=r"\[1007\] JOINT_OVER_LIMIT"):
            await d.read()
        with pytest.raises(DeviceFault, match="1007"):
            await d.move_joints_vel((-5.0, 0, 0, 0, 0, 0))
        assert d.error_code == 1007 and d.paused
        assert 174.9 < r.world.arm.q[0] <= 175.0          # stopped at the limit
        assert await d.reset_error() == 2005
        assert d.paused and not d.status.error            # reset does not resume
        with pytest.raises(DeviceFault, match="paused"):
            await d.move_joints_vel((-5.0, 0, 0, 0, 0, 0))
        await d.resume_motion()
        q1 = (await fresh(d))[0].q_deg[0]
        await stream(d, (-10.0, 0, 0, 0, 0, 0), 0.2)
        await world_wait(r.world, 0.05)
        assert (await fresh(d))[0].q_deg[0] < q1 - 1.0


async def test_wrist_singularity_is_a_typed_fault():
    async with rig() as r:
        r.world.teleport_arm((0.0, -10.0, 20.0, 0.0, 3.0, 0.0))
        d = await ready(r.make(vel_timeout_s=0.2))
        with pytest.raises(DeviceFault, match=r"\[1012\] SINGULARITY"):
            await stream(d, (0, 0, 0, 0, -10.0, 0), 2.0)      # J5 -> 0.5 deg in ~0.25 s
        assert d.error_code == 1012
        assert 0.4 < r.world.arm.q[4] < 1.0                   # stopped before the band
        assert await d.reset_error() == 2005
        await d.resume_motion()
        await d.move_joints_vel((0, 0, 0, 0, 10.0, 0))        # moving out is allowed
        await d.sync()
        await world_wait(r.world, 0.1)
        assert r.world.arm.q[4] > 1.0 and d.fault is None


# ------------------------------------------------------------------------- streaming
async def test_streaming_500hz_moves_joints_by_rate_times_time():
    async with rig() as r:
        d = await ready(r.make(vel_timeout_s=0.01))
        timeout = d.vel_timeout_s
        assert r.world.arm.p.vel_timeout_s == timeout     # SetVelTimeout reached the World
        times = record_vel_commands(r.world)
        s0, _ = await fresh(d)
        q0 = s0.q_deg
        mid = {}

        async def sample(elapsed):
            if "s" not in mid and elapsed > 1.5:
                mid["s"] = await d.read()
                mid["c"] = d.last_cycle

        sent = await stream(d, V, 2.0, on_tick=sample)
        await d.sync()
        assert len(times) == sent                         # every command reached the arm
        # mid-stream: displacement = rate x time the reference was on - tau x qdot
        s, c = mid["s"], mid["c"]
        t_s = c.timestamp_us / 1e6
        on_s, seg_s = reference_on(times, timeout, t_s)
        for i in range(6):
            lag = LAG * s.qdot_deg_s[i]
            expected = V[i] * on_s - lag
            tol = abs(V[i]) * TS * seg_s + 2 * Q_RES
            assert s.q_deg[i] - q0[i] == pytest.approx(expected, abs=tol), (i, on_s, seg_s)
        # after the stream: the arm comes to rest and the lag is made up
        await world_wait(r.world, 0.2)
        s1, _ = await fresh(d)
        assert s1.qdot_deg_s == (0.0,) * 6
        on, segments = reference_on(times, timeout)
        for i in range(6):
            tol = abs(V[i]) * TS * segments + 2 * Q_RES
            assert s1.q_deg[i] - q0[i] == pytest.approx(V[i] * on, abs=tol), (i, on, segments)
        # with no stall the reference was on for the whole stream plus one timeout
        assert on == pytest.approx(times[-1] - times[0] + timeout, abs=1e-9) or segments > 1
        assert on > 1.0 and d.errors == 0 and d.lost == 0


async def test_velocity_timeout_stops_the_arm():
    async with rig() as r:
        d = await ready(r.make(vel_timeout_s=0.05))
        times = record_vel_commands(r.world)
        for timeout in (0.05, 0.01):
            await d.set_vel_timeout(timeout)
            await d.sync()
            q0 = (await fresh(d))[0].q_deg
            n = len(times)
            await d.move_joints_vel((20.0, 0, 0, 0, 0, -40.0))   # once, never repeated
            await d.sync()
            await world_wait(r.world, 0.2)
            s, _ = await fresh(d)
            assert len(times) == n + 1
            assert s.qdot_deg_s == (0.0,) * 6                     # decelerated to rest
            assert s.q_deg[0] - q0[0] == pytest.approx(20.0 * timeout, abs=20 * TS + 2 * Q_RES)
            assert s.q_deg[5] - q0[5] == pytest.approx(-40.0 * timeout, abs=40 * TS + 2 * Q_RES)
            s2, _ = await fresh(d)
            assert s2.q_deg == s.q_deg                            # and stays there


# ----------------------------------------------------------------------- dropped link
async def test_dropped_link_pauses_and_requires_an_explicit_resume():
    async with rig() as r:
        d = await ready(r.make(vel_timeout_s=0.5))
        await stream(d, (20.0, 0, 0, 0, 0, 0), 0.1)
        r.server.drop_clients()                             # cable pulled mid-stream
        await until(lambda: not d.connected, what="link loss noticed")
        with pytest.raises(DeviceFault, match="link"):
            await d.read()
        with pytest.raises(DeviceFault, match="link down"):
            await d.move_joints_vel((20.0, 0, 0, 0, 0, 0))
        assert r.server.paused
        await world_wait(r.world, 0.15)                     # < the 0.5 s velocity timeout
        assert r.world.arm.qdot == [0.0] * 6                # stopped by the robot itself

        await d.reconnect()
        assert d.connected and d.reconnects == 1 and d.paused
        with pytest.raises(DeviceFault, match="paused"):
            await d.move_joints_vel((20.0, 0, 0, 0, 0, 0))
        await d.resume_motion()
        assert not d.paused
        q1 = (await fresh(d))[0].q_deg[0]
        await stream(d, (20.0, 0, 0, 0, 0, 0), 0.1)
        await world_wait(r.world, 0.05)
        assert (await fresh(d))[0].q_deg[0] > q1 + 1.0

        # the client side drops (its socket dies): the robot pauses too
        d._ctrl.transport.abort()
        await until(lambda: r.server.paused and not d.connected, what="robot paused")
        await d.reconnect()
        assert d.paused


# ------------------------------------------------------------------------- monitoring
async def test_monitoring_at_2ms_loses_no_cycles():
    async with rig() as r:
        d = r.make(monitoring_interval_s=0.002)
        await d.connect()
        assert d.realtime_codes == (2210, 2212)
        client = r.server.monitor_clients[0]
        await until(lambda: d.received >= 1, what="first cycle")
        n0, g0, r0, ts0 = d.received, d.gaps, d.repeated, d.last_cycle.timestamp_us
        t0 = time.monotonic()
        seqs = []
        end = t0 + 1.5
        while time.monotonic() < end:
            seqs.append((await d.read()).seq)
            await asyncio.sleep(0.01)
        last = await d.read()
        n1, g1, r1, ts1 = d.received, d.gaps, d.repeated, d.last_cycle.timestamp_us
        assert last.seq == n1                   # seq counts cycles
        elapsed = time.monotonic() - t0
        await r.server.close()              # flushes what was sent, then closes
        await until(lambda: not d.connected, what="end of stream")
        # every cycle the server sent arrived and became one sample (seq += 1 per cycle)
        assert d.received == client.cycles_sent
        assert d.errors == 0 and d.lost == 0
        assert seqs == sorted(seqs) and seqs[-1] <= n1
        # every world step (2 ms) is reported once or counted as a gap; a cycle sent while
        # the World was not stepped repeats its timestamp and is counted as repeated
        assert (ts1 - ts0) / 2000 == pytest.approx((n1 - n0) - (r1 - r0) + (g1 - g0))
        assert d.gaps <= r.server.skipped_cycles
        assert (n1 - n0) / elapsed > 100        # a loaded machine still streams


async def test_several_monitoring_clients():
    async with rig() as r:
        d = r.make()
        await d.connect()
        readers = [await asyncio.open_connection("127.0.0.1", r.server.monitor_port)
                   for _ in range(2)]
        try:
            for reader, _ in readers:
                first = decode_response(await read_frame(reader))
                assert first.code == 2007                        # the state at connection
                codes = [decode_response(await read_frame(reader)).code for _ in range(8)]
                assert 2230 in codes and 2210 in codes and 2212 in codes
            assert len(r.server.monitor_clients) == 3
            await d.read()
        finally:
            for _, writer in readers:
                writer.close()
                await writer.wait_closed()


async def test_move_joints_checkpoint_pause_and_discard():
    async with rig() as r:
        d = await ready(r.make())
        target = (10.0, 0.0, 10.0, 0.0, 30.0, 0.0)
        await d.move_joints(target, wait=True)
        assert await d.get_joints() == pytest.approx(target, abs=Q_RES + 1e-3)
        # PauseMotion keeps the queue: the move finishes after ResumeMotion
        await d.move_joints((-110.0, 0.0, 10.0, 0.0, 30.0, 0.0))     # 120 deg: ~0.8 s
        await d.sync()
        await d.pause_motion()
        assert d.paused
        await world_wait(r.world, 0.15)     # 150 deg/s to rest (< 0.001): 8 ms x ln(1.5e5)
        assert r.world.arm.qdot == [0.0] * 6 and r.world.arm.q[0] > -100.0
        await d.resume_motion()
        await d.wait_idle()
        assert r.world.arm.q[0] == pytest.approx(-110.0, abs=1e-3)
        # a checkpoint behind a long move is discarded by ClearMotion ([3040])
        await d.move_joints((10.0, -10.0, 30.0, 10.0, 60.0, 0.0))      # 120 deg back
        waiting = asyncio.create_task(d.checkpoint())
        await d.sync()
        await d.clear_motion()
        with pytest.raises(DeviceFault, match="3040"):
            await waiting
        assert d.paused and r.world.arm.q[0] < 0.0
        await d.resume_motion()
        # stop(): at rest, queue dropped, and ready for the next command
        await d.move_joints((-30.0, -10.0, 30.0, 10.0, 60.0, 0.0))
        await asyncio.sleep(0.05)
        await d.stop()
        assert not d.paused
        await world_wait(r.world, 0.15)
        assert r.world.arm.qdot == [0.0] * 6
        q = r.world.arm.q[0]
        await d.move_joints_vel((10.0, 0, 0, 0, 0, 0))
        await d.sync()
        await world_wait(r.world, 0.02)
        assert r.world.arm.q[0] > q


# ------------------------------------------------------------------- unpleasant bytes
async def test_simulator_answers_bad_commands_like_the_robot():
    async with rig(step=False) as r:
        r.world.teleport_arm((0.0,) * 6)
        reader, writer = await asyncio.open_connection("127.0.0.1", r.server.port)

        async def ask(cmd: bytes, skip=(2007,)):
            writer.write(cmd + b"\0")
            return decode_response(await read_frame(reader, skip))

        try:
            await read_frame(reader)
            assert (await ask(b"Frobnicate(1)")).code == 1001
            assert (await ask(b"GetJoints(1")).code == 1002
            assert (await ask(b"SetVelTimeout(a)")).code == 1003
            assert (await ask(b"MoveJoints(1,2)")).code == 1003              # 2 of 6 args
            assert (await ask(b"x" * 2000)).code == 3003                      # too long
            assert (await ask(b"SetVelTimeout(0.05)")).code == 1005          # motion queue
            assert (await ask(b"ActivateRobot")).code == 2000
            assert (await ask(b"ActivateRobot")).code == 2000                # again: same
            assert (await ask(b"MoveJointsVel(1,0,0,0,0,0)")).code == 1006
            assert (await ask(b"home")).code == 2002                          # any case
            assert (await ask(b"SetVelTimeout(2)")).code == 1003             # 0.001..1 s
            assert (await ask(b"SetVelTimeout(0.0005)")).code == 1003
            assert (await ask(b"MoveJointsVel(151,0,0,0,0,0)")).code == 1003  # J1 150 deg/s
            assert (await ask(b"SetCheckpoint(9000)")).code == 1003          # ids 1..8191
            pose = (await ask(b"GetPose")).values()
            assert pose == pytest.approx((190, 0, 308, 0, 90, 0), abs=1e-6)   # devices.md
            # MoveJoints outside the joint range: error message, then status with es=1
            assert (await ask(b"MoveJoints(180,0,0,0,0,0)")).code == 1007
            st = RobotStatus.from_payload((await ask(b"GetStatusRobot", skip=())).payload)
            assert st.error and st.paused
            assert (await ask(b"MoveJointsVel(1,0,0,0,0,0)")).code == 1011
            assert (await ask(b"ResetError")).code == 2005
            assert (await ask(b"ResetError")).code == 2006
            st = RobotStatus.from_payload((await ask(b"GetStatusRobot", skip=())).payload)
            assert not st.error and st.paused                    # ResumeMotion still needed
            assert (await ask(b"ResumeMotion")).code == 2043
            assert (await ask(b"SyncCmdQueue(7)")).payload == "7"
            assert r.server.bad_frames == 9
        finally:
            writer.close()
            await writer.wait_closed()


# ------------------------------------------------------------------ connection watchdog
#: The simulator looks at the watchdog every poll (1 ms); a loaded shared machine may delay
#: its event loop by a few tens of ms: the margin of every bound below.
WATCHDOG_MARGIN_S = 0.1


async def test_the_simulator_safety_stops_on_an_expired_connection_watchdog():
    """Mecademic's documented behaviour: only ConnectionWatchdog refreshes it; on expiry the
    robot pauses motion and closes the application's sockets."""
    async with rig() as r:
        reader, writer = await asyncio.open_connection("127.0.0.1", r.server.port)
        mon_reader, mon_writer = await asyncio.open_connection("127.0.0.1",
                                                               r.server.monitor_port)

        async def ask(cmd: bytes, skip=(2007, 3012)):
            writer.write(cmd + b"\0")
            return decode_response(await read_frame(reader, skip))

        try:
            await read_frame(reader)
            assert (await ask(b"ActivateRobot")).code == 2000
            assert (await ask(b"Home")).code == 2002
            assert (await ask(b"ConnectionWatchdog(0)")).payload == "0"      # 0: disabled
            timeout = 0.1
            # the robot arms it between the command's sending and its reply's reading: it
            # expires no sooner than the timeout after the one, no later than the margin
            # after the other
            sent = time.monotonic()
            reply = await ask(b"ConnectionWatchdog(0.1)")
            assert (reply.code, reply.payload) == (2177, "1")
            armed = time.monotonic()
            # 1 s velocity timeout: only the watchdog can stop this motion in time
            writer.write(b"SetVelTimeout(1)\0MoveJointsVel(20,0,0,0,0,0)\0")
            q0 = r.world.arm.q[0]
            # other traffic does not refresh the watchdog
            closed_at = None
            while time.monotonic() - armed < timeout + 1.0:
                try:
                    writer.write(b"GetStatusRobot\0")
                    frame = await asyncio.wait_for(reader.readuntil(b"\0"), 0.02)
                except TimeoutError:
                    continue
                except (asyncio.IncompleteReadError, ConnectionError):
                    closed_at = time.monotonic()
                    break
                assert decode_response(frame[:-1]).code in (2007, 3012)
            assert closed_at is not None, "the robot kept the connection"
            assert closed_at - sent >= timeout
            assert closed_at - armed <= timeout + WATCHDOG_MARGIN_S
            assert r.server.watchdog_expiries == 1 and r.server.paused
            assert not r.server.in_error                 # a stop condition, not an error
            # the monitoring connection of the same application is closed too
            while await asyncio.wait_for(mon_reader.read(65536), 2.0):
                pass                                     # cycles, then end of stream
            # the arm is at rest: 20 deg/s for at most the watchdog time (+ margin), then the
            # servo's first-order lag (tau 8 ms) brings it down
            await world_wait(r.world, 0.1)
            assert r.world.arm.qdot == pytest.approx([0.0] * 6, abs=1e-6)
            moved = r.world.arm.q[0] - q0
            assert 0.0 < moved <= 20.0 * (timeout + WATCHDOG_MARGIN_S + TAU)
            # the next application finds the robot paused, not in error: ResumeMotion needed
            writer.close()
            reader, writer = await asyncio.open_connection("127.0.0.1", r.server.port)
            await read_frame(reader)
            st = RobotStatus.from_payload((await ask(b"GetStatusRobot", skip=())).payload)
            assert st.paused and not st.error and st.activated and st.homed
            assert (await ask(b"ResumeMotion")).code == 2043
        finally:
            for w in (writer, mon_writer):
                w.close()
                with contextlib.suppress(ConnectionError):
                    await w.wait_closed()


async def test_the_driver_arms_the_watchdog_and_its_reads_keep_it_alive():
    async with rig() as r:
        d = await ready(r.make(connection_watchdog_s=0.05))
        assert r.server.watchdog_s == 0.05                 # armed at connection
        f0 = d.watchdog_feeds
        t0 = time.monotonic()
        while time.monotonic() - t0 < 0.5:                 # ten watchdog times of ticks
            await d.read()
            await d.move_joints_vel(np.zeros(6))
            await asyncio.sleep(0.002)
        assert d.connected and r.server.watchdog_expiries == 0
        # refreshed at most every quarter of the time: 40 in 0.5 s, fewer when ticks are late
        assert 10 <= d.watchdog_feeds - f0 <= 0.5 / (0.05 / 4) + 1


async def test_a_silent_driver_loses_the_arm_within_the_watchdog_time():
    """The control task stops calling the driver (frozen, stuck): the robot stops a long
    MoveJoints that the velocity timeout does not cover, and drops the connection."""
    async with rig() as r:
        timeout = 0.1
        d = await ready(r.make(connection_watchdog_s=timeout))
        q0 = r.world.arm.q[0]
        await d.move_joints((q0 - 120.0, *r.world.arm.q[1:]))   # 120 deg at 150 deg/s: 0.8 s
        last_feed = d._watchdog_fed_t
        await until(lambda: not d.connected, timeout=2.0, what="link closed by the robot")
        lost = time.monotonic()
        assert timeout <= lost - last_feed <= timeout + WATCHDOG_MARGIN_S
        with pytest.raises(DeviceFault, match="link down"):
            await d.read()
        await world_wait(r.world, 0.1)
        assert r.world.arm.qdot == pytest.approx([0.0] * 6, abs=1e-6)
        # stopped far short of the target: at most 150 deg/s for the watchdog time + margin
        assert q0 - r.world.arm.q[0] <= 150.0 * (timeout + WATCHDOG_MARGIN_S + TAU)
        assert r.server.paused and r.server.watchdog_expiries == 1
        # a new connection finds the robot paused: ResumeMotion is needed (devices.md)
        await d.reconnect()
        assert d.paused


async def test_connect_to_a_silent_peer_is_a_typed_timeout_naming_the_address():
    async with silent_peer() as port:
        d = Meca500Driver("127.0.0.1", port, port + 1, response_timeout_s=0.3)
        t0 = time.monotonic()
        with pytest.raises(ConnectTimeout) as e:
            await d.connect()
        took = time.monotonic() - t0
        assert 0.3 <= took <= 0.3 + 0.5
        assert e.value.device == "meca500" and f"127.0.0.1:{port}" in str(e.value)
        assert "greeting" in str(e.value) and e.value.timeout_s == 0.3
        await d.close()


async def test_driver_survives_garbage_from_the_robot():
    async with rig() as r:
        d = r.make()
        await d.connect()
        await until(lambda: d.received >= 3, what="cycles")
        e0 = d.errors
        for junk in (b"garbage\0", b"[2200][1,2]\0", b"\xff\xfe\0", b"x" * 5000 + b"\0",
                     b"[2230][notanumber]\0", b"[22", b"00][1,2,3]\0"):          # split + short
            r.server.inject(junk, to="monitor")
        n = d.received
        await until(lambda: d.received >= n + 5, what="cycles after garbage")
        assert d.errors >= e0 + 6
        await d.read()                                      # still fine
        # control port: an unknown code is ignored, an unsolicited error latches a fault
        r.server.inject(b"[9999][whatever]\0[1011][The robot is already in error.]\0",
                        to="control")
        await until(lambda: d.fault is not None, what="latched fault")
        with pytest.raises(DeviceFault, match=r"\[1011\] ALREADY_IN_ERROR"):
            await d.read()
        assert await d.reset_error() == 2006
        await d.read()


async def test_recover_after_an_error_and_after_a_dropped_link_leaves_the_arm_ready():
    """The operator's reset (``recover``): error reset and motion resumed; a dropped link
    reconnected first. Nothing moves until commanded; then commands are taken again."""
    async with rig() as r:
        r.world.teleport_arm((170.0, -10.0, 20.0, 0.0, 80.0, 0.0))
        d = await ready(r.make(vel_timeout_s=0.2))
        with pytest.raises(DeviceFault, match="1007"):
            await stream(d, (20.0, 0, 0, 0, 0, 0), 2.0)
        await until(lambda: d.status.error, what="status es=1")
        await d.recover()
        assert d.error_code == 0 and not d.paused and not d.status.error
        q0 = r.world.arm.q[0]
        await world_wait(r.world, 0.05)
        assert r.world.arm.q[0] == q0                       # nothing moved by itself
        r.server.drop_clients()
        await until(lambda: not d.connected, what="link loss noticed")
        await d.recover()
        assert d.connected and not d.paused
        q1 = (await fresh(d))[0].q_deg[0]
        await stream(d, (-10.0, 0, 0, 0, 0, 0), 0.2)
        await world_wait(r.world, 0.05)
        assert (await fresh(d))[0].q_deg[0] < q1 - 1.0
