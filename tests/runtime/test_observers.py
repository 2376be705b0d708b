"""The observers on synthetic signals with known answers (what a real drive and arm report),
and the fault reaction that never waits for a silent device."""

from __future__ import annotations

import asyncio
import math

import pytest

from dentibot.runtime.actuate import stop_all
from dentibot.runtime.observers import (
    FractureObserver,
    ObserverLimits,
    SpindleObserver,
    TipSpeedObserver,
)

TS = 0.002
LIM = ObserverLimits()
TAU_S = 0.010            # a first-order speed loop (the simulated drive's)


def _first_tick_with(findings_by_tick) -> int | None:
    return next((k for k, f in enumerate(findings_by_tick) if f), None)


def test_a_drive_that_follows_its_command_is_never_flagged():
    obs = SpindleObserver(TS, LIM)
    rpm, out = 0.0, []
    for k in range(1000):                        # 2 s: spin up to 60 rpm and hold
        rpm += (60.0 - rpm) * (1.0 - math.exp(-TS / TAU_S))
        out.append(obs.check(("vel", 60.0), rpm, True, 8.0))
    assert _first_tick_with(out) is None


def test_power_lost_is_found_when_the_speed_leaves_its_band_plus_the_persistence():
    obs = SpindleObserver(TS, LIM)
    for _ in range(500):
        obs.check(("vel", 60.0), 60.0, True, 8.0)
    out = []
    for k in range(1, 50):                       # coasting down, no current (no load)
        rpm = 60.0 * math.exp(-k * TS / TAU_S)
        out.append(obs.check(("vel", 60.0), rpm, True, 0.0))
    first = _first_tick_with(out) + 1
    # out of the 18 rpm band (30 % of 60) after tau * ln(60 / 42) = 3.6 ms, i.e. from tick 2;
    # then 4 ticks of persistence (8 ms)
    leave = math.ceil(TAU_S * math.log(60.0 / 42.0) / TS)
    assert first == leave + round(LIM.persist_s / TS) - 1
    assert out[first - 1][0].kind == "handpiece_speed"


def test_a_loaded_file_that_slows_the_motor_is_left_to_the_torque_regulation():
    obs = SpindleObserver(TS, LIM)
    out = [obs.check(("vel", 60.0), 30.0, True, 45.0) for _ in range(200)]
    assert _first_tick_with(out) is None


def test_a_disabled_output_and_a_foreign_spin_are_faults():
    obs = SpindleObserver(TS, LIM)
    for _ in range(100):
        obs.check(("vel", 60.0), 60.0, True, 5.0)
    f = obs.check(("vel", 60.0), 59.0, False, 5.0)
    assert f and f[0].kind == "handpiece_disabled"
    obs = SpindleObserver(TS, LIM)
    out = [obs.check(("stop",), 0.0 if k < 100 else 150.0, True, 0.0) for k in range(120)]
    assert _first_tick_with(out) == 100 + round(LIM.persist_s / TS) - 1
    assert "while commanded to stop" in out[-1][0].detail


def _run_fracture(obs, torques, depths, rpm=60.0):
    return [obs.check(60.0, rpm, t, d) for t, d in zip(torques, depths)]


def test_a_file_that_breaks_while_fed_is_found_within_the_recent_window():
    obs = FractureObserver(TS, LIM)
    n = 100
    depths = [5.0 + 0.001 * k for k in range(2 * n)]          # fed in at 0.5 mm/s
    torques = [20.0] * n + [0.3] * n
    out = _run_fracture(obs, torques, depths)
    first = _first_tick_with(out)
    assert first == n - 1 + round(LIM.fracture_recent_s / TS)   # the 3rd sample after
    assert out[first][0].kind == "fracture_suspected"


def test_no_fracture_when_withdrawing_outside_or_fading():
    n = 100
    torques = [20.0] * n + [0.3] * n
    out = _run_fracture(FractureObserver(TS, LIM), torques,
                        [5.0 - 0.002 * k for k in range(2 * n)])       # withdrawn at 1 mm/s
    assert _first_tick_with(out) is None
    out = _run_fracture(FractureObserver(TS, LIM), torques, [0.2] * (2 * n))   # not inside
    assert _first_tick_with(out) is None
    fading = [20.0 * max(0.0, 1.0 - k / 150) for k in range(2 * n)]      # 300 ms fade
    out = _run_fracture(FractureObserver(TS, LIM), fading, [5.0] * (2 * n))
    assert _first_tick_with(out) is None


def test_the_free_running_level_is_learnt_outside_the_canal():
    """A real file runs free at about 17 mNm: a drop to that level is a drop to nothing."""
    obs = FractureObserver(TS, LIM)
    _run_fracture(obs, [17.0] * 300, [-3.0] * 300)
    assert obs.free_mnm == pytest.approx(17.0)
    out = _run_fracture(obs, [37.0] * 100 + [17.2] * 10, [6.0] * 110)
    assert _first_tick_with(out) == 99 + round(LIM.fracture_recent_s / TS)


def test_the_measured_tip_speed_bound():
    obs = TipSpeedObserver(TS, LIM)
    fast = [obs.check((0.070 * k * 1000 * TS, 0.0, 0.0)) for k in range(20)]   # 70 mm/s
    # the first sample has no speed; then 4 ticks above the bound (8 ms)
    assert _first_tick_with(fast) == round(LIM.persist_s / TS)
    obs = TipSpeedObserver(TS, LIM)
    slow = [obs.check((0.040 * k * 1000 * TS, 0.0, 0.0)) for k in range(100)]  # 40 mm/s
    assert _first_tick_with(slow) is None


def test_a_late_joint_sample_does_not_read_as_a_doubled_speed():
    """40 mm/s with every 4th sample a period late (the same position twice, then a double
    step), as a loaded machine delivers them in real time: not above 60 mm/s."""
    obs, x, out = TipSpeedObserver(TS, LIM), 0.0, []
    for k in range(200):
        if k % 4 != 1:
            x += 0.040 * 1000 * TS * (2 if k % 4 == 2 else 1)
        out.append(obs.check((x, 0.0, 0.0)))
    assert _first_tick_with(out) is None


class _Device:
    def __init__(self, hang_s: float = 0.0) -> None:
        self.hang_s = hang_s
        self.stopped = False

    async def stop(self) -> None:
        await asyncio.sleep(self.hang_s)
        self.stopped = True


async def test_the_fault_reaction_does_not_wait_for_a_silent_device():
    motor, arm = _Device(), _Device(hang_s=60.0)       # a half-open link: no answer
    unfinished: set = set()
    await stop_all(motor, arm, unfinished)
    assert motor.stopped                               # the file's stop went out and is done
    assert not arm.stopped and len(unfinished) == 1    # still waiting, in the background
    for t in unfinished:
        t.cancel()
    await asyncio.sleep(0)
