"""The tooth's pose from the patient tracker, and depth measured in the tooth's frame.

Each tick (:meth:`ToothFrame.update`): the six string lengths give the tooth clamp's pose in
the handpiece mount, ``MT_T`` (:func:`dentibot.control.strings.track` from the previous
tick's pose), and with the flange pose ``0T_6`` (the tick's kinematic chain) and the mount on
the flange ``6T_M`` the tooth in the base frame::

    0T_T = 0T_6 6T_M MT_T

The depth reference (orifice point and canal axis) is registered in {T} when the file goes
in (:meth:`register`) and mapped back to {0} every tick (:meth:`reference_0`), so the depth,
the working-length stop, the retract target and the supervisor's depth limit all follow the
tooth when the patient moves, along the canal axis included. Without a tracker the reference
stays frozen in {0}, as in the thesis, and a patient moving along the canal changes the true
depth unseen.

With hybrid control (``ToothConfig.feedforward``) the tooth's rigid motion, estimated from
successive poses, is fed forward to the arm as a twist at the file tip
(:meth:`ToothFrame.feedforward_h`): the file moves with the part of the tooth it is in and
the handpiece turns with a turning tooth.

A string that goes slack, over its range, out of agreement with the others, or a tracker that
stops answering, is a fault while a reference is held (the working length is no longer
protected); before the file goes in it only makes the tooth pose unknown.
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, field

import numpy as np

from dentibot.control.depth import depth_along
from dentibot.control.strings import (
    LengthLimits,
    StringGeometry,
    check_lengths,
    forward,
    track,
)
from dentibot.control.strings_kernels import matrix_rotvec
from dentibot.runtime.finding import Finding

#: The tooth's velocities are differences over this many control periods (16 ms at 500 Hz).
DIFF_TICKS = 8
#: How fast a patient's head can move the tooth (assumption: a startle or a jerk of the
#: head, 200 mm/s and 200 deg/s), and the pose's noise on top (mm, deg): a pose further from
#: the last one seen than that in the time between is another solution of the same lengths.
MAX_TOOTH_MM_S = 200.0
MAX_TOOTH_DEG_S = 200.0
JUMP_MM = 0.5
JUMP_DEG = 3.0


@dataclass(frozen=True)
class ToothConfig:
    """The tracker's geometry as the runtime knows it (calibrated anchors, the mount on the
    flange ``6T_M``, a starting guess of ``MT_T``), the strings' limits (slack, range, jump
    between ticks, the residual above which the six lengths disagree) and the length noise
    (mm) of the first solve."""

    geometry: StringGeometry
    mount_in_flange: np.ndarray = field(default_factory=lambda: np.eye(4))
    start_pose: np.ndarray = field(default_factory=lambda: np.eye(4))
    limits: LengthLimits = field(default_factory=LengthLimits)
    sigma_mm: float = 0.01
    #: hybrid control: the arm moves with the tooth (its rigid motion fed forward)
    feedforward: bool = False
    #: time constant of the orifice velocity's low-pass filter (s) and the speed below which
    #: nothing is fed forward (mm/s): a still patient feeds no encoder noise to the arm
    velocity_tau_s: float = 0.008
    deadband_mm_s: float = 2.0
    #: the same for the tooth's turning rate (s, deg/s). The orientation's noise (about
    #: 0.01 deg per reading) differenced over one 2 ms period is about 9 deg/s per axis; the
    #: 16 ms filter brings a still tooth's rate to 1.2 deg/s (median) and 3.3 deg/s (the
    #: largest in 10 s of the simulated tracker), below the 5 deg/s deadband
    rotation_tau_s: float = 0.016
    deadband_deg_s: float = 5.0


class ToothFrame:
    """The tracked tooth and the depth reference in its frame (see the module docstring)."""

    def __init__(self, cfg: ToothConfig, period_s: float = 0.002) -> None:
        self.cfg = cfg
        self.ts = period_s
        self._alpha = period_s / (cfg.velocity_tau_s + period_s)
        self._alpha_w = period_s / (cfg.rotation_tau_s + period_s)
        self.velocity_0: np.ndarray | None = None   # the orifice's velocity (mm/s), filtered
        self.omega_0: np.ndarray | None = None      # the tooth's turning rate (rad/s), filtered
        self._o_prev: np.ndarray | None = None
        self._hist: deque = deque()                 # (orifice, 0R_T) of the last ticks
        self.point_0: np.ndarray | None = None      # the file tip of the last tick ({0}, mm)
        self.pose_mt: np.ndarray | None = None      # MT_T of the last good tick
        self.pose_0t: np.ndarray | None = None      # 0T_T of the last good tick
        self.residual_mm = float("nan")
        self._previous_mm = None                    # the last sample's lengths (jump check)
        self._lost = False                          # the last sample could not be trusted
        self._last_0t: np.ndarray | None = None     # 0T_T last seen (kept while lost)
        self._last_t = 0.0                          # when (s, the samples' time)
        self._ref_t: tuple[np.ndarray, np.ndarray] | None = None   # (orifice, axis) in {T}

    @property
    def registered(self) -> bool:
        return self._ref_t is not None

    def update(self, sample, r_0_6, p_0_6) -> Finding | None:
        """The tooth's pose from ``sample`` (a StringSample) and the flange pose; a Finding
        when the strings cannot be trusted (the pose is then unknown)."""
        c = self.cfg
        bad = check_lengths(sample.lengths_mm, c.limits, previous_mm=self._previous_mm)
        # the next sample is checked against this one, good or not: a jump is one sample's
        # finding, not every sample's after it (a load calibration swings the mount by tens
        # of millimetres; the strings are back in range and consistent once it ends)
        if np.isfinite(sample.lengths_mm).all():
            self._previous_mm = sample.lengths_mm
        if bad or not sample.ok:
            self.pose_0t = None
            self._lost = True
            why = "; ".join(f"string {f.string + 1}: {f.message or f.kind}" for f in bad) or \
                f"tracker status {sample.status}"
            return Finding("tracker", why)
        t0m = np.eye(4)
        t0m[:3, :3] = r_0_6
        t0m[:3, 3] = p_0_6
        t0m = t0m @ c.mount_in_flange                 # 0T_M: the mount moves with the flange
        # the guess: the tooth where it was last seen in {0}, seen from the mount now (the
        # arm's own motion is known; only the patient's is left to the strings)
        if self._last_0t is not None:
            guess = np.linalg.solve(t0m, self._last_0t)
        else:
            guess = c.start_pose if self.pose_mt is None else self.pose_mt
        lim = c.limits.max_residual_mm
        res = math.inf
        if self.pose_mt is not None and not self._lost:
            pose, res = track(c.geometry, sample.lengths_mm, guess, iterations=1)
        if not res <= lim:
            # a full solve from the prediction: one Gauss-Newton step follows a tick's motion,
            # not a lost stretch's nor a fast swing of the arm's
            est = forward(c.geometry, sample.lengths_mm, guess, sigma_mm=c.sigma_mm)
            pose, res = est.pose, est.rms_mm
        self.residual_mm = res
        if not res <= lim:
            return self._lose(f"the six string lengths disagree: rms residual {res:.3f} mm > "
                              f"{lim} mm")
        t0t = t0m @ pose
        if self._last_0t is not None:
            # a patient moves the tooth so far in the time since it was last seen, no further
            # (a solve that lands elsewhere found another pose with the same six lengths)
            dt = max(sample.t - self._last_t, 0.0)
            dp = float(np.linalg.norm(t0t[:3, 3] - self._last_0t[:3, 3]))
            turn = matrix_rotvec(t0t[:3, :3] @ self._last_0t[:3, :3].T)
            da = math.degrees(math.sqrt(turn @ turn))
            if dp > JUMP_MM + MAX_TOOTH_MM_S * dt or da > JUMP_DEG + MAX_TOOTH_DEG_S * dt:
                return self._lose(f"the tooth's pose jumped {dp:.2f} mm, {da:.1f} deg in "
                                  f"{dt * 1e3:.0f} ms (a patient's head moves at most "
                                  f"{MAX_TOOTH_MM_S:g} mm/s, {MAX_TOOTH_DEG_S:g} deg/s)")
        self._lost = False
        self.pose_mt = pose
        self.pose_0t = self._last_0t = t0t
        self._last_t = sample.t
        return None

    def _lose(self, why: str) -> Finding:
        self.pose_0t = None
        self._lost = True
        return Finding("tracker", why)

    def tick(self, sample, chain, ctx, est) -> Finding | None:
        """Step 2 with a tracker: the tooth's pose from ``sample`` and the tick's kinematic
        ``chain`` (its last frame is the flange), then the depth reference ``ctx.depth_ref``
        and the estimate's depth ``est.depth_mm`` from the tooth's pose now. A Finding when
        the strings fail while a reference is held."""
        flange = chain[1][5]                     # 0R_6 by columns, then the origin
        finding = self.update(sample, flange[:3].T.copy(), flange[3].copy())
        if self._ref_t is None:
            return None
        if finding is not None:
            return Finding(finding.kind, f"{finding.detail}: the depth in the tooth's frame "
                                         "is lost with the file in the canal")
        ctx.depth_ref = ref = self.reference_0()
        self._track_velocity(np.array(ref[0]), self.pose_0t[:3, :3])
        self.point_0 = np.array(est.tip_0, float)
        est.depth_mm = depth_along(est.tip_0, ref)
        return None

    def _track_velocity(self, o: np.ndarray, r_0_t: np.ndarray | None = None) -> None:
        """The tooth's velocities from this tick's orifice ``o`` ({0}, mm) and orientation
        ``r_0_t`` (0R_T; None: the orientation is not tracked), by finite differences over
        ``DIFF_TICKS`` periods, through first-order low-passes of time constants
        ``velocity_tau_s`` and ``rotation_tau_s`` (:meth:`feedforward_h`).

        The tooth's pose in {0} is the arm's (from its encoders, quantised to 0.001 deg: a few
        micrometres at the mount) times the strings'. A difference over one 2 ms period
        turns those micrometres into mm/s while the arm moves (8-22 mm/s and up to 30 deg/s
        of a still tooth measured during an alignment); over ``DIFF_TICKS`` periods the
        bounded quantisation error is divided by that many."""
        hist = self._hist
        hist.append((o, None if r_0_t is None else np.array(r_0_t, float)))
        if len(hist) > DIFF_TICKS:
            o0, r0 = hist.popleft()
            span = DIFF_TICKS * self.ts
            raw = (o - o0) / span
            v = self.velocity_0
            self.velocity_0 = raw if v is None else v + self._alpha * (raw - v)
            if r_0_t is not None and r0 is not None:
                raw = matrix_rotvec(r_0_t @ r0.T) / span
                w = self.omega_0
                self.omega_0 = raw if w is None else w + self._alpha_w * (raw - w)
        self._o_prev = o

    def feedforward_h(self, r_0_h: np.ndarray, point_0=None) -> np.ndarray | None:
        """Hybrid control's feedforward: the tooth's rigid motion as a twist in {H} axes
        (mm/s, rad/s), taken at the point of the tooth that coincides with the controller's
        reference point: ``point_0`` ({0}, mm), by default the file tip of the last tick
        (point B of self-alignment; a caller whose reference point is elsewhere, point A
        while dragging, passes it)::

            omega = 0omega_T                     (rad/s)
            v     = v_O + omega x (point - O)    (mm/s; O the registered orifice)
            twist = (0R_H^T v, 0R_H^T omega)

        ``v_O`` and ``omega`` are estimated from successive tracked poses: the orifice's
        displacement over one period, and the rotation vector of ``0R_T(k) 0R_T(k-1)^T``
        over one period (the angular velocity in {0}), low-passed with the time constants
        ``velocity_tau_s`` and ``rotation_tau_s``. Deadbands, so that a still patient feeds
        no encoder noise to the arm: nothing at all while the orifice is slower than
        ``deadband_mm_s`` and the tooth turns slower than ``deadband_deg_s``; a turn slower
        than ``deadband_deg_s`` is fed as none (omega = 0) while the tooth translates. None
        when nothing is fed, while no reference is held, the pose is unknown, or without
        ``feedforward`` in the configuration."""
        c = self.cfg
        v, w = self.velocity_0, self.omega_0
        if not c.feedforward or self._ref_t is None or v is None or self.pose_0t is None:
            return None
        moving = float(np.linalg.norm(v)) >= c.deadband_mm_s
        turning = w is not None and float(np.degrees(np.linalg.norm(w))) >= c.deadband_deg_s
        if not (moving or turning):
            return None
        if not turning:
            return np.concatenate([r_0_h.T @ v, np.zeros(3)])
        point = self.point_0 if point_0 is None else np.asarray(point_0, float)
        v_p = v if point is None else v + np.cross(w, point - self._o_prev)
        return np.concatenate([r_0_h.T @ v_p, r_0_h.T @ w])

    def register(self, orifice_0, axis_0) -> None:
        """Keep the depth reference (orifice point, canal axis; {0}) in the tooth's frame."""
        if self.pose_0t is None:
            self._ref_t = None
            return
        R, p = self.pose_0t[:3, :3], self.pose_0t[:3, 3]
        self._ref_t = (R.T @ (np.asarray(orifice_0, float) - p), R.T @ np.asarray(axis_0, float))

    def forget(self) -> None:
        self._ref_t = None
        self.velocity_0 = self._o_prev = self.omega_0 = self.point_0 = None
        self._hist.clear()

    def reference_0(self) -> tuple[tuple, tuple] | None:
        """The registered reference mapped into {0} with the tooth's pose now."""
        if self._ref_t is None or self.pose_0t is None:
            return None
        R, p = self.pose_0t[:3, :3], self.pose_0t[:3, 3]
        o, a = self._ref_t
        return tuple((R @ o + p).tolist()), tuple((R @ a).tolist())

