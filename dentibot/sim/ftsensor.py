"""ATI Mini40 F/T sensor at the wrist (thesis 4.2), frame {S}.

{S}: origin ``offset_mm`` along the flange z axis, axes turned by ``mount_angle_deg`` about it
(6T_S = Tz(offset) Rz(th)). The reading is (thesis eq 4.1-4.3)::

    f   = f0 + f_g + f_e          f_g = m * Rz(th)^T 0R_6^T (0, 0, -g)
    tau = tau0 + r x f_g + tau_e  (torques about the {S} origin, N*m; r in m)

plus Gaussian noise, quantised to the Mini40 resolution and saturated at its range (status bit
``WRENCH_SATURATED``). ``bias()`` tares: the current reading becomes zero.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from dentibot.io.interfaces import WRENCH_SATURATED

#: Standard gravity (m/s^2).
G = 9.80665


@dataclass(frozen=True)
class FTSensorParams:
    # thesis 5.1: handpiece with adapter about 139 g.
    mass_kg: float = 0.139
    # assumption: centroid slightly off-axis, 45 mm down the handpiece (mm, in {S}).
    centroid_mm: tuple = (3.0, -2.0, 45.0)
    # assumption: sensor origin 10 mm along the flange z (adapter plate thickness).
    offset_mm: float = 10.0
    # assumption: sensor mounted turned 15 deg about the flange z.
    mount_angle_deg: float = 15.0
    # Mini40 SI-20-1 range and resolution (ATI data sheet, thesis 4.2).
    range_n: tuple = (20.0, 20.0, 60.0)
    range_nm: float = 1.0
    res_n: tuple = (0.01, 0.01, 0.02)
    res_nm: float = 1.0 / 4000.0
    # assumption: power-up offsets drawn per seed, sigma 1 N and 0.02 N*m.
    offset_sigma_n: float = 1.0
    offset_sigma_nm: float = 0.02
    # assumption: noise about one resolution step rms (N, N*m).
    noise_n: tuple = (0.01, 0.01, 0.02)
    noise_nm: float = 0.0003


class FTSensorModel:
    def __init__(self, params: FTSensorParams, rng: np.random.Generator) -> None:
        self.p = p = params
        self.rng = rng
        off = rng.standard_normal(6)
        self.f0 = tuple(float(x) * p.offset_sigma_n for x in off[:3])
        self.tau0 = tuple(float(x) * p.offset_sigma_nm for x in off[3:])
        th = math.radians(p.mount_angle_deg)
        self._c, self._s = math.cos(th), math.sin(th)
        self._sigma = np.array(list(p.noise_n) + [p.noise_nm] * 3)
        self._block()
        self.tare = (0.0,) * 6
        self.last = (0.0,) * 6        # after tare
        self.raw = (0.0,) * 6         # before tare (quantised)
        self.status = 0
        self._res = tuple(p.res_n) + (p.res_nm,) * 3
        self._rng = tuple(p.range_n) + (p.range_nm,) * 3
        self._inv_res = tuple(1.0 / r for r in self._res)
        self._off = self.f0 + self.tau0
        self._r_m = tuple(x * 1e-3 for x in p.centroid_mm)

    def _block(self) -> None:
        self._noise = (self.rng.standard_normal((4096, 6)) * self._sigma).tolist()
        self._k = 0

    def origin(self, R06, p06) -> tuple[float, float, float]:
        """{S} origin in {0} (mm) given the flange rotation rows R06 and position p06."""
        d = self.p.offset_mm
        return (p06[0] + R06[0][2] * d, p06[1] + R06[1][2] * d, p06[2] + R06[2][2] * d)

    def true_wrench(self, R06, f0_ext, tau0_ext) -> tuple:
        """Noise-free reading without offsets: gravity + external, in {S} (N, N*m).

        ``f0_ext`` (N) and ``tau0_ext`` (N*m, about the {S} origin) are in {0}.
        """
        p = self.p
        fz = -p.mass_kg * G
        fx0, fy0, fz0 = f0_ext[0], f0_ext[1], f0_ext[2] + fz
        # into {6}: R06^T v
        r0, r1, r2 = R06
        f6 = (r0[0] * fx0 + r1[0] * fy0 + r2[0] * fz0, r0[1] * fx0 + r1[1] * fy0 + r2[1] * fz0,
              r0[2] * fx0 + r1[2] * fy0 + r2[2] * fz0)
        a, b, c_ = tau0_ext
        t6 = (r0[0] * a + r1[0] * b + r2[0] * c_, r0[1] * a + r1[1] * b + r2[1] * c_,
              r0[2] * a + r1[2] * b + r2[2] * c_)
        c, s = self._c, self._s
        fx, fy, fz_ = c * f6[0] + s * f6[1], -s * f6[0] + c * f6[1], f6[2]
        tx, ty, tz = c * t6[0] + s * t6[1], -s * t6[0] + c * t6[1], t6[2]
        # gravity torque r x f_g, with f_g in {S}
        g6z = fz  # gravity alone in {6}: R06^T (0,0,fz)
        gx6, gy6, gz6 = R06[2][0] * g6z, R06[2][1] * g6z, R06[2][2] * g6z
        gx, gy = c * gx6 + s * gy6, -s * gx6 + c * gy6
        rx, ry, rz = self._r_m
        tx += ry * gz6 - rz * gy
        ty += rz * gx - rx * gz6
        tz += rx * gy - ry * gx
        return (fx, fy, fz_, tx, ty, tz)

    def sample(self, R06, f0_ext, tau0_ext) -> tuple:
        """One reading (after tare), updating ``last``, ``raw`` and ``status``."""
        w = self.true_wrench(R06, f0_ext, tau0_ext)
        k = self._k
        if k == 4096:
            self._block()
            k = 0
        self._k = k + 1
        n = self._noise[k]
        off = self._off
        x = [a + b + c for a, b, c in zip(w, off, n)]
        lim = self._rng
        status = 0
        for i in range(6):
            if x[i] >= lim[i]:
                x[i], status = lim[i], WRENCH_SATURATED
            elif x[i] <= -lim[i]:
                x[i], status = -lim[i], WRENCH_SATURATED
        raw = [round(a * b) * c for a, b, c in zip(x, self._inv_res, self._res)]
        self.raw = raw = tuple(raw)
        t = self.tare
        self.last = last = (raw[0] - t[0], raw[1] - t[1], raw[2] - t[2],
                            raw[3] - t[3], raw[4] - t[4], raw[5] - t[5])
        self.status = status
        return last

    def bias(self) -> None:
        """Software tare: the current raw reading reads zero from now on."""
        self.tare = self.raw
        self.last = (0.0,) * 6
