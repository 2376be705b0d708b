"""ATI Mini40 F/T sensor at the wrist (thesis 4.2), frame {S}.

{S}: origin ``offset_mm`` along the flange z axis, axes turned by ``mount_angle_deg`` about it
(6T_S = Tz(offset) Rz(th)). The reading is (thesis eq 4.1-4.3)::

    f   = f0 + f_g + f_e          f_g = m * Rz(th)^T 0R_6^T (0, 0, -g)
    tau = tau0 + r x f_g + tau_e  (torques about the {S} origin, N*m; r in m)

plus Gaussian noise, through an optional first-order low-pass filter (``lowpass_s``: the
sensor's own filter setting and whatever the reading passes through before the controller
reads it), quantised to the Mini40 resolution and saturated at its range (status bit
``WRENCH_SATURATED``). ``bias()`` tares: the current reading becomes zero.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

import dentibot.sim.ftsensor_kernels as kern
from dentibot.io.interfaces import WRENCH_SATURATED
from dentibot.sim.state_view import scalar, vector

#: Rows of noise drawn at a time (the seeded stream, block by block).
NOISE_BLOCK = 4096
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
    # time constant (s) of a first-order low-pass on the reading, sampled every world period;
    # 0: none (a protocol's sensor is read unfiltered, as a real Net F/T's).
    lowpass_s: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.lowpass_s) and self.lowpass_s >= 0.0):
            raise ValueError(f"lowpass_s {self.lowpass_s!r}: a time constant >= 0 s")


class FTSensorModel:
    """The sensor (its state in the arrays of :mod:`dentibot.sim.ftsensor_kernels`, whose
    kernels :meth:`sample` and :meth:`true_wrench` call)."""

    def __init__(self, params: FTSensorParams, rng: np.random.Generator,
                 period_s: float = 0.002) -> None:
        """``period_s``: how often the world samples it (the low-pass filter's step)."""
        self.p = p = params
        self.rng = rng
        off = rng.standard_normal(6)
        self.f0 = tuple(float(x) * p.offset_sigma_n for x in off[:3])
        self.tau0 = tuple(float(x) * p.offset_sigma_nm for x in off[3:])
        th = math.radians(p.mount_angle_deg)
        self._sigma = np.array(list(p.noise_n) + [p.noise_nm] * 3)
        self.noise = self._draw()
        self.ss = np.zeros(len(kern.STATE_FIELDS))
        res = (*p.res_n, *(p.res_nm,) * 3)
        consts = {
            "weight_n": p.mass_kg * G, "cos_mount": math.cos(th), "sin_mount": math.sin(th),
            "rx_m": p.centroid_mm[0] * 1e-3, "ry_m": p.centroid_mm[1] * 1e-3,
            "rz_m": p.centroid_mm[2] * 1e-3, "offset_mm": p.offset_mm,
            "saturated": WRENCH_SATURATED,
            "lp_keep": math.exp(-period_s / p.lowpass_s) if p.lowpass_s > 0.0 else 0.0,
            **{f"offset{i}": x for i, x in enumerate(self.f0 + self.tau0)},
            **{f"res{i}": x for i, x in enumerate(res)},
            **{f"inv_res{i}": 1.0 / x for i, x in enumerate(res)},
            **{f"range{i}": x for i, x in enumerate((*p.range_n, *(p.range_nm,) * 3))},
        }
        self.sp = np.array([float(consts[k]) for k in kern.PARAM_FIELDS])
        self._F = np.zeros((4, 3))

    def _draw(self) -> np.ndarray:
        return self.rng.standard_normal((NOISE_BLOCK, 6)) * self._sigma

    def refill(self) -> None:
        """The next block of the seeded noise stream, when this one is used up (before a
        sample)."""
        if self.ss[kern.S["k"]] >= NOISE_BLOCK:
            self.noise = self._draw()
            self.ss[kern.S["k"]] = 0.0

    last = vector("ss", kern.S["last0"], 6, "The last reading after tare (N, N*m, {S}).",
                  settable=False)
    raw = vector("ss", kern.S["raw0"], 6, "The last reading before tare (quantised).",
                 settable=False)
    tare = vector("ss", kern.S["tare0"], 6, "What :meth:`bias` subtracts from every reading.",
                  settable=False)
    status = scalar("ss", kern.S["status"], int, "The last reading's status word "
                    "(``WRENCH_SATURATED`` when saturated).", settable=False)

    def origin(self, R06, p06) -> tuple[float, float, float]:
        """{S} origin in {0} (mm) given the flange rotation rows R06 and position p06."""
        d = self.p.offset_mm
        return (p06[0] + R06[0][2] * d, p06[1] + R06[1][2] * d, p06[2] + R06[2][2] * d)

    def _frame(self, R06) -> np.ndarray:
        F = self._F
        F[:3] = np.asarray(R06, dtype=float).T
        return F

    def true_wrench(self, R06, f0_ext, tau0_ext) -> tuple:
        """Noise-free reading without offsets: gravity + external, in {S} (N, N*m).

        ``f0_ext`` (N) and ``tau0_ext`` (N*m, about the {S} origin) are in {0}; ``R06`` the
        flange's rotation (rows)."""
        out = np.empty(6)
        kern.true_wrench(self.sp, self._frame(R06), float(f0_ext[0]), float(f0_ext[1]),
                         float(f0_ext[2]), float(tau0_ext[0]), float(tau0_ext[1]),
                         float(tau0_ext[2]), out)
        return tuple(out.tolist())

    def sample(self, R06, f0_ext, tau0_ext) -> tuple:
        """One reading (after tare), updating ``last``, ``raw`` and ``status``."""
        self.sample_frame(self._frame(R06), f0_ext, tau0_ext)
        return self.last

    def sample_frame(self, F: np.ndarray, f0_ext, tau0_ext) -> None:
        """:meth:`sample` with the flange's pose as the kinematics kernels give it (``F``,
        shape (4, 3): the rotation's columns, then the origin)."""
        self.refill()
        kern.sample(self.ss, self.sp, self.noise, F, f0_ext[0], f0_ext[1], f0_ext[2],
                    tau0_ext[0], tau0_ext[1], tau0_ext[2])

    def bias(self) -> None:
        """Software tare: the current raw reading reads zero from now on."""
        self.ss[12:18] = self.ss[6:12]
        self.ss[0:6] = 0.0
