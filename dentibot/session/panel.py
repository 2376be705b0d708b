"""The live panel's text: :class:`~dentibot.session.controller.PanelData` -> rich Text.

A pure function (no terminal, no runtime), so it is cheap to call several times a second and
easy to test. Units: depth mm, wrench N and N*m in {H}, file torque mNm, motor rpm.
"""

from __future__ import annotations

from rich.text import Text

from dentibot.session.controller import PanelData

BAR_WIDTH = 24
_LABEL = 10
#: Lines of the panel (constant, so that a redraw never needs a new layout).
LINES = 9


def bar(value: float | None, full: float, width: int = BAR_WIDTH) -> tuple[str, float]:
    """A bar of ``width`` cells filled in proportion to ``value / full`` (clipped to 0..1)
    and that fraction."""
    if value is None or not full > 0:
        return "." * width, 0.0
    frac = min(max(value / full, 0.0), 1.0)
    n = round(frac * width)
    return "#" * n + "." * (width - n), frac


def _num(v: float | None, fmt: str) -> str:
    return "--" if v is None else format(v, fmt)


def _line(lines: list[Text], label: str) -> Text:
    t = Text()
    t.append(f"{label:<{_LABEL}}", style="bold")
    lines.append(t)
    return t


def state_path(state: str) -> str:
    """``treating.drilling.feeding`` -> ``treating > drilling > feeding``."""
    return " > ".join(state.split("."))


def render(d: PanelData) -> Text:
    """The whole panel as one text (:func:`render_lines` joined)."""
    return Text("\n").join(render_lines(d))


def render_lines(d: PanelData) -> list[Text]:
    """The panel's :data:`LINES` lines."""
    lines: list[Text] = []
    t = Text()
    lines.append(t)
    t.append("DentiBot session", style="bold")
    t.append(f"  {d.source}")
    if d.connected or d.state != "not connected":
        t.append(f"  t {d.t_s:8.2f} s")
    if d.recording:
        t.append(f"  REC {d.recording} ({d.recording_rows} ticks)", style="bold red")
    else:
        t.append("  recording off", style="dim")

    t = _line(lines, "State")
    style = "bold red" if d.state == "fault" else "bold green" if d.state.startswith(
        "treating") else "bold"
    t.append(state_path(d.state), style=style)
    if d.activity:
        t.append(f"   [{d.activity}]", style="cyan")
    if d.busy:
        t.append(f"   {d.busy}...", style="yellow")
    if d.state != "not connected" and not d.calibrated:
        t.append("   load not calibrated", style="yellow")
    t = _line(lines, "Fault")                    # always there: the panel's height never changes
    if d.control_error:
        t.append(d.control_error + "; ", style="red")
    if d.fault_causes:
        t.append("; ".join(d.fault_causes), style="red")
    elif not d.control_error:
        t.append("none", style="dim")

    t = _line(lines, "Depth")
    b, _ = bar(d.depth_mm, d.working_length_mm)
    t.append(f"{_num(d.depth_mm, '6.2f')} / {d.working_length_mm:.2f} mm  [{b}]")
    if d.depth_frame == "tooth":
        where = "--" if d.tooth_mm is None else " ".join(f"{x:.1f}" for x in d.tooth_mm)
        t.append(f"  in the tooth (at {where} mm)")
    else:
        t.append("  in the robot's frame", style="dim")
    if d.true_depth_mm is not None:
        t.append(f"  sim: true {d.true_depth_mm:.2f} mm", style="dim")
        if d.completeness is not None:
            t.append(f", shaped {100 * d.completeness:.1f} %", style="dim")

    t = _line(lines, "Wrench{H}")
    w = d.wrench_h
    if w is None:
        t.append("--")
    else:
        t.append("f " + " ".join(f"{x:+6.2f}" for x in w[:3]) + " N   ")
        t.append("tau " + " ".join(f"{x:+7.4f}" for x in w[3:]) + " N*m")

    t = _line(lines, "Torque")
    b, frac = bar(d.file_torque_mnm, d.torque_limit_mnm)
    tstyle = "red" if frac >= 0.9 else "yellow" if frac >= 0.7 else "green"
    t.append(f"[{b}]", style=tstyle)
    t.append(f" {_num(d.file_torque_mnm, '5.1f')} / {d.torque_limit_mnm:.1f} mNm limit")
    if d.tau_d_mnm is not None:
        t.append(f"  (tau_d {d.tau_d_mnm:.0f})", style="dim")

    t = _line(lines, "Motor")
    t.append(f"{_num(d.motor_rpm, '6.1f')} rpm   reversals {d.reversals}")

    t = _line(lines, "Patient")
    if d.patient_moved:
        t.append("MOVED (file stopped, following)", style="bold red")
    else:
        t.append("still")
    t.append(f"   episodes {d.patient_episodes}")

    t = _line(lines, "Loop")
    tm = d.timing
    if not tm:
        t.append("--")
    elif d.realtime:
        rate = "--" if d.rate_hz is None else f"{d.rate_hz:.0f}"
        t.append(f"{rate} Hz  {tm['ticks']} ticks  late p50<={tm['lateness_us_p50']:.0f} "
                 f"p99<={tm['lateness_us_p99']:.0f} max {tm['lateness_us_max']:.0f} us  "
                 f"compute {tm['compute_us_mean']:.0f} us  ")
        bad = tm["overruns"] or tm["skipped"]
        t.append(f"overruns {tm['overruns']} skipped {tm['skipped']}",
                 style="yellow" if bad else "")
    else:
        rate = "" if d.rate_hz is None else f" ({d.rate_hz * d.period_s:.1f}x real time)"
        t.append(f"lock-step: {tm['ticks']} ticks{rate}, compute {tm['compute_us_mean']:.0f} us")
    return lines
