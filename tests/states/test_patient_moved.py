"""The patient-moved state (fig 5.6) ends in a release or a fault, whatever the force does."""

from __future__ import annotations

import math
from types import SimpleNamespace

from dentibot.runtime.config import Thresholds
from dentibot.states.behaviours import PatientMoved

TS = 0.002


def _run(force_at, ticks: int, moved_mm_s: float = 0.0):
    """Feeds PatientMoved a force norm ``force_at(t)`` (N) with the tip moving at
    ``moved_mm_s`` along x; returns (tick of the first event, the event) or None."""
    rt = SimpleNamespace(cfg=SimpleNamespace(thresholds=Thresholds()), ts=TS)
    est = SimpleNamespace(force_norm_n=force_at(0.0), tip_0=(0.0, 0.0, 0.0))
    b = PatientMoved()
    b.enter(None, rt, est, "treating.drilling.feeding")
    for k in range(1, ticks + 1):
        est.force_norm_n = force_at(k * TS)
        est.tip_0 = (moved_mm_s * k * TS, 0.0, 0.0)
        ev = b.events(None, rt, est)
        if ev:
            return k, ev[0]
    return None


def test_a_force_ringing_across_the_release_threshold_is_a_fault_at_the_persist_time():
    # 1.5 |sin| at 19 Hz: below 1.0 N for 2 asin(2/3) / pi of each 26 ms half-period (12 ms),
    # never the 0.1 s a release needs; the state may last 2 s: the fault comes at tick 1001
    th = Thresholds()
    assert (th.patient_release_n, th.patient_release_s, th.patient_persist_s) == (1.0, 0.1, 2.0)
    got = _run(lambda t: 1.5 * abs(math.sin(2 * math.pi * 19.0 * t)), 3000)
    assert got is not None
    k, (kind, detail) = got
    assert kind == "fault" and k == 1001
    assert "not released 2.0 s" in detail and "peak 1.50 N" in detail


def test_a_force_that_falls_below_the_threshold_for_the_release_time_releases():
    # 1.4 N for 0.5 s, then 0.6 N: released at the 50th tick below (0.1 s)
    got = _run(lambda t: 1.4 if t <= 0.5 else 0.6, 3000)
    assert got is not None
    k, (kind, _) = got
    assert kind == "patient_released" and k == 250 + 50


def test_a_steady_force_that_the_arm_does_not_relieve_is_a_fault_at_the_persist_time():
    got = _run(lambda t: 1.2, 3000)
    assert got is not None and got[1][0] == "fault" and got[0] == 1001
    assert "at or above 1.0 N 100 %" in got[1][1]
