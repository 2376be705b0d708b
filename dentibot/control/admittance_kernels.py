"""The admittance law of one period, compiled (numba): the six Tustin mass-damper filters
of eq 4.23-4.25 with the desired insertion force added along z_H (f_d of 4.4), the
feedforward twist, then the joint rates, limits and target of
:func:`~dentibot.control.joint_rate_kernels.joint_step`.

:class:`~dentibot.control.admittance.AdmittanceFilter` and
:class:`~dentibot.control.admittance.AdmittanceController` hold the state arrays (``v``, the
last input ``f_prev``, the last joint rates) and call these; they are the only implementation.
Units: N, N*m in; mm/s, rad/s out (see :mod:`dentibot.control.admittance`).

Compiled at import, as :mod:`~dentibot.control.kinematics_kernels` explains.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from dentibot.control.joint_rate_kernels import joint_step


@njit(cache=True)
def lateral_scale(depth_mm: float, file_length_mm: float, ref_free_mm: float) -> float:
    """How many times the lateral axes' (x and y of {H}) damping and mass are raised at
    ``depth_mm``: ``(ref / L)^3`` once the file's free part ``L = file length - depth``
    (between the chuck and the canal) is shorter than ``ref_free_mm``, else 1; 1 without a
    depth (NaN) or with ``ref_free_mm`` 0 (off).

    Why: the handpiece feels the file sideways as a cantilever of its free length, stiffness
    ``3 E I / L^3``. Through an arm that answers a velocity command late (the Meca500's
    16 ms in its queue and its 6.3 ms filter, fitted on the bench), the lateral admittance
    loop ``k/b x stiffness`` rings once the stiffness passes what its delay allows (12 Hz,
    from about 11 mm deep with b = 80): scaling b (and m, keeping m/b) with the stiffness
    holds the loop's gain at its value for a free length ``ref_free_mm``."""
    if not (ref_free_mm > 0.0) or not math.isfinite(depth_mm):
        return 1.0
    free = max(file_length_mm - depth_mm, 0.1 * ref_free_mm)
    if free >= ref_free_mm:
        return 1.0
    r = ref_free_mm / free
    return r * r * r


@njit(cache=True)
def filter_step(a: np.ndarray, c: np.ndarray, v: np.ndarray, f_prev: np.ndarray,
                f: np.ndarray, fz: float, out: np.ndarray, lateral: float = 1.0) -> None:
    """Eq 4.25 on each axis, ``v = a (f + f_prev) - c v`` with ``a = k ts / (ts b + 2m)`` and
    ``c = (ts b - 2m) / (ts b + 2m)`` (zero on a switched-off axis), driven by ``f`` plus
    ``fz`` on z: updates ``v`` and ``f_prev`` in place and writes ``v`` to ``out``. On x and
    y, ``a`` is divided by ``lateral`` (:func:`lateral_scale`): their b and m ``lateral``
    times larger, the same time constant, ``1/lateral`` of the gain."""
    for i in range(6):
        fi = f[i] + fz if i == 2 else f[i]
        ai = a[i] / lateral if i < 2 else a[i]
        vi = ai * (fi + f_prev[i]) - c[i] * v[i]
        f_prev[i] = fi
        v[i] = vi
        out[i] = vi


@njit(cache=True)
def command(a: np.ndarray, c: np.ndarray, v: np.ndarray, f_prev: np.ndarray,
            wrench: np.ndarray, fz: float, feedforward: np.ndarray, jh: np.ndarray,
            frames: np.ndarray, q_deg: np.ndarray, w_prev: np.ndarray, half_ts_deg: float,
            q_lo: np.ndarray, q_hi: np.ndarray, singular_sigma: float, elbow_offset: float,
            wrist_frame: int, thresholds: np.ndarray, lo_rad: np.ndarray, hi_rad: np.ndarray,
            vmax_rad_s: np.ndarray, margin_rad: float, ts: float, lateral: float):
    """One period of fig 4.2: :func:`filter_step` on ``wrench`` + ``fz`` z_H (the lateral
    axes' gain divided by ``lateral``), plus the ``feedforward`` twist (zeros for none), then
    :func:`joint_step`; ``w_prev`` (the last joint rates, rad/s) is updated in place.

    Returns ``(twist, q_next_deg, qdot_deg_s, sing, singularity scale, speed scale,
    guarded)``; ``twist`` is the filter's output plus the feedforward, before limits."""
    twist = np.empty(6)
    filter_step(a, c, v, f_prev, wrench, fz, twist, lateral)
    for i in range(6):
        twist[i] += feedforward[i]
    q_next, qdot, sing, s_scale, speed_scale, guarded = joint_step(
        jh, twist, frames, q_deg, w_prev, half_ts_deg, q_lo, q_hi, singular_sigma,
        elbow_offset, wrist_frame, thresholds, lo_rad, hi_rad, vmax_rad_s, margin_rad, ts)
    qdot_deg_s = np.empty(6)
    for i in range(6):
        w_prev[i] = qdot[i]
        qdot_deg_s[i] = math.degrees(qdot[i])
    return twist, q_next, qdot_deg_s, sing, s_scale, speed_scale, guarded


def warm_up() -> None:
    """Compile (or load from the cache) the kernels for the argument types the controller
    passes. Called once, at import."""
    from dentibot.control.kinematics_kernels import dh_frames

    dh = np.zeros((6, 5))
    dh[:, 0] = 1.0
    q, one = np.zeros(6), np.ones(6)
    th = np.array([5.0, 20.0, 0.03, 0.17, 0.03, 0.17])
    filter_step(q, q, np.zeros(6), np.zeros(6), q, 0.0, np.zeros(6))
    command(q, q, np.zeros(6), np.zeros(6), q, 0.0, q, np.eye(6), dh_frames(dh, q), q,
            np.zeros(6), 0.06, -one, one, 0.05, 0.0, 4, th, -one, one, one, 0.1, 0.002, 1.0)
    lateral_scale(1.0, 25.0, 18.0)


warm_up()      # at import: before any device streams or loop runs
