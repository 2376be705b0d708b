"""Steps 4-5 of the tick (docs/architecture.md, "The tick"): the state's mode put in force,
the arm's command of that mode, and the fault reaction that stops the file and the arm.

A command a device refuses or cannot deliver raises; the control task turns that into the
latched fault of the same tick (:meth:`~dentibot.runtime.control_task.Runtime.tick`).
"""

from __future__ import annotations

import asyncio
import math

import numpy as np
import structlog

from dentibot.control.admittance_kernels import lateral_scale
from dentibot.control.canal_axis import CanalAxisServo
from dentibot.control.tick import admittance_command
from dentibot.runtime.estimate import MotorView
from dentibot.states.behaviours import feed_force_n
from dentibot.states.modes import Mode, admittance_params, drag_point_note

log = structlog.get_logger("dentibot.runtime")

_ZERO6 = np.zeros(6)
#: Longest the fault reaction waits for the devices to take their stop commands (s): five
#: control periods. A device that has not answered by then (a half-open link waits seconds for
#: its acknowledgement) finishes in the background while the loop goes on ticking.
STOP_BOUND_S = 0.01


async def _stop(device) -> None:
    try:
        await device.stop()
    except Exception as exc:  # noqa: BLE001 - the stop of the other device must go on
        log.warning("stop command failed", device=type(device).__name__, error=str(exc))


async def stop_all(motor, arm, unfinished: set[asyncio.Task]) -> None:
    """Stop the file and the arm at once: both stop commands are issued (the file's first)
    before either is awaited, and the reaction waits at most :data:`STOP_BOUND_S`; neither a
    failing nor a silent device keeps the other from stopping or the loop from ticking. A stop
    still waiting for its answer goes to ``unfinished`` (whoever ends the loop cancels it)."""
    tasks = [asyncio.ensure_future(_stop(d)) for d in (motor, arm)]
    _, pending = await asyncio.wait(tasks, timeout=STOP_BOUND_S)
    for t in pending:
        unfinished.add(t)
        t.add_done_callback(unfinished.discard)
        log.warning("stop command not acknowledged in time: left to finish",
                    bound_s=STOP_BOUND_S)


def apply_mode(rt, mode: Mode, est) -> None:
    """``mode`` in force (``rt.mode``): its admittance's parameters and reference point when
    they change (the filter restarts from rest, and ``est``'s wrench is redone at the new
    point), and a note when dragging's reference point moves (``drag_point``)."""
    was, rt.mode = rt.mode, mode
    note = drag_point_note(was, mode)
    if note is not None:
        rt.note("drag_point", note)
    if mode.admittance is None:
        return
    params = admittance_params(mode, rt.cfg.plan)
    if (params, mode.ref) != (rt.admittance.params, rt._ref):
        rt.admittance.set_params(params, rt.cfg.tool.grip_h_mm if mode.ref == "A" else None)
        rt._ref = mode.ref
        if est is not None:                  # the reference point changed: step 2 again
            est2 = rt._estimate(est.q_deg, est.wrench_s, MotorView(est))
            est.wrench_h, est.force_norm_n = est2.wrench_h, est2.force_norm_n


async def arm_command(rt, est):
    """Send the arm what the state's mode wants; returns the joint velocities commanded (None
    when the arm is stopped or scripted). Commands the supervisor refuses are replaced by a
    hold, and the refusal becomes a fault of the next tick."""
    mode = rt.mode
    arm = rt.dev.arm
    if mode.arm == "stop":
        return None
    if mode.arm == "script":
        target = rt.ctx.script_target
        if target is not None:
            await arm.move_joints(target)
        return None
    if mode.arm == "hold":
        await arm.move_joints_vel(_ZERO6)
        return _ZERO6
    tooth = rt.ctx.tooth
    tooth_ff = ff = None if tooth is None else tooth.feedforward_h(rt.r_0_6 @ rt.R_6_H)
    turn = axis_servo_twist(rt, est)
    if turn is not None and ff is None:   # a moving tooth bends the file too: not a tilt
        ff = turn
    cmd = admittance_command(rt.admittance, est.q_deg, est.wrench_h,
                             feed_force_n(mode, rt.ctx, rt.cfg.plan), rt.chain, ff,
                             lateral_scale(math.nan if est.depth_mm is None else est.depth_mm,
                                           rt.cfg.file.length_mm,
                                           rt.cfg.plan.lateral_free_ref_mm))
    bad = rt.supervisor.check_command(cmd.qdot_deg_s, cmd.twist, rt.speed_limits, tooth_ff)
    if bad:
        rt.pending.extend(("fault", str(f)) for f in bad)
        await arm.move_joints_vel(_ZERO6)
        return _ZERO6
    await arm.move_joints_vel(cmd.qdot_deg_s)
    return cmd.qdot_deg_s


def axis_servo_twist(rt, est):
    """Self-alignment's orientation loop (:mod:`dentibot.control.canal_axis`) for this tick:
    stepped while the file tip is the reference point and the plan has the loop; its rotation
    (a twist at the tip, {H}) or None. Built, or rebuilt, when the plan's parameters change."""
    params = rt.cfg.plan.axis_servo
    ctx = rt.ctx
    if params is None or rt.mode.ref != "B":
        if params is None:
            ctx.axis_servo = None
        return None
    servo = ctx.axis_servo
    if servo is None or servo.p is not params:
        servo = ctx.axis_servo = CanalAxisServo(rt.cfg.file, params, rt.cfg.period_s)
    servo.step(est.depth_mm, est.wrench_h)
    return servo.twist()


async def recover_all(motor, arm, aux) -> str | None:
    """On the operator's reset: every device back to ready (the drive's fault reset and its
    output enabled, the arm's error reset and motion resumed, the aux I/O's watchdog fault
    acknowledged); the cause of the first that cannot, or None."""
    for device in (motor, arm, aux):
        if device is None:
            continue
        try:
            await device.recover()
        except Exception as exc:  # noqa: BLE001 - reported as the new fault's cause
            return f"reset: {type(device).__name__} did not recover: {exc}"
    return None
