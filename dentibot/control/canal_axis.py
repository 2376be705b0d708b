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

from dentibot.control import canal_axis_kernels as ak
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
    """The orientation loop of the module docstring for one file, stepped every period (its
    state in the arrays of :mod:`dentibot.control.canal_axis_kernels`, whose kernels the
    methods call)."""

    def __init__(self, beam: FileBeam, params: AxisServoParams = AxisServoParams(),
                 ts: float = 0.002) -> None:
        self.beam = beam
        self.p = params
        self.ts = ts
        par = np.empty(len(ak.PARAM_FIELDS))
        par[ak.P_A_TARE] = ts / (params.tare_filter_s + ts)
        par[ak.P_A_LOAD] = ts / (params.filter_s + ts)
        par[ak.P_MAX_RATE] = math.radians(params.max_rate_deg_s)
        par[ak.P_HOLD] = math.radians(params.hold_deg)
        par[ak.P_STOP] = math.radians(params.stop_deg)
        par[ak.P_GAIN] = params.gain_per_s
        par[ak.P_MIN_DEPTH] = params.min_depth_mm
        self.par = par
        self.st = np.zeros(len(ak.STATE_FIELDS))
        self._beam = (float(beam.length_mm), *beam.integrals)

    def reset(self) -> None:
        """Back to the start: no tare taken, no loads, no tilt."""
        self.st[:] = 0.0

    @property
    def tilt(self) -> np.ndarray:
        """The canal's direction's tilt from the tool axis, (x, y) in {H} (rad, small angle):
        a view on the state (assigning writes it)."""
        return self.st[ak.S_TILT:ak.S_TILT + 2]

    @tilt.setter
    def tilt(self, value) -> None:
        self.st[ak.S_TILT:ak.S_TILT + 2] = value

    @property
    def angle_rad(self) -> float:
        """The misalignment between the tool axis and the canal's estimated direction."""
        return ak.angle_rad(self.st)

    def step(self, depth_mm: float | None, wrench_h) -> None:
        """Take one period's depth (mm, None when unknown) and wrench at the tip in {H}
        (:func:`~dentibot.control.canal_axis_kernels.step`)."""
        known = depth_mm is not None
        ak.step(self.st, self.par, float(depth_mm) if known else 0.0, known,
                np.asarray(wrench_h, dtype=float), *self._beam)

    def chord_tilt(self, depth_mm: float, force_n, arms_nmm) -> np.ndarray:
        """The tilt (rad, x and y in {H}) of the chord of the file's part in a canal
        ``depth_mm`` deep under the lateral force ``force_n`` and the loads' moment arms
        ``arms_nmm`` (= z x M about the tip): steps 2-3 of the module docstring
        (:func:`~dentibot.control.canal_axis_kernels.chord_tilt`)."""
        out = np.empty(2)
        ak.chord_tilt(float(depth_mm), float(force_n[0]), float(force_n[1]),
                      float(arms_nmm[0]), float(arms_nmm[1]), *self._beam, out)
        return out

    def twist(self) -> np.ndarray | None:
        """The rotation rate (rad/s in {H}, about the tip) that turns the tool axis towards the
        canal, as a twist [0, 0, 0, wx, wy, 0]; None while there is nothing to turn."""
        out = np.empty(6)
        return out if ak.twist(self.st, self.par, out) else None

    def feed_scale(self) -> float:
        """The factor (0..1) on the insertion force: 1 below ``hold_deg`` of misalignment, 0
        from ``stop_deg`` (the file is not pushed deeper while bent through the tilt)."""
        return ak.feed_scale(self.st, self.par)
