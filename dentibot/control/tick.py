"""The maths of one control tick (docs/architecture.md, "The tick", steps 2 and 5): the chain
the runtime calls every period and the benchmark times, so what is measured is what runs.

Raw sensor wrench in {S} -> offset and gravity removed (eq 4.18) -> moved to the active
reference point in {H} (eq 4.26-4.31) -> plus the desired wrench f_d = (0, 0, fz, 0, 0, 0)
(self-alignment, 4.4) -> admittance step, tool Jacobian, joint rates, limits (4.3). The
forward chain is computed once per tick (:func:`sense`) and shared by the gravity model
(flange orientation), the Jacobian and the tip.

Pure maths: the runtime reads the devices and sends the commands.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dentibot.control import tick_kernels
from dentibot.control.admittance import AdmittanceController, JointCommand
from dentibot.control.linalg import readonly
from dentibot.control.wrench import GravityModel, WrenchTransform

#: What :func:`sense` passes for the gravity model and the transform before a load is known
#: (read-only, as the models' own arrays: one compiled signature).
_NO_MODEL = (readonly(np.zeros(6)), readonly(np.zeros((6, 3))), readonly(np.eye(6)))


@dataclass(frozen=True)
class Sensed:
    """Step 2's maths for one tick (:func:`sense`)."""

    chain: tuple               # (J_H, frames): what :meth:`AdmittanceController.step` takes
    r_0_6: np.ndarray          # flange orientation 0R_6 (3x3, a view on the frames)
    wrench_h: np.ndarray       # external wrench at the reference point, {H} (N, N*m)
    force_norm_n: float        # its norm
    file_torque_mnm: float     # from the motor current (eq 5.4-5.5)
    tip_0: tuple               # file tip 0p_H (mm)
    axis_0: tuple              # file axis z_H in {0}


def sense(admittance: AdmittanceController, q_deg: np.ndarray, wrench_s_raw: np.ndarray,
          current_a: float, velocity_rpm: float, gravity: GravityModel | None,
          to_h: WrenchTransform | None, efficiency: float = 1.0,
          friction_current_a: float = 0.0) -> Sensed:
    """The forward chain and the tool Jacobian at ``q_deg`` for the admittance's reference
    point, the external wrench there in {H} (eq 4.18 then eq 4.26-4.31; zero without a
    gravity model), the file torque from the motor current and the tip and axis: one
    compiled call (:func:`~dentibot.control.tick_kernels.sense`)."""
    robot = admittance.robot
    offset, gain, matrix = _NO_MODEL if gravity is None else \
        (gravity._offset, gravity._gain, to_h.matrix)
    frames, jh, wrench_h, norm, tau, tip = tick_kernels.sense(
        q_deg, wrench_s_raw, float(current_a), float(velocity_rpm), robot._dh_arr,
        robot.tool, admittance.ref_h, gravity is not None, offset, gain, matrix,
        float(efficiency), float(friction_current_a))
    t = tip.tolist()
    return Sensed((jh, frames), frames[5, :3].T, wrench_h, norm, tau, tuple(t[3]),
                  tuple(t[2]))


def admittance_command(admittance: AdmittanceController, q_deg, wrench_h: np.ndarray,
                       fz_n: float, kin, feedforward: np.ndarray | None = None,
                       lateral: float = 1.0) -> JointCommand:
    """One admittance step driven by ``wrench_h`` plus the desired insertion force ``fz_n``
    along the file axis z_H (f_d of 4.4), with an optional ``feedforward`` twist in {H} and
    the lateral axes' damping raised ``lateral`` times."""
    return admittance.step(q_deg, wrench_h, kin, feedforward, fz_n, lateral)


@dataclass(frozen=True)
class TickResult:
    wrench_h: np.ndarray  # external wrench at the reference point, {H} axes (N, N*m)
    command: JointCommand


@dataclass
class ControlComputation:
    """The whole chain for one tick, as the runtime runs it (compensation, frame change,
    admittance)."""

    gravity: GravityModel
    to_h: WrenchTransform
    admittance: AdmittanceController

    def step(self, q_deg, wrench_s_raw: np.ndarray, fz_n: float = 0.0) -> TickResult:
        """``wrench_s_raw``: the sensor reading (N, N*m); ``fz_n``: desired insertion force."""
        q = np.asarray(q_deg, dtype=float)
        s = sense(self.admittance, q, np.asarray(wrench_s_raw, dtype=float), 0.0, 0.0,
                  self.gravity, self.to_h)
        return TickResult(s.wrench_h, admittance_command(self.admittance, q, s.wrench_h, fz_n,
                                                         s.chain))
