"""Observers of what a real set-up can report: the handpiece's speed and enabled state against
what DentiBot commanded, file fracture from the torque signature, and the file tip's measured
speed. None of them reads anything a simulator knows and a device cannot (a fracture flag, a
power-loss flag): they see the drive's speed, enabled bit and current, and the arm's joints.

Each returns :class:`~dentibot.runtime.finding.Finding` s that the control task latches as
a fault (file and arm stopped in the same tick).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dentibot.runtime import supervisor_kernels as sk
from dentibot.runtime.finding import Finding


@dataclass(frozen=True)
class ObserverLimits:
    """Bounds of the observers (assumptions, each with its reason)."""

    # The drive reaches a new speed within this time (EPOS4 profile velocity mode at the
    # handpiece's acceleration; the simulated speed loop has a 10 ms time constant: 5 time
    # constants and a margin): no speed comparison before it.
    settle_s: float = 0.1
    # Actual speed further than this from the command (rpm, or this share of the command,
    # whichever is larger) for ``persist_s`` is a drive that does not do what it was told
    # (power lost, a second master, a broken coupling) ...
    speed_tolerance_rpm: float = 15.0
    speed_tolerance_share: float = 0.3
    persist_s: float = 0.008
    # ... unless the file is loaded (a binding file slows the motor: the torque regulation and
    # the torque limit deal with that), i.e. its torque is above this (mNm).
    loaded_mnm: float = 20.0
    # The file's torque is "loaded" when its mean over the reference window is at least this
    # much above the free-running level (mNm; 7 times the mean's noise: the current reading's
    # 0.75 mNm rms over the 17 samples of the window) ...
    fracture_loaded_mnm: float = 5.0
    # ... and a fracture is suspected when the mean of the last ``fracture_recent_s`` falls to
    # this share of the loaded excess and into the free-running band, the motor still at
    # speed and the tip in the canal: all resistance vanished at once. An intact file that
    # stops cutting (the feed backs off) keeps rubbing the walls (several mNm at depth); one
    # leaving the canal loses its load over hundreds of ms.
    fracture_share: float = 0.25
    fracture_free_band_mnm: float = 3.0
    fracture_recent_s: float = 0.006
    fracture_reference_s: float = 0.040
    fracture_min_depth_mm: float = 0.5
    # Withdrawal over the window that disables the fracture signature (mm; 0.5 mm/s over the
    # 46 ms window: the feed backing off or a retraction, not a held file's noise).
    fracture_withdraw_mm: float = 0.02
    # The measured tip speed (from the joint readings) above this for ``persist_s``: the arm
    # is moving faster than anything commanded near a patient may (the command cap is 50 mm/s).
    tip_speed_mm_s: float = 60.0


class SpindleObserver:
    """The handpiece does what it was told: enabled while commanded to turn, at the commanded
    speed (after ``settle_s``), still when commanded to stop. (Compiled:
    :func:`~dentibot.runtime.supervisor_kernels.spindle`.)"""

    def __init__(self, ts: float, limits: ObserverLimits) -> None:
        self.ts, self.lim = ts, limits
        self._cmd = None
        self._st = np.zeros(len(sk.SPINDLE_FIELDS))
        self._lim = np.array([limits.settle_s, limits.speed_tolerance_rpm,
                              limits.speed_tolerance_share, limits.loaded_mnm,
                              limits.persist_s])

    def check(self, file_cmd, rpm: float, enabled: bool, torque_mnm: float) -> list[Finding]:
        changed = file_cmd != self._cmd
        if changed:
            self._cmd = file_cmd
        compared = file_cmd is not None and file_cmd[0] != "reverse"
        want = file_cmd[1] if compared and file_cmd[0] == "vel" else 0.0
        code = sk.spindle(self._st, self._lim, self.ts, changed, compared, float(want),
                          float(rpm), bool(enabled), float(torque_mnm))
        if code == sk.SPINDLE_DISABLED:
            return [Finding("handpiece_disabled",
                            f"the drive reports its output disabled while commanded "
                            f"{want:g} rpm (file at {rpm:.0f} rpm)")]
        if code == sk.SPINDLE_SPEED:
            what = "to stop" if want == 0.0 else f"{want:g} rpm"
            return [Finding("handpiece_speed",
                            f"file turning at {rpm:.0f} rpm while commanded {what} for "
                            f"{1000 * self._st[sk.SP_BAD] * self.ts:.0f} ms (tolerance "
                            f"{self._st[sk.SP_TOL]:.0f} rpm; drive power lost, or another "
                            "master on the bus)")]
        return []


class FractureObserver:
    """A file that breaks in the canal loses its resistance at once: the motor's torque falls
    from a loaded level to the free-running level within a few milliseconds while the motor
    keeps its speed. The free-running level is learnt while the file turns outside the canal.

    Only while the file is held or pushed in (its depth not decreasing over the window): a
    file drawn out of a canal shaped to its own size loses its wall contact as quickly as a
    broken one loses its load, so a drop while withdrawing says nothing (a fracture on the
    way out is left to the report of the broken length).

    The detection is compiled (:func:`~dentibot.runtime.supervisor_kernels.fracture`) over
    this object's window and state arrays."""

    def __init__(self, ts: float, limits: ObserverLimits) -> None:
        self.ts, self.lim = ts, limits
        n_ref = max(1, round(limits.fracture_reference_s / ts))
        self.n_recent = max(1, round(limits.fracture_recent_s / ts))
        self._st = np.zeros(len(sk.FRACTURE_FIELDS))
        self._ring = np.zeros((n_ref + self.n_recent, 3))   # torque, depth, depth known
        self._lim = np.array([limits.fracture_loaded_mnm, limits.fracture_share,
                              limits.fracture_free_band_mnm, limits.fracture_min_depth_mm,
                              limits.fracture_withdraw_mm])
        self._out = np.zeros(2)

    @property
    def free_mnm(self) -> float:
        """The free-running torque learnt so far (mNm)."""
        return float(self._st[sk.F_FREE])

    def reset(self) -> None:
        """Empty the window (the free-running torque stays)."""
        self._st[sk.F_HEAD] = self._st[sk.F_COUNT] = 0.0

    def check(self, forward_rpm: float | None, rpm: float, torque_mnm: float,
              depth_mm: float | None) -> list[Finding]:
        """``forward_rpm``: the commanded forward speed (None when the file is not commanded
        forward: then nothing is compared)."""
        lim = self.lim
        at_speed = forward_rpm is not None and forward_rpm > 0.0 and \
            abs(rpm - forward_rpm) < lim.speed_tolerance_share * forward_rpm
        known = depth_mm is not None
        if not sk.fracture(self._st, self._ring, self._lim, self.n_recent, at_speed,
                           float(torque_mnm), float(depth_mm) if known else 0.0, known,
                           self._out):
            return []
        free = self.free_mnm
        loaded, now = self._out
        return [Finding("fracture_suspected",
                        f"file torque fell from {loaded + free:.1f} to "
                        f"{now + free:.1f} mNm within "
                        f"{1000 * self.n_recent * self.ts:.0f} ms at {depth_mm:.1f} mm deep, "
                        f"the motor at {rpm:.0f} rpm: the file has probably broken")]


class TipSpeedObserver:
    """The tip's measured speed (its kinematic position over the last ``window`` ticks)
    against a bound: what the arm does, not what it was told (a drifting force reading can
    drive it anywhere). Over a window, so that a joint sample that arrived a period late (real
    time) does not read as a doubled speed. (Compiled:
    :func:`~dentibot.runtime.supervisor_kernels.tip_speed`.)"""

    window = 5

    def __init__(self, ts: float, limits: ObserverLimits) -> None:
        self.ts, self.lim = ts, limits
        self._st = np.zeros(len(sk.TIP_FIELDS))
        self._ring = np.zeros((self.window + 1, 3))

    def check(self, tip_0) -> list[Finding]:
        """``tip_0`` None: not watched this tick (the arm is scripted or stopped)."""
        st = self._st
        if tip_0 is None:
            st[:] = 0.0
            return []
        v = sk.tip_speed(st, self._ring, float(tip_0[0]), float(tip_0[1]), float(tip_0[2]),
                         self.ts, self.lim.tip_speed_mm_s)
        bad = st[sk.T_BAD]
        if v < 0.0 or bad * self.ts < self.lim.persist_s:
            return []
        n = int(st[sk.T_COUNT])
        return [Finding("tip_speed_measured",
                        f"file tip moving at {v:.0f} mm/s (measured over "
                        f"{1000 * (n - 1) * self.ts:.0f} ms) for "
                        f"{1000 * bad * self.ts:.0f} ms: above "
                        f"{self.lim.tip_speed_mm_s:g} mm/s")]
