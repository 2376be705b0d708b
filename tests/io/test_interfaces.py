"""The simulated devices satisfy the io protocols; sample types behave."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from dentibot.errors import ConfigError
from dentibot.io import Arm, AuxIO, AuxState, ForceSensor, Handpiece, JointState, MotorState, Wrench
from dentibot.sim import World, WorldConfig, make_devices


def test_sim_devices_satisfy_the_protocols():
    arm, ft, hp, aux = make_devices(World(WorldConfig()))
    assert isinstance(arm, Arm)
    assert isinstance(ft, ForceSensor)
    assert isinstance(hp, Handpiece)
    assert isinstance(aux, AuxIO)
    assert not isinstance(ft, Arm)


async def test_reads_return_typed_samples_with_time_and_seq():
    world = World(WorldConfig())
    arm, ft, hp, aux = make_devices(world)
    world.step()
    world.step()
    js, w, ms, ax = await arm.read(), await ft.read(), await hp.read(), await aux.read()
    assert isinstance(js, JointState) and isinstance(w, Wrench)
    assert isinstance(ms, MotorState) and isinstance(ax, AuxState)
    assert {js.seq, w.seq, ms.seq, ax.seq} == {2}
    assert js.t == w.t == pytest.approx(0.004)
    assert w.as_array().shape == (6,) and w.as_array()[0] == w.force_n[0]
    with pytest.raises(dataclasses.FrozenInstanceError):
        js.seq = 3  # type: ignore[misc]


async def test_device_commands_reach_the_world():
    world = World(WorldConfig())
    arm, ft, hp, aux = make_devices(world)
    await hp.set_velocity(60.0)
    with pytest.raises(ConfigError):
        await hp.set_velocity(250.0)
    await aux.set_platform((1.0, 2.0, 3.0))
    await aux.set_indicator("ready", True)
    await arm.move_joints_vel((5.0, 0, 0, 0, 0, 0))
    world.run(0.1)
    assert (await hp.read()).velocity_rpm == pytest.approx(60.0, abs=0.1)
    assert (await aux.read()).platform_mm == (1.0, 2.0, 3.0)
    assert world.indicators == {"ready": True}
    assert (await arm.read()).q_deg[0] > 0.0
    await ft.bias()
    np.testing.assert_allclose((await ft.read()).as_array(), 0.0)
