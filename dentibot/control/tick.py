"""The maths of one control tick (docs/architecture.md, "The tick", steps 2 and 5): the chain
the runtime calls every period and the benchmark times, so what is measured is what runs.

Raw sensor wrench in {S} -> offset and gravity removed (eq 4.18) -> moved to the active
reference point in {H} (eq 4.26-4.31) -> plus the desired wrench f_d = (0, 0, fz, 0, 0, 0)
(self-alignment, 4.4) -> admittance step, tool Jacobian, joint rates, limits (4.3). The
forward chain is computed once per tick (:func:`forward_chain`) and shared by the gravity model
(flange orientation) and the Jacobian.

Pure maths: the runtime reads the devices and sends the commands.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dentibot.control.admittance import AdmittanceController, JointCommand
from dentibot.control.wrench import GravityModel, WrenchTransform


def forward_chain(admittance: AdmittanceController, q_deg):
    """The tick's forward kinematic chain at ``q_deg`` and the flange orientation 0R_6 (3x3).

    Returns ``(kin, r_0_6)``; ``kin`` is what :meth:`AdmittanceController.step` and the tool
    Jacobian take, so the chain is computed once per tick.
    """
    kin = admittance.kinematics(q_deg)
    return kin, kin[1][5, :3].T             # the chain stores 0R_6 by columns


def external_wrench_h(gravity: GravityModel, to_h: WrenchTransform, wrench_s_raw: np.ndarray,
                      r_0_6: np.ndarray) -> np.ndarray:
    """The external wrench at the reference point, in {H} axes (N, N*m): eq 4.18 then
    eq 4.26-4.31."""
    return to_h.apply(gravity.external_wrench(wrench_s_raw, r_0_6))


def admittance_command(admittance: AdmittanceController, q_deg, wrench_h: np.ndarray,
                       fz_n: float, kin, feedforward: np.ndarray | None = None) -> JointCommand:
    """One admittance step driven by ``wrench_h`` plus the desired insertion force ``fz_n``
    along the file axis z_H (f_d of 4.4), with an optional ``feedforward`` twist in {H}."""
    f_in = wrench_h.copy()
    f_in[2] += fz_n
    return admittance.step(q_deg, f_in, kin, feedforward)


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
        kin, r_0_6 = forward_chain(self.admittance, q_deg)
        wrench_h = external_wrench_h(self.gravity, self.to_h, wrench_s_raw, r_0_6)
        return TickResult(wrench_h, admittance_command(self.admittance, q_deg, wrench_h, fz_n,
                                                       kin))
