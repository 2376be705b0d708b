"""The bench-fitted world: the physics of the thesis lab's experiment-1 bench, each parameter
in one place with its source and how it was fitted.

Source: the thesis lab's recordings, experiment 1 (LabVIEW logs at 10 ms with PhaseSpace
motion capture; per-trial figures of 19 trials, and three trials' trajectories at 20 Hz).
``tools/fit_bench.py`` in the source tree re-derives every value below from them and prints
it with its residual; the values here are what it prints, rounded as noted.

:class:`BenchPhysics` holds the values; :meth:`BenchPhysics.world_config` gives the
:class:`~dentibot.sim.world.WorldConfig` of the bench (arm, canal, sensor, handpiece and the
platform's path), :func:`axial_chase` is the reduced model (the insertion axis alone) the
canal's axial drag and bottom stiffness are fitted with.

Units: mm, s, N, mNm (file torque as the bench logged it: eq 5.4, Km GR I).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from dentibot.control.feedrate import GEAR_RATIO, KM_MNM_PER_A
from dentibot.sim.arm import ArmParams
from dentibot.sim.canal import CanalParams
from dentibot.sim.canal_kernels import axial_drag_n
from dentibot.sim.ftsensor import FTSensorParams
from dentibot.sim.handpiece import HandpieceParams
from dentibot.sim.patient import BenchSquarePath

#: Logged torque per motor ampere as the bench computed it (eq 5.4: Km GR, no efficiency).
LOGGED_MNM_PER_A = KM_MNM_PER_A * GEAR_RATIO

#: The platform loop (Stewart frame, mm) at phase i/24 of each square: least squares of a
#: periodic piecewise-linear curve on the 12 recorded squares (residual rms x/y/z 1.0/1.0/
#: 0.6 mm: the square-to-square wander), rounded to 0.1 mm.
PLATFORM_KNOTS_MM = (
    (0.0, 0.0, 0.0), (-1.2, -0.9, -0.2), (-2.9, -0.4, 0.1), (-4.9, -0.3, 0.1),
    (-7.3, -0.2, 0.2), (-10.3, 0.1, 0.1), (-12.6, -0.2, 0.3), (-13.9, -0.4, 2.4),
    (-14.9, -0.4, 4.7), (-15.6, -0.5, 7.1), (-16.2, -0.1, 9.7), (-16.6, 0.5, 12.4),
    (-16.2, 0.2, 13.9), (-15.3, -0.1, 14.1), (-14.8, -0.5, 14.3), (-13.5, -0.4, 14.4),
    (-10.9, -0.6, 14.6), (-8.0, -0.8, 14.7), (-3.6, -0.9, 14.5), (-1.4, -0.2, 12.1),
    (-1.1, -0.2, 9.4), (-0.9, 0.1, 7.0), (-0.4, 0.1, 4.4), (-0.4, 0.9, 2.1))


@dataclass(frozen=True)
class BenchPhysics:
    """Every bench-fitted parameter (see the module docstring for the source)."""

    # --- arm, velocity interface (Stewart z axis, command -> TCP motion). Median of the
    # 19 trials' 100 Hz fits of a first-order-plus-dead-time model (the 20 Hz re-fit of the
    # tool confirms the gain, 0.80, but cannot resolve 16 ms): dead time 15.9 ms, lag
    # 6.3 ms, realised gain 0.804 of the command. Rounded to the 2 ms control period
    # (queue delay 16 ms) and 0.1 ms.
    arm_dead_time_s: float = 0.016
    arm_lag_s: float = 0.0063
    # The realised gain: documented as fitted. No mechanism of the velocity interface
    # (queue, filter, SetVelTimeout) reproduces a steady 0.8 with a command renewed every
    # period, so it is kept as the measured ratio.
    arm_gain: float = 0.804
    # --- the force the bench's controller read: first-order low-pass, 113 ms. The recorded
    # contact force lags the file's motion: at rest with the file bottomed out, the axial
    # loop chatters at 2.8-3.3 Hz (the recordings' Fz_chatter_peak_hz, A and B at 1 N),
    # where the arm alone (dead time and lag above) turns it by only 24 deg past the
    # admittance's integration; a contact cannot lag (it is passive), the reading can (the
    # sensor's filter and the bench's processing). The time constant is the one that makes
    # up the half turn at the chatter's median peak, 3.08 Hz (tool: "the reading's
    # low-pass"). Least squares of :func:`axial_chase` with the time constant free as well
    # put it at 80 ms, residual 0.313 against 0.315 at 113 ms: the time series hardly tell.
    ft_lowpass_s: float = 0.113
    # --- canal, axial: drag and the bottom's stiffness, least squares of
    # :func:`axial_chase` on the three recorded trials' tip-root distance and contact force
    # along z, with the reading's low-pass above. Pressed into its seat the file does not
    # slide along the walls; off it, the walls drag it in proportion to the slip; a still
    # file (A's) is held by friction more, a Coulomb drag. The drag acts along the file's
    # length in the canal (assumption: wall contact): the values hold at the depth they were
    # fitted at, the bench's file at its seat (its canal's 16 mm working length and 0.5 mm to
    # the bottom), in proportion elsewhere. The free fit (tool: "canal axial, filtered
    # reading") puts the drag at 0.199 N per mm/s, the still file's friction at 2.32 N and
    # the bottom at 6.59 N/mm (residual 0.318), which takes one more of A's figures out of
    # range (the file out of its seat in square 4, 0.93 mm); with the bottom held at the
    # 7.4 N/mm of the model before (tool: "--bottom 7.4"), 0.207 N per mm/s, 1.21 N and
    # 0.019 N of Coulomb drag (residual 0.320), kept (rounded to 0.01 N per mm/s, 0.05 N and
    # 0.01 N). The time series hardly tell the still file's friction from a drag a constant
    # factor harder (6.0 times, viscous: residual 0.316), the model before: it made the
    # admittance's loop a gain of 6.3 for a still file at full depth, and a file stopped in
    # the canal (a patient movement, hand-guiding) rang through the arm's delay. The world
    # before that (drag on the seated file too, 0.11 N per mm/s, 0.34 N of Coulomb drag,
    # 2.7 N/mm) had 0.448, its steep Coulomb part standing in for the lag and ringing at
    # 19 Hz through the arm's delay.
    drag_n_s_per_mm: float = 0.21
    drag_coulomb_n: float = 0.02
    drag_v0_mm_s: float = 0.5
    bottom_n_mm: float = 7.4
    drag_static_factor: float = 1.0
    drag_still_coulomb_n: float = 1.2
    drag_depth_mm: float = 16.5
    # assumption: lateral sliding damped like the axial (same N per mm/s).
    drag_lat_n_s_per_mm: float = 0.10
    # --- canal, lateral: the phantom's holder on the Stewart platform moves sideways under
    # the file's loads (mm/N), softer across the square's plane (platform y) than along its
    # travel (x): on the recordings the tip's offset from the platform moves -1.1..-1.4 mm
    # per N of admittance input along x and -1.7..-2.1 along y (least-squares slopes during
    # the squares of A, B and C; the tool prints them). The simulated slopes, at seed 1, for
    # (x, y) = (1.0, 1.0): -1.9 / -0.5; (0.5, 2.0): -1.5 / -0.8; (0.3, 3.0): -1.3 / -0.9 mm
    # per N; (0.5, 2.0) has the best share of figures in range (seeds 1, 2). Part of the
    # y slope is still missing (see docs/sim-to-real.md).
    support_mm_per_n: float = 0.5
    support_y_mm_per_n: float | None = 2.0
    # --- logged file torque (handpiece measurement only). Free running: median of the
    # turning trial without feedrate control (16.94 mNm); motor off: median of config A
    # (-0.32 mNm); wander: that trial's std (0.35 mNm), as a slow sinusoid of amplitude
    # std * sqrt 2. Pressed onto the canal bottom: least squares of torque - free running on
    # the force pressing the seated file in that same trial (B: 1 N and more, up to 2.5 N at
    # its p99): 0.06 logged mNm per N, nothing to speak of (the canal's physical value is this
    # times the gearhead efficiency). C's peaks (30-36 mNm) come as the file re-enters the
    # canal after detaching: the flutes' engagement with the walls, which the canal model's
    # cutting torque gives, not the bottom.
    torque_free_mnm: float = 16.94
    torque_off_mnm: float = -0.32
    torque_wander_mnm: float = 0.35
    torque_press_mnm_per_n: float = 0.06
    # --- F/T noise in {H} at 100 Hz (std at rest before the first square, x and y; the
    # 20 Hz means times sqrt 5): 0.024 and 0.046 N; Fz assumed like Fy.
    ft_noise_n: tuple = (0.024, 0.046, 0.046)
    # --- the platform: loop shape (PLATFORM_KNOTS_MM), per-square durations and pauses
    # (medians over the 19 trials: measured speeds between leg midpoints 2.94, 3.94, 4.88,
    # 7.46 mm/s) and the Stewart frame's yaw from the robot's base -y (README of the
    # recordings: about 12 deg).
    durations_s: tuple = (20.39, 15.24, 12.30, 8.04)
    pauses_s: tuple = (9.66, 9.67, 10.08)
    frame_yaw_deg: float = 12.0
    platform_knots_mm: tuple = PLATFORM_KNOTS_MM
    # The squares differ from the loop and from each other: each square's deviation from
    # the fitted loop, less its mean and smoothed over 1/12 of the loop, has an rms of 0.53
    # (x), 0.41 (y) and 0.13 (z) mm (median over the 12 recorded squares); what is faster
    # (0.24/0.23/0.11 mm) is left to the motion capture's noise. Drawn per square from the
    # world's seed (:class:`~dentibot.sim.patient.BenchSquarePath`).
    platform_wander_mm: tuple = (0.53, 0.41, 0.13)
    # The platform turns as it moves: on the recordings the tip's offset from the platform's
    # measured centre follows the platform's own travel across it (least squares during the
    # squares on travel and admittance input force together, A/B/C: -0.061/-0.054/-0.063 mm
    # of y per mm of x travel), and the handpiece, turned with the canal, moves its LED the
    # other way (0.136/0.116/0.138 mm of y per mm of x). A roll about x_S proportional to
    # the x travel, about a centre ``platform_centre_above_tip_mm`` above the canal's
    # bottom, gives both: the tip moves h * roll across, the LED (44 mm up the file)
    # 44 * roll the other way, so h = 44 * 0.06 / 0.13 = 20 mm and roll = -0.06 / 20 rad per
    # mm of x. No pitch: the tip's x offset also follows the z travel (-0.05 mm per mm),
    # but the LED's x does not (0.02 mm per mm, where a pitch about the same centre would
    # give 0.13): that part is the x lag of the legs, and a pitch put the simulated rel_x
    # out of range (B 4.5 mm, real 1.9-3.0). The tool prints these slopes and -0.0031 rad
    # per mm about a centre 19.6 mm up (rounded here to -0.0030 and 20 mm).
    platform_tilt_rad_per_mm: tuple = (-0.0030, 0.0)
    platform_centre_above_tip_mm: float = 20.0
    # --- the handpiece LED the bench's relative distance was measured at: 44 mm behind the
    # file tip along the file.
    led_behind_tip_mm: float = 44.0

    # ------------------------------------------------------------------ world
    def arm(self) -> ArmParams:
        return ArmParams(servo_tau_s=self.arm_lag_s, vel_dead_time_s=self.arm_dead_time_s,
                         vel_gain=self.arm_gain)

    def canal_drag(self, base: CanalParams | None = None) -> CanalParams:
        """``base`` (default: the default canal) with the walls' fitted drag on the file."""
        return replace(base or CanalParams(), drag_n_s_per_mm=self.drag_n_s_per_mm,
                       drag_coulomb_n=self.drag_coulomb_n, drag_v0_mm_s=self.drag_v0_mm_s,
                       drag_static_factor=self.drag_static_factor,
                       drag_still_coulomb_n=self.drag_still_coulomb_n,
                       drag_depth_mm=self.drag_depth_mm,
                       drag_lat_n_s_per_mm=self.drag_lat_n_s_per_mm)

    def canal(self, base: CanalParams | None = None, efficiency: float = 0.7) -> CanalParams:
        """The bench's phantom: the drag, its bottom and its holder on the platform."""
        return replace(self.canal_drag(base), bottom_n_mm=self.bottom_n_mm,
                       support_mm_per_n=self.support_mm_per_n,
                       support_y_mm_per_n=self.support_y_mm_per_n,
                       bottom_torque_mnm_per_n=self.torque_press_mnm_per_n * efficiency)

    def handpiece(self) -> HandpieceParams:
        """The free-running level as no-load current (the logged torque is Km GR I)."""
        return HandpieceParams(
            friction_current_a=(self.torque_free_mnm - self.torque_off_mnm) / LOGGED_MNM_PER_A,
            current_offset_a=self.torque_off_mnm / LOGGED_MNM_PER_A,
            current_wander_a=self.torque_wander_mnm * math.sqrt(2.0) / LOGGED_MNM_PER_A,
            current_noise_a=0.0002)

    def sensor(self) -> FTSensorParams:
        return FTSensorParams(noise_n=tuple(self.ft_noise_n), lowpass_s=self.ft_lowpass_s)

    def platform(self, start_s: float = 0.0, seed: int = 0) -> BenchSquarePath:
        return BenchSquarePath(self.platform_knots_mm, self.durations_s, self.pauses_s,
                               self.frame_yaw_deg, start_s=start_s,
                               wander_mm=self.platform_wander_mm,
                               rng=np.random.default_rng([seed, 0x57A6E]),
                               tilt_rad_per_mm=self.platform_tilt_rad_per_mm)

    @staticmethod
    def phantom_pose(tool_pose: np.ndarray, ex, gap_mm: float) -> np.ndarray:
        """0T_P of the phantom on the platform: the canal's orifice ``gap_mm`` ahead of the
        file tip (``tool_pose``, 0T_tool at the start) along the file (as
        :class:`~dentibot.sim.world.World` places it), its x axis turned about the canal to
        the platform's x ``ex`` (the square's travel), so that the holder's compliances act
        along the platform's axes."""
        t = np.array(tool_pose, float)
        z = t[:3, 2]
        t[:3, 3] += gap_mm * z
        ex = np.asarray(ex, float)
        x = ex - np.dot(ex, z) * z
        x /= np.linalg.norm(x)
        t[:3, 0], t[:3, 1] = x, np.cross(z, x)
        return t

    def world_config(self, seed: int = 0, canal: CanalParams | None = None,
                     start_s: float = 0.0, **kw):
        """The bench's :class:`~dentibot.sim.world.WorldConfig` (platform starting its first
        square at ``start_s``; the phantom as :meth:`phantom_pose` places it unless ``kw``
        gives its pose; the platform turning about its centre
        ``platform_centre_above_tip_mm`` above the file tip at ``q0_deg``)."""
        from dentibot.control.kinematics import Meca500
        from dentibot.sim.world import WorldConfig

        path = self.platform(start_s, seed)
        cfg = WorldConfig(seed=seed, arm=self.arm(), canal=self.canal(canal),
                          sensor=self.sensor(), handpiece=self.handpiece(), motion=path, **kw)
        tool_pose = Meca500(tool=cfg.tool).fk_tool(cfg.q0_deg)
        if cfg.phantom_pose is None:
            cfg.phantom_pose = self.phantom_pose(tool_pose, path.ex, cfg.orifice_gap_mm)
        tip = tool_pose[:3, 3]
        path.centre_mm = (float(tip[0]), float(tip[1]),
                          float(tip[2]) + self.platform_centre_above_tip_mm)
        return cfg


#: The preset.
BENCH = BenchPhysics()


# ---------------------------------------------------------------------------- reduced model
def fz_des_law(config: str, tau_logged_mnm: float, f_norm_n: float) -> float:
    """Insertion force (N) as the bench ran it: A, B 1 N; C (K 500) ``0.025 (37.6 - tau)``
    capped at 0.5 N; C_K250 ``0.05 (37.6 - tau)`` capped at 1 N (the same chase speed
    k fz_max / b); for C both at least 0 N and 0 while |F_H| > 1.5 N (patient moved,
    fig 5.6). ``tau`` is the logged torque (mNm, free running included)."""
    if config in ("A", "B"):
        return 1.0
    kp, cap = (0.05, 1.0) if config == "C_K250" else (0.025, 0.5)
    if f_norm_n > 1.5:
        return 0.0
    return min(cap, max(0.0, kp * (37.6 - tau_logged_mnm)))


def axial_chase(t, platform_z_mm, config: str, arm_gain: float = BENCH.arm_gain,
                dead_ms: float = 1000 * BENCH.arm_dead_time_s,
                tau_ms: float = 1000 * BENCH.arm_lag_s,
                drag_n_s_per_mm: float = BENCH.drag_n_s_per_mm,
                coulomb_n: float = BENCH.drag_coulomb_n, v0_mm_s: float = BENCH.drag_v0_mm_s,
                bottom_n_mm: float = BENCH.bottom_n_mm,
                still_factor: float = BENCH.drag_static_factor,
                drag_depth_mm: float = BENCH.drag_depth_mm,
                still_coulomb_n: float = BENCH.drag_still_coulomb_n,
                lowpass_ms: float = 1000 * BENCH.ft_lowpass_s,
                press_mnm_per_n: float = BENCH.torque_press_mnm_per_n,
                free_mnm: float = BENCH.torque_free_mnm, ts: float = 0.002) -> dict:
    """The insertion axis alone: the file seated at the canal bottom of a root moving with
    ``platform_z_mm`` (at times ``t``), held by the admittance law (k/b = 6.25 mm/s per N,
    or 3.125 for C_K250) on the force read through the first-order low-pass ``lowpass_ms``,
    through the arm's dead time, lag and gain; the canal bottom a spring, the walls dragging
    the file off its seat (``still_factor`` times harder in A, whose file does not turn,
    and held there by ``still_coulomb_n`` of friction more; in proportion to its length
    left in the canal, seated at ``drag_depth_mm``, when that is > 0).
    Returns at the times ``t``: ``gap_mm`` (tip out of its seat, + out) and ``fz_h_n`` (the
    contact force along the file in {H} as read, + tension)."""
    t = np.asarray(t, float)
    pz = np.asarray(platform_z_mm, float)
    tt = np.arange(t[0], t[-1], ts)
    p = np.interp(tt, t, pz)
    kb = 3.125 if config == "C_K250" else 6.25
    nd = max(int(round(dead_ms / 1000.0 / ts)), 0)
    a = 1.0 - math.exp(-ts / max(tau_ms / 1000.0, 1e-6))
    keep = math.exp(-ts / (lowpass_ms / 1000.0)) if lowpass_ms > 0.0 else 0.0
    turning = config != "A"
    fz0 = fz_des_law(config, free_mnm, 0.0)
    y = p[0] - fz0 / bottom_n_mm           # tip seated under the initial insertion force
    seat = p[0]
    queue = [0.0] * (nd + 1)
    v = 0.0
    slip = 0.0
    read = fz0
    prev_gap = y - seat
    gap_out = np.empty(len(tt))
    f_out = np.empty(len(tt))
    af = ts / (0.004 + ts)
    for i in range(len(tt)):
        gap = y - (p[i] - p[0] + seat)
        # pressed into its seat the file does not slide along the walls
        slip += (((gap - prev_gap) / ts if gap >= 0.0 else 0.0) - slip) * af
        prev_gap = gap
        n = bottom_n_mm * -gap if gap < 0.0 else 0.0
        f_up = n - axial_drag_n(slip, turning, max(drag_depth_mm - max(gap, 0.0), 0.0),
                                drag_n_s_per_mm, coulomb_n, v0_mm_s, still_factor,
                                still_coulomb_n, drag_depth_mm)
        read += (f_up - read) * (1.0 - keep)
        tau = free_mnm + press_mnm_per_n * max(read, 0.0)
        fz = fz_des_law(config, tau, abs(read))
        queue.append(kb * (read - fz))
        vc = queue.pop(0)
        v += (arm_gain * vc - v) * a
        y += v * ts
        gap_out[i] = gap
        f_out[i] = -read
    return {"gap_mm": np.interp(t, tt, gap_out), "fz_h_n": np.interp(t, tt, f_out)}
