"""The Meca500 wire simulator driven by Mecademic's own client (``mecademicpy.robot.Robot``).

Everything runs on 127.0.0.1 with ephemeral ports; the simulated World is stepped in real time
in a thread of its own (mecademicpy is a blocking, threaded client). Expected numbers come
from the product's documentation, not from the simulator:

- the flange pose at zero joints is (190, 0, 308, 0, 90, 0) mm/deg (Meca500 R3: base height
  135 + upper arm 135 + 38 mm offset, forearm 120 + wrist 70 mm);
- poses are mobile XYZ Euler angles, R = Rx(alpha) Ry(beta) Rz(gamma), so a relative move of
  d along the tool axes moves the TCP by R d in the world;
- a commanded absolute target (joints or pose) is where the arm ends; a relative joint move
  adds to where it started;
- answer codes of the programming manual ([3086] safety stop, status as/hs/es/pm).
Tolerances: the measured joints are quantised to 0.001 deg (a few um on the pose); a linear
move is tracked with the servo's lag (8 ms at 300 mm/s: under 3 mm off the line).
"""

from __future__ import annotations

import asyncio
import math
import socket
import threading
import time
from types import SimpleNamespace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dentibot.sim import RealTimeStepper, World, WorldConfig
from dentibot.sim.meca500_server import Meca500Server

mdr = pytest.importorskip("mecademicpy.robot")

pytestmark = [pytest.mark.wire, pytest.mark.timeout(60)]

ZERO_POSE = (190.0, 0.0, 308.0, 0.0, 90.0, 0.0)     # flange at zero joints (product data)
HOME = (0.0, -10.0, 20.0, 0.0, 80.0, 0.0)
Q_TOL = 2e-3                                        # deg: encoder quantum and arrival
P_TOL = 0.01                                        # mm / deg on a pose


class _Sim:
    """World + real-time stepper + Meca500Server in a background event loop."""

    def __init__(self) -> None:
        self._ready = threading.Event()
        self._quit: asyncio.Event | None = None
        self.loop: asyncio.AbstractEventLoop | None = None
        self._thread = threading.Thread(target=lambda: asyncio.run(self._main()),
                                        name="meca500-sim-loop", daemon=True)
        self._thread.start()
        assert self._ready.wait(10), "simulator did not start"

    async def _main(self) -> None:
        self.world = World(WorldConfig())
        stop = asyncio.Event()
        self._quit = asyncio.Event()
        self.loop = asyncio.get_running_loop()
        task = asyncio.create_task(RealTimeStepper(self.world).run(stop))
        self.server = Meca500Server(self.world, "127.0.0.1", port=0, monitor_port=0)
        await self.server.start()
        self._ready.set()
        try:
            await self._quit.wait()
        finally:
            await self.server.close()
            stop.set()
            await task

    def close(self) -> None:
        self.loop.call_soon_threadsafe(self._quit.set)
        self._thread.join(10)


@pytest.fixture
def sim():
    s = _Sim()
    robots: list = []

    def robot(monitor: bool = False, **kw):
        r = mdr.Robot()
        robots.append(r)
        port = s.server.monitor_port if monitor else s.server.port
        r.Connect(f"127.0.0.1:{port}", monitor_mode=monitor, timeout=2, **kw)
        return r

    try:
        yield SimpleNamespace(sim=s, server=s.server, world=s.world, robot=robot)
    finally:
        for r in robots:
            r.Disconnect()
        s.close()


def ready(r) -> None:
    r.ActivateRobot()
    r.WaitActivated(timeout=5)
    r.Home()
    r.WaitHomed(timeout=5)
    r.SetJointVel(100)
    r.SetJointAcc(100)
    r.SetCartLinVel(300)
    r.SetCartAngVel(100)
    r.SetBlending(0)


def rt_joints(r):
    return r.GetRtJointPos(synchronous_update=True)


def rt_pose(r):
    return r.GetRtCartPos(synchronous_update=True)


def same_pose(a, b, tol=P_TOL) -> bool:
    """Positions within ``tol`` mm and the same rotation (Euler triples are not unique)."""
    ra = Rotation.from_euler("XYZ", a[3:], degrees=True)
    rb = Rotation.from_euler("XYZ", b[3:], degrees=True)
    return bool(np.allclose(a[:3], b[:3], atol=tol) and
                math.degrees((ra * rb.inv()).magnitude()) < tol)


def until(cond, timeout: float = 3.0, what: str = "condition") -> None:
    end = time.monotonic() + timeout
    while not cond():
        assert time.monotonic() < end, f"timed out waiting for {what}"
        time.sleep(0.005)


# ------------------------------------------------------------------------------ connect
def test_connect_identifies_a_meca500_r3_with_firmware_9(sim):
    r = sim.robot()
    info = r.GetRobotInfo()
    assert (info.model, info.revision) == ("Meca500", 3)
    assert (info.version.major, info.version.minor) == (9, 3)
    assert info.serial == sim.server.serial
    st = r.GetStatusRobot(synchronous_update=True)
    assert not st.activation_state and not st.homing_state and not st.error_status


def test_basic_example_joint_moves_through_the_wrist_singularity(sim):
    r = sim.robot()
    ready(r)
    r.MoveJoints(0, 0, 0, 0, 0, 0)          # the wrist singularity: a joint move may end there
    r.WaitIdle(timeout=10)
    assert rt_joints(r) == pytest.approx((0.0,) * 6, abs=Q_TOL)
    assert same_pose(r.GetRtTargetCartPos(synchronous_update=True), ZERO_POSE)
    r.MoveJoints(*HOME)                     # and back, across q5 = 0
    r.WaitIdle(timeout=10)
    assert rt_joints(r) == pytest.approx(HOME, abs=Q_TOL)
    r.MoveJointsRel(10, -5, 5, 20, -90, 30)   # q5 80 -> -10 deg: crosses it again
    r.WaitIdle(timeout=10)
    assert rt_joints(r) == pytest.approx((10.0, -15.0, 25.0, 20.0, -10.0, 30.0), abs=Q_TOL)
    assert r.GetRtJointVel(synchronous_update=True) == pytest.approx((0.0,) * 6, abs=1e-6)
    st = r.GetStatusRobot(synchronous_update=True)
    assert st.activation_state and st.homing_state and not st.error_status
    assert not st.pause_motion_status and st.end_of_block_status


def test_cartesian_moves_reach_their_targets_on_a_straight_line(sim):
    r = sim.robot()
    ready(r)
    r.MoveJoints(*HOME)
    r.WaitIdle(timeout=10)
    start = rt_pose(r)
    target = (start[0] + 30.0, start[1] - 20.0, start[2] + 10.0, *start[3:])
    r.MovePose(*target)
    r.WaitIdle(timeout=10)
    assert same_pose(rt_pose(r), target)

    # back along a line: every sample during the move is on the segment
    a, b = np.array(target[:3]), np.array(start[:3])
    r.MoveLin(*start)
    samples = []
    t_end = time.monotonic() + 3.0
    while time.monotonic() < t_end:
        samples.append(np.array(r.GetRtTargetCartPos(synchronous_update=True)[:3]))
        if np.linalg.norm(samples[-1] - b) < 0.01:
            break
    r.WaitIdle(timeout=10)
    assert same_pose(rt_pose(r), start)
    u = (b - a) / np.linalg.norm(b - a)
    moving = [p for p in samples if 1.0 < np.linalg.norm(p - a) and np.linalg.norm(p - b) > 1.0]
    assert moving, "no sample while the arm was on its way"
    off = [np.linalg.norm((p - a) - np.dot(p - a, u) * u) for p in moving]
    assert max(off) < 3.0

    # 10 mm along the tool's own z axis: R(alpha, beta, gamma) @ (0, 0, 10) in the world
    r.MoveLinRelTrf(0, 0, 10, 0, 0, 0)
    r.WaitIdle(timeout=10)
    rot = Rotation.from_euler("XYZ", start[3:], degrees=True).as_matrix()
    expected = (*(np.array(start[:3]) + rot @ (0.0, 0.0, 10.0)), *start[3:])
    assert same_pose(rt_pose(r), expected)


def test_reference_frames_shift_the_reported_pose(sim):
    r = sim.robot()
    ready(r)
    r.MoveJoints(0, 0, 0, 0, 0, 0)
    r.SetTrf(0, 0, 50, 0, 0, 0)             # TCP 50 mm along the flange z (the world's +x here)
    r.SetWrf(10, 0, 0, 0, 0, 0)             # world frame 10 mm along the base x
    r.WaitIdle(timeout=10)
    assert r.GetRtTrf(synchronous_update=True) == pytest.approx((0, 0, 50, 0, 0, 0))
    assert r.GetRtWrf(synchronous_update=True) == pytest.approx((10, 0, 0, 0, 0, 0))
    # at zero joints the flange z axis is the base x axis (beta = 90 deg)
    assert same_pose(rt_pose(r), (190.0 + 50.0 - 10.0, 0.0, 308.0, 0.0, 90.0, 0.0))


def test_a_linear_move_does_not_start_from_a_singularity(sim):
    r = sim.robot(disconnect_on_exception=False)   # the client drops the link on an error
    ready(r)
    r.MoveJoints(0, 0, 0, 0, 0, 0)
    r.WaitIdle(timeout=10)
    r.MoveLinRelWrf(0, 0, -10, 0, 0, 0)     # wrist singular at the start: [1012]
    with pytest.raises(Exception):          # noqa: B017 - mecademicpy's interrupt
        r.WaitIdle(timeout=5)
    until(lambda: r.GetStatusRobot().error_status, what="error status")
    assert rt_joints(r) == pytest.approx((0.0,) * 6, abs=Q_TOL)      # did not move
    r.ResetError()
    r.WaitErrorReset(timeout=2)
    r.ResumeMotion()
    r.WaitMotionResumed(timeout=2)
    r.MoveJoints(*HOME)
    r.WaitIdle(timeout=10)
    assert rt_joints(r) == pytest.approx(HOME, abs=Q_TOL)


def test_pause_resume_and_clear(sim):
    r = sim.robot()
    ready(r)
    r.SetJointVel(20)                        # 30 deg/s on J1: 60 deg takes 2 s
    r.MoveJoints(60, -10, 20, 0, 80, 0)
    time.sleep(0.2)
    r.PauseMotion()
    r.WaitMotionPaused(timeout=2)
    until(lambda: not sim.world.arm.moving, what="arm at rest")
    q_paused = sim.world.arm.q[0]
    assert 1.0 < q_paused < 59.0
    time.sleep(0.1)
    assert sim.world.arm.q[0] == q_paused                    # nothing moves while paused
    r.SetJointVel(100)
    r.ResumeMotion()
    r.WaitMotionResumed(timeout=2)
    r.WaitIdle(timeout=10)
    assert rt_joints(r)[0] == pytest.approx(60.0, abs=Q_TOL)
    r.SetJointVel(10)
    r.MoveJoints(*HOME)                      # 60 deg at 15 deg/s: 4 s
    time.sleep(0.1)
    r.ClearMotion()
    r.WaitMotionCleared(timeout=2)
    until(lambda: not sim.world.arm.moving, what="arm at rest")
    assert r.GetStatusRobot(synchronous_update=True).pause_motion_status
    r.ResumeMotion()
    r.WaitMotionResumed(timeout=2)
    r.DeactivateRobot()
    r.WaitDeactivated(timeout=2)
    assert not sim.server.activated


def test_monitoring_port_connection(sim):
    m = sim.robot(monitor=True)
    info = m.GetRobotInfo()
    assert (info.model, info.revision, info.version.major) == ("Meca500", 3, 9)
    m.WaitEndOfCycle(timeout=2)
    assert m.GetRtTargetJointPos(synchronous_update=False) == \
        pytest.approx(tuple(sim.world.arm.q), abs=Q_TOL)
    r = sim.robot()                         # a control client alongside
    ready(r)
    r.MoveJoints(5, -10, 20, 0, 80, 0)
    r.WaitIdle(timeout=10)
    m.WaitEndOfCycle(timeout=2)
    m.WaitEndOfCycle(timeout=2)
    assert m.GetRtTargetJointPos(synchronous_update=False)[0] == pytest.approx(5.0, abs=Q_TOL)
    assert m.GetStatusRobot().activation_state


def test_disconnect_frees_the_control_port(sim):
    r = sim.robot()
    ready(r)
    r.Disconnect()
    until(lambda: sim.server.control_client is None, what="control port free")
    r2 = sim.robot()
    st = r2.GetStatusRobot(synchronous_update=True)
    assert st.activation_state and st.homing_state


def test_expired_connection_watchdog_safety_stops_and_closes(sim):
    r = sim.robot()
    ready(r)
    mon = socket.create_connection(("127.0.0.1", sim.server.monitor_port), timeout=3)
    try:
        mon.sendall(b"\0")
        r.SetVelTimeout(1)                  # only the watchdog can stop this in time
        r.MoveJointsVel(20, 0, 0, 0, 0, 0)
        timeout = 0.1
        r.ConnectionWatchdog(timeout)
        armed = time.monotonic()
        until(lambda: not r.IsConnected(), timeout=3, what="robot closed the connection")
        assert time.monotonic() - armed >= timeout
        assert sim.server.watchdog_expiries == 1 and sim.server.paused
        data = b""
        while chunk := mon.recv(65536):     # the monitoring stream until the robot closes it
            data += chunk
        frames = data.split(b"\0")
        assert frames[0] == b"[3000][Connected to Meca500 R3 v9.3.0]"
        assert b"[3086][1]" in frames                          # the safety stop reported
        until(lambda: not sim.world.arm.moving, what="arm at rest")
    finally:
        mon.close()
    r.Disconnect()
    # the next application finds the robot paused (not in error) and resumes it
    r2 = sim.robot()
    st = r2.GetStatusRobot(synchronous_update=True)
    assert st.pause_motion_status and not st.error_status and st.activation_state
    r2.ResumeMotion()
    r2.WaitMotionResumed(timeout=2)
    until(lambda: not sim.server.paused and not sim.server.safety_stop, what="stop cleared")
