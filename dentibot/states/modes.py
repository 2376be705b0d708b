"""What each state asks of the arm and the file: data read by the control task every tick.

- ``arm``: "hold" (zero joint velocity streamed, so the arm's dead-man stays fed),
  "admittance" (the admittance law drives the arm), "script" (a routine of the control task
  moves it, e.g. the load calibration poses), "stop" (stopped once on entry, then held).
- ``admittance``: preset name ("dragging", "self_alignment") and ``ref``: the reference point
  of fig 4.7 ("A" the grip for dragging, "B" the file tip for self-alignment).
- ``feed``: the desired insertion force fz in f_d = (0, 0, fz, 0, 0, 0) (self-alignment, 4.4):
  "zero", "align" (the configured alignment force), "strategy" (the drilling strategy: feedrate
  PD, sections ...), "retract" (a negative force that withdraws the file).
- ``file``: "stop", "forward" (drilling speed), "align" (turning during alignment if
  configured), "reverse" (the 90 deg inverse rotation of 5.2, once on entry).
"""

from __future__ import annotations

from dataclasses import dataclass

from dentibot.control.admittance import PRESETS, AdmittanceParams, with_axial_lag


@dataclass(frozen=True)
class Mode:
    arm: str
    admittance: str | None = None
    ref: str | None = None
    feed: str = "zero"
    file: str = "stop"


def admittance_params(mode: Mode, plan) -> AdmittanceParams:
    """The admittance parameters of ``mode``: its preset (Table 4.3), or for self-alignment the
    plan's own (Table 6.4 configurations) when it has them; self-alignment and drilling with
    the plan's lag along the file (``axial_lag_s``, None: Table 4.3's)."""
    if mode.admittance == "self_alignment" and mode.feed == "align" \
            and plan.align_params is not None:
        return plan.align_params
    params = PRESETS[mode.admittance]
    if mode.admittance == "self_alignment" and plan.axial_lag_s is not None:
        return with_axial_lag(params, plan.axial_lag_s)
    return params


def file_command(mode: Mode, drilling_rpm: float, align_rpm: float) -> tuple:
    """What the handpiece is told on entering a state of ``mode``: ``("vel", rpm)``,
    ``("reverse",)`` (the inverse rotation, once) or ``("stop",)``."""
    if mode.file == "forward":
        return ("vel", drilling_rpm)
    if mode.file == "align":
        return ("vel", align_rpm)
    if mode.file == "reverse":
        return ("reverse",)
    return ("stop",)


async def send_file_command(motor, mode: Mode, cfg, current: tuple | None) -> tuple:
    """Tell the handpiece what ``mode`` wants (:func:`file_command`), unless it already does
    (a reversal is sent every time); returns the command now in force."""
    hp = cfg.handpiece
    cmd = file_command(mode, hp.drilling_rpm, cfg.plan.align_rpm)
    if cmd == ("reverse",):
        await motor.move_relative(-hp.reversal_deg)
    elif cmd == current:
        return cmd
    elif cmd[0] == "vel" and cmd[1] != 0.0:
        await motor.set_velocity(cmd[1])
    else:
        await motor.stop()
    return cmd


_DRILL = {"arm": "admittance", "admittance": "self_alignment", "ref": "B"}

MODES: dict[str, Mode] = {
    "idle": Mode("hold"),
    "calibrating.tcp": Mode("admittance", "dragging", "B"),
    "calibrating.load": Mode("script"),
    "dragging": Mode("admittance", "dragging", "A"),
    "self_aligning": Mode(**_DRILL, feed="align", file="align"),
    "treating.drilling.feeding": Mode(**_DRILL, feed="strategy", file="forward"),
    "treating.drilling.reversing": Mode(**_DRILL, feed="zero", file="reverse"),
    "treating.patient_moved": Mode(**_DRILL, feed="zero", file="stop"),
    "treating.paused": Mode(**_DRILL, feed="zero", file="stop"),
    "treating.retracting": Mode(**_DRILL, feed="retract", file="forward"),
    "done": Mode("hold"),
    "fault": Mode("stop"),
}

#: Dragging while the file is in the canal: the arm yields to the hand at the file tip with
#: self-alignment's gains (and the plan's lag along the file), the insertion force zero and
#: the file still. At the grip with Table 4.3's dragging gains (3x self-alignment's on the
#: translations), the walls' force on the tip is also a moment about the grip, which the
#: rotations answer: the tip moves sideways at roughly (grip-to-tip)^2 x 9.4 rad/s per N m,
#: and through the arm's 22 ms that loop rings against the walls (about 25 Hz on the
#: bench-fitted world, 3 mm deep) until the tip-speed limit faults. About the tip, a turn
#: of the handpiece does not move the tip, and the translations are those the file already
#: bears when it is fed.
DRAGGING_IN_CANAL = Mode(**_DRILL, feed="zero", file="stop")


def state_mode(state: str, file_in_canal: bool) -> Mode:
    """The mode of ``state``: :data:`MODES`, except dragging with the file in the canal
    (:data:`DRAGGING_IN_CANAL`)."""
    if state == "dragging" and file_in_canal:
        return DRAGGING_IN_CANAL
    return MODES[state]


def drag_point_note(was: Mode, mode: Mode) -> str | None:
    """What an operator is told when ``mode`` follows ``was``: where dragging now yields to
    the hand, when that is the tip or goes back to the grip; None otherwise."""
    if mode is DRAGGING_IN_CANAL and was is not DRAGGING_IN_CANAL:
        return "tip: the file is in the canal"
    if was is DRAGGING_IN_CANAL and mode is MODES["dragging"]:
        return "grip: the file is out of the canal"
    return None
