"""Two DentiBot runs in a row against one simulated Meca500, and the operator's explicit
resume of an arm found paused or in error at connection.

What a real Meca500 does (programming manual): a dropped control connection pauses motion and
the pause outlives the connection (ResumeMotion needed); DeactivateRobot then ActivateRobot
starts from a clean state; ResetError clears the error flag (es) but leaves motion paused.
Everything runs on 127.0.0.1 with ephemeral ports.
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from types import SimpleNamespace

import pytest

from dentibot.errors import DeviceFault
from dentibot.io.meca500 import RESETTABLE_ERRORS, Meca500Driver
from dentibot.sim import RealTimeStepper, World, WorldConfig
from dentibot.sim.meca500_server import Meca500Server

pytestmark = [pytest.mark.wire, pytest.mark.timeout(30)]

NEAR_J1_LIMIT = (170.0, -10.0, 20.0, 0.0, 80.0, 0.0)     # J1 range is +-175 deg


@contextlib.asynccontextmanager
async def rig():
    world = World(WorldConfig())
    stop = asyncio.Event()
    task = asyncio.create_task(RealTimeStepper(world).run(stop))
    server = Meca500Server(world, port=0)
    drivers: list[Meca500Driver] = []

    def make(**kw) -> Meca500Driver:
        kw.setdefault("connection_watchdog_s", 0)
        d = Meca500Driver("127.0.0.1", server.port, server.monitor_port, **kw)
        drivers.append(d)
        return d

    try:
        await server.start()
        yield SimpleNamespace(world=world, server=server, make=make)
    finally:
        for d in drivers:
            await d.close(deactivate=False)
        await server.close()
        stop.set()
        await task


async def until(cond, timeout: float = 3.0, what: str = "condition") -> None:
    end = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > end:
            raise AssertionError(f"timed out waiting for {what}")
        await asyncio.sleep(0.002)


async def run(d: Meca500Driver, world: World, dq: float) -> None:
    """One run as ``open_devices`` does it: connect, activate, home, then a move."""
    await d.connect()
    await d.activate()
    await d.home()
    q = list(world.arm.q)
    q[0] += dq
    await d.move_joints(q, wait=True)
    assert world.arm.q[0] == pytest.approx(q[0], abs=1e-3)


async def hit_joint_limit(d: Meca500Driver, world: World) -> None:
    """Stream J1 into its limit: the robot reports [1007] and goes into error."""
    world.teleport_arm(NEAR_J1_LIMIT)
    with pytest.raises(DeviceFault, match="1007"):
        for _ in range(500):
            await d.move_joints_vel((50.0, 0, 0, 0, 0, 0))
            await asyncio.sleep(0.002)
    await until(lambda: d.status.error, what="status es=1")


async def test_two_runs_in_a_row_both_move_the_arm():
    async with rig() as r:
        first = r.make()
        await run(first, r.world, 5.0)
        await first.close()                          # the end of the first run parks the arm
        await until(lambda: r.server.control_client is None, what="control port free")
        assert not r.server.activated and not r.server.paused
        second = r.make()
        await run(second, r.world, -5.0)             # refused before: "motion is paused"
        assert not second.paused and second.fault is None
        await second.close()
        assert not r.server.activated


async def test_an_arm_left_paused_is_resumed_only_on_request():
    async with rig() as r:
        first = r.make()
        await run(first, r.world, 5.0)
        await first.close(deactivate=False)          # a run that ended without parking
        await until(lambda: r.server.paused, what="robot paused by the dropped link")
        d = r.make()
        await d.connect()
        assert d.paused and d.activated and d.homed
        with pytest.raises(DeviceFault, match="paused"):
            await d.move_joints_vel((5.0, 0, 0, 0, 0, 0))
        q0 = r.world.arm.q[0]
        await d.resume()
        assert not d.paused and not r.server.paused
        await asyncio.sleep(0.05)
        assert r.world.arm.q[0] == pytest.approx(q0, abs=1e-3)   # resuming moves nothing
        await d.move_joints((q0 + 3.0, *r.world.arm.q[1:]), wait=True)
        assert r.world.arm.q[0] == pytest.approx(q0 + 3.0, abs=1e-3)


async def test_resume_refuses_an_error_raised_before_this_connection():
    async with rig() as r:
        first = r.make(vel_timeout_s=0.2)
        await run(first, r.world, 1.0)
        await hit_joint_limit(first, r.world)
        await first.close(deactivate=False)
        d = r.make()
        await d.connect()
        assert d.status.error and d.error_code == 0          # es=1, cause unknown here
        with pytest.raises(DeviceFault, match="in error"):
            await d.resume()
        with pytest.raises(DeviceFault, match="before this connection"):
            await d.resume(reset_error=True)
        assert r.server.in_error and r.server.paused        # nothing was changed


async def test_resume_resets_a_known_resettable_error_when_asked():
    async with rig() as r:
        assert 1007 in RESETTABLE_ERRORS
        d = r.make(vel_timeout_s=0.2)
        await run(d, r.world, 1.0)
        await hit_joint_limit(d, r.world)
        with pytest.raises(DeviceFault, match=r"\[1007\]"):
            await d.resume()                                 # not without the operator's word
        await d.resume(reset_error=True)
        assert d.fault is None and not d.paused and not r.server.in_error
        q_limit = r.world.arm.q[0]
        assert q_limit == pytest.approx(175.0)               # stopped at the limit
        await d.move_joints_vel((-20.0, 0, 0, 0, 0, 0))     # away from the limit
        await d.sync()
        await until(lambda: r.world.arm.q[0] < q_limit - 1.0, what="J1 moving back")


async def test_resume_refuses_an_arm_that_is_not_activated():
    async with rig() as r:
        d = r.make()
        await d.connect()
        with pytest.raises(DeviceFault, match="not activated"):
            await d.resume()
