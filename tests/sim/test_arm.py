"""Meca500 servo model: velocity timeout, speed limits, joint limit and singularity errors."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from dentibot.errors import DeviceFault
from dentibot.sim import SimArm, World, WorldConfig
from dentibot.sim.arm import ERROR_JOINT_LIMIT, ERROR_SINGULARITY

VMAX = np.array([150.0, 150.0, 180.0, 300.0, 300.0, 500.0])   # Meca500 manual, deg/s


def test_velocity_command_times_out_and_the_arm_comes_to_rest(world):
    world.arm.command_velocity((10.0, 0, 0, 0, 0, 0), world.t)
    t_cmd = world.t
    world.run(0.04)
    assert world.arm.qdot[0] == pytest.approx(10.0, rel=0.02)    # 5 lag constants of 8 ms
    while world.t < t_cmd + 0.05 - 1e-9:
        world.step()
    assert world.arm.qdot[0] > 9.0                               # still moving at the timeout
    world.run(0.1)                                               # 12 lag constants later
    assert world.arm.qdot == [0.0] * 6
    q = list(world.arm.q)
    world.run(0.05)
    assert world.arm.q == q


def test_repeated_velocity_commands_keep_it_moving(world):
    for _ in range(100):
        world.arm.command_velocity((0, 0, 0, 0, 0, 20.0), world.t)
        world.step()
    assert world.arm.qdot[5] == pytest.approx(20.0, rel=1e-3)


@settings(max_examples=25, deadline=None)
@given(st.lists(st.floats(-2000, 2000), min_size=6, max_size=6), st.booleans())
def test_joint_speed_never_exceeds_the_limit(cmd, position):
    world = World(WorldConfig(seed=0))
    q0 = np.array(world.arm.q)
    for k in range(60):
        if position:
            world.arm.command_position(q0 + np.sign(cmd) * 30.0)
        else:
            world.arm.command_velocity(cmd, world.t)
        qa = np.array(world.arm.q)
        world.step()
        measured = (np.array(world.arm.q) - qa) / world.ts
        assert np.all(np.abs(measured) <= VMAX * (1 + 1e-9))
        assert np.all(np.abs(world.arm.qdot) <= VMAX)


async def test_commanding_past_a_joint_limit_stops_at_it_with_1007():
    world = World(WorldConfig(seed=0))
    arm = SimArm(world)
    world.teleport_arm((170.0, -10.0, 20.0, 0.0, 80.0, 0.0))
    for _ in range(500):
        await arm.move_joints_vel((100.0, 0, 0, 0, 0, 0))
        world.step()
        if world.arm.error_code:
            break
    assert arm.error_code == ERROR_JOINT_LIMIT
    assert world.arm.q[0] <= 175.0
    assert world.arm.q[0] > 174.0
    world.run(0.05)
    assert world.arm.qdot == [0.0] * 6 and world.arm.q[0] <= 175.0
    with pytest.raises(DeviceFault):
        await arm.move_joints_vel((-10.0, 0, 0, 0, 0, 0))
    await arm.reset_error()
    await arm.move_joints_vel((-10.0, 0, 0, 0, 0, 0))
    world.run(0.04)
    assert world.arm.q[0] < 175.0 and arm.error_code == 0


def test_move_joints_past_the_limit_stops_at_the_limit():
    world = World(WorldConfig(seed=0))
    world.arm.command_position((0.0, -10.0, 20.0, 0.0, 80.0, 0.0))
    world.arm.command_position((0.0, -10.0, 100.0, 0.0, 80.0, 0.0))  # J3 max is 70
    world.run(1.0)
    assert world.arm.error_code == ERROR_JOINT_LIMIT
    assert world.arm.q[2] == pytest.approx(70.0)


def test_a_joint_move_crosses_the_wrist_singularity():
    """Programming manual, MoveJoints: "the robot can cross singularities without any
    problem"; only joint limits stop a joint-space move."""
    world = World(WorldConfig(seed=0))
    world.teleport_arm((0.0, -10.0, 20.0, 0.0, 5.0, 0.0))
    world.arm.command_position((0.0, -10.0, 20.0, 0.0, -5.0, 0.0))
    world.run(0.5)
    assert world.arm.error_code == 0
    assert world.arm.q[4] == pytest.approx(-5.0, abs=1e-3)


def test_wrist_singularity_latches_1012_before_entering_it():
    world = World(WorldConfig(seed=0))
    world.teleport_arm((0.0, -10.0, 20.0, 0.0, 5.0, 0.0))
    for _ in range(250):                        # -20 deg/s on J5, refreshed every step
        world.arm.command_velocity((0.0, 0.0, 0.0, 0.0, -20.0, 0.0), world.t)
        world.run(world.ts)
    assert world.arm.error_code == ERROR_SINGULARITY
    assert abs(math.sin(math.radians(world.arm.q[4]))) >= math.sin(math.radians(0.5))
    assert world.kin.singularity(world.arm.q).wrist >= math.sin(math.radians(0.5))


def test_encoder_reading_is_quantised(world):
    world.teleport_arm((0.12345, -10.0, 20.0, 0.0, 80.0, 0.0))
    q, _ = world.arm.reading()
    assert q[0] == pytest.approx(0.123, abs=1e-12)


def test_queued_commands_take_effect_after_the_dead_time_in_order_however_many():
    """With a 1 s dead time, commands given every millisecond for 0.2 s (200, more than the
    queue first holds) each take effect 1 s after it was given, in order, none lost."""
    from dentibot.sim.arm import QUEUE, ArmParams, SimArmModel

    arm = SimArmModel(World().kin, (0.0, -10.0, 20.0, 0.0, 80.0, 0.0),
                      ArmParams(vel_dead_time_s=1.0, vel_timeout_s=10.0))
    n = 200
    assert n > QUEUE
    for k in range(n):
        arm.command_velocity((0.01 * k, 0, 0, 0, 0, 0), 0.001 * k)
    assert arm.vel_cmd == [0.0] * 6                # none in force yet
    for t, k in ((1.0005, 0), (1.0505, 50), (1.1995, 199)):
        arm.step(t, 0.002)
        assert arm.vel_cmd[0] == pytest.approx(0.01 * k)   # the last one due by t
        assert arm.vel_cmd_t == pytest.approx(0.001 * k + 1.0)


def test_a_command_is_clipped_to_each_joints_speed(world):
    world.arm.command_velocity((1e9, -1e9, 1e9, 1.0, -1.0, -1e9), world.t)
    assert world.arm.vel_cmd == [150.0, -150.0, 180.0, 1.0, -1.0, -500.0]   # VMAX
