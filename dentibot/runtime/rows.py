"""Step 6 of the tick: one telemetry row (docs/architecture.md, "The tick"); the fields are
:data:`dentibot.telemetry.schema.TICK_FIELDS`, laid out by
:func:`~dentibot.telemetry.blocks.tick_row`."""

from __future__ import annotations

import numpy as np

from dentibot.control.kinematics import euler_xyz_deg
from dentibot.control.kinematics_kernels import tool_euler_deg
from dentibot.runtime.estimate import Estimate
from dentibot.states.behaviours import feed_force_n
from dentibot.telemetry.blocks import tick_row


def telemetry_row(rt, k: int, est: Estimate, qdot, events, lateness_s: float,
                  compute_s: float) -> dict:
    """Step 6 of the tick: the telemetry row of tick ``k`` (fields: :data:`TICK_FIELDS`)."""
    mode = rt.mode
    fz = feed_force_n(mode, rt.ctx, rt.cfg.plan) if mode.arm == "admittance" else 0.0
    truth = rt.truth() if rt.truth is not None else _NO_TRUTH
    return tick_row(
        k * rt.ts, k, rt.step_name, rt.treatment.state, est.q_deg.tolist(),
        [0.0] * 6 if qdot is None else (
            qdot.tolist() if type(qdot) is np.ndarray else [float(x) for x in qdot]),
        [*est.tip_0, *tool_euler_deg(rt.chain[1], rt.R_6_H)], truth["phantom_pose"],
        _tooth_pose(rt.ctx.tooth), est.wrench_s.tolist(), est.wrench_h.tolist(), fz,
        # the PD output that decided this tick (also when it just triggered a reversal)
        rt.ctx.decision.fz_star_n if rt.ctx.decided == k else fz,
        est.file_torque_mnm, est.motor_current_a, est.motor_rpm, est.depth_mm,
        truth["true_depth_mm"], rt.cfg.plan.working_length_mm, truth["completeness"],
        rt.treatment.state == "treating.patient_moved", rt.ctx.reversals,
        truth["fractured"], [e for e, _ in events], max(lateness_s, 0.0) * 1e6,
        compute_s * 1e6,
        # lock-step time has no deadlines: nothing can be late
        rt.clock.realtime and lateness_s + compute_s > rt.ts)


#: what a row says where no simulation knows the truth
_NO_TRUTH = {"phantom_pose": None, "true_depth_mm": None, "completeness": None,
             "fractured": False}


def _tooth_pose(tooth) -> list[float] | None:
    """The tracked tooth's pose in {0} as x, y, z mm and mobile XYZ Euler angles (deg)."""
    t = None if tooth is None else tooth.pose_0t
    if t is None:
        return None
    return [*t[:3, 3].tolist(), *euler_xyz_deg(t[:3, :3])]
