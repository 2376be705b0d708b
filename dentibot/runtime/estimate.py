"""What the control task reads and estimates each tick (docs/architecture.md, "The tick",
steps 1-2): the devices it reads, and the estimate step 2 produces."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dentibot.control.depth import depth_along
from dentibot.control.tick import sense
from dentibot.io.interfaces import Arm, AuxIO, ForceSensor, Handpiece, PatientTracker


@dataclass
class Devices:
    arm: Arm
    ft: ForceSensor
    motor: Handpiece
    aux: AuxIO | None = None
    tracker: PatientTracker | None = None

    async def read(self) -> tuple:
        """Step 1: the newest sample of each device, ``(joints, wrench, motor, aux or None)``
        (a device that cannot answer raises :class:`~dentibot.errors.DeviceFault`)."""
        js = await self.arm.read()
        w = await self.ft.read()
        m = await self.motor.read()
        return js, w, m, (await self.aux.read() if self.aux is not None else None)

    async def read_tracker(self):
        """The patient tracker's newest string lengths, or None without a tracker."""
        return None if self.tracker is None else await self.tracker.read()


@dataclass
class Estimate:
    """What step 2 of the tick produced (also the live view's figures)."""

    q_deg: np.ndarray
    wrench_s: np.ndarray       # raw sensor reading (N, N*m)
    wrench_h: np.ndarray       # external wrench at the reference point, {H}
    force_norm_n: float        # ||{H} f|| (fig 5.6: forces and torques, N and N*m)
    file_torque_mnm: float
    motor_rpm: float
    motor_current_a: float
    motor_pos_deg: float
    tip_0: tuple
    axis_0: tuple
    depth_mm: float | None


class MotorView:
    """The motor figures of an Estimate, shaped like a MotorState for re-estimation."""

    def __init__(self, est: Estimate) -> None:
        self.current_a = est.motor_current_a
        self.velocity_rpm = est.motor_rpm
        self.position_deg = est.motor_pos_deg


def estimate(q: np.ndarray, raw: np.ndarray, m, admittance, gravity, to_h, handpiece,
             depth_ref) -> tuple[Estimate, tuple, np.ndarray]:
    """Step 2 of the tick: the external wrench at the admittance's reference point in {H}
    (zero until a gravity model is known), the file torque from the motor current (eq
    5.4-5.5), the tip and tool axis in {0} (:func:`~dentibot.control.tick.sense`: one
    compiled call), and the depth along ``depth_ref`` = (orifice point, canal axis). Also
    returns the tick's chain (J_H, frames) and flange orientation 0R_6."""
    s = sense(admittance, q, raw, m.current_a, m.velocity_rpm, gravity, to_h,
              handpiece.efficiency, handpiece.friction_current_a)
    depth = None if depth_ref is None else depth_along(s.tip_0, depth_ref)
    return Estimate(q, raw, s.wrench_h, s.force_norm_n, s.file_torque_mnm, m.velocity_rpm,
                    m.current_a, m.position_deg, s.tip_0, s.axis_0, depth), s.chain, s.r_0_6
