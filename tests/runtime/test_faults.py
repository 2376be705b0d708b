"""The fault catalogue: each fault injected while drilling ends in a safe state within its
detection bound, with every tick recorded (in-process devices, and over the wire)."""

from __future__ import annotations

import inspect
import math

import pytest

from dentibot.app.selftest import EXPECT, run_fault
from dentibot.app.selftest_wire import (HOST_FAULTS, WIRE_FAULTS, run_wire_fault,
                                        wire_stale_periods)
from dentibot.io.epos4 import DEFAULT_QUICK_STOP_FILE_RPM_S
from dentibot.runtime.config import RuntimeConfig
from dentibot.runtime.observers import ObserverLimits
from dentibot.sim.faults import FAULTS
from dentibot.sim.world import WorldConfig

pytestmark = pytest.mark.wire


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


# --- over the wire: bounds from the configuration, independently of the selftest's own
_TS_MS = RuntimeConfig().period_s * 1e3             # control period and SYNC cycle (2 ms)
_STALE_MS = 20 * _TS_MS                             # the wire selftest's stale bound
_LIM = ObserverLimits()
_TAU_MS = WorldConfig().handpiece.tau_s * 1e3       # the simulated speed loop (10 ms)
#: loopback delivery and scheduling on a loaded 2-core machine, on top of every bound
_SLACK_MS = 30.0


def _crossing_ms(rpm: float, target: float, tol_share: float) -> float:
    """First order (tau) from ``rpm`` toward ``target``: time to leave the tolerance band."""
    tol = max(_LIM.speed_tolerance_rpm, tol_share * rpm)
    return _TAU_MS * math.log(abs(target - rpm) / (abs(target - rpm) - tol))


_WIRE_DETECT_MS = {
    "ft_stream_stop": _STALE_MS + _TS_MS,
    "arm_disconnect": _TS_MS,
    "can_silence": _STALE_MS + _TS_MS,
    "emcy": 2 * _TS_MS,
    # the drive follows the foreign set-point within its settling time, then persistence
    "can_foreign_master": _LIM.settle_s * 1e3 + _LIM.persist_s * 1e3 + 2 * _TS_MS,
    # from the foreign write's acknowledgement: the aux driver's 10 ms poll and the tick that
    # reads the driver, plus four Modbus requests in turn (_MODBUS_REQUESTS_MS)
    "modbus_foreign_client": 10.0 + _TS_MS,
    "arm_half_open": _STALE_MS + _TS_MS,
    # coasting from 60 rpm toward 0 leaves the 30 % band, then persistence, SYNC, tick
    "handpiece_power_loss": _crossing_ms(60.0, 0.0, _LIM.speed_tolerance_share)
    + _LIM.persist_s * 1e3 + 2 * _TS_MS,
    "command_error": 2 * _TS_MS,
}
RUNTIME_WIRE_FAULTS = [f for f in WIRE_FAULTS if f not in HOST_FAULTS]


def _modbus_requests_ms(r) -> float:
    """The foreign write lands just after a read-back was sent and a feed follows it (the feed
    restores the registers until the foreign client writes again): those two, then the next
    poll's inputs and read-back, each as long as the worst round trip the aux driver measured
    in the run (the loop it shares with the simulators makes one 2-18 ms)."""
    if r.fault != "wire:modbus_foreign_client":
        return 0.0
    assert r.round_trip_ms is not None and r.round_trip_ms > 0.0, r
    return 4 * r.round_trip_ms


def test_every_wire_fault_has_a_bound_here():
    assert set(_WIRE_DETECT_MS) == set(RUNTIME_WIRE_FAULTS)
    assert set(HOST_FAULTS) <= set(WIRE_FAULTS)


def _heartbeat_lost_first(name: str, r) -> bool:
    """The foreign CAN master's 1 kHz traffic runs in this one process with the simulators
    and the control loop, its frames handed from reader threads to the loop. Handed over one
    by one they queued for 30-40 ms, past the drive's 30 ms heartbeat consumer; in batches
    (LoopReader) the latency stays under 10 ms, but with another CPU-bound job on a 2-core
    machine a run still now and then ends in that other fault first (the motor stream stale,
    the host's heartbeat lost: EMCY 0x8130; rightly latched), not in the case under test
    (measured: none in 30 quiet runs, 2 in 20 beside a busy process)."""
    first = r.cause.split("; ")[0]
    return name == "can_foreign_master" and ("0x8130" in first
                                             or first.startswith("stale_motor"))


def _machine_stalled(r) -> bool:
    """The runtime, the simulators and the drivers share one event loop here: a run in which
    that loop stalled longer than the aux driver's 10 ms poll (a collection, a compilation,
    the other test worker's burst on a 2-core machine) and that missed a bound measured the
    machine. Seen once on a loaded CI machine: the foreign Modbus client detected at 56 ms
    against 48."""
    return not r.ok and r.loop_stall_ms is not None and r.loop_stall_ms > 10.0


@pytest.mark.timeout(90)
@pytest.mark.parametrize("name", RUNTIME_WIRE_FAULTS)
async def test_wire_fault_ends_in_the_latched_fault(name):
    for _ in range(3):              # see _heartbeat_lost_first, _machine_stalled: three tries
        r = await run_wire_fault(name)
        if not (_heartbeat_lost_first(name, r) or _machine_stalled(r)):
            break
    assert r.final_state == "fault" and r.samples_lost == 0 and r.ok, r
    assert r.cause
    # the foreign CAN master's own traffic runs in the simulators' process: twice the slack
    slack = 2 * _SLACK_MS if name == "can_foreign_master" else _SLACK_MS
    assert r.detected_ms <= _WIRE_DETECT_MS[name] + _modbus_requests_ms(r) + slack, r
    # the stop goes out with the next SYNC; the speed loop brings the fastest speed the fault
    # allows (the foreign master's 150 rpm, else 60 rpm) below 1 rpm
    top = 150.0 if name == "can_foreign_master" else 60.0
    assert r.file_stopped_ms <= _TS_MS + _TAU_MS * math.log(top) + slack, r
    assert abs(r.file_rpm) < 1.0 and r.arm_speed_deg_s < 1.0
    expected_cause = {"can_foreign_master": "handpiece_speed",
                      "handpiece_power_loss": "handpiece_speed",
                      "modbus_foreign_client": "host watchdog overwritten",
                      "command_error": "[1000]", "arm_half_open": "stale_arm"}.get(name)
    if expected_cause is not None:
        assert expected_cause in r.cause.split("; ")[0], r.cause


#: host_kill is the same child, signal and measurement as the kill -9 case of
#: tests/integration/test_liveness.py, which also checks the drive's own state: run once.
HOST_FAULTS_HERE = tuple(f for f in HOST_FAULTS if f != "host_kill")


@pytest.mark.slow
@pytest.mark.timeout(180)
@pytest.mark.parametrize("name", HOST_FAULTS_HERE)
async def test_host_fault_leaves_nothing_moving(name, tmp_path):
    r = await run_wire_fault(name, directory=tmp_path)
    assert r.ok and r.samples_lost == 0, r
    assert abs(r.file_rpm) < 1.0 and r.arm_speed_deg_s < 1.0
    if name in ("host_kill", "host_freeze"):
        # the drive's heartbeat consumer (30 ms after the last beat), its quick-stop ramp
        # from 60 rpm, the speed loop below 1 rpm: within the required 100 ms
        bound = 30.0 + 60.0 / DEFAULT_QUICK_STOP_FILE_RPM_S * 1e3 + _TAU_MS * math.log(60.0)
        assert r.file_stopped_ms <= min(bound + 15.0, 100.0), r
        assert r.final_state == "drive FAULT" and "0x8130" in r.reaction
    else:
        assert r.final_state == f"exit {128 + {'sigint': 2, 'sigterm': 15}[name]}", r
        assert "recording finished" in r.reaction and r.detected_ms is not None


def test_simulators_bind_loopback_by_default():
    from dentibot.sim.aux_modbus_server import AuxModbusServer
    from dentibot.sim.meca500_server import Meca500Server
    from dentibot.sim.netft_server import NetFTServer
    from dentibot.sim.serve import ServePorts
    from dentibot.sim.socketcand import SocketcandServer

    for cls in (Meca500Server, NetFTServer, AuxModbusServer, SocketcandServer):
        assert inspect.signature(cls).parameters["host"].default == "127.0.0.1", cls
    assert ServePorts().host == "127.0.0.1"


def test_the_foreign_can_master_gives_the_motor_stream_its_extra_slack():
    """40 ms (20 periods of 2 ms) for every stream; with the foreign master's traffic in the
    process, the motor's 30 ms more: 70 ms, 35 periods. The others keep theirs."""
    assert wire_stale_periods("emcy") == {"arm": 20, "ft": 20, "motor": 20, "aux": 100}
    assert wire_stale_periods("can_foreign_master") == {"arm": 20, "ft": 20, "motor": 35,
                                                        "aux": 100}


@pytest.mark.parametrize("failures, calls, ok", [(2, 3, True), (3, 3, False)])
async def test_a_wire_fault_whose_set_up_fails_is_set_up_again_never_measured_twice(
        monkeypatch, failures, calls, ok):
    """A procedure not drilling when the fault is due (the set-up on a loaded machine) is set
    up anew, at most ATTEMPTS (3) times; a run that reached the injection is never run
    again."""
    import dentibot.app.selftest_wire as sw

    seen = []

    async def attempt(name, seed, settle_s, watch_s):
        seen.append(name)
        if len(seen) <= failures:
            raise sw.NotReady("wire selftest: not drilling before the injection (fault)")
        return "measured"

    monkeypatch.setattr(sw, "_run_runtime_fault", attempt)
    if ok:
        assert await run_wire_fault("emcy") == "measured"
    else:
        with pytest.raises(sw.NotReady, match="not drilling before the injection"):
            await run_wire_fault("emcy")
    assert seen == ["emcy"] * calls and sw.ATTEMPTS == 3
