"""Step 6 of the tick: one telemetry row (docs/architecture.md, "The tick"); the fields are
:data:`dentibot.telemetry.schema.TICK_FIELDS`."""

from __future__ import annotations

import numpy as np

from dentibot.control.kinematics import euler_xyz_deg
from dentibot.runtime.estimate import Estimate
from dentibot.states.behaviours import feed_force_n


def telemetry_row(rt, k: int, est: Estimate, qdot, events, lateness_s: float,
                  compute_s: float) -> dict:
    """Step 6 of the tick: the telemetry row of tick ``k`` (fields: :data:`TICK_FIELDS`)."""
    mode = rt.mode
    fz = feed_force_n(mode, rt.ctx, rt.cfg.plan) if mode.arm == "admittance" else 0.0
    euler = euler_xyz_deg((rt.r_0_6 @ rt.R_6_H).tolist())
    row = {
        "t": k * rt.ts, "tick": k, "step": rt.step_name, "state": rt.treatment.state,
        "q_deg": est.q_deg.tolist(),
        "qdot_cmd_deg_s": [0.0] * 6 if qdot is None else (
            qdot.tolist() if type(qdot) is np.ndarray else [float(x) for x in qdot]),
        "tool_pose": [*est.tip_0, *euler],
        "phantom_pose": None,
        "tooth_pose": _tooth_pose(rt.ctx.tooth),
        "wrench_s": est.wrench_s.tolist(), "wrench_h": est.wrench_h.tolist(),
        "f_d": [0.0, 0.0, fz, 0.0, 0.0, 0.0],
        # the PD output that decided this tick (also when it just triggered a reversal)
        "fz_star_n": rt.ctx.decision.fz_star_n if rt.ctx.decided == k else fz,
        "fz_n": fz,
        "file_torque_mnm": est.file_torque_mnm, "motor_current_a": est.motor_current_a,
        "motor_rpm": est.motor_rpm,
        "depth_mm": est.depth_mm, "true_depth_mm": None, "working_length_mm": rt.cfg.plan.working_length_mm,
        "completeness": None, "patient_moved": rt.treatment.state ==
        "treating.patient_moved", "reversals": rt.ctx.reversals, "fractured": False,
        "events": [e for e, _ in events],
        "lateness_us": max(lateness_s, 0.0) * 1e6, "compute_us": compute_s * 1e6,
        # lock-step time has no deadlines: nothing can be late
        "overrun": rt.clock.realtime and lateness_s + compute_s > rt.ts,
    }
    if rt.truth is not None:
        row.update(rt.truth())
    return row


def _tooth_pose(tooth) -> list[float] | None:
    """The tracked tooth's pose in {0} as x, y, z mm and mobile XYZ Euler angles (deg)."""
    t = None if tooth is None else tooth.pose_0t
    if t is None:
        return None
    return [*t[:3, 3].tolist(), *euler_xyz_deg(t[:3, :3].tolist())]
