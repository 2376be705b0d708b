"""Self-alignment's orientation loop: the canal's direction read from how the file bends.

Thesis 4.4: in self-alignment the handpiece "amends the inserting direction by itself to
lower the contact resistance": the admittance law yields to the wrench at the file tip
(point B). A file entering a canal tilted from its axis is pushed one way near the orifice
and the other way at the tip; about the tip that couple is a moment, which the rotational
axes of the admittance (b4 = b5 = 80, Table 4.3) turn into a rotation. The file is flexible
(:class:`~dentibot.control.filebeam.FileBeam`), so that moment is a few N*mm: the admittance
alone turns the handpiece by well under 1 deg/s, while the file goes millimetres deep in a
second. This loop closes the orientation on the file's measured shape instead:

1. tare: while the file is out of the canal (depth < 0) the lateral force and moment at the
   tip are low-passed; that is the sensor's residual bias (gravity compensation, drift) at
   this orientation, and it is taken off in the canal;
2. loads: with the tip ``d`` mm deep, the lateral force ``F`` and moment ``M`` at the tip are
   two loads on the file, ``P_o`` at the orifice and ``P_t`` at the tip: ``d P_o = z x M``
   (moment about the tip) and ``P_o + P_t = F``;
3. shape: the file is a cantilever clamped in the chuck, so the loads deflect it by
   ``w_i = sum_j c(i, j) P_j`` (:meth:`FileBeam.compliance_mm_n`); the chord of the file's
   part in the canal, from the orifice to the tip, is ``d z + w_t - w_o``: the canal's
   direction, within the play of the file in the lumen;
4. rotation: the handpiece turns about the tip towards that direction at ``gain`` times the
   angle (a rate added to the admittance's twist, bounded), and while the angle is large the
   insertion force is scaled down (:meth:`CanalAxisServo.feed_scale`): the file is not pushed
   deeper while it is bent through the canal's tilt.

Units: N, N*m in (the wrench at the tip in {H}), mm, rad/s out; angles in rad inside.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dentibot.control.filebeam import FileBeam
from dentibot.errors import ConfigError


@dataclass(frozen=True)
class AxisServoParams:
    """Gains and bounds of the orientation loop (all assumptions, chosen on the simulator:
    the canal's direction is known within the file's play in the lumen, about 2 deg at 3 mm
    in a #15/.02 glide path; the arm's response is tens of ms)."""

    gain_per_s: float = 10.0         # rotation rate per rad of misalignment
    max_rate_deg_s: float = 20.0    # bound of the added rotation rate
    min_depth_mm: float = 1.0       # below this depth the chord is too short to read
    filter_s: float = 0.08          # low-pass of the loads in the canal
    tare_filter_s: float = 0.1      # low-pass of the residual out of the canal
    hold_deg: float = 0.5           # full insertion force below this misalignment ...
    stop_deg: float = 2.0           # ... none above this (linear in between)

    def __post_init__(self) -> None:
        for name in ("gain_per_s", "max_rate_deg_s", "min_depth_mm", "filter_s",
                     "tare_filter_s", "hold_deg"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0.0):
                raise ConfigError(f"align.axis_servo.{name}", v, "a finite number > 0")
        if not self.stop_deg > self.hold_deg:
            raise ConfigError("align.axis_servo.stop_deg", self.stop_deg,
                              f"> hold_deg ({self.hold_deg})")


class CanalAxisServo:
    """The orientation loop of the module docstring for one file, stepped every period."""

    def __init__(self, beam: FileBeam, params: AxisServoParams = AxisServoParams(),
                 ts: float = 0.002) -> None:
        self.beam = beam
        self.p = params
        self.ts = ts
        self._a_tare = ts / (params.tare_filter_s + ts)
        self._a = ts / (params.filter_s + ts)
        self._max_rate = math.radians(params.max_rate_deg_s)
        self._hold = math.radians(params.hold_deg)
        self._stop = math.radians(params.stop_deg)
        self.reset()

    def reset(self) -> None:
        self._tare = (0.0, 0.0, 0.0, 0.0)  # fx, fy (N), mx, my (N*m) out of the canal
        self._tared = False
        self._loads = None                 # filtered fx, fy (N), Gx, Gy (N*mm) in the canal
        #: the canal's direction's tilt from the tool axis, (x, y) in {H} (rad, small angle)
        self.tilt = np.zeros(2)

    @property
    def angle_rad(self) -> float:
        """The misalignment between the tool axis and the canal's estimated direction."""
        return math.atan(math.hypot(self.tilt[0], self.tilt[1]))

    def step(self, depth_mm: float | None, wrench_h) -> None:
        """Take one period's depth (mm, None when unknown) and wrench at the tip in {H}.
        (Four numbers a period: plain floats, no numpy per-call overhead.)"""
        w = (float(wrench_h[0]), float(wrench_h[1]), float(wrench_h[3]), float(wrench_h[4]))
        if depth_mm is None or depth_mm < 0.0:
            a = 1.0 if not self._tared else self._a_tare
            self._tare = tuple(t + a * (x - t) for x, t in zip(w, self._tare))
            self._tared = True
            self._loads = None
            self.tilt = np.zeros(2)
            return
        if depth_mm < self.p.min_depth_mm:
            self._loads = None
            self.tilt = np.zeros(2)
            return
        t = self._tare
        fx, fy = w[0] - t[0], w[1] - t[1]
        mx, my = (w[2] - t[2]) * 1e3, (w[3] - t[3]) * 1e3
        x = (fx, fy, -my, mx)              # F, and z x M: the loads' moment arms (N*mm)
        loads = self._loads or (0.0, 0.0, 0.0, 0.0)   # they build up from zero in the canal
        a = self._a
        self._loads = loads = tuple(v + a * (u - v) for u, v in zip(x, loads))
        self.tilt = self.chord_tilt(depth_mm, loads[:2], loads[2:])

    def chord_tilt(self, depth_mm: float, force_n, arms_nmm) -> np.ndarray:
        """The tilt (rad, x and y in {H}) of the chord of the file's part in a canal
        ``depth_mm`` deep under the lateral force ``force_n`` and the loads' moment arms
        ``arms_nmm`` (= z x M about the tip): steps 2-3 of the module docstring."""
        d = float(depth_mm)
        b = self.beam
        c00, c0d, cdd = b.compliance_mm_n(0.0, 0.0), b.compliance_mm_n(0.0, d), \
            b.compliance_mm_n(d, d)
        out = np.empty(2)
        for i in range(2):
            p_o = float(arms_nmm[i]) / d
            p_t = float(force_n[i]) - p_o
            out[i] = ((c00 - c0d) * p_t + (c0d - cdd) * p_o) / d
        return out

    def twist(self) -> np.ndarray | None:
        """The rotation rate (rad/s in {H}, about the tip) that turns the tool axis towards the
        canal, as a twist [0, 0, 0, wx, wy, 0]; None while there is nothing to turn."""
        tx, ty = self.tilt
        if tx == 0.0 and ty == 0.0:
            return None
        k = self.p.gain_per_s
        wx, wy = -k * ty, k * tx           # z x (tx, ty, 1): turn z towards the chord
        n = math.hypot(wx, wy)
        if n > self._max_rate:
            wx, wy = wx * self._max_rate / n, wy * self._max_rate / n
        return np.array((0.0, 0.0, 0.0, wx, wy, 0.0))

    def feed_scale(self) -> float:
        """The factor (0..1) on the insertion force: 1 below ``hold_deg`` of misalignment, 0
        from ``stop_deg`` (the file is not pushed deeper while bent through the tilt)."""
        a = self.angle_rad
        if a <= self._hold:
            return 1.0
        return max(0.0, (self._stop - a) / (self._stop - self._hold))
