"""The live panel's text from known figures."""

from __future__ import annotations

from dentibot.session.controller import PanelData
from dentibot.session.panel import BAR_WIDTH, LINES, bar, render, render_lines, state_path

TIMING = {"ticks": 5000, "overruns": 0, "skipped": 0, "lateness_us_p50": 5.0,
          "lateness_us_p99": 20.0, "lateness_us_max": 180.0, "compute_us_mean": 61.0}


def figures(**kw) -> PanelData:
    kw = {"state": "treating.drilling.feeding", **kw}
    return PanelData(
        connected=True, source="built-in simulator (real time)", t_s=10.0, depth_mm=8.0,
        working_length_mm=16.0, wrench_h=[0.1, -0.2, 0.5, 0.001, 0.0, -0.002],
        file_torque_mnm=kw.pop("file_torque_mnm", 27.9), torque_limit_mnm=55.8,
        tau_d_mnm=40.0, motor_rpm=60.0, calibrated=True, timing=TIMING,
        rate_hz=kw.pop("rate_hz", 500.0), **kw)


def test_bars_are_proportional_and_clipped():
    assert bar(8.0, 16.0) == ("#" * 12 + "." * 12, 0.5)
    assert bar(-1.0, 16.0)[1] == 0.0 and bar(40.0, 16.0) == ("#" * BAR_WIDTH, 1.0)
    assert bar(None, 16.0) == ("." * BAR_WIDTH, 0.0)


def test_panel_lines():
    lines = render_lines(figures())
    assert len(lines) == LINES                    # constant: a redraw never needs a layout
    text = render(figures()).plain
    assert "treating > drilling > feeding" in text
    assert "  8.00 / 16.00 mm  [" + "#" * 12 + "." * 12 + "]" in text
    # half the 55.8 mNm limit (90 % of the thesis's 62 mNm file strength): half a bar
    assert "[" + "#" * 12 + "." * 12 + "]  27.9 / 55.8 mNm limit" in text
    assert "f  +0.10  -0.20  +0.50 N" in text and "+0.0010" in text
    assert " 60.0 rpm" in text and "still" in text and "Fault     none" in text
    assert "500 Hz  5000 ticks" in text and "overruns 0 skipped 0" in text
    assert "recording off" in text


def test_torque_near_the_limit_is_red_and_flags_show():
    lines = render_lines(figures(file_torque_mnm=53.0, patient_moved=True, patient_episodes=2,
                                 state="treating.patient_moved", recording="runs/a.mcap",
                                 recording_rows=250))
    torque = next(t for t in lines if t.plain.startswith("Torque"))
    assert any("red" in str(s.style) for s in torque.spans)           # 95 % of the limit
    text = "\n".join(t.plain for t in lines)
    assert "MOVED" in text and "episodes 2" in text and "REC runs/a.mcap (250 ticks)" in text


def test_fault_lock_step_and_not_connected():
    text = render(figures(state="fault", fault_causes=["software emergency stop"],
                          realtime=False, rate_hz=5000.0, period_s=0.002)).plain
    assert "Fault     software emergency stop" in text
    assert "lock-step: 5000 ticks (10.0x real time)" in text
    text = render(PanelData(False, "built-in simulator (real time)", "not connected",
                            working_length_mm=16.0, torque_limit_mnm=55.8)).plain
    assert "not connected" in text and "-- / 16.00 mm" in text
    assert state_path("calibrating.load") == "calibrating > load"
