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
from collections import deque
from dataclasses import dataclass

from dentibot.control.kinematics import Meca500

#: Meca500 error codes used here (programming manual, "error codes").
ERROR_JOINT_LIMIT = 1007
ERROR_SINGULARITY = 1012


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
    """Joint-space arm state stepped by ``step(t, ts)``; all state in Python floats."""

    def __init__(self, kin: Meca500, q0_deg, params: ArmParams = ArmParams()) -> None:
        self.kin = kin
        self.p = params
        self.q = [float(x) for x in q0_deg]
        self.qdot = [0.0] * 6
        self.lo = [float(x) for x in kin.joint_limits_deg[:, 0]]
        self.hi = [float(x) for x in kin.joint_limits_deg[:, 1]]
        self.vmax = [float(x) for x in kin.joint_speed_limits_deg_s]
        self.mode = "idle"  # idle | vel | pos
        self.vel_cmd = [0.0] * 6
        self.vel_cmd_t = -math.inf
        self.target = list(self.q)
        self.error_code = 0
        self.moving = False
        #: position mode speed limit as a fraction of ``vmax`` (SetJointVel / 100)
        self.pos_speed_scale = 1.0
        #: velocity commands waiting in the robot's queue: (time they take effect, rates)
        self._queue: deque = deque()

    # ------------------------------------------------------------------ commands
    def command_velocity(self, qdot_deg_s, t: float) -> bool:
        """MoveJointsVel; returns False (ignored) when the arm is in error."""
        if self.error_code:
            return False
        v = [float(x) for x in qdot_deg_s]
        v = [max(-m, min(m, x)) for x, m in zip(v, self.vmax)]
        if self.p.vel_dead_time_s > 0.0:
            if self.mode != "vel":
                self.vel_cmd = [0.0] * 6
                self.vel_cmd_t = t
            self._queue.append((t + self.p.vel_dead_time_s, v))
        else:
            self.vel_cmd = v
            self.vel_cmd_t = t
        self.mode = "vel"
        return True

    def command_position(self, q_deg) -> bool:
        """MoveJoints; returns False (ignored) when the arm is in error."""
        if self.error_code:
            return False
        self.target = [float(x) for x in q_deg]
        self.mode = "pos"
        return True

    def stop(self) -> None:
        self.mode = "idle"
        self.vel_cmd = [0.0] * 6
        self._queue.clear()

    def reset_error(self) -> None:
        self.error_code = 0
        self.mode = "idle"
        self._queue.clear()

    def teleport(self, q_deg) -> None:
        """Put the arm at ``q_deg`` at rest (tests and scenario set-up only)."""
        self.q = [float(x) for x in q_deg]
        self.qdot = [0.0] * 6
        self.target = list(self.q)
        self.mode = "idle"
        self._queue.clear()

    # ------------------------------------------------------------------ dynamics
    def step(self, t: float, ts: float) -> None:
        q, qd, vmax = self.q, self.qdot, self.vmax
        if self.error_code or self.mode == "idle":
            ref = (0.0,) * 6
        elif self.mode == "vel":
            queue = self._queue
            while queue and queue[0][0] <= t + 1e-9:      # commands leaving the queue
                self.vel_cmd_t, self.vel_cmd = queue.popleft()
            ref = self.vel_cmd if t - self.vel_cmd_t <= self.p.vel_timeout_s else (0.0,) * 6
            g = self.p.vel_gain
            if g != 1.0:
                ref = [g * r for r in ref]
        else:
            k = 1.0 / max(self.p.position_tau_s, ts)
            ref = [(a - b) * k for a, b in zip(self.target, q)]
            s = max(self.pos_speed_scale, 1e-6)
            scale = max(abs(r) / (m * s) for r, m in zip(ref, vmax))
            if scale > 1.0:  # synchronous scaling: straight line in joint space
                ref = [r / scale for r in ref]
        a = -math.expm1(-ts / self.p.servo_tau_s)   # exact first-order discretisation
        moving = False
        new_q = [0.0] * 6
        for i in range(6):
            v = qd[i] + (ref[i] - qd[i]) * a
            m = vmax[i]
            v = m if v > m else (-m if v < -m else v)  # noqa: FURB136 (hot path)
            if self.mode == "pos" and not self.error_code:
                # never overshoot the target within one period
                rem = self.target[i] - q[i]
                if (v > 0.0 and v * ts > rem > 0.0) or (v < 0.0 and v * ts < rem < 0.0):
                    v = rem / ts
            if abs(v) < 1e-9 or (ref[i] == 0.0 and abs(v) < self.p.rest_deg_s):
                v = 0.0
            else:
                moving = True
            qd[i] = v
            new_q[i] = q[i] + v * ts
        self.moving = moving
        if not moving:
            return
        for i in range(6):
            if new_q[i] < self.lo[i] or new_q[i] > self.hi[i]:
                new_q[i] = min(max(new_q[i], self.lo[i]), self.hi[i])
                self._fault(ERROR_JOINT_LIMIT)
        if self.mode == "vel" and \
                abs(math.sin(math.radians(new_q[4]))) < self.p.wrist_singularity_min and \
                abs(math.sin(math.radians(new_q[4]))) < abs(math.sin(math.radians(q[4]))):
            # stop before entering the singular band (moving out of it is allowed)
            new_q = list(q)
            self._fault(ERROR_SINGULARITY)
        self.q = new_q
        if self.error_code:
            self.qdot = [0.0] * 6

    def _fault(self, code: int) -> None:
        if not self.error_code:
            self.error_code = code
        self.mode = "idle"
        self.vel_cmd = [0.0] * 6
        self._queue.clear()

    def reading(self) -> tuple[tuple, tuple]:
        """Quantised (q_deg, qdot_deg_s) as the controller sees them."""
        r = self.p.encoder_res_deg
        return (tuple(round(x / r) * r for x in self.q), tuple(self.qdot))
