"""One control computation, the maths of a 2 ms tick (docs/architecture.md, "The tick", steps 2-4).

Raw sensor wrench in {S} -> offset and gravity removed (eq 4.18) -> moved to the active
reference point in {H} (eq 4.26-4.31) -> plus the desired wrench f_d (self-alignment, eq in
4.4) -> admittance step, tool Jacobian, joint rates, limits (4.3). The forward chain is computed
once and shared by the gravity model (flange orientation) and the Jacobian.

Pure maths: the runtime reads the devices and sends the commands.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dentibot.control.admittance import AdmittanceController, JointCommand
from dentibot.control.wrench import GravityModel, WrenchTransform


@dataclass(frozen=True)
class TickResult:
    wrench_h: np.ndarray  # external wrench at the reference point, {H} axes (N, N*m)
    command: JointCommand


@dataclass
class ControlComputation:
    """Compensation + frame change + admittance for one tick."""

    gravity: GravityModel
    to_h: WrenchTransform
    admittance: AdmittanceController

    def step(self, q_deg, wrench_s_raw: np.ndarray, f_d: np.ndarray | None = None) -> TickResult:
        """``wrench_s_raw``: the sensor reading (N, N*m); ``f_d``: desired wrench in {H}."""
        kin = self.admittance.kinematics(q_deg)
        r_0_6 = np.array(kin[1][-1][0]).T  # the chain stores 0R_6 by columns
        ext_s = self.gravity.external_wrench(wrench_s_raw, r_0_6)
        wrench_h = self.to_h.apply(ext_s)
        f_in = wrench_h if f_d is None else wrench_h + f_d
        return TickResult(wrench_h, self.admittance.step(q_deg, f_in, kin))

