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

from dentibot.io.interfaces import WRENCH_SATURATED
from dentibot.runtime.finding import Finding
from dentibot.runtime.observers import (
    FractureObserver,
    ObserverLimits,
    SpindleObserver,
    TipSpeedObserver,
)

__all__ = ["Finding", "Freshness", "Supervisor", "SupervisorLimits", "non_finite"]


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


class Freshness:
    """Tracks the last tick at which each stream's ``seq`` changed."""

    def __init__(self, bounds_periods: dict[str, int]) -> None:
        self.bounds = dict(bounds_periods)
        self._seq: dict[str, int] = {}
        self._tick: dict[str, int] = {}

    def reset(self) -> None:
        self._seq.clear()
        self._tick.clear()

    def check(self, name: str, seq: int, tick: int) -> Finding | None:
        last = self._seq.get(name)
        if last is None or seq != last:
            self._seq[name] = seq
            self._tick[name] = tick
            return None
        age = tick - self._tick[name]
        bound = self.bounds.get(name, 10)
        if age > bound:
            return Finding(f"stale_{name}",
                           f"{name} stream: seq {seq} unchanged for {age} periods "
                           f"(limit {bound})")
        return None


def non_finite(name: str, values) -> Finding | None:
    for i, v in enumerate(values):
        if not math.isfinite(v):
            return Finding(f"nonfinite_{name}", f"{name}[{i}] = {v} (must be finite)")
    return None


class Supervisor:
    """Stateful checks (freshness, jumps, disagreement timers) over the tick's data."""

    def __init__(self, stale_periods: dict[str, int], ts: float,
                 limits: SupervisorLimits | None = None) -> None:
        self.lim = limits or SupervisorLimits()
        self.ts = ts
        self.freshness = Freshness(stale_periods)
        self._last_force: tuple[float, float, float] | None = None
        self._joint_bounds: tuple | None = None       # (limits array, margin, lo, hi floats)
        self._disagree_ticks = 0
        olim = ObserverLimits()
        self.spindle = SpindleObserver(ts, olim)
        self.fracture = FractureObserver(ts, olim)
        self.tip_speed = TipSpeedObserver(ts, olim)

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

    def check_inputs(self, k: int, js, w, m, aux) -> list[Finding]:
        out: list[Finding] = []
        fr = self.freshness
        for name, sample in (("arm", js), ("ft", w), ("motor", m), ("aux", aux)):
            if sample is not None:
                f = fr.check(name, sample.seq, k)
                if f:
                    out.append(f)
        if aux is not None and aux.estop:
            out.append(Finding("estop", "emergency stop pressed (aux input)"))
        for name, vals in (("wrench", w.force_n + w.torque_nm), ("joints", js.q_deg),
                           ("motor", (m.current_a, m.velocity_rpm, m.position_deg))):
            f = non_finite(name, vals)
            if f:
                out.append(f)
                return out
        if w.status & WRENCH_SATURATED:
            out.append(Finding("ft_saturated",
                               f"F/T reading saturated (status 0x{w.status:x}): force "
                               f"{np.round(w.force_n, 2).tolist()} N, torque "
                               f"{np.round(w.torque_nm, 4).tolist()} N*m"))
        # plain floats: three components do not pay numpy's per-call overhead (every tick)
        force = tuple(float(x) for x in w.force_n)
        last = self._last_force
        if last is not None:
            jump = max(abs(force[0] - last[0]), abs(force[1] - last[1]),
                       abs(force[2] - last[2]))
            if jump > self.lim.ft_jump_n:
                out.append(Finding("ft_jump", f"F/T force changed by {jump:.1f} N in one "
                                              f"sample (limit {self.lim.ft_jump_n} N)"))
        self._last_force = force
        if m.fault:
            out.append(Finding("motor", m.fault))
        return out

    def check_estimate(self, est, kin_robot, frames, depth_ref, working_length_mm,
                       file_turning: bool) -> list[Finding]:
        lim = self.lim
        out: list[Finding] = []
        # two torque sources: the sensor sees the canal's reaction about the file axis
        if file_turning:
            tau_ft = -1e3 * float(est.wrench_h[5])
            diff = abs(est.file_torque_mnm - tau_ft)
            if diff > lim.torque_disagreement_mnm:
                self._disagree_ticks += 1
                if self._disagree_ticks * self.ts > lim.torque_disagreement_s:
                    out.append(Finding("torque_disagreement",
                                       f"file torque from current {est.file_torque_mnm:.1f} "
                                       f"mNm vs F/T {tau_ft:.1f} mNm: {diff:.1f} mNm apart for "
                                       f"{self._disagree_ticks * self.ts:.2f} s (limit "
                                       f"{lim.torque_disagreement_mnm} mNm, "
                                       f"{lim.torque_disagreement_s} s)"))
            else:
                self._disagree_ticks = 0
        else:
            self._disagree_ticks = 0
        if depth_ref is not None:
            o, a = depth_ref
            d = [est.tip_0[i] - o[i] for i in range(3)]
            axial = d[0] * a[0] + d[1] * a[1] + d[2] * a[2]
            lateral = math.sqrt(max(0.0, d[0] ** 2 + d[1] ** 2 + d[2] ** 2 - axial ** 2))
            if lateral > lim.workspace_lateral_mm or axial < -lim.workspace_above_mm or \
                    axial > working_length_mm + lim.workspace_past_wl_mm:
                out.append(Finding("workspace",
                                   f"file tip {lateral:.1f} mm sideways, {axial:.1f} mm deep "
                                   f"(box: {lim.workspace_lateral_mm} mm sideways, "
                                   f"-{lim.workspace_above_mm}..{working_length_mm + lim.workspace_past_wl_mm:.1f} mm)"))
        q = est.q_deg
        limits = kin_robot.joint_limits_deg
        b = self._joint_bounds
        if b is None or b[0] is not limits or b[1] != lim.joint_margin_deg:
            b = self._joint_bounds = (limits, lim.joint_margin_deg,
                                      [float(x) - lim.joint_margin_deg for x in limits[:, 0]],
                                      [float(x) + lim.joint_margin_deg for x in limits[:, 1]])
        q_lo, q_hi = b[2], b[3]
        qf = q.tolist() if isinstance(q, np.ndarray) else [float(x) for x in q]
        for i in range(6):
            if qf[i] < q_lo[i] or qf[i] > q_hi[i]:
                lo, hi = limits[:, 0], limits[:, 1]
                out.append(Finding("joint_range", f"J{i + 1} = {q[i]:.2f} deg outside "
                                                  f"{lo[i]:.0f}..{hi[i]:.0f} deg"))
        s = kin_robot.singularity(q, frames=frames)
        for name, value, bound, unit in (("shoulder", s.shoulder_mm, lim.shoulder_min_mm, " mm"),
                                         ("elbow", s.elbow, lim.elbow_min, ""),
                                         ("wrist", s.wrist, lim.wrist_min, "")):
            if value < bound:
                out.append(Finding("singularity", f"{name} singularity measure {value:.4f}"
                                                  f"{unit} below the margin {bound:.4f}{unit}"))
        return out

    def check_command(self, qdot_deg_s, twist, speed_limits_deg_s,
                      tooth_twist=None) -> list[Finding]:
        """The joint rates against their limits, and the file tip's commanded speed against
        the cap: relative to the tracked tooth when its motion is fed forward
        (``tooth_twist``, hybrid control), since the cap protects the patient from the file,
        and a file that moves with a jerking tooth is not fast for the tooth."""
        out: list[Finding] = []
        if isinstance(qdot_deg_s, np.ndarray):
            qdot_deg_s = qdot_deg_s.tolist()
        for i in range(6):
            if abs(qdot_deg_s[i]) > speed_limits_deg_s[i] * (1.0 + 1e-9):
                out.append(Finding("joint_speed", f"J{i + 1} commanded {qdot_deg_s[i]:.1f} "
                                                  f"deg/s > {speed_limits_deg_s[i]:.0f} deg/s"))
        rel = twist if tooth_twist is None else [twist[i] - tooth_twist[i] for i in range(3)]
        v = math.sqrt(float(rel[0]) ** 2 + float(rel[1]) ** 2 + float(rel[2]) ** 2)
        if v > self.lim.tip_speed_cap_mm_s:
            what = "" if tooth_twist is None else " relative to the tracked tooth"
            out.append(Finding("tip_speed", f"file tip commanded {v:.1f} mm/s{what} > cap "
                                            f"{self.lim.tip_speed_cap_mm_s} mm/s"))
        return out
