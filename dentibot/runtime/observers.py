"""Observers of what a real set-up can report: the handpiece's speed and enabled state against
what DentiBot commanded, file fracture from the torque signature, and the file tip's measured
speed. None of them reads anything a simulator knows and a device cannot (a fracture flag, a
power-loss flag): they see the drive's speed, enabled bit and current, and the arm's joints.

Each returns :class:`~dentibot.runtime.finding.Finding` s that the control task latches as
a fault (file and arm stopped in the same tick).
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass

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
    speed (after ``settle_s``), still when commanded to stop."""

    def __init__(self, ts: float, limits: ObserverLimits) -> None:
        self.ts, self.lim = ts, limits
        self._cmd = None
        self._since = 0
        self._bad = 0

    def check(self, file_cmd, rpm: float, enabled: bool, torque_mnm: float) -> list[Finding]:
        lim = self.lim
        if file_cmd != self._cmd:
            self._cmd, self._since, self._bad = file_cmd, 0, 0
        self._since += 1
        if file_cmd is None or file_cmd[0] == "reverse":
            return []
        want = file_cmd[1] if file_cmd[0] == "vel" else 0.0
        if self._since * self.ts < lim.settle_s:
            return []
        if want != 0.0 and not enabled:
            return [Finding("handpiece_disabled",
                            f"the drive reports its output disabled while commanded "
                            f"{want:g} rpm (file at {rpm:.0f} rpm)")]
        tol = max(lim.speed_tolerance_rpm, lim.speed_tolerance_share * abs(want))
        slow_under_load = abs(rpm) < abs(want) and abs(torque_mnm) > lim.loaded_mnm
        if abs(rpm - want) > tol and not slow_under_load:
            self._bad += 1
        else:
            self._bad = 0
        if self._bad * self.ts >= lim.persist_s:
            what = "to stop" if want == 0.0 else f"{want:g} rpm"
            return [Finding("handpiece_speed",
                            f"file turning at {rpm:.0f} rpm while commanded {what} for "
                            f"{1000 * self._bad * self.ts:.0f} ms (tolerance {tol:.0f} rpm; "
                            "drive power lost, or another master on the bus)")]
        return []


class FractureObserver:
    """A file that breaks in the canal loses its resistance at once: the motor's torque falls
    from a loaded level to the free-running level within a few milliseconds while the motor
    keeps its speed. The free-running level is learnt while the file turns outside the canal.

    Only while the file is held or pushed in (its depth not decreasing over the window): a
    file drawn out of a canal shaped to its own size loses its wall contact as quickly as a
    broken one loses its load, so a drop while withdrawing says nothing (a fracture on the
    way out is left to the report of the broken length)."""

    def __init__(self, ts: float, limits: ObserverLimits) -> None:
        self.ts, self.lim = ts, limits
        n_ref = max(1, round(limits.fracture_reference_s / ts))
        self.n_recent = max(1, round(limits.fracture_recent_s / ts))
        self._hist: collections.deque[float] = collections.deque(maxlen=n_ref + self.n_recent)
        self._depths: collections.deque = collections.deque(maxlen=n_ref + self.n_recent)
        self.free_mnm = 0.0
        self._free_n = 0

    def reset(self) -> None:
        self._hist.clear()
        self._depths.clear()

    def check(self, forward_rpm: float | None, rpm: float, torque_mnm: float,
              depth_mm: float | None) -> list[Finding]:
        """``forward_rpm``: the commanded forward speed (None when the file is not commanded
        forward: then nothing is compared)."""
        lim = self.lim
        at_speed = forward_rpm is not None and forward_rpm > 0.0 and \
            abs(rpm - forward_rpm) < lim.speed_tolerance_share * forward_rpm
        if not at_speed:
            self.reset()
            return []
        if depth_mm is not None and depth_mm < -1.0 and self._free_n < 10_000:
            # outside the canal: the free-running torque (mean of up to 20 s of samples)
            self._free_n += 1
            self.free_mnm += (torque_mnm - self.free_mnm) / self._free_n
        h, d = self._hist, self._depths
        h.append(torque_mnm)
        d.append(depth_mm)
        if len(h) < h.maxlen or depth_mm is None or depth_mm < lim.fracture_min_depth_mm \
                or d[0] is None or depth_mm < d[0] - lim.fracture_withdraw_mm:
            return []
        vals = list(h)
        ref = vals[:-self.n_recent]
        recent = vals[-self.n_recent:]
        loaded = sum(ref) / len(ref) - self.free_mnm
        now = sum(recent) / len(recent) - self.free_mnm
        if loaded >= lim.fracture_loaded_mnm and \
                now <= min(lim.fracture_share * loaded, lim.fracture_free_band_mnm):
            self.reset()
            return [Finding("fracture_suspected",
                            f"file torque fell from {loaded + self.free_mnm:.1f} to "
                            f"{now + self.free_mnm:.1f} mNm within "
                            f"{1000 * self.n_recent * self.ts:.0f} ms at {depth_mm:.1f} mm deep, "
                            f"the motor at {rpm:.0f} rpm: the file has probably broken")]
        return []


class TipSpeedObserver:
    """The tip's measured speed (its kinematic position over the last ``window`` ticks)
    against a bound: what the arm does, not what it was told (a drifting force reading can
    drive it anywhere). Over a window, so that a joint sample that arrived a period late (real
    time) does not read as a doubled speed."""

    window = 5

    def __init__(self, ts: float, limits: ObserverLimits) -> None:
        self.ts, self.lim = ts, limits
        self._tips: collections.deque = collections.deque(maxlen=self.window + 1)
        self._bad = 0

    def check(self, tip_0) -> list[Finding]:
        """``tip_0`` None: not watched this tick (the arm is scripted or stopped)."""
        tips = self._tips
        if tip_0 is None:
            tips.clear()
            self._bad = 0
            return []
        tips.append(tuple(tip_0))
        if len(tips) < 2:
            return []
        v = math.dist(tips[0], tips[-1]) / ((len(tips) - 1) * self.ts)
        self._bad = self._bad + 1 if v > self.lim.tip_speed_mm_s else 0
        if self._bad * self.ts >= self.lim.persist_s:
            return [Finding("tip_speed_measured",
                            f"file tip moving at {v:.0f} mm/s (measured over "
                            f"{1000 * (len(tips) - 1) * self.ts:.0f} ms) for "
                            f"{1000 * self._bad * self.ts:.0f} ms: above "
                            f"{self.lim.tip_speed_mm_s:g} mm/s")]
        return []
