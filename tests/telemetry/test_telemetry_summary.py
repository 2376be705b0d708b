"""Run summaries: numbers worked out by hand from synthetic rows; live == from the file."""

from __future__ import annotations

import json
import math
import time

import pytest
from rich.console import Console
from telemetry_helpers import ramp_row

from dentibot.errors import ConfigError
from dentibot.telemetry import (
    McapRecorder,
    SummaryAccumulator,
    default_row,
    read_recording,
    summarize_file,
    summarize_recording,
    summary_json,
    summary_table,
)

pytestmark = pytest.mark.timeout(30)

RATE_HZ = 100


def synthetic_rows() -> list[dict]:
    """300 ticks at 100 Hz: step "approach" (ticks 0-99) then "drilling" (100-299).

    approach: motor stopped (rpm 0), torque 5 mNm but -8 at tick 50; force 5 N at tick 77
      ([3, 4, 0]); patient moves at ticks 20-29; overrun at tick 5; reversal #1 at tick 50;
      no depth, no completeness.
    drilling: torque ramp 0.25 * (i - 100) mNm (0 .. 49.75), rpm 300 (-300 at ticks 250-254,
      0 at ticks 200-209); force 10 N at tick 260 ([0, -6, 8]); patient moves at 150-159;
      overruns at 120 and 250; reversals #2 at 130, #3 at 200; fractured from tick 280;
      depth 0.125 * (i - 100) mm; completeness 0.25, 0.75 at tick 290, null after.
    lateness_us = tick number everywhere.
    """
    rows = []
    for i in range(300):
        drilling = i >= 100
        k = i - 100
        row = default_row(
            t=i / RATE_HZ, tick=i, step="drilling" if drilling else "approach",
            state="treating.drilling.feeding" if drilling else "positioning",
            wrench_h=[0.0, 0.0, -1.0, 0.0, 0.0, 0.0],
            file_torque_mnm=0.25 * k if drilling else 5.0,
            motor_rpm=300.0 if drilling else 0.0,
            patient_moved=20 <= i <= 29 or 150 <= i <= 159,
            overrun=i in (5, 120, 250),
            lateness_us=float(i),
            reversals=(i >= 50) + (i >= 130) + (i >= 200),
            fractured=i >= 280,
            depth_mm=0.125 * k if drilling else None,
            completeness=(0.75 if i == 290 else 0.25 if i < 290 else None) if drilling else None,
            events=["PatientMoved"] if i in (20, 150) else ["Fracture"] if i == 280 else [],
        )
        if i == 50:
            row["file_torque_mnm"] = -8.0
        if i == 77:
            row["wrench_h"] = [3.0, 4.0, 0.0, 0.0, 0.0, 0.0]
        if i == 260:
            row["wrench_h"] = [0.0, -6.0, 8.0, 0.5, 0.0, 0.0]
        if 250 <= i <= 254:
            row["motor_rpm"] = -300.0
        if 200 <= i <= 209:
            row["motor_rpm"] = 0.0
        rows.append(row)
    return rows


EVENTS = [("transition", "positioning -> drilling", 1.0, 100),
          ("transition", "drilling -> stopped", 2.8, 280),
          ("fault", "file fractured", 2.8, 280)]
STATUS, REASON = "fracture", "file fractured at 22.5 mm"


def _live(rows, rate_hz=RATE_HZ):
    acc = SummaryAccumulator(rate_hz=rate_hz)
    for row in rows:
        acc.add(row)
    for kind, detail, t, tick in EVENTS:
        acc.add_event(kind, detail, t=t, tick=tick)
    return acc.finish(STATUS, REASON)


def test_summary_numbers_match_the_hand_computed_ones():
    s = _live(synthetic_rows())
    assert (s.status, s.reason, s.ticks) == (STATUS, REASON, 300)
    assert s.duration_s == 3.0
    assert s.peak_file_torque_mNm == 49.75
    # mean |torque| over ticks with rpm != 0: drilling ticks k = 0..199 except k = 100..109
    assert s.mean_file_torque_mNm == 0.25 * (sum(range(200)) - sum(range(100, 110))) / 190
    assert s.peak_force_N == 10.0
    assert s.patient_moved_episodes == 2
    assert s.deadline_misses == 3
    assert s.reversals == 3
    assert s.fractures == 1
    assert s.completeness == 0.75
    assert s.depth_reached_mm == 0.125 * 199
    # nearest rank: ceil(0.99 * 300) = 297th smallest of 0..299
    assert s.lateness_p99_us == 296.0
    assert s.events == {"transition": 2, "fault": 1}
    assert s.detections == {"PatientMoved": 2, "Fracture": 1}

    approach, drilling = s.steps
    assert approach.name == "approach" and drilling.name == "drilling"
    assert (approach.ticks, approach.duration_s) == (100, 1.0)
    assert approach.peak_file_torque_mNm == 8.0          # |-8|, motor stopped or not
    assert approach.mean_file_torque_mNm is None         # the motor never turned
    assert approach.peak_force_N == 5.0
    assert approach.patient_moved_episodes == 1 and approach.deadline_misses == 1
    assert approach.reversals == 1 and approach.fractures == 0
    assert approach.depth_reached_mm is None and approach.completeness is None
    assert approach.lateness_p99_us == 98.0              # 99th smallest of 0..99
    assert (drilling.ticks, drilling.duration_s) == (200, 2.0)
    assert drilling.peak_file_torque_mNm == 49.75
    assert drilling.mean_file_torque_mNm == s.mean_file_torque_mNm
    assert drilling.peak_force_N == 10.0
    assert drilling.patient_moved_episodes == 1 and drilling.deadline_misses == 2
    assert drilling.reversals == 2 and drilling.fractures == 1
    assert drilling.depth_reached_mm == 24.875 and drilling.completeness == 0.75
    assert drilling.lateness_p99_us == 297.0             # 198th smallest of 100..299


def test_without_rate_the_duration_is_the_last_t():
    s = _live(synthetic_rows(), rate_hz=None)
    assert s.duration_s == 2.99
    assert s.steps[0].duration_s == pytest.approx(0.99, abs=1e-12)
    assert s.steps[1].duration_s == pytest.approx(2.0, abs=1e-12)


def test_report_from_the_file_equals_the_live_summary(tmp_path):
    rows = synthetic_rows()
    rows[150]["depth_mm"] = math.nan          # written as null; skipped live and from file
    path = tmp_path / "run.mcap"
    live = SummaryAccumulator(rate_hz=RATE_HZ)
    with McapRecorder(path, {"protocol": "synthetic", "rate_hz": RATE_HZ}) as rec:
        for i, row in enumerate(rows):
            rec.record(row)
            live.add(row)
            for kind, detail, t, tick in EVENTS:
                if tick == i:
                    rec.event(kind, detail, t=t, tick=tick)
                    live.add_event(kind, detail, t=t, tick=tick)
        rec.close(STATUS, REASON)
    from_file = summarize_recording(read_recording(path))
    assert from_file == live.finish(STATUS, REASON)
    assert summarize_file(path) == from_file                 # streamed: the same
    assert summary_json(from_file) == summary_json(live.finish(STATUS, REASON))
    assert from_file.depth_reached_mm == 24.875


def test_report_from_a_long_file_equals_live(tmp_path):
    rows = [ramp_row(i) for i in range(1000)]
    path = tmp_path / "run.mcap"
    live = SummaryAccumulator(rate_hz=500)
    with McapRecorder(path, {"rate_hz": 500}) as rec:
        for row in rows:
            rec.record(row)
            live.add(row)
    assert summarize_recording(read_recording(path)) == live.finish("ok")
    assert summarize_file(path) == live.finish("ok")


def test_a_recording_without_end_is_incomplete(tmp_path):
    path = tmp_path / "run.mcap"
    rec = McapRecorder(path, {"rate_hz": RATE_HZ}, flush_interval_s=0.02)
    try:
        for row in synthetic_rows()[:50]:
            rec.record(row)
        deadline = time.monotonic() + 10.0
        while rec.rows_flushed < 50:
            assert time.monotonic() < deadline, "rows not flushed in time"
            time.sleep(0.005)
        cut = tmp_path / "cut.mcap"
        cut.write_bytes(path.read_bytes())
    finally:
        rec.close("ok")
    s = summarize_recording(read_recording(cut))
    assert summarize_file(cut) == s
    assert s.status == "incomplete" and "/run/end" in s.reason
    assert s.ticks == 50 and s.duration_s == 0.5


def test_summary_json_and_table():
    s = _live(synthetic_rows())
    d = json.loads(summary_json(s))
    for key in ("status", "completeness", "fractures", "peak_file_torque_mNm",
                "deadline_misses", "duration_s", "steps"):
        assert key in d
    assert d["status"] == "fracture" and d["fractures"] == 1
    assert [st["name"] for st in d["steps"]] == ["approach", "drilling"]
    assert d["steps"][1]["depth_reached_mm"] == 24.875
    console = Console(record=True, width=120)
    console.print(summary_table(s))
    text = console.export_text()
    assert "DentiBot run: fracture" in text and REASON in text
    assert "approach" in text and "drilling" in text and "whole run" in text
    assert "49.8" in text and "75.0%" in text        # peak torque, completeness
    assert "transition x2" in text


def test_bad_status_and_rate_are_config_errors():
    with pytest.raises(ConfigError, match="status"):
        SummaryAccumulator().finish("great")
    with pytest.raises(ConfigError, match="rate_hz"):
        SummaryAccumulator(rate_hz=-5)


def test_empty_run():
    s = SummaryAccumulator(rate_hz=500).finish("aborted", "operator")
    assert s.ticks == 0 and s.duration_s == 0.0 and s.steps == []
    assert s.peak_file_torque_mNm is None and s.lateness_p99_us is None
    json.loads(summary_json(s))


def test_non_finite_and_non_numbers_count_as_unknown():
    from dentibot.telemetry.summary import _num
    assert _num(1.5) == 1.5 and _num(2) == 2.0 and type(_num(2)) is float
    for bad in (math.nan, math.inf, -math.inf, None, True, "1.0"):
        assert _num(bad) is None, bad
