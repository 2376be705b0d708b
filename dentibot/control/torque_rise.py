"""A file torque that rises faster than the reaction to it can follow.

The drilling strategy reverses the file when its torque passes a limit (thesis 5.2-5.4). That
reaction takes time: the tick that sees the torque, the drive turning the file round (about
10 ms). A torque that rises at thousands of mNm/s (the tooth jerked along the canal onto the
file: 15 to 68 mNm in 16 ms) passes the file's strength within that time. So the torque is
projected ``horizon_s`` ahead along its rising slope, and the reaction starts when the
projection passes the limit while the slope is steeper than drilling ever rises
(``min_slope_mnm_s``): near a high desired torque the drilling's own ripple would otherwise
project past the limit and reverse the file for nothing. The caller disarms it while the
motor spins up (after a reversal the current that accelerates the rotor rises at several
thousand mNm/s, and is not the file's torque).

The slope is the torque's derivative through a first-order filter (``filter_s``) so that the
motor current's noise is not amplified: drilling in the simulated resin canal rises at most
about 600 mNm/s (4 ms filter), a jerk at 40 mm/s 3,300 mNm/s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from dentibot.errors import ConfigError


@dataclass(frozen=True)
class TorqueRiseParams:
    # assumption: one tick to see it, 10 ms for the drive to turn the file round
    horizon_s: float = 0.012
    filter_s: float = 0.004          # s, the slope's low-pass
    # assumption: drilling rises at most about 600 mNm/s (4 ms filter, resin and acrylic
    # phantoms at tau_d 40-50); a jerk onto the file rises at 2,000 mNm/s and more
    min_slope_mnm_s: float = 1000.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.min_slope_mnm_s) and self.min_slope_mnm_s > 0.0):
            raise ConfigError("limits.torque_rise.min_slope_mnm_s", self.min_slope_mnm_s, "> 0")
        for name in ("horizon_s", "filter_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and 0.0 < v <= 1.0):
                raise ConfigError(f"limits.torque_rise.{name}", v, "0 < s <= 1")


#: :class:`TorqueRise`'s state array: whether a torque was taken, the last one (mNm), the
#: filtered slope (mNm/s).
R_HAS, R_LAST, R_SLOPE = 0, 1, 2


@njit(cache=True)
def rise_step(st, a: float, ts: float, min_slope_mnm_s: float, horizon_s: float,
              tau_mnm: float) -> float:
    """Take one period's torque into the slope (``st``: :data:`R_HAS` ...; ``a`` the
    low-pass coefficient ``ts / (filter_s + ts)``); the projected torque (mNm): ``tau +
    slope * horizon`` while the slope is at least ``min_slope_mnm_s``, else ``tau``."""
    if st[R_HAS] != 0.0:
        raw = (tau_mnm - st[R_LAST]) / ts
        st[R_SLOPE] += a * (raw - st[R_SLOPE])
    st[R_LAST] = tau_mnm
    st[R_HAS] = 1.0
    if st[R_SLOPE] < min_slope_mnm_s:
        return tau_mnm
    return tau_mnm + st[R_SLOPE] * horizon_s


class TorqueRise:
    """The file torque's filtered slope (mNm/s) and its projection ``horizon_s`` ahead (state
    in ``st``, compiled step :func:`rise_step`)."""

    def __init__(self, params: TorqueRiseParams = TorqueRiseParams(), ts: float = 0.002) -> None:
        self.p = params
        self.ts = ts
        self._a = ts / (params.filter_s + ts)
        self.st = np.zeros(3)

    @property
    def slope_mnm_s(self) -> float:
        return float(self.st[R_SLOPE])

    def reset(self) -> None:
        self.st[:] = 0.0

    def step(self, tau_mnm: float) -> float:
        """Take this tick's torque; return the projected torque (mNm): ``tau + slope *
        horizon`` while the slope is steeper than ``min_slope_mnm_s``, else ``tau``."""
        return rise_step(self.st, self._a, self.ts, self.p.min_slope_mnm_s, self.p.horizon_s,
                         float(tau_mnm))


TorqueRise().step(0.0)      # compiled (or loaded from the cache) at import
