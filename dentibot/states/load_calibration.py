"""Calibration routines run by the control task.

TCP (section 3.4): the operator holds the file tip on one fixed point in several flange
orientations and presses the pedal at each; eq 3.21-3.23 give the tool tip 6p_H.

Load (section 4.2): static poses -> offsets, weight, centroid.

Run tick by tick by the control task in ``calibrating.load``: for each wrist pose around the
start pose, move there (MoveJoints), wait until the joints are within ``tol_deg`` and at rest,
let the arm settle, average the raw sensor wrench over ``average_s``, record 0R_6; then solve
eq 4.5-4.17 (:func:`dentibot.control.wrench.identify_load`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dentibot.control.calibration import TcpCalibration, calibrate_tcp
from dentibot.control.wrench import LoadIdentification, identify_load
from dentibot.errors import DentibotError

#: Wrist offsets (dq4, dq5, dq6) in deg from the start pose: orientations spread enough for
#: a well-conditioned identification (rotations about two different axes, several gravity
#: directions in {S}).
DEFAULT_OFFSETS_DEG = ((0, 0, 0), (0, 0, 90), (0, 0, -90), (60, -30, 0), (-60, -30, 45),
                       (0, 25, 180), (45, 20, -135))


@dataclass(frozen=True)
class LoadCalibrationParams:
    offsets_deg: tuple = DEFAULT_OFFSETS_DEG
    tol_deg: float = 0.05
    settle_s: float = 0.3
    average_s: float = 0.2
    timeout_s: float = 10.0   # per pose


class LoadCalibration:
    """Per-tick routine; ``step`` returns the command to send, ``result`` once finished."""

    def __init__(self, q_start_deg, ts: float, params: LoadCalibrationParams | None = None,
                 limits_deg=None) -> None:
        self.p = params or LoadCalibrationParams()
        self.ts = ts
        q0 = np.asarray(q_start_deg, dtype=float)
        self.targets = []
        for d4, d5, d6 in self.p.offsets_deg:
            q = q0.copy()
            q[3] += d4
            q[4] += d5
            q[5] += d6
            if limits_deg is not None:
                q = np.clip(q, limits_deg[:, 0] + 1.0, limits_deg[:, 1] - 1.0)
            self.targets.append(q)
        self.targets.append(q0.copy())   # back where it started
        self.index = 0
        self.phase = "move"
        self.count = 0
        self.rotations: list[np.ndarray] = []
        self.wrenches: list[np.ndarray] = []
        self._acc = np.zeros(6)
        self.result: LoadIdentification | None = None
        self.error: str | None = None

    @property
    def done(self) -> bool:
        return self.result is not None or self.error is not None

    def step(self, q_deg, raw_wrench: np.ndarray, R_0_6: np.ndarray):
        """Advance one tick. Returns a joint target to send (MoveJoints) or None."""
        if self.done:
            return None
        target = self.targets[self.index]
        last = self.index == len(self.targets) - 1
        self.count += 1
        if self.phase == "move":
            if self.count == 1:
                return target
            if np.max(np.abs(np.asarray(q_deg) - target)) < self.p.tol_deg:
                self.phase, self.count = "settle", 0
            elif self.count * self.ts > self.p.timeout_s:
                self.error = (f"pose {self.index + 1}: joints not within {self.p.tol_deg} deg "
                              f"of {np.round(target, 2).tolist()} after {self.p.timeout_s} s")
            return None
        if self.phase == "settle":
            if self.count * self.ts >= self.p.settle_s:
                if last:
                    self._finish()
                    return None
                self.phase, self.count, self._acc = "average", 0, np.zeros(6)
            return None
        self._acc += raw_wrench
        if self.count * self.ts >= self.p.average_s:
            self.wrenches.append(self._acc / self.count)
            self.rotations.append(np.array(R_0_6, dtype=float))
            self.index += 1
            self.phase, self.count = "move", 0
        return None

    def _finish(self) -> None:
        w = np.array(self.wrenches)
        try:
            self.result = identify_load(np.array(self.rotations), w)
        except DentibotError as exc:   # IdentificationError names condition, limit, advice
            self.error = str(exc)


class TcpRoutine:
    """Collects flange poses (one per pedal press) and solves the TCP once there are enough.

    ``add`` returns None (need more), an explanation string (the poses do not determine the
    tip yet: add more, better spread) or the :class:`TcpCalibration`.
    """

    def __init__(self, points: int = 4, max_points: int = 12,
                 max_residual_mm: float = 0.5) -> None:
        self.points = points
        self.max_points = max_points
        # assumption: a hand-held touch-off repeats within 0.5 mm; worse means a pose slipped
        self.max_residual_mm = max_residual_mm
        self.rotations: list[np.ndarray] = []
        self.positions: list[np.ndarray] = []

    def add(self, R_0_6: np.ndarray, p_0_6_mm: np.ndarray) -> TcpCalibration | str | None:
        self.rotations.append(np.asarray(R_0_6, dtype=float))
        self.positions.append(np.asarray(p_0_6_mm, dtype=float))
        if len(self.rotations) < self.points:
            return None
        try:
            result = calibrate_tcp(np.array(self.rotations), np.array(self.positions))
        except DentibotError as exc:
            return str(exc)
        if result.residual_max_mm > self.max_residual_mm:
            return (f"residual {result.residual_max_mm:.2f} mm > {self.max_residual_mm} mm "
                    "(a pose slipped off the point): add poses")
        return result
