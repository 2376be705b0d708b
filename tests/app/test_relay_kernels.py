"""A compiled call's groups of ticks sent to the recorder's process as the call computes
them (app/relay_kernels.py, on a real recorder process)."""

from __future__ import annotations

import os
import signal
import time

import numpy as np
import pytest
from numba import njit

from dentibot.app import relay_kernels as rk
from dentibot.telemetry.blocks import COL, WIDTH
from dentibot.telemetry.reader import read_recording
from dentibot.telemetry.recorder import TelemetryOverflow
from dentibot.telemetry.recorder_process import RecorderProcess, Wire

pytestmark = pytest.mark.timeout(60)

TS = 1.0 / 500.0
META = {"protocol": "relay", "seed": 1, "rate_hz": 500.0}
BLOCK = ("4:drill", "treating.drilling.feeding", TS, 16.0, 0, (180.0, 0.0, 90.0))


@njit(nogil=True)
def _call(n, relay, rows):
    """A compiled call's shape: hold before each tick, write its row, publish after it."""
    rk.begin(relay)
    ran = n
    for i in range(n):
        if not rk.hold(relay):
            ran = i
            break
        x = 0.0
        for j in range(500):                  # some work
            x += np.sqrt(j + i)
        for c in range(rows.shape[1]):
            rows[i, c] = i + c / 100.0
        rows[i, 0] = x
        rk.publish(relay, i)
    rk.end(relay)
    return ran


def _relay(rec: RecorderProcess, rows: np.ndarray, ctl: np.ndarray, every: int = 25):
    wire = Wire(rec, WIDTH, 256)
    return wire, rk.wire_args(every, ctl, wire.begin(*BLOCK), rows, COL["compute_us"], 0)


def test_each_group_reaches_the_recording_with_its_compute_time(tmp_path):
    rec = RecorderProcess(tmp_path / "r.mcap", dict(META), validate=False, max_queue=50)
    rows = np.zeros((256, WIDTH))
    ctl = np.zeros(rk.CTL_SIZE, dtype=np.int64)
    wire, relay = _relay(rec, rows, ctl)
    t0 = time.perf_counter()
    assert _call(110, relay, rows) == 110
    wall_us = (time.perf_counter() - t0) * 1e6
    wire.end(99, TS, 25)
    assert ctl[rk.PUB] == 100 and ctl[rk.TAIL_NS] > 0
    # each group's compute time, shared out over its rows: one positive value per group,
    # and the groups' times together within the call's wall time
    us = rows[:100, COL["compute_us"]].reshape(4, 25)
    assert (us > 0).all() and (us == us[:, :1]).all()
    assert 25 * us[:, 0].sum() + ctl[rk.TAIL_NS] / 1e3 <= wall_us
    assert rec.rows_queued == 100 and rec.at_risk_max <= rec.budget
    rec.close()
    got = read_recording(tmp_path / "r.mcap").rows
    assert [r["tick"] for r in got] == list(range(100))
    assert [r["q_deg"][0] for r in got] == rows[:100, 0].tolist()


def test_a_group_the_recorder_makes_no_room_for_stops_the_call_before_its_next_tick(tmp_path):
    rec = RecorderProcess(tmp_path / "s.mcap", dict(META), validate=False, max_wait_s=0.2,
                          max_queue=50)
    rows = np.zeros((256, WIDTH))
    ctl = np.zeros(rk.CTL_SIZE, dtype=np.int64)
    wire, relay = _relay(rec, rows, ctl)
    os.kill(rec.pid, signal.SIGSTOP)
    try:
        # the budget of 50 holds two groups; the third finds no room in 0.2 s
        assert _call(200, relay, rows) == 75
        assert ctl[rk.PUB] == 50 and ctl[rk.ABORT] == 1
        with pytest.raises(TelemetryOverflow, match="ticks 50 to 74 dropped"):
            wire.end(49, TS, 25)
    finally:
        os.kill(rec.pid, signal.SIGCONT)
    rec.close("fault", "telemetry overflow")
    assert rec.ticks_written == 50


def test_a_call_that_sends_nothing_runs_every_tick():
    rows = np.zeros((64, WIDTH))
    assert _call(64, rk.OFF, rows) == 64
    assert not rk.OFF[2].any()
