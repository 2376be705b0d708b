"""Joint-rate limits applied after the admittance law (thesis 4.3, "Robot Command Decision").

The arm is commanded in joint space precisely so that these checks can run before anything is
sent: singularity slowing, joint-range guarding and joint-speed clamping. Units: joint angles
deg, joint rates rad/s (what the Jacobian produces).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from dentibot.control.joint_rate_kernels import limit_rates
from dentibot.control.kinematics import Meca500, SingularityMeasure
from dentibot.errors import ConfigError


@dataclass(frozen=True)
class SingularityThresholds:
    """Where slowing starts and where motion toward a singularity stops.

    Assumptions (no vendor figure): the Meca500 refuses motion very near a singularity
    (error 1012); slowing from about 10 deg (wrist, elbow) or 20 mm (shoulder) away keeps the
    arm clear of it with a smooth approach.
    """

    shoulder_start_mm: float = 20.0
    shoulder_stop_mm: float = 5.0
    elbow_start: float = math.sin(math.radians(10.0))
    elbow_stop: float = math.sin(math.radians(2.0))
    wrist_start: float = math.sin(math.radians(10.0))
    wrist_stop: float = math.sin(math.radians(2.0))

    def __post_init__(self) -> None:
        for name in ("shoulder", "elbow", "wrist"):
            start, stop = getattr(self, f"{name}_start"
                                  + ("_mm" if name == "shoulder" else "")), getattr(
                self, f"{name}_stop" + ("_mm" if name == "shoulder" else ""))
            if not 0.0 <= stop < start:
                raise ConfigError(f"singularity.{name}_start", start,
                                  f"must be greater than {name}_stop = {stop} >= 0")


@dataclass(frozen=True)
class LimitReport:
    """What the limiter changed this tick (all 1.0 / empty when nothing)."""

    singularity_scale: float = 1.0
    speed_scale: float = 1.0
    guarded_joints: tuple[int, ...] = ()
    singularity: SingularityMeasure | None = None

    @property
    def limited(self) -> bool:
        return self.singularity_scale < 1.0 or self.speed_scale < 1.0 or bool(self.guarded_joints)


@dataclass
class JointLimiter:
    """Scales and clamps joint rates so the arm never leaves its envelope.

    - Singularities: each of the three factors of ``det J`` (see ``SingularityMeasure``) that is
      below its start threshold *and decreasing* scales the whole rate vector down, to zero at
      the stop threshold. Moving away from a singularity is never slowed.
    - Joint range: a joint moving toward its limit may go at most ``v_max * d / margin``
      (d = distance left) and never further than the limit in one period; that joint alone is
      clamped, so motions that do not push the joint further stay available.
    - Joint speed: if any joint exceeds ``speed_fraction`` of its limit the whole vector is
      scaled uniformly (the Cartesian direction is kept).
    """

    robot: Meca500
    ts: float = 0.002
    range_margin_deg: float = 5.0
    speed_fraction: float = 1.0
    singularity: SingularityThresholds = field(default_factory=SingularityThresholds)

    def __post_init__(self) -> None:
        if not 0.0 < self.speed_fraction <= 1.0:
            raise ConfigError("limits.speed_fraction", self.speed_fraction, "0 < value <= 1")
        if self.range_margin_deg <= 0.0:
            raise ConfigError("limits.range_margin_deg", self.range_margin_deg, "> 0 deg")
        self.lo_rad = np.radians(self.robot.joint_limits_deg[:, 0])
        self.hi_rad = np.radians(self.robot.joint_limits_deg[:, 1])
        self.vmax_rad_s = self.robot.joint_speed_limits_rad_s * self.speed_fraction
        self.margin_rad = math.radians(self.range_margin_deg)
        th = self.singularity
        #: the singularity thresholds as the kernels take them
        #: (:mod:`dentibot.control.joint_rate_kernels`)
        self.thresholds = np.array([th.shoulder_stop_mm, th.shoulder_start_mm, th.elbow_stop,
                                    th.elbow_start, th.wrist_stop, th.wrist_start])

    def apply(self, q_deg, qdot_rad_s: np.ndarray,
              sing: SingularityMeasure | None = None) -> tuple[np.ndarray, LimitReport]:
        """Limited joint rates (rad/s) for the configuration ``q_deg``
        (:func:`~dentibot.control.joint_rate_kernels.limit_rates`)."""
        if sing is None:
            sing = self.robot.singularity(q_deg, qdot_rad_s)
        qdot, s_scale, speed_scale, guarded = limit_rates(
            np.asarray(q_deg, dtype=float), np.asarray(qdot_rad_s, dtype=float),
            _factors(sing), self.thresholds, self.lo_rad, self.hi_rad, self.vmax_rad_s,
            self.margin_rad, self.ts)
        return qdot, LimitReport(s_scale, speed_scale, guarded_joints(guarded), sing)


def _factors(s: SingularityMeasure) -> tuple[float, ...]:
    return (float(s.shoulder_mm), float(s.elbow), float(s.wrist), float(s.shoulder_rate),
            float(s.elbow_rate), float(s.wrist_rate))


def guarded_joints(mask: np.ndarray) -> tuple[int, ...]:
    """The joints a kernel's per-joint ``guarded`` mask marks, as 0-based indices."""
    return tuple(i for i, g in enumerate(mask.tolist()) if g)
