"""The F/T sensor's reading, compiled (numba): gravity and the external wrench in {S},
offsets, noise, the reading's low-pass filter, saturation and quantisation, on arrays.

These kernels are the only implementation of the sensor's model (explained in
:mod:`dentibot.sim.ftsensor`, whose :class:`~dentibot.sim.ftsensor.FTSensorModel` calls
them). A sensor is its state ``ss`` (:data:`STATE_FIELDS`), its constants ``sp``
(:data:`PARAM_FIELDS`) and a block of seeded noise (rows of six: N, N, N, N*m, N*m, N*m),
refilled by its owner when ``ss[k]`` reaches the block's length.

The flange's pose is the array ``F`` of shape (4, 3) the kinematics kernels give
(:func:`~dentibot.control.kinematics_kernels.dh_frames`): ``F[j]`` the rotation's column j
(``0R_6[i][j] = F[j, i]``), ``F[3]`` the origin (mm).
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: The sensor's state: the reading after tare, before tare (quantised), the tare, the status.
STATE_FIELDS = (
    *(f"last{i}" for i in range(6)),
    *(f"raw{i}" for i in range(6)),
    *(f"tare{i}" for i in range(6)),
    "status",
    "k",            # next row of the noise block
    *(f"filt{i}" for i in range(6)),   # the low-pass filter's output (before saturation)
    "primed",       # 1 once the filter holds a reading
)
#: The sensor's constants.
PARAM_FIELDS = (
    "weight_n",     # the handpiece's weight, m g (N)
    "cos_mount", "sin_mount",        # the mount angle about the flange z
    "rx_m", "ry_m", "rz_m",          # the load's centroid in {S} (m)
    *(f"offset{i}" for i in range(6)),   # power-up offsets (N, N*m)
    *(f"res{i}" for i in range(6)),      # resolution (N, N*m)
    *(f"inv_res{i}" for i in range(6)),
    *(f"range{i}" for i in range(6)),    # saturation (N, N*m)
    "offset_mm",    # {S} origin along the flange z (mm)
    "saturated",    # the status word's saturation bit
    "lp_keep",      # the low-pass filter's exp(-period / time constant); 0: no filter
)

S = {name: i for i, name in enumerate(STATE_FIELDS)}
P = {name: i for i, name in enumerate(PARAM_FIELDS)}

_LAST, _RAW, _TARE, _STATUS, _K, _FILT, _PRIMED = 0, 6, 12, 18, 19, 20, 26
_WEIGHT, _COS, _SIN, _RX, _RY, _RZ = 0, 1, 2, 3, 4, 5
_OFFSET, _RES, _INV_RES, _RANGE, _OFFSET_MM, _SATURATED, _LP_KEEP = 6, 12, 18, 24, 30, 31, 32
#: Indices other kernels use (compiled constants).
P_OFFSET_MM = _OFFSET_MM


@njit(cache=True)
def true_wrench(sp: np.ndarray, F: np.ndarray, fx0: float, fy0: float, fz0: float,
                ta: float, tb: float, tc: float, out: np.ndarray) -> None:
    """Noise-free reading without offsets into ``out``: gravity + external, in {S} (N, N*m).

    ``(fx0, fy0, fz0)`` (N) and ``(ta, tb, tc)`` (N*m, about the {S} origin) are in {0}
    (thesis eq 4.1-4.3)."""
    fz = -sp[_WEIGHT]
    fz0 = fz0 + fz
    # into {6}: R06^T v (the rows of R06^T are F's columns)
    f60 = F[0, 0] * fx0 + F[0, 1] * fy0 + F[0, 2] * fz0
    f61 = F[1, 0] * fx0 + F[1, 1] * fy0 + F[1, 2] * fz0
    f62 = F[2, 0] * fx0 + F[2, 1] * fy0 + F[2, 2] * fz0
    t60 = F[0, 0] * ta + F[0, 1] * tb + F[0, 2] * tc
    t61 = F[1, 0] * ta + F[1, 1] * tb + F[1, 2] * tc
    t62 = F[2, 0] * ta + F[2, 1] * tb + F[2, 2] * tc
    c, s = sp[_COS], sp[_SIN]
    fx, fy, fz_ = c * f60 + s * f61, -s * f60 + c * f61, f62
    tx, ty, tz = c * t60 + s * t61, -s * t60 + c * t61, t62
    # gravity torque r x f_g, with f_g in {S}: gravity alone in {6} is R06^T (0, 0, fz)
    gx6, gy6, gz6 = F[0, 2] * fz, F[1, 2] * fz, F[2, 2] * fz
    gx, gy = c * gx6 + s * gy6, -s * gx6 + c * gy6
    rx, ry, rz = sp[_RX], sp[_RY], sp[_RZ]
    out[0], out[1], out[2] = fx, fy, fz_
    out[3] = tx + (ry * gz6 - rz * gy)
    out[4] = ty + (rz * gx - rx * gz6)
    out[5] = tz + (rx * gy - ry * gx)


@njit(cache=True)
def sample(ss: np.ndarray, sp: np.ndarray, noise: np.ndarray, F: np.ndarray, fx0: float,
           fy0: float, fz0: float, ta: float, tb: float, tc: float) -> None:
    """One reading: :func:`true_wrench` plus offsets and noise, through the first-order
    low-pass filter (``y += (x - y) (1 - keep)``, the first reading taken as it is),
    saturated, quantised and tared, into ``ss`` (``last``, ``raw``, ``status``).
    ``noise[ss[k]]`` must exist."""
    w = np.empty(6)
    true_wrench(sp, F, fx0, fy0, fz0, ta, tb, tc, w)
    k = int(ss[_K])
    ss[_K] = k + 1
    status = 0.0
    keep = sp[_LP_KEEP]
    primed = ss[_PRIMED] != 0.0
    for i in range(6):
        x = w[i] + sp[_OFFSET + i] + noise[k, i]
        if keep != 0.0:
            if primed:
                x = ss[_FILT + i] + (x - ss[_FILT + i]) * (1.0 - keep)
            ss[_FILT + i] = x
        lim = sp[_RANGE + i]
        if x >= lim:
            x, status = lim, sp[_SATURATED]
        elif x <= -lim:
            x, status = -lim, sp[_SATURATED]
        raw = round(x * sp[_INV_RES + i]) * sp[_RES + i]
        ss[_RAW + i] = raw
        ss[_LAST + i] = raw - ss[_TARE + i]
    ss[_STATUS] = status
    ss[_PRIMED] = 1.0


def warm_up() -> None:
    """Compile (or load from the cache) the kernels (a simulator serving a real-time
    controller must not stall). Called once, at import."""
    ss = np.zeros(len(STATE_FIELDS))
    sp = np.ones(len(PARAM_FIELDS))
    F = np.zeros((4, 3))
    sample(ss, sp, np.zeros((2, 6)), F, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0)
    true_wrench(sp, F, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, np.zeros(6))


warm_up()      # at import: before any device streams or loop runs
