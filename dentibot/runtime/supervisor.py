"""The safety supervisor: checks made every tick, independent of the state's control law.

Inputs (before anything is estimated):
- freshness: each stream's sequence number must advance within its bound (in control
  periods); a stale stream is a fault, never a held value;
- values: NaN/inf in any sample; F/T saturation (status bit); an implausible F/T jump
  between two consecutive samples; a motor fault (EMCY, drive fault, fracture);
- the emergency stop input (aux I/O).

Estimates (after step 2 of the tick):
- the two file-torque sources disagree (motor current vs the F/T sensor's torque about the
  file axis) for longer than a grace time;
- the file tip leaves the workspace box around the tooth (when the orifice is known);
- joints beyond their range; closer to a singularity than the hard margin.

Commands (before they are sent): joint speed above the Meca500 limits, tool-tip speed above
the cap.

Observers (:mod:`dentibot.runtime.observers`, what a real device can report): the handpiece
against its command, file fracture from the torque signature, the tip's measured speed.

Each finding names its cause, the value and the limit; the control task turns it into the
latched ``fault`` (arm and file stopped in the same tick).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dentibot.control.kinematics import WRIST_CENTRE_FRAME
from dentibot.runtime import supervisor_kernels as sk
from dentibot.runtime.finding import Finding
from dentibot.runtime.observers import (
    FractureObserver,
    ObserverLimits,
    SpindleObserver,
    TipSpeedObserver,
)

__all__ = ["Finding", "Supervisor", "SupervisorLimits"]

#: The names of the groups :func:`~dentibot.runtime.supervisor_kernels.inputs` checks for
#: non-finite values, by its group number.
_VALUE_GROUPS = {1: "wrench", 2: "joints", 3: "motor"}


@dataclass(frozen=True)
class SupervisorLimits:
    """Hard limits of the supervisor (assumptions where the thesis gives no figure)."""

    # assumption: the Mini40 cannot see a real 15 N change within one 2 ms period in this
    # task (contact forces stay below 5 N); a larger step is a glitch or a collision.
    ft_jump_n: float = 15.0
    # assumption: current-based and F/T-based file torque may differ by 15 mNm for 0.1 s
    # (noise, spin-up transients); longer means a sensor or model fault.
    torque_disagreement_mnm: float = 15.0
    torque_disagreement_s: float = 0.1
    # assumption: a coarse box around where the orifice was when alignment began, in that
    # frame (file axis): the patient moves the tooth (thesis experiment 1: a 15 mm square),
    # and the robot follows by force, so the box holds that motion: +-25 mm sideways, from
    # 60 mm above to 20 mm past the working length. The depth limit (working length +
    # margin, from the depth estimate) is the fine apical bound.
    workspace_lateral_mm: float = 25.0
    workspace_above_mm: float = 60.0
    workspace_past_wl_mm: float = 20.0
    # Joint range: the Meca500's own limits (a measured joint beyond them is a fault).
    joint_margin_deg: float = 0.0
    # Singularity hard margins: half the limiter's stop thresholds.
    shoulder_min_mm: float = 2.5
    elbow_min: float = math.sin(math.radians(1.0))
    wrist_min: float = math.sin(math.radians(1.0))
    # assumption: the file tip never needs more than 50 mm/s near a patient (dragging at
    # 18.75 mm/s per N reaches it only with a 2.7 N push).
    tip_speed_cap_mm_s: float = 50.0


class Supervisor:
    """Stateful checks (freshness, jumps, disagreement timers) over the tick's data: the
    detection compiled (:mod:`dentibot.runtime.supervisor_kernels`, over this object's
    arrays), the wording of a finding here."""

    def __init__(self, stale_periods: dict[str, int], ts: float,
                 limits: SupervisorLimits | None = None) -> None:
        lim = self.lim = limits or SupervisorLimits()
        self.ts = ts
        #: each stream's freshness bound (periods), in the order of ``sk.STREAMS``
        self.bounds = np.array([float(stale_periods.get(n, 10)) for n in sk.STREAMS])
        self._fresh = np.zeros((len(sk.STREAMS), len(sk.FRESH_FIELDS)))
        self._last_force = np.zeros(4)          # fx, fy, fz, and whether one was kept
        self._in_out = np.zeros(len(sk.INPUT_OUT_FIELDS))
        self._disagree = np.zeros(1)            # periods the torque sources disagreed
        self._est_lim = np.array([lim.torque_disagreement_mnm, lim.torque_disagreement_s,
                                  lim.workspace_lateral_mm, lim.workspace_above_mm,
                                  lim.workspace_past_wl_mm, lim.shoulder_min_mm, lim.elbow_min,
                                  lim.wrist_min])
        self._est_out = np.zeros(len(sk.ESTIMATE_OUT_FIELDS))
        self._joint_bounds: tuple | None = None     # (limits array, lo, hi arrays)
        self._cmd_out = np.zeros(1)
        self._speed_limits: tuple | None = None     # (the list given, as an array)
        olim = ObserverLimits()
        self.spindle = SpindleObserver(ts, olim)
        self.fracture = FractureObserver(ts, olim)
        self.tip_speed = TipSpeedObserver(ts, olim)

    def reset(self) -> None:
        """Forget the streams' sequence numbers (a reconnection starts them again)."""
        self._fresh[:] = 0.0

    def observe(self, file_cmd, m, est, near_patient: bool) -> list[Finding]:
        """The observers (:mod:`dentibot.runtime.observers`): the handpiece against its
        command, file fracture, and (``near_patient``: the arm follows forces with the file at
        the tooth, from alignment on; not while the operator drags or calibrates) the tip's
        measured speed."""
        forward = file_cmd[1] if file_cmd is not None and file_cmd[0] == "vel" \
            and file_cmd[1] > 0.0 else None
        return [*self.spindle.check(file_cmd, m.velocity_rpm, m.enabled, est.file_torque_mnm),
                *self.fracture.check(forward, m.velocity_rpm, est.file_torque_mnm,
                                     est.depth_mm),
                *self.tip_speed.check(est.tip_0 if near_patient else None)]

    def check_inputs(self, k: int, js, w, m, aux, wrench: np.ndarray | None = None,
                     q_deg: np.ndarray | None = None) -> list[Finding]:
        """The samples' checks (:func:`~dentibot.runtime.supervisor_kernels.inputs`);
        ``wrench`` and ``q_deg``: the samples' values as float arrays, if the caller has
        them already."""
        if wrench is None:
            wrench = w.as_array()
        if q_deg is None:
            q_deg = np.asarray(js.q_deg, dtype=float)
        o = self._in_out
        found = sk.inputs(self._fresh, self.bounds, self._last_force, k, js.seq, w.seq, m.seq,
                          0 if aux is None else aux.seq, aux is not None, wrench, q_deg,
                          float(m.current_a), float(m.velocity_rpm), float(m.position_deg),
                          int(w.status), self.lim.ft_jump_n, o)
        estop = aux is not None and aux.estop
        if not (found or estop or m.fault):
            return []
        out: list[Finding] = []
        seqs = (js.seq, w.seq, m.seq, None if aux is None else aux.seq)
        for i, name in enumerate(sk.STREAMS):
            age = o[sk.O_STALE + i]
            if age >= 0.0:
                out.append(Finding(f"stale_{name}",
                                   f"{name} stream: seq {seqs[i]} unchanged for {age:.0f} "
                                   f"periods (limit {self.bounds[i]:.0f})"))
        if estop:
            out.append(Finding("estop", "emergency stop pressed (aux input)"))
        group = int(o[sk.O_BAD_GROUP])
        if group:
            name = _VALUE_GROUPS[group]
            out.append(Finding(f"nonfinite_{name}", f"{name}[{int(o[sk.O_BAD_INDEX])}] = "
                                                    f"{o[sk.O_BAD_VALUE]} (must be finite)"))
            return out
        if o[sk.O_SATURATED]:
            out.append(Finding("ft_saturated",
                               f"F/T reading saturated (status 0x{w.status:x}): force "
                               f"{np.round(w.force_n, 2).tolist()} N, torque "
                               f"{np.round(w.torque_nm, 4).tolist()} N*m"))
        jump = o[sk.O_JUMP]
        if jump >= 0.0:
            out.append(Finding("ft_jump", f"F/T force changed by {jump:.1f} N in one "
                                          f"sample (limit {self.lim.ft_jump_n} N)"))
        if m.fault:
            out.append(Finding("motor", m.fault))
        return out

    def check_estimate(self, est, kin_robot, frames, depth_ref, working_length_mm,
                       file_turning: bool) -> list[Finding]:
        """The estimate's checks (:func:`~dentibot.runtime.supervisor_kernels.estimate_checks`):
        the two torque sources, the workspace box, the joint ranges, the singularity
        margins."""
        lim = self.lim
        limits = kin_robot.joint_limits_deg
        b = self._joint_bounds
        if b is None or b[0] is not limits:
            b = self._joint_bounds = (limits, limits[:, 0] - lim.joint_margin_deg,
                                      limits[:, 1] + lim.joint_margin_deg)
        boxed = depth_ref is not None
        (ox, oy, oz), (ax, ay, az) = depth_ref if boxed else ((0.0,) * 3, (0.0,) * 3)
        tip = est.tip_0
        q = np.asarray(est.q_deg, dtype=float)
        o = self._est_out
        bits = sk.estimate_checks(
            self._disagree, self._est_lim, self.ts, bool(file_turning),
            float(est.file_torque_mnm), float(est.wrench_h[5]), boxed, ox, oy, oz, ax, ay, az,
            tip[0], tip[1], tip[2], float(working_length_mm), q, b[1], b[2], frames,
            kin_robot.elbow_offset_rad, WRIST_CENTRE_FRAME, o)
        if not bits:
            return []
        out: list[Finding] = []
        if bits & sk.TORQUE_BIT:
            t = self._disagree[0] * self.ts
            out.append(Finding("torque_disagreement",
                               f"file torque from current {est.file_torque_mnm:.1f} "
                               f"mNm vs F/T {o[sk.E_TAU_FT]:.1f} mNm: {o[sk.E_DIFF]:.1f} mNm "
                               f"apart for {t:.2f} s (limit "
                               f"{lim.torque_disagreement_mnm} mNm, "
                               f"{lim.torque_disagreement_s} s)"))
        if bits & sk.WORKSPACE_BIT:
            out.append(Finding("workspace",
                               f"file tip {o[sk.E_LATERAL]:.1f} mm sideways, "
                               f"{o[sk.E_AXIAL]:.1f} mm deep (box: "
                               f"{lim.workspace_lateral_mm} mm sideways, "
                               f"-{lim.workspace_above_mm}.."
                               f"{working_length_mm + lim.workspace_past_wl_mm:.1f} mm)"))
        for i in range(6):
            if bits & (sk.JOINT_BIT << i):
                out.append(Finding("joint_range", f"J{i + 1} = {q[i]:.2f} deg outside "
                                                  f"{limits[i, 0]:.0f}..{limits[i, 1]:.0f} deg"))
        for name, bit, field, bound, unit in (
                ("shoulder", sk.SHOULDER_BIT, sk.E_SHOULDER, lim.shoulder_min_mm, " mm"),
                ("elbow", sk.ELBOW_BIT, sk.E_ELBOW, lim.elbow_min, ""),
                ("wrist", sk.WRIST_BIT, sk.E_WRIST, lim.wrist_min, "")):
            if bits & bit:
                out.append(Finding("singularity", f"{name} singularity measure "
                                                  f"{o[field]:.4f}{unit} below the margin "
                                                  f"{bound:.4f}{unit}"))
        return out

    def check_command(self, qdot_deg_s, twist, speed_limits_deg_s,
                      tooth_twist=None) -> list[Finding]:
        """The joint rates against their limits, and the file tip's commanded speed against
        the cap: relative to the tracked tooth when its motion is fed forward
        (``tooth_twist``, hybrid control), since the cap protects the patient from the file,
        and a file that moves with a jerking tooth is not fast for the tooth
        (:func:`~dentibot.runtime.supervisor_kernels.command_checks`)."""
        sl = self._speed_limits
        if sl is None or sl[0] is not speed_limits_deg_s:
            sl = self._speed_limits = (speed_limits_deg_s,
                                       np.asarray(speed_limits_deg_s, dtype=float))
        tooth = tooth_twist is not None
        bits = sk.command_checks(np.asarray(qdot_deg_s, dtype=float),
                                 np.asarray(twist, dtype=float), sl[1], tooth,
                                 np.asarray(tooth_twist, dtype=float) if tooth else sl[1],
                                 self.lim.tip_speed_cap_mm_s, self._cmd_out)
        if not bits:
            return []
        out: list[Finding] = []
        for i in range(6):
            if bits & (1 << i):
                out.append(Finding("joint_speed", f"J{i + 1} commanded {qdot_deg_s[i]:.1f} "
                                                  f"deg/s > {speed_limits_deg_s[i]:.0f} deg/s"))
        if bits & sk.TIP_SPEED_BIT:
            what = "" if tooth_twist is None else " relative to the tracked tooth"
            out.append(Finding("tip_speed", f"file tip commanded {self._cmd_out[0]:.1f} mm/s"
                                            f"{what} > cap {self.lim.tip_speed_cap_mm_s} mm/s"))
        return out
