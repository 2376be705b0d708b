"""The fault catalogue: each fault injected while drilling ends in a safe state within its
detection bound, with every tick recorded (in-process devices, and over the wire)."""

from __future__ import annotations

import inspect

import pytest

from dentibot.app.selftest import EXPECT, WIRE_FAULTS, run_fault, run_wire_fault
from dentibot.sim.faults import FAULTS


def test_every_fault_has_an_expectation():
    assert set(EXPECT) == set(FAULTS)


@pytest.mark.parametrize("name", FAULTS)
async def test_fault_is_handled_safely_in_time_and_nothing_is_lost(name, tmp_path):
    r = await run_fault(name, directory=tmp_path)
    states, bound = EXPECT[name]
    assert r.final_state in states, r
    assert r.samples_lost == 0
    if bound is not None:
        assert r.detected_ms is not None and r.detected_ms <= bound, r
    if r.final_state == "fault":
        # the file is stopped (spinning down) and the arm is at rest, and the cause is named
        assert r.file_rpm < 5.0 and r.arm_speed_deg_s < 1.0
        assert r.cause
    assert r.ok


@pytest.mark.parametrize("name, bound_ms", [
    ("ft_nan", 2.0), ("ft_saturation", 2.0), ("emcy", 2.0), ("bus_off", 2.0),
    ("arm_disconnect", 2.0),
    # stale bounds: 4 periods (F/T, motor, arm), plus the tick that notices: 10 ms, the
    # bound every abrupt fault is held to
    ("ft_stream_stop", 2.0 * 5), ("can_silence", 2.0 * 5), ("arm_half_open", 2.0 * 5),
])
async def test_detection_bounds_follow_from_the_supervisor_limits(name, bound_ms, tmp_path):
    r = await run_fault(name, directory=tmp_path)
    assert r.detected_ms == pytest.approx(bound_ms)


@pytest.mark.timeout(60)
@pytest.mark.parametrize("name", WIRE_FAULTS)
async def test_wire_fault_ends_in_the_latched_fault(name):
    r = await run_wire_fault(name)
    assert r.final_state == "fault" and r.samples_lost == 0 and r.ok, r
    # real time on loopback: within the stale bound used (20 periods = 40 ms) plus margin
    assert r.detected_ms <= 60.0


def test_simulators_bind_loopback_by_default():
    from dentibot.sim.aux_modbus_server import AuxModbusServer
    from dentibot.sim.meca500_server import Meca500Server
    from dentibot.sim.netft_server import NetFTServer
    from dentibot.sim.serve import ServePorts
    from dentibot.sim.socketcand import SocketcandServer

    for cls in (Meca500Server, NetFTServer, AuxModbusServer, SocketcandServer):
        assert inspect.signature(cls).parameters["host"].default == "127.0.0.1", cls
    assert ServePorts().host == "127.0.0.1"
