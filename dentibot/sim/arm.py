"""Meca500 joint servo: MoveJointsVel / MoveJoints tracking with speed limits, lag, timeout.

Behaviour modelled (Meca500 R3 programming manual):
- velocity mode (MoveJointsVel): the commanded joint rates are held for ``vel_timeout_s``
  (SetVelTimeout, default 0.05 s), then the arm decelerates to rest; optionally a command
  waits ``vel_dead_time_s`` in the robot's queue and the trajectory filter realises
  ``vel_gain`` of it (the bench-fitted arm; defaults: no delay, unit gain);
- position mode (MoveJoints): joint-space motion to the target, all joints scaled together so
  that none exceeds its speed limit times ``pos_speed_scale`` (SetJointVel, as a fraction);
- a joint that would pass its limit stops the arm at the limit and latches error 1007;
  approaching the wrist singularity (|sin q5| < sin 0.5 deg) in velocity mode latches 1012.
  Position mode crosses singularities (manual, MoveJoints: "the robot can cross singularities
  without any problem"); Cartesian moves are checked by their planner (the wire simulator).
  In error the arm is at rest and ignores motion commands until ``reset_error()``.
Joint speeds (Meca500 manual) are never exceeded, including during the servo lag.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

import dentibot.sim.arm_kernels as kern
from dentibot.control.kinematics import Meca500
from dentibot.sim.arm_kernels import ERROR_JOINT_LIMIT, ERROR_SINGULARITY
from dentibot.sim.state_view import listed, scalar

__all__ = ["ERROR_JOINT_LIMIT", "ERROR_SINGULARITY", "ArmParams", "SimArmModel"]

_ERROR = kern.S["error_code"]
#: Velocity commands the robot's queue holds before it grows (a 16 ms dead time at 500 Hz
#: holds 8).
QUEUE = 64


@dataclass(frozen=True)
class ArmParams:
    # assumption: first-order servo lag of the joint velocity loop, 8 ms (5-10 ms asked).
    servo_tau_s: float = 0.008
    # Meca500 SetVelTimeout default (0.05 s).
    vel_timeout_s: float = 0.05
    # assumption: encoder/reading resolution 0.001 deg (the Meca500 reports 3 decimals).
    encoder_res_deg: float = 0.001
    # the wrist is singular when |sin q5| < sin(0.5 deg).
    wrist_singularity_min: float = math.sin(math.radians(0.5))
    # assumption: below 0.001 deg/s with a zero reference the joint is at rest (brakes on).
    rest_deg_s: float = 0.001
    # assumption: MoveJoints position loop time constant (s) before the speed clamp.
    position_tau_s: float = 0.008
    # Velocity interface (MoveJointsVel) as a real Meca500 realises it: a command waits
    # ``vel_dead_time_s`` in the robot's command queue before its trajectory filter (the
    # first-order ``servo_tau_s`` above) starts to follow it, and the filter settles at
    # ``vel_gain`` times the command. Defaults: no queue delay, unit gain (the ideal arm).
    # The bench preset (:mod:`dentibot.sim.bench_physics`) sets the fitted values.
    vel_dead_time_s: float = 0.0
    vel_gain: float = 1.0


class SimArmModel:
    """Joint-space arm state stepped by ``step(t, ts)`` (its state in the arrays of
    :mod:`dentibot.sim.arm_kernels`, whose kernel it calls)."""

    def __init__(self, kin: Meca500, q0_deg, params: ArmParams = ArmParams()) -> None:
        self.kin = kin
        self.ast = np.zeros(len(kern.STATE_FIELDS))
        self.ast[kern.S["pos_speed_scale"]] = 1.0
        self.p = params
        #: rows: lower and upper joint limits (deg), joint speed limits (deg/s)
        self.lims = np.array([kin.joint_limits_deg[:, 0], kin.joint_limits_deg[:, 1],
                              kin.joint_speed_limits_deg_s], dtype=float)
        self._q = np.array([float(x) for x in q0_deg])
        self._qd = np.zeros(6)
        self._vel_cmd = np.zeros(6)
        self._target = self._q.copy()
        #: velocity commands waiting in the robot's queue: when they take effect, their rates
        self._queue_t = np.zeros(QUEUE)
        self._queue_v = np.zeros((QUEUE, 6))

    # ------------------------------------------------------------------ state
    @property
    def p(self) -> ArmParams:
        """The arm's constants (SetVelTimeout replaces them while it runs)."""
        return self._p

    @p.setter
    def p(self, params: ArmParams) -> None:
        self._p = params
        self.ap = np.array([float(getattr(params, k)) for k in kern.PARAM_FIELDS])

    q = listed("_q", doc="Joint angles (deg).")
    qdot = listed("_qd", doc="Joint rates (deg/s).")
    vel_cmd = listed("_vel_cmd", doc="The velocity command in force (deg/s).")
    target = listed("_target", doc="The position mode's target (deg).")
    lo = listed("lims", 0, "Lower joint limits (deg).")
    hi = listed("lims", 1, "Upper joint limits (deg).")
    vmax = listed("lims", 2, "Joint speed limits (deg/s).")

    @property
    def mode(self) -> str:
        """``idle``, ``vel`` (MoveJointsVel) or ``pos`` (MoveJoints)."""
        return kern.MODES[int(self.ast[kern.S["mode"]])]

    @mode.setter
    def mode(self, mode: str) -> None:
        self.ast[kern.S["mode"]] = kern.MODES.index(mode)

    error_code = scalar("ast", kern.S["error_code"], int, "The latched Meca500 error "
                        "(0: none).")
    moving = scalar("ast", kern.S["moving"], bool, "A joint moved in the last step.",
                    settable=False)
    pos_speed_scale = scalar("ast", kern.S["pos_speed_scale"], doc="Position mode speed limit "
                             "as a fraction of ``vmax`` (SetJointVel / 100).")
    vel_cmd_t = scalar("ast", kern.S["vel_cmd_t"], doc="When the velocity command in force "
                       "was given (s).", settable=False)

    # ------------------------------------------------------------------ commands
    def command_velocity(self, qdot_deg_s, t: float) -> bool:
        """MoveJointsVel; returns False (ignored) when the arm is in error
        (:func:`dentibot.sim.arm_kernels.command_velocity`)."""
        if self.ast[_ERROR]:
            return False
        v = np.asarray(qdot_deg_s, dtype=float)
        dead = self._p.vel_dead_time_s
        while not kern.command_velocity(self.ast, self.lims, self._vel_cmd, self._queue_t,
                                        self._queue_v, v, t, dead):
            self._grow_queue()
        return True

    def _grow_queue(self) -> None:
        """The command queue, full, twice as long (oldest first)."""
        ast = self.ast
        head, count = int(ast[kern.S["head"]]), int(ast[kern.S["count"]])
        cap = self._queue_t.shape[0]
        order = (head + np.arange(count)) % cap
        self._queue_t = np.concatenate([self._queue_t[order], np.zeros(cap)])
        self._queue_v = np.concatenate([self._queue_v[order], np.zeros((cap, 6))])
        ast[kern.S["head"]] = 0.0

    def command_position(self, q_deg) -> bool:
        """MoveJoints; returns False (ignored) when the arm is in error."""
        if self.error_code:
            return False
        self._target[:] = [float(x) for x in q_deg]
        self.mode = "pos"
        return True

    def stop(self) -> None:
        self.mode = "idle"
        self._vel_cmd[:] = 0.0
        self._clear_queue()

    def _clear_queue(self) -> None:
        self.ast[kern.S["head"]] = self.ast[kern.S["count"]] = 0.0

    def reset_error(self) -> None:
        self.error_code = 0
        self.mode = "idle"
        self._clear_queue()

    def teleport(self, q_deg) -> None:
        """Put the arm at ``q_deg`` at rest (tests and scenario set-up only)."""
        self._q[:] = [float(x) for x in q_deg]
        self._qd[:] = 0.0
        self._target[:] = self._q
        self.mode = "idle"
        self._clear_queue()

    # ------------------------------------------------------------------ dynamics
    def step(self, t: float, ts: float) -> None:
        """One period of the servo (:func:`dentibot.sim.arm_kernels.step`)."""
        kern.step(self.ast, self.ap, self.lims, self._q, self._qd, self._vel_cmd, self._target,
                  self._queue_t, self._queue_v, t, ts)

    def reading(self) -> tuple[tuple, tuple]:
        """Quantised (q_deg, qdot_deg_s) as the controller sees them."""
        r = self.p.encoder_res_deg
        return (tuple(round(x / r) * r for x in self._q.tolist()), tuple(self._qd.tolist()))
